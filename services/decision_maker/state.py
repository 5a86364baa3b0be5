"""The decision maker's state and its file (DESIGN §7, §9): k, RR_{i-1}, the last window answered and the
selection that announced them, for one calibration, and what it knows of the wearer's movement at work. The
file is validated on load as strictly as a message; a damaged one is moved aside and the service starts afresh
at the initial k."""

from __future__ import annotations

import logging
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Annotated, NamedTuple

import msgspec

from common.decision import Params, Personal, PersonalState, State, Step, personal_step, reanchored, step
from common.hrv.calibration import load_calibration
from common.hrv.movement import Baseline, baseline_of, moved
from common.runtime.admission import SKEW_S, TimeLine
from common.runtime.node import admitted
from common.runtime.storage import Loaded, atomic_write, load_checked
from schemas.base import MAX_TIME_NS, RR_MAX_S, RR_MIN_S, NonNegInt, RrSeconds, TimeNs
from schemas.decision import MAX_N, Reason, Selection, SolutionIndex
from schemas.hrv import HrvWindow
from schemas.operator import Calibration

log = logging.getLogger("cadence.decision_maker")

STATE_FILE = "decision_state.json"
# Windows come every 30 s. One that starts more than this after the last answered is out of line (a
# broken clock, a hostile message) until a second one agrees with it; one that ends within this before it
# is a duplicate (a replay, a republish), answered already.
WINDOW_AHEAD_S = 600.0
WINDOW_DUPLICATE_S = 600.0


class PersonalRecord(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """The personal mode's state beside k (common/decision.py ``PersonalState``), persisted with it."""

    ref: RrSeconds
    sum_rr: Annotated[float, msgspec.Meta(ge=0.0, le=1e9)] = 0.0
    sum_n: Annotated[float, msgspec.Meta(ge=0.0, le=1e9)] = 0.0
    effort: Annotated[float, msgspec.Meta(ge=-RR_MAX_S, le=0.0)] = 0.0


class DecisionRecord(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """``decision_state.json``. ``last_end_ns`` is -1 before the first window of a calibration."""

    calibration: Calibration
    n: SolutionIndex
    k: SolutionIndex
    rr_prev: str  # RR_{i-1} as the decimal it was written as (common/decision.py)
    last_end_ns: Annotated[int, msgspec.Meta(ge=-1, le=MAX_TIME_NS)]
    seq: NonNegInt
    delta: Annotated[int, msgspec.Meta(ge=-MAX_N, le=MAX_N)]
    reason: Reason
    t_ns: TimeNs
    window_end_ns: TimeNs | None
    movement: Baseline = Baseline()
    personal: PersonalRecord | None = None  # the personal mode's state (``decide = "personal"``)

    def __post_init__(self) -> None:
        if self.k > self.n:
            raise ValueError(f"k = {self.k} is above n = {self.n}")
        try:
            rr = Decimal(self.rr_prev)
        except InvalidOperation:
            raise ValueError(f"rr_prev = {self.rr_prev!r} is not a number") from None
        if not (rr.is_finite() and Decimal(str(RR_MIN_S)) <= rr <= Decimal(str(RR_MAX_S))):
            raise ValueError(f"rr_prev = {self.rr_prev!r} is not an RR a heart has ({RR_MIN_S}–{RR_MAX_S} s)")

    @property
    def state(self) -> State:
        return State(self.k, Decimal(self.rr_prev))


def params_of(cal: Calibration, n: int) -> Params:
    return Params.of(cal.rr_rest_s, n, cal.sigma_rest_s, cal.rr_stress_offset_s, cal.sigma_stress_s)


def same_calibration(a: Calibration, b: Calibration) -> bool:
    return msgspec.structs.replace(a, t_ns=0, seq=0) == msgspec.structs.replace(b, t_ns=0, seq=0)


def load_record(path: Path) -> Loaded[DecisionRecord]:
    return load_checked(path, lambda b: msgspec.json.decode(b, type=DecisionRecord))


class MovementRule(NamedTuple):
    """When a window is held for movement (common/hrv/movement.py, ``moved``)."""

    margin_mg: float = 40.0
    back_s: float = 0.02  # the hold ends when mean RR is back within this of RR before the effort (Δ_rs)
    max_hold_s: float = 300.0  # or this long after the last moving window, RR_{i-1} then re-anchored
    learn_windows: int = 4


class Decider:
    """The service's state. A change is proposed as a new record, persisted, and only then adopted and
    announced (``commit``), so what is published is always what a restart would resume."""

    def __init__(
        self,
        data_dir: Path,
        n: int,
        rule: MovementRule | None = None,
        skew_s: float = SKEW_S,
        personal: Personal | None = None,
    ) -> None:
        """``personal``: decide in the personal mode with these settings; None: the paper's Alg. 1."""
        self.path = data_dir / STATE_FILE
        self.n = n
        self.rule = rule or MovementRule()
        self.personal = personal
        self.record: DecisionRecord | None = None
        self.params: Params | None = None
        self.skew_s = skew_s
        self.line = self.new_line()
        self.issued = 0  # the highest seq this decider has published (a fixed condition's included)
        self.applied = 0  # the seq of the selection in force at the executor, as its robot/state says

    def next_seq(self) -> int:
        """The next selection's seq: after every one this decider published and the one in force at the
        executor (DESIGN §8). A restart whose state file was moved aside resumes after the executor's, not
        from 1; and one a rogue with this account took is passed at once."""
        return max(self.record.seq if self.record is not None else 0, self.issued, self.applied) + 1

    def new_line(self) -> TimeLine:
        return TimeLine(WINDOW_AHEAD_S, duplicate_s=WINDOW_DUPLICATE_S, skew_s=self.skew_s)

    @property
    def selection(self) -> Selection | None:
        """The record's, with the thresholds of the parameters in force, so that whoever watches k sees
        what it was decided against."""
        r, p = self.record, self.params
        if r is None or p is None:
            return None

        def positive(x: Decimal) -> float | None:  # a calibration at a very fast rest leaves no RR_s^max
            return float(x) if x > 0 else None

        return Selection(
            t_ns=r.t_ns,
            seq=r.seq,
            k=r.k,
            n=r.n,
            delta=r.delta,
            reason=r.reason,
            window_end_ns=r.window_end_ns,
            rr_rest_s=positive(p.rr_rest),
            rr_stress_s=positive(p.rr_stress),
            rr_stress_max_s=positive(p.rr_stress_max),
        )

    def calibrated(self, cal: Calibration, t_ns: int) -> DecisionRecord | None:
        """The record that starts a calibration at the initial k; None when it is the one in use."""
        if self.record is not None and same_calibration(self.record.calibration, cal):
            return None
        return self.starting(cal, t_ns)

    def starting(self, cal: Calibration, t_ns: int) -> DecisionRecord:
        """Alg. 1 at its initial k on ``cal`` (a session of condition (c) starts there again)."""
        initial = State.initial(params_of(cal, self.n))
        seq = self.next_seq()
        if cal.posture == "working" and cal.movement_mg is not None:  # the task's own level
            movement = baseline_of(cal.movement_mg, cal.movement_sd_mg)
        elif self.record is not None and same_calibration(self.record.calibration, cal):
            movement = Baseline(self.record.movement.level_mg, self.record.movement.sd_mg)
        else:  # learnt from the first windows at work: a calibration at rest says nothing of it
            movement = Baseline()
        return DecisionRecord(
            calibration=cal,
            n=self.n,
            k=initial.k,
            rr_prev=str(initial.rr_prev),
            last_end_ns=-1,
            seq=seq,
            delta=0,
            reason="initial",
            t_ns=t_ns,
            window_end_ns=None,
            movement=movement,
        )

    def admit(self, w: HrvWindow, clock_ns: int) -> bool:
        """Whether the window's time line starts afresh with it (logged); ``Rejected`` for a window that
        must not be answered (common/runtime/admission.py: answered already, far from the others)."""
        verdict = self.line.admit(w.start_ns, w.end_ns, clock_ns=clock_ns)
        admitted(verdict)
        if verdict.action == "restart":
            log.warning("hrv/window: %s", verdict.detail)
        return verdict.action == "restart"

    def answer(self, w: HrvWindow) -> DecisionRecord:
        """Alg. 1 (or the personal mode) on a window that the time line admitted."""
        assert self.record is not None and self.params is not None
        rec, good = self.record, w.quality == "good" and w.mean_rr_s is not None
        rr = w.mean_rr_s if good else None
        held, movement, reanchor = moved(rec.movement, w.movement_mg, w.start_ns, w.end_ns, rr,
                                         float(rec.rr_prev), *self.rule)  # fmt: skip
        personal = rec.personal
        if held and good:  # mean RR says nothing of mental load while the body works: k and RR_{i-1} stay
            r = Step(rec.state, 0, "movement")
        elif reanchor and rr is not None:  # held its longest: read from here on, with no step for the effort
            r = Step(State(rec.k, Decimal(str(rr))), 0, "movement")
            if self.personal is not None:  # the mode's own state too (common/decision.py ``reanchored``)
                after = reanchored(self.personal_state(rec), rr, w.n_beats)
                personal = PersonalRecord(after.ref, after.sum_rr, after.sum_n, after.effort)
        elif self.personal is not None:
            # a window held only for how few beats it has (a wrist's) still says something, at its weight
            usable = good or (w.quality == "low" and w.reason == "coverage")
            before = self.personal_state(rec)
            length_s = (w.end_ns - w.start_ns) / 1e9
            after, delta, reason = personal_step(self.params, self.personal, before, w.mean_rr_s, w.n_beats,
                                                 usable and not held, length_s)  # fmt: skip
            rr_prev = Decimal(str(w.mean_rr_s)) if good else rec.state.rr_prev
            r = Step(State(after.k, rr_prev), delta, reason)
            personal = PersonalRecord(after.ref, after.sum_rr, after.sum_n, after.effort)
        else:
            r = step(self.params, rec.state, w.mean_rr_s, good_quality=good)
        return msgspec.structs.replace(
            rec,
            movement=movement,
            k=r.state.k,
            rr_prev=str(r.state.rr_prev),
            last_end_ns=w.end_ns,
            seq=self.next_seq(),
            delta=r.delta,
            reason=r.reason,
            t_ns=w.end_ns,
            window_end_ns=w.end_ns,
            personal=personal,
        )

    def personal_state(self, rec: DecisionRecord) -> PersonalState:
        assert self.params is not None
        if rec.personal is None:  # from the calibration: its RR_r, at the k in force
            return PersonalState(rec.k, float(self.params.rr_rest))
        r = rec.personal
        return PersonalState(rec.k, r.ref, r.sum_rr, r.sum_n, r.effort)

    def commit(self, record: DecisionRecord, resumed: bool = False) -> None:
        fresh = self.record is None or not same_calibration(self.record.calibration, record.calibration)
        self.record, self.params = record, params_of(record.calibration, self.n)
        self.issued = max(self.issued, record.seq)
        if fresh:
            self.line = self.new_line()
            if resumed and record.last_end_ns >= 0:
                self.line.anchor(record.last_end_ns)

    def persist(self, record: DecisionRecord) -> None:
        atomic_write(self.path, msgspec.json.format(msgspec.json.encode(record), indent=1))


def calibration_in_force(data_dir: Path, rr_rest_s: float | None, problems: list[str]) -> Calibration | None:
    """The calibration `cadence calibrate` stored (``load_calibration``), else one from the config's
    ``rr_rest_s``."""
    loaded = load_calibration(data_dir)
    if loaded.problem:
        problems.append(loaded.problem)
    if loaded.value is not None:
        return loaded.value
    if rr_rest_s is not None:
        return Calibration(t_ns=0, seq=0, subject="config", rr_rest_s=rr_rest_s)
    return None


def resume(decider: Decider, data: Path, rr_rest_s: float | None) -> list[str]:
    """Resume the persisted state, or start at the initial k; what was wrong with the files on disk."""
    problems: list[str] = []
    cal = calibration_in_force(data, rr_rest_s, problems)
    loaded = load_record(decider.path)
    if loaded.problem:
        problems.append(loaded.problem)
    rec = loaded.value
    if rec is not None and rec.n != decider.n:
        log.info("%s was written for n = %d, not %d: starting afresh", decider.path, rec.n, decider.n)
        rec = None
    if rec is not None and (cal is None or same_calibration(rec.calibration, cal)):
        decider.commit(rec, resumed=True)
        log.info("resumed at k = %d", rec.k)
    elif cal is not None and (fresh := decider.calibrated(cal, 0)) is not None:
        decider.commit(fresh)
    for p in problems:
        log.error("%s", p)
    return problems
