"""The paper's evaluation (§III-C, §IV) on simulated operators: conditions (a) minimum time (k = N
throughout), (b) minimum jerk (k = 1) and (c) tuned online (Alg. 1 on the operator's 30 s windows).

A simulation, labelled as such wherever it is shown: each subject is an operator twin (common/sim/twin.py)
with its own seed, resting RR and tolerance. Simulated time runs as fast as the machine allows: the robot's
cycle is played from the Pareto sets' exact trajectories (joint velocities at ``OBSERVE_HZ``), and the
operator's beats are windowed directly (the closed-loop demo covers ECG synthesis and detection).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from common.decision import Params, State, k_for_path, step
from common.hrv.stream import intervals, window_stats
from common.sim.twin import Operator, TwinParams
from common.trajectory import bspline as bs
from common.trajectory.task import Task

OBSERVE_HZ = 20.0  # how often the operator "sees" the robot's joint velocities
WINDOW_S = 30.0
CONDITIONS = ("a", "b", "c")
NAMES = {"a": "minimum time", "b": "minimum jerk", "c": "tuned online"}


@dataclass(frozen=True, slots=True)
class Subject:
    index: int
    seed: int
    rr_rest_s: float
    tolerance: float

    def twin(self) -> TwinParams:
        return TwinParams(seed=self.seed, rr_rest_s=self.rr_rest_s, tolerance=self.tolerance)


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


def simulate(
    task: Task,
    moves: dict[tuple[str, int], Motion],
    n_per_path: dict[str, int],
    subject: Subject,
    condition: str,
    minutes: float,
) -> Outcome:
    op = Operator(subject.twin())
    params = Params.of(subject.rr_rest_s, max(n_per_path.values()))
    state = State.initial(params)
    n = max(n_per_path.values())
    fixed = {"a": n, "b": 1}.get(condition)
    t, end = 0.0, minutes * 60.0
    cycles = errors = 0
    beats: list[float] = [op.beats[-1]]
    win_start, rr_norm, ks = 0.0, [], []

    def idle(seconds: float) -> None:
        nonlocal t
        for x in np.arange(t, t + seconds, 1.0 / OBSERVE_HZ):
            op.observe(float(x), np.zeros(6))
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
                rr_norm.append(w.mean_rr_s / subject.rr_rest_s)
            state = step(params, state, w.mean_rr_s, w.quality == "good").state
            win_start += WINDOW_S
            del beats[: max(0, next((i for i, b in enumerate(beats) if b >= win_start - 10.0), 0))]

    while t < end:
        for s in task.cycle:
            if s.move is not None:
                k = k_for_path(fixed if fixed is not None else state.k, n_per_path[s.move])
                ks.append(k)
                t_f, qd = moves[(s.move, k)]
                for i, v in enumerate(qd):
                    op.observe(t + i / OBSERVE_HZ, v)
                t += t_f
            elif s.wait is not None:
                idle(s.wait)
            elif s.wait_for is not None:
                op.advance(t)
                idle(op.handling_time())
            close_windows()
        cycles += 1
        op.advance(t)
        errors += int(op.makes_error())
    return Outcome(
        subject.index,
        condition,
        cycles,
        errors,
        t / 60.0,
        float(np.mean(rr_norm)) if rr_norm else float("nan"),
        ks,
    )


METRICS = ("productivity_per_min", "error_rate", "mean_rr_norm")


def compare(outcomes: list[Outcome]) -> dict:
    """Per condition mean ± sd of φ, ε and normalised mean RR; Wilcoxon signed-rank p-values (paired by
    subject) for a–b, a–c and b–c, as in the paper's Table I."""
    from scipy.stats import wilcoxon

    by = {c: sorted((o for o in outcomes if o.condition == c), key=lambda o: o.subject) for c in CONDITIONS}

    def mean_sd(values: list[float]) -> list[float]:
        return [float(np.mean(values)), float(np.std(values, ddof=1)) if len(values) > 1 else 0.0]

    table = {c: {m: mean_sd([getattr(o, m) for o in by[c]]) for m in METRICS} for c in CONDITIONS}
    tests: dict[str, dict[str, object]] = {}
    for a, b in (("a", "b"), ("a", "c"), ("b", "c")):
        tests[f"{a}-{b}"] = {}
        for m in METRICS:
            x = np.array([getattr(o, m) for o in by[a]])
            y = np.array([getattr(o, m) for o in by[b]])
            diff = float(np.median(y - x))
            p = float(wilcoxon(x, y).pvalue) if np.any(x != y) else 1.0
            tests[f"{a}-{b}"][m] = {"p": p, "median_difference": diff}
    return {"means_sd": table, "wilcoxon": tests}
