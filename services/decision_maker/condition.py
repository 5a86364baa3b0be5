"""The study's conditions (paper §III-B) as a session sets them on ``decision/condition`` (DESIGN §7).

(c) is Alg. 1 ("adaptive"); (a) and (b) hold one k ("fixed": ``a`` minimum time, k = n; ``b`` minimum
jerk, k = 1; or a number). The condition a session set wins over the config's and is kept in
``condition.json``, so that a restart mid-session stays in it. A session that has just calibrated names
its calibration, and the condition waits for it: the topic and the query travel apart, and (c) must start
from the new RR_r.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import Annotated, Literal

import msgspec

from common.decision import fixed_k
from common.runtime.bus import QueryError
from common.runtime.storage import Loaded, atomic_write, load_checked
from schemas.base import Name, TimeNs
from schemas.decision import MAX_N, Selection
from schemas.topology import CALIBRATION_NOT_YET

CONDITION_FILE = "condition.json"
FixedK = Annotated[int, msgspec.Meta(ge=1, le=MAX_N)] | Literal["a", "b"]


class Condition(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """``condition.json``: the study condition in force, as a session set it on ``decision/condition``."""

    mode: Literal["adaptive", "fixed"]
    fixed_k: FixedK = "a"
    t_ns: TimeNs = 0
    by: Name = ""


def load_condition(data_dir: Path) -> Loaded[Condition]:
    return load_checked(data_dir / CONDITION_FILE, lambda b: msgspec.json.decode(b, type=Condition))


def store_condition(data_dir: Path, condition: Condition) -> None:
    atomic_write(data_dir / CONDITION_FILE, msgspec.json.format(msgspec.json.encode(condition), indent=1))


def fixed_selection(preset: int | str, n: int, t_ns: int, seq: int = 0) -> Selection:
    """A fixed condition's selection: one k, stated once, republished like any other. ``seq``: the
    decider's last, so a selection captured before it is older by seq and by stamp (the executor refuses
    such a one: DESIGN §8)."""
    return Selection(t_ns=t_ns, seq=seq, k=fixed_k(preset, n), n=n, delta=0, reason="fixed")


def parse_condition(p: dict[str, str], n: int, t_ns: int) -> Condition:
    """``mode=fixed;k=a`` (``a``, ``b`` or a number) or ``mode=adaptive``, with ``by=<who>``: a QueryError
    says what is wrong, so the session that asked can tell its user."""
    mode, k, by = p.get("mode", ""), p.get("k", "a"), p.get("by", "")[:200]
    if mode not in ("adaptive", "fixed"):
        raise QueryError(f"mode={mode!r}: expected mode=adaptive or mode=fixed;k=a|b|<1…{n}>")
    preset: int | str = int(k) if k.isdecimal() else k
    try:
        fixed_k(preset, n)
    except ValueError as exc:
        raise QueryError(f"k={k}: {exc}") from None
    return Condition(mode=mode, fixed_k=preset, t_ns=t_ns, by=by)  # type: ignore[arg-type]


class Conditions:
    """The condition in force, its fixed selection (None while adaptive), and the calibrations that have
    reached the service (their t_ns: a session asks after its own)."""

    def __init__(self, configured: Condition, n: int) -> None:
        self.n = n
        self.current = configured
        self.fixed: Selection | None = None
        self.calibrations_seen: deque[int] = deque(maxlen=16)

    def resume(self, data_dir: Path) -> list[str]:
        """The condition a session stored, over the configured one; what was wrong with the file."""
        stored = load_condition(data_dir)
        problems = [stored.problem] if stored.problem else []
        if stored.value is not None:
            try:
                fixed_k(stored.value.fixed_k, self.n)
                self.current = stored.value
            except ValueError as exc:
                problems.append(f"{CONDITION_FILE}: {exc} (n = {self.n}); the config's condition holds")
        return problems

    def apply(self, c: Condition, t_ns: int, calibrated: bool, seq: int = 0) -> str:
        """Put ``c`` in force; the service's state that says so."""
        self.current = c
        self.fixed = fixed_selection(c.fixed_k, self.n, t_ns, seq) if c.mode == "fixed" else None
        if self.fixed is not None:
            return f"fixed at k = {self.fixed.k} of {self.n} (fixed_k = {c.fixed_k!r})"
        return "running" if calibrated else "waiting for calibration"

    def requested(self, params: dict[str, str], t_ns: int) -> Condition:
        """The condition a session asks for, once the calibration it names (if any) is in force."""
        c = parse_condition(params, self.n, t_ns)
        wanted = params.get("calibration")
        if wanted is not None and (not wanted.isdecimal() or int(wanted) not in self.calibrations_seen):
            raise QueryError(f"{CALIBRATION_NOT_YET}: calibration {wanted[:40]}")
        return c
