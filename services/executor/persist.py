"""What the executor keeps on disk besides its sets (DESIGN §9): the last selection it applied and the
newest it received (a decision maker that decided 11 and 14 while a path ran at 8 is not taken back to 8
by a restart), so a restart while the decision maker is unreachable can go on at the last decided k (if
that is young enough); the cycle in progress, so a restart says which cycle it cut short; and a stop
latched and not yet resumed, or a motion not ended in order, so that a restart (the service crashed, the
host rebooted) comes up stopped until a person resumes. Validated on load like a message; a damaged file
is moved aside."""

from __future__ import annotations

import threading
from pathlib import Path

import msgspec

from common.runtime.clock import wall_ns
from common.runtime.storage import Loaded, atomic_write, load_checked
from schemas.base import NonNegInt, TimeNs
from schemas.decision import Selection, SolutionIndex

FILE = "executor_state.json"


class AppliedSelection(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """A selection as the record keeps it: enough to go on at it after a restart, and how old it is."""

    k: SolutionIndex
    n: SolutionIndex
    seq: NonNegInt
    t_ns: TimeNs  # the selection's data time
    applied_ns: TimeNs  # wall clock, when a path first ran with it

    def __post_init__(self) -> None:
        if self.k > self.n:
            raise ValueError(f"k = {self.k} is above n = {self.n}")

    def age_s(self, now_ns: int | None = None) -> float:
        return ((now_ns or wall_ns()) - self.applied_ns) / 1e9

    def selection(self) -> Selection:
        return Selection(t_ns=self.t_ns, seq=self.seq, k=self.k, n=self.n, delta=0, reason="hold")


class ExecutorRecord(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """What a restart must know of the last run, as it is on disk."""

    selection: AppliedSelection | None = None
    cycle_in_progress: NonNegInt | None = None
    received: AppliedSelection | None = None  # the newest selection received (``applied_ns``: when)
    latched: str | None = None  # a stop latched and not yet resumed: why (a restart keeps it)
    moving: str | None = None  # the path the arm may be moving on (a restart finding one latches a stop)

    @property
    def newest(self) -> AppliedSelection | None:
        """The selection to go on at: the newest the decision maker was heard to decide."""
        got = [s for s in (self.received, self.selection) if s is not None]
        return max(got, key=lambda s: (s.t_ns, s.seq, s.applied_ns)) if got else None


class ExecutorStore:
    """Owns the record's file: one read-change-write at a time, each written whole (atomically)."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / FILE
        self.record = ExecutorRecord()
        self._lock = threading.Lock()  # writers in worker threads: one read-change-write at a time

    def load(self) -> Loaded[ExecutorRecord]:
        loaded = load_checked(self.path, lambda b: msgspec.json.decode(b, type=ExecutorRecord))
        if loaded.value is not None:
            self.record = loaded.value
        return loaded

    def _change(self, **fields: object) -> None:
        with self._lock:
            record = msgspec.structs.replace(self.record, **fields)
            if record != self.record:
                atomic_write(self.path, msgspec.json.encode(record))
                self.record = record

    def applied(self, sel: Selection) -> None:
        """A path starts with ``sel``: kept if it is another selection than the one on file."""
        if (kept := _kept(self.record.selection, sel)) is not None:
            self._change(selection=kept)

    def received(self, sel: Selection) -> None:
        """A selection came: kept if it is another than the one on file (a republished one is not)."""
        if (kept := _kept(self.record.received, sel)) is not None:
            self._change(received=kept)

    def cycle(self, in_progress: int | None) -> None:
        self._change(cycle_in_progress=in_progress)

    def latch(self, why: str | None) -> None:
        self._change(latched=why)

    def moving(self, path_id: str | None) -> None:
        self._change(moving=path_id)

    def forget_stop(self) -> None:
        """Neither a latched stop nor a motion cut short (a new simulated arm: the demo's)."""
        self._change(latched=None, moving=None)


def _kept(old: AppliedSelection | None, sel: Selection) -> AppliedSelection | None:
    """``sel`` as it is kept, or None when it is the one on file already."""
    if old is not None and (old.k, old.n, old.seq, old.t_ns) == (sel.k, sel.n, sel.seq, sel.t_ns):
        return None
    return AppliedSelection(k=sel.k, n=max(sel.n, sel.k), seq=sel.seq, t_ns=sel.t_ns, applied_ns=wall_ns())
