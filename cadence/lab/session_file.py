"""A study session's file (paper §III-C; schemas/session.py): written by `cadence session` on a live cell
and by the simulated study, read by `cadence study analyse`, which reads nothing else.

One MCAP per subject and condition: the cell's traffic as `cadence record` writes it, plus the session's
description (``cadence.session``) at its start and its end (``cadence.session.end``) when it is closed.
The measures are taken between the two records' data times: φ = cycles / minutes, ε = errors / cycles,
the mean of the good windows' mean RR, and that mean over the subject's resting RR (RR_r).

A file is refused, with what is wrong and where, when it cannot stand for its session: it was never
closed, it has no calibration, its keys come from more than one cell, or its publishers' data clocks
disagree (a replay at 10× beside an executor at 1× makes every rate a fiction).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import msgspec
import numpy as np
from numpy.typing import NDArray

from cadence import version
from cadence.lab.marks import counted
from cadence.tools.recording import Recorder, read
from common.runtime.errors import InputError
from schemas import (
    CycleReport,
    HrvWindow,
    Message,
    OperatorError,
    Selection,
)
from schemas.session import SESSION_END_RECORD, SESSION_RECORD, SessionEnd, SessionInfo
from schemas.topology import (
    ROOT,
    decode_any,
    encode,
)
from schemas.topology import key as key_of

# keys whose t_ns is the publisher's data time at publishing: they tell its clock's rate and offset
# (a selection or a status is republished with an old t_ns and says nothing about the clock)
CLOCKED = ("ecg/samples", "ecg/rr", "hrv/beats", "hrv/window", "robot/state", "robot/cycle")
RATE_TOLERANCE = 1.25  # data time per wall time may differ this much between publishers
OFFSET_TOLERANCE_S = 60.0  # and their clocks this much (data time): a window is published after its end
S = TypeVar("S", bound=msgspec.Struct)


def software() -> str:
    return f"cadence {version()}"


def task_digest(path: Path) -> str:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror}") from None


def _record(struct: msgspec.Struct) -> dict[str, str]:
    """A metadata record: the whole struct as JSON (what the analysis reads), and its top-level fields as
    text, for MCAP tools that list metadata."""
    flat = {k: str(v) for k, v in msgspec.structs.asdict(struct).items() if not isinstance(v, msgspec.Struct)}
    return flat | {"json": msgspec.json.encode(struct).decode()}


class SessionWriter:
    """The file from its first message on (a session records its health check and calibration too);
    ``begin`` writes the description once the condition is in force, ``close`` the end record."""

    def __init__(self, path: Path, cell: str) -> None:
        self.path = path
        self.cell = cell
        self.recorder = Recorder(path)

    def begin(self, info: SessionInfo) -> None:
        self.recorder.metadata(SESSION_RECORD, _record(info))

    def put(self, suffix: str, msg: Message, log_time_ns: int | None = None) -> None:
        """A message as it would have come on ``cadence/<cell>/<suffix>`` (the simulated study)."""
        self.recorder.write(key_of(self.cell, suffix), encode(msg), log_time_ns)

    def close(self, end: SessionEnd) -> None:
        self.recorder.metadata(SESSION_END_RECORD, _record(end))
        self.recorder.close()


@dataclass
class Session:
    path: Path
    info: SessionInfo
    end: SessionEnd
    windows: list[HrvWindow] = field(default_factory=list)
    selections: list[Selection] = field(default_factory=list)
    cycles: list[CycleReport] = field(default_factory=list)
    errors: list[OperatorError] = field(default_factory=list)

    def inside(self, t_ns: int) -> bool:
        return self.info.start_ns < t_ns <= self.end.end_ns

    @property
    def minutes(self) -> float:
        return (self.end.end_ns - self.info.start_ns) / 60e9

    @property
    def n_cycles(self) -> int:
        return sum(self.inside(c.t_ns) for c in self.cycles)

    @property
    def counted_errors(self) -> list[OperatorError]:
        """The errors inside the session that count (cadence/lab/marks.py: less the marks withdrawn)."""
        return counted(e for e in self.errors if self.inside(e.t_ns))

    @property
    def n_errors(self) -> int:
        return len(self.counted_errors)

    def k_at(self, t_ns: int) -> int | None:
        """The k in force at data time ``t_ns``: the latest selection at or before it."""
        last = max((x for x in self.selections if x.t_ns <= t_ns), key=lambda x: x.t_ns, default=None)
        return None if last is None else last.k

    @property
    def mean_k(self) -> float:
        """The k in force, averaged over the session's data time (what a yoked session holds)."""
        sels = sorted(self.selections, key=lambda x: x.t_ns)
        start, end = self.info.start_ns, self.end.end_ns
        if not sels:
            return float("nan")
        k = self.k_at(start) or sels[0].k
        total, t = 0.0, start
        for x in sels:
            if start < x.t_ns <= end:
                total += k * (x.t_ns - t)
                k, t = x.k, x.t_ns
        return (total + k * (end - t)) / (end - start)

    @property
    def tlx_raw(self) -> float:
        return self.end.tlx.raw if self.end.tlx is not None else float("nan")

    @property
    def productivity_per_min(self) -> float:
        return self.n_cycles / self.minutes if self.minutes > 0 else 0.0

    @property
    def error_rate(self) -> float:
        return self.n_errors / self.n_cycles if self.n_cycles else 0.0

    @property
    def good_rr_s(self) -> list[float]:
        return [
            w.mean_rr_s
            for w in self.windows
            if w.quality == "good" and w.mean_rr_s is not None and self.inside(w.end_ns)
        ]

    @property
    def mean_rr_s(self) -> float:
        good = self.good_rr_s
        return float(np.mean(good)) if good else float("nan")

    @property
    def rr_rest_s(self) -> float:
        assert self.info.calibration is not None  # load_session refuses a file without one
        return self.info.calibration.rr_rest_s

    @property
    def mean_rr_norm(self) -> float:
        return self.mean_rr_s / self.rr_rest_s

    @property
    def working_calibration(self) -> bool:
        return self.info.calibration is not None and self.info.calibration.posture == "working"

    @property
    def mean_rr_resting_norm(self) -> float:
        """Mean RR over the level at rest. Calibrated at work (k = 1, in the task), RR_r is the working
        level, so mean RR / RR_r is about 1 in condition (b) by construction; the level at rest, which a
        working calibration keeps beside it, is what the conditions can be compared against. NaN where a
        working calibration kept none."""
        cal = self.info.calibration
        assert cal is not None
        rest = cal.rr_resting_s if cal.posture == "working" else cal.rr_rest_s
        return self.mean_rr_s / rest if rest else float("nan")


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    from mcap.reader import make_reader

    try:
        with path.open("rb") as f:
            return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    except FileNotFoundError:
        raise InputError(f"{path}: no such session file") from None
    except Exception as exc:  # the mcap package raises many kinds on a damaged or unfinished file
        raise InputError(
            f"{path}: incomplete or damaged session file ({type(exc).__name__}: {exc}); a session cut short "
            "with Ctrl-C is complete, one whose recorder was killed is not"
        ) from None


def _struct(path: Path, records: dict[str, dict[str, str]], name: str, typ: type[S]) -> S:
    try:
        return msgspec.json.decode(records[name]["json"], type=typ)
    except (KeyError, msgspec.DecodeError) as exc:
        raise InputError(f"{path}: the {name} record is damaged ({exc})") from None


def read_records(path: Path) -> tuple[SessionInfo, SessionEnd]:
    """A session file's description and end record, without its traffic."""
    records = _metadata(path)
    if SESSION_RECORD not in records:
        raise InputError(
            f"{path}: not a session file (no {SESSION_RECORD} record); `cadence session` writes them"
        )
    info = _struct(path, records, SESSION_RECORD, SessionInfo)
    if SESSION_END_RECORD not in records:
        raise InputError(
            f"{path}: incomplete: no {SESSION_END_RECORD} record (the recorder did not close it)"
        )
    return info, _struct(path, records, SESSION_END_RECORD, SessionEnd)


def load_session(path: Path) -> Session:
    """A session file, checked (see the module's docstring); ``InputError`` says what is wrong."""
    info, end = read_records(path)
    if info.calibration is None:
        raise InputError(
            f"{path}: subject {info.subject}, condition {info.condition}: no calibration, so no RR_r to "
            "normalise by (run the session with --calibrate, or `cadence calibrate` before it)"
        )
    if end.end_ns <= info.start_ns:
        raise InputError(
            f"{path}: the session ends (data time {end.end_ns}) before it starts ({info.start_ns})"
        )
    session = Session(path, info, end)
    cells: set[str] = set()
    clocks: dict[str, list[tuple[int, int]]] = {}
    for rec in read(path):
        parts = rec.key.split("/", 2)
        if len(parts) == 3 and parts[0] == ROOT:
            cells.add(parts[1])
        if rec.encoding != "msgpack":
            continue
        try:
            msg = decode_any(rec.data)
        except msgspec.DecodeError:
            continue  # kept in the file as it came; counted by nothing here
        if len(parts) == 3 and parts[2] in CLOCKED:
            clocks.setdefault(parts[2], []).append((rec.log_time, msg.t_ns))
        if isinstance(msg, HrvWindow):
            session.windows.append(msg)
        elif isinstance(msg, Selection):
            session.selections.append(msg)
        elif isinstance(msg, CycleReport):
            session.cycles.append(msg)
        elif isinstance(msg, OperatorError):
            session.errors.append(msg)
    if cells - {info.cell}:
        raise InputError(
            f"{path}: mixes cells: keys of {', '.join(sorted(cells))} in a session of cell {info.cell}"
        )
    if (problem := clock_problem(clocks)) is not None:
        raise InputError(f"{path}: mixes clocks: {problem}")
    return session


def clock_problem(clocks: dict[str, list[tuple[int, int]]]) -> str | None:
    """Whether the publishers' data clocks disagree, from (log time, data time) pairs per key: each key's
    rate (data time per wall time, first to last) and its offset at the common rate must agree."""
    fits: dict[str, tuple[float, NDArray[np.float64]]] = {}
    for key, pts in clocks.items():
        log = np.array([p[0] for p in pts], dtype=np.float64)
        data = np.array([p[1] for p in pts], dtype=np.float64)
        if len(pts) >= 3 and log[-1] - log[0] >= 2e9:
            fits[key] = ((data[-1] - data[0]) / (log[-1] - log[0]), np.stack([log, data]))
    if len(fits) < 2:
        return None
    rates = {k: r for k, (r, _) in fits.items()}
    slow, fast = min(rates, key=rates.__getitem__), max(rates, key=rates.__getitem__)
    if rates[fast] > RATE_TOLERANCE * max(rates[slow], 1e-9):
        return (
            f"data time runs at {rates[fast]:.3g}× the wall clock on {fast} but {rates[slow]:.3g}× on {slow} "
            "(a replay beside a live cell?)"
        )
    rate = float(np.median(list(rates.values())))
    offsets = {k: float(np.median(ld[1] - rate * ld[0])) for k, (_, ld) in fits.items()}
    early, late = min(offsets, key=offsets.__getitem__), max(offsets, key=offsets.__getitem__)
    if (offsets[late] - offsets[early]) / 1e9 > OFFSET_TOLERANCE_S:
        return (
            f"{late}'s data time is {(offsets[late] - offsets[early]) / 1e9:.0f} s ahead of {early}'s "
            "(an old recording replayed beside a live cell?)"
        )
    return None
