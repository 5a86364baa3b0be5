"""`cadence bench plan` and `cadence bench replan`: the planner's time and front against the paper's
baseline (a stop at every waypoint) and the naive planner, the re-planning of an edited path, and the
front's convergence over generations."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from msgspec import structs
from numpy.typing import NDArray

from cadence.bench.naive import evaluate_naive
from cadence.bench.protocol import Side, interleaved, protocol, sides_json
from common.robot.ur16e import JointLimits
from common.trajectory.planner import (
    TrajectoryProblem,
    evaluate,
    hypervolume,
    plan_path,
)
from common.trajectory.task import PathPlan, PlannerSettings, Task


def longest_path(task: Task) -> PathPlan:
    """Most waypoints; ties broken by the longest lower-bound time."""

    def key(p: PathPlan) -> tuple[int, float]:
        lb = np.max(np.abs(np.diff(p.waypoints, axis=0)) / task.limits.velocity, axis=1).sum()
        return len(p.waypoints), float(lb)

    return max(task.paths.values(), key=key)


def ruckig_stop_at_every_waypoint(path: PathPlan, limits: JointLimits) -> float | None:
    """Time of the same motion as jerk-limited time-optimal moves that stop at every waypoint (Ruckig).

    None when the optional `ruckig` package is absent (`uv sync --extra bench`).
    """
    try:
        from ruckig import InputParameter, Result, Ruckig, Trajectory
    except ImportError:
        return None
    d = path.waypoints.shape[1]
    otg = Ruckig(d)
    total = 0.0
    for a, b in zip(path.waypoints[:-1], path.waypoints[1:], strict=True):
        inp = InputParameter(d)
        inp.current_position = a.tolist()
        inp.current_velocity = [0.0] * d
        inp.current_acceleration = [0.0] * d
        inp.target_position = b.tolist()
        inp.target_velocity = [0.0] * d
        inp.target_acceleration = [0.0] * d
        inp.max_velocity = limits.velocity.tolist()
        inp.max_acceleration = limits.acceleration.tolist()
        inp.max_jerk = limits.jerk.tolist()
        traj = Trajectory(d)
        if otg.calculate(inp, traj) not in (Result.Working, Result.Finished):
            raise RuntimeError("ruckig could not compute a segment")
        total += traj.duration
    return total


@dataclass(frozen=True, slots=True)
class PlanBench:
    """The longest path planned by the array engine beside the straightforward evaluation, in the same run
    under the timing protocol (cadence/bench/protocol.py): medians of CPU seconds, equal tries."""

    path_id: str
    n_waypoints: int
    generations: int
    population: int
    plan: dict[str, Side]  # "fast" and "naive": a whole plan
    evaluation: dict[str, Side]  # "fast" and "naive": one generation's evaluation
    hv: float
    naive_hv: float
    tf_exact: float
    tf_hull: float
    tf_ruckig: float | None
    protocol: dict[str, Any]

    @property
    def plan_s(self) -> float:
        return self.plan["fast"].cpu

    @property
    def naive_plan_s(self) -> float:
        return self.plan["naive"].cpu

    @property
    def eval_ms(self) -> float:
        return self.evaluation["fast"].cpu * 1e3

    @property
    def naive_eval_ms(self) -> float:
        return self.evaluation["naive"].cpu * 1e3

    @property
    def plan_ratio(self) -> float:
        return self.naive_plan_s / self.plan_s

    @property
    def eval_ratio(self) -> float:
        return self.naive_eval_ms / self.eval_ms


EVAL_TRIES = 5  # one generation's evaluation takes milliseconds: this many tries of each per plan's try


def bench_plan(task: Task, settings: PlannerSettings, repeat: int = 3) -> PlanBench:
    """Planning time of the longest path against the straightforward evaluation, in the same run."""
    path = longest_path(task)
    exact = structs.replace(settings, constraints="exact")
    plan, last = interleaved({"fast": lambda: plan_path(path, task.limits, exact),
                              "naive": lambda: plan_path(path, task.limits, exact, evaluator=evaluate_naive)},
                             repeat)  # fmt: skip
    fast, slow = last["fast"], last["naive"]
    hull = plan_path(path, task.limits, structs.replace(settings, constraints="hull"))

    # One generation's evaluation, both ways, on the same population.
    problem = TrajectoryProblem(path, task.limits, "exact", settings.kappa)
    rng = np.random.default_rng(settings.seed)
    pop = np.exp(rng.uniform(np.log(problem.lb), np.log(problem.ub), (settings.population, len(problem.lb))))
    evaluation, _ = interleaved({"fast": lambda: evaluate(pop, path, task.limits, "exact"),
                                 "naive": lambda: evaluate_naive(pop, path, task.limits, "exact")},
                                repeat * EVAL_TRIES)  # fmt: skip

    both = np.concatenate([fast.front, slow.front])
    ideal, nadir = both.min(axis=0), both.max(axis=0)
    return PlanBench(
        path_id=path.id,
        n_waypoints=len(path.waypoints),
        generations=fast.generations,
        population=settings.population,
        plan=plan,
        evaluation=evaluation,
        hv=hypervolume(fast.front, ideal, nadir),
        naive_hv=hypervolume(slow.front, ideal, nadir),
        tf_exact=fast.solutions[-1].t_f,
        tf_hull=hull.solutions[-1].t_f,
        tf_ruckig=ruckig_stop_at_every_waypoint(path, task.limits),
        protocol=protocol(repeat, 1),
    )


@dataclass(frozen=True, slots=True)
class Replanning:
    """Today's planner (pymoo's loop, one path after the other) beside the fast one, in the same run, under
    the timing protocol (cadence/bench/protocol.py): equal tries, interleaved, CPU of the process tree and
    wall, medians; the whole task on one process on both sides, and the fast one's parallel figure apart.

    Hypervolumes are shares of a long reference run's (``reference_generations``, another seed) under its
    normalisation, per path; the edit moves the middle waypoint of every path by ``edit_deg`` on every
    joint and plans it again warm (seeded by the last set) and cold.
    """

    path_id: str
    workers: int  # the fast engine's parallel run only (``task_parallel_s``)
    reference_generations: int
    tries: int
    one_path: dict[str, Side]  # the longest path: "cadence" and "pymoo"
    whole_task: dict[str, Side]  # every path on one process: "cadence" and "pymoo"
    task_parallel_s: float  # every path, fast engine, ``workers`` forked processes, pool start-up included
    warm_s: float  # every edited path, warm, in the pool
    hv: dict[str, float]  # path → share, fast engine, cold
    pymoo_hv: dict[str, float]
    warm_hv: dict[str, float]
    edit_deg: float
    protocol: dict[str, Any]

    @property
    def path_ratio(self) -> float:
        """pymoo's CPU over the fast engine's, one path."""
        return self.one_path["pymoo"].cpu / self.one_path["cadence"].cpu

    @property
    def task_ratio(self) -> float:
        """The same, the whole task on one process each."""
        return self.whole_task["pymoo"].cpu / self.whole_task["cadence"].cpu

    def to_json(self) -> dict[str, Any]:
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["one_path"], out["whole_task"] = sides_json(self.one_path), sides_json(self.whole_task)
        return out


def _edited(path: PathPlan, deg: float) -> PathPlan:
    wp = path.waypoints.copy()
    wp[len(wp) // 2] += np.radians(deg)
    return dataclasses.replace(path, waypoints=wp)


def bench_replanning(
    task: Task, settings: PlannerSettings, workers: int = 2, reference_generations: int = 600,
    edit_deg: float = 4.0, repeat: int = 2,
) -> Replanning:  # fmt: skip
    """Issue 31's figures: one path, the whole task, a warm replan after an edit, and their fronts."""
    from common.trajectory.pool import plan_paths

    paths = list(task.paths.values())
    longest = longest_path(task)
    one_path, _ = interleaved({"cadence": lambda: plan_path(longest, task.limits, settings),
                               "pymoo": lambda: plan_path(longest, task.limits, settings, engine="pymoo")},
                              repeat)  # fmt: skip
    whole_task, last = interleaved(
        {"cadence": lambda: plan_paths(paths, task.limits, settings, 1),
         "pymoo": lambda: {p.id: plan_path(p, task.limits, settings, engine="pymoo") for p in paths}},
        repeat,
    )  # fmt: skip
    fast, slow = last["cadence"], last["pymoo"]
    parallel, _ = interleaved({"cadence": lambda: plan_paths(paths, task.limits, settings, workers)}, repeat)
    edited = [_edited(p, edit_deg) for p in paths]
    warm = {p.id: [s.h for s in fast[p.id].solutions] for p in paths}
    warm_run = {"warm": lambda: plan_paths(edited, task.limits, settings, workers, warm)}
    warmed_run, last_warm = interleaved(warm_run, repeat)
    warm_s, warmed = warmed_run["warm"].wall, last_warm["warm"]
    long = structs.replace(settings, generations=reference_generations, seed=10_000)
    ref = plan_paths(paths, task.limits, long, workers)
    ref_edit = plan_paths(edited, task.limits, long, workers)

    def share(front: NDArray[np.float64], reference: NDArray[np.float64]) -> float:
        ideal, nadir = reference.min(axis=0), reference.max(axis=0)
        return hypervolume(front, ideal, nadir) / hypervolume(reference, ideal, nadir)

    return Replanning(
        path_id=longest.id,
        workers=workers,
        reference_generations=reference_generations,
        tries=repeat,
        one_path=one_path,
        whole_task=whole_task,
        task_parallel_s=parallel["cadence"].wall,
        warm_s=warm_s,
        hv={p.id: share(fast[p.id].front, ref[p.id].front) for p in paths},
        pymoo_hv={p.id: share(slow[p.id].front, ref[p.id].front) for p in paths},
        warm_hv={p.id: share(warmed[p.id].front, ref_edit[p.id].front) for p in paths},
        edit_deg=edit_deg,
        protocol=protocol(repeat, 1),
    )


@dataclass(frozen=True, slots=True)
class Convergence:
    """Hypervolume of default-setting runs after each checkpoint, as a share of a long run's."""

    path_id: str
    reference_generations: int
    checkpoints: list[int]
    shares: dict[int, list[float]]  # seed → share at each checkpoint (before the final polish)
    final: dict[int, float]  # seed → share of the finished run (after polishing its ends)


def convergence(
    task: Task,
    settings: PlannerSettings,
    seeds: list[int],
    reference_generations: int,
    checkpoints: list[int],
) -> Convergence:
    """How the default number of generations was chosen (docs/design.md, "The planner")."""
    path = longest_path(task)
    ref = plan_path(
        path, task.limits, structs.replace(settings, generations=reference_generations, seed=10_000)
    )
    ideal, nadir = ref.front.min(axis=0), ref.front.max(axis=0)
    hv_ref = hypervolume(ref.front, ideal, nadir)
    shares, final = {}, {}
    for seed in seeds:
        run = plan_path(
            path,
            task.limits,
            structs.replace(settings, generations=max(checkpoints), seed=seed),
            track_hypervolume=(ideal, nadir),
        )
        shares[seed] = [run.hypervolume_history[g - 1] / hv_ref for g in checkpoints]
        default = plan_path(path, task.limits, structs.replace(settings, seed=seed))
        final[seed] = hypervolume(default.front, ideal, nadir) / hv_ref
    return Convergence(path.id, reference_generations, checkpoints, shares, final)
