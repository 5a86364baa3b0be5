"""The paper's evaluation (§III-C, §IV) on simulated operators: conditions (a) minimum time (k = N
throughout), (b) minimum jerk (k = 1) and (c) tuned online (Alg. 1 on the operator's 30 s windows).

A simulation, labelled as such wherever it is shown: each subject is an operator twin (common/sim/twin.py)
with its own seed, resting RR and tolerance. Simulated time runs as fast as the machine allows: the robot's
cycle is played from the Pareto sets' exact trajectories (joint velocities at ``OBSERVE_HZ``), and the
operator's beats are windowed directly (the closed-loop demo covers ECG synthesis and detection).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np
from numpy.typing import NDArray

from cadence.lab.session_file import SessionWriter, software, task_digest
from common.decision import Params, State, k_for_path, step
from common.hrv.calibration import calibration
from common.hrv.stream import intervals, window_message, window_stats, windows
from common.runtime.numeric import numeric_build
from common.sim.twin import Operator, TwinParams
from common.trajectory import bspline as bs
from common.trajectory.task import Task
from schemas import Calibration, CycleReport, Message, OperatorError, Selection
from schemas.decision import Reason
from schemas.operator import ErrorKind
from schemas.session import Condition, SessionEnd, SessionInfo
from schemas.topology import HRV_WINDOW, OPERATOR_ERROR, ROBOT_CYCLE, SELECTION, validated
from services.registry import EXECUTOR

OBSERVE_HZ = 20.0  # how often the operator "sees" the robot's joint velocities
WINDOW_S = 30.0
Model = dict[str, float]  # TwinParams fields shared by a cohort, e.g. a fit's handling_s
CONDITIONS = ("a", "b", "c")
NAMES = {"a": "minimum time", "b": "minimum jerk", "c": "tuned online"}


@dataclass(frozen=True, slots=True)
class Subject:
    index: int
    seed: int
    rr_rest_s: float
    tolerance: float

    @property
    def name(self) -> str:
        """The subject's ID in session files and their calibration."""
        return f"twin-{self.index:02d}"

    def twin(self, model: Model | None = None) -> TwinParams:
        """This subject's twin; ``model`` overrides the parameters all subjects share (a fit's)."""
        p = TwinParams(seed=self.seed, rr_rest_s=self.rr_rest_s, tolerance=self.tolerance)
        return msgspec.convert(msgspec.structs.asdict(p) | (model or {}), TwinParams)


def subjects(n: int, seed: int) -> list[Subject]:
    """A simulated cohort: resting RR and tolerance drawn per subject (seeded)."""
    rng = np.random.default_rng(seed)
    return [
        Subject(
            i + 1,
            int(rng.integers(1, 2**31 - 1)),
            float(np.clip(rng.normal(0.85, 0.07), 0.65, 1.1)),
            float(np.clip(rng.normal(0.8, 0.1), 0.5, 1.1)),
        )
        for i in range(n)
    ]


@dataclass(frozen=True, slots=True)
class Outcome:
    subject: int
    condition: str
    cycles: int
    errors: int
    minutes: float
    mean_rr_norm: float  # mean of the good windows' mean RR over the subject's resting RR
    ks: list[int]

    @property
    def productivity_per_min(self) -> float:
        return self.cycles / self.minutes

    @property
    def error_rate(self) -> float:
        return self.errors / self.cycles if self.cycles else 0.0


Motion = tuple[float, NDArray[np.float64]]  # (t_f, joint velocities at OBSERVE_HZ)


def motions(task: Task, solutions: dict[str, list[NDArray[np.float64]]]) -> dict[tuple[str, int], Motion]:
    """Every (path, k)'s duration and sampled velocities, computed once for the whole study."""
    out = {}
    for pid, hs in solutions.items():
        path = task.paths[pid]
        for k, h in enumerate(hs, start=1):
            t_f = float(np.sum(h))
            t = np.arange(0.0, t_f, 1.0 / OBSERVE_HZ)
            qd = bs.evaluate_dense(h, path.waypoints, path.boundary, t)[1]
            out[(pid, k)] = (t_f, qd)
    return out


# where simulated data time starts (2026-01-01T00:00Z): any fixed origin would do
ORIGIN_NS = 1_767_225_600 * 10**9


def calibrate_twin(subject: Subject, minutes: float, model: Model | None = None) -> Calibration:
    """The subject at rest for ``minutes``, windowed and made into a calibration as `cadence calibrate`
    makes one: RR_r is measured, not the twin's parameter."""
    op = Operator(subject.twin(model))
    end = minutes * 60.0
    ts = np.arange(0.0, end + 15.0, 1.0 / OBSERVE_HZ)
    op.observe_all(ts, np.zeros((len(ts), 6)))
    op.advance(end + 15.0)
    iv = intervals(np.array(op.beats_until(end + 15.0)))
    wins = windows(iv, WINDOW_S, 0.0, end)
    return calibration(wins, subject.name, ORIGIN_NS, measured_sigma=False)[0]


def simulate(
    task: Task,
    moves: dict[tuple[str, int], Motion],
    n_per_path: dict[str, int],
    subject: Subject,
    condition: str,
    minutes: float,
    cal: Calibration | None = None,
    out: SessionWriter | None = None,
    model: Model | None = None,
) -> Outcome:
    """One subject in one condition. ``out``: the messages a live cell would carry (windows, selections,
    cycles, errors), on data time from ``ORIGIN_NS``, go into that session file."""
    op = Operator(subject.twin(model))
    rr_rest = cal.rr_rest_s if cal is not None else subject.rr_rest_s
    n = max(n_per_path.values())
    params = Params.of(rr_rest, n)
    state = State.initial(params)
    fixed = {"a": n, "b": 1}.get(condition)
    t, end = 0.0, minutes * 60.0
    cycles = 0
    cycle_ends: list[float] = []
    error_times: list[float] = []
    beats: list[float] = [op.beats[-1]]
    win_start, rr_norm, ks = 0.0, [], []
    seq = dict.fromkeys(("window", "selection", "cycle", "error"), 0)

    def emit(suffix: str, what: str, msg: Message) -> None:
        if out is not None:
            out.put(suffix, validated(msg), msg.t_ns)
        seq[what] += 1

    def ns(t_s: float) -> int:
        return ORIGIN_NS + round(t_s * 1e9)

    def select(t_s: float, delta: int, reason: Reason, window_end: int | None) -> None:
        k = fixed if fixed is not None else state.k
        sel = Selection(
            t_ns=ns(t_s), seq=seq["selection"], k=k, n=n, delta=delta, reason=reason, window_end_ns=window_end
        )
        emit(SELECTION.suffix, "selection", sel)

    select(0.0, 0, "fixed" if fixed is not None else "initial", None)

    def error(t_s: float, kind: ErrorKind, source: str, description: str) -> None:
        error_times.append(t_s)
        msg = OperatorError(t_ns=ns(t_s), seq=seq["error"], cycle=cycles, kind=kind, source=source,
                            description=description)  # fmt: skip
        emit(OPERATOR_ERROR.suffix, "error", msg)

    def idle(seconds: float) -> None:
        nonlocal t
        ts = np.arange(t, t + seconds, 1.0 / OBSERVE_HZ)
        op.observe_all(ts, np.zeros((len(ts), 6)))
        t += seconds

    def close_windows() -> None:
        nonlocal win_start, state
        beats.extend(op.beats_until(t))
        while win_start + WINDOW_S + 5.0 <= beats[-1]:  # the following beats exist for the cleaning
            iv = intervals(
                np.array([b for b in beats if win_start - 10.0 <= b < win_start + WINDOW_S + 10.0])
            )
            w = window_stats(win_start, win_start + WINDOW_S, iv)
            if w.mean_rr_s is not None and w.quality == "good":
                rr_norm.append((w.mean_rr_s / rr_rest, w.end_s))
            emit(HRV_WINDOW.suffix, "window", window_message(w, ORIGIN_NS, seq["window"]))
            if fixed is None:
                r = step(params, state, w.mean_rr_s, w.quality == "good")
                state = r.state
                select(w.end_s, r.delta, r.reason, ns(w.end_s))
            win_start += WINDOW_S
            del beats[: max(0, next((i for i, b in enumerate(beats) if b >= win_start - 10.0), 0))]

    while t < end:
        start = t
        used: dict[str, int] = {}
        for s in task.cycle:
            if s.move is not None:
                k = k_for_path(fixed if fixed is not None else state.k, n_per_path[s.move])
                ks.append(k)
                used[s.move] = k
                t_f, qd = moves[(s.move, k)]
                op.observe_all(t + np.arange(len(qd)) / OBSERVE_HZ, np.asarray(qd, dtype=float))
                t += t_f
            elif s.wait is not None:
                idle(s.wait)
            elif s.wait_for is not None:
                op.advance(t)
                handling = op.handling_time()
                if s.deadline is not None and handling > s.deadline:  # the executor's late error
                    then = "kept waiting" if s.on_late == "wait" else "went on without it"
                    error(t + s.deadline, "late", EXECUTOR.name, f"'{s.wait_for}' late: {then}")
                    if s.on_late == "go_on":
                        handling = s.deadline
                idle(handling)
            close_windows()
        report = CycleReport(
            t_ns=ns(t), seq=seq["cycle"], cycle=cycles, cycle_time_s=t - start, k_per_path=used
        )
        emit(ROBOT_CYCLE.suffix, "cycle", report)
        cycle_ends.append(t)
        op.advance(t)
        if op.makes_error():  # as the twin in the ECG gateway does at each cycle's report
            error(t, "wrong_object", "twin", f"simulated (stress {op.stress:.2f})")
        cycles += 1
    # the session ends at its planned minutes, as a live one does: the cycle running then (recorded, as
    # live) ends after it and is not counted, nor what it brought
    counted = sum(1 for c in cycle_ends if c <= end)
    return Outcome(
        subject.index,
        condition,
        counted,
        sum(1 for e in error_times if e <= end),
        minutes,
        float(np.mean([r for r, e in rr_norm if e <= end])) if rr_norm else float("nan"),
        ks,
    )


def session_info(
    subject: Subject,
    condition: Condition,
    cal: Calibration,
    minutes: float,
    task_path: Path,
    model: Model,
    sets: str = "",
) -> SessionInfo:
    return SessionInfo(
        subject=subject.name,
        condition=condition,
        cell="simulated",
        calibration=cal,
        start_ns=ORIGIN_NS,
        minutes=minutes,
        task=task_path.name,
        task_sha256=task_digest(task_path),
        software=software(),
        simulated=True,
        sets_sha256=sets,
        build=numeric_build(),
        notes=f"operator twin: seed {subject.seed}, resting RR {subject.rr_rest_s:.3f} s, "
        f"tolerance {subject.tolerance:.2f}" + "".join(f", {k} {v:.4g}" for k, v in model.items()),
    )


def simulate_session(
    task: Task,
    task_path: Path,
    moves: dict[tuple[str, int], Motion],
    n_per_path: dict[str, int],
    subject: Subject,
    cal: Calibration,
    condition: Condition,
    minutes: float,
    path: Path,
    model: Model | None = None,
    sets: str = "",
) -> Outcome:
    """One session file, as a live `cadence session` writes it, for a twin subject; ``sets``: the digest
    of the planned sets ``moves`` come from."""
    info = session_info(subject, condition, cal, minutes, task_path, model or {}, sets)
    writer = SessionWriter(path, info.cell)
    writer.begin(info)
    try:
        outcome = simulate(task, moves, n_per_path, subject, condition, minutes, cal, writer, model)
    except BaseException:
        writer.close(SessionEnd(end_ns=ORIGIN_NS + 1, complete=False, reason="the simulation failed"))
        raise
    writer.close(SessionEnd(end_ns=ORIGIN_NS + round(minutes * 60e9), complete=True, reason="on time"))
    return outcome
