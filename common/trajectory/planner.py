"""Time/jerk Pareto sets of quintic B-spline trajectories (paper §II-B, §III-B; DESIGN §5).

The problem (``TrajectoryProblem``) is kept apart from the algorithm (``plan_path``), as in pymoo. Its
``_evaluate`` is vectorised: X is (P, W+1) interval vectors h, rows are individuals; F is (P, 2) =
[f_time, f_jerk], both minimised; G is (P, 3·D + 1) ≤ 0 = the velocity, acceleration and jerk ratios to
the limits minus one, per joint, and the upper bound h ≤ κ·h_lb.

Time scaling drives the repair. Stretching every interval by α leaves the control points Θ of A(h)Θ = B
unchanged and scales the d-th derivative by α^-d: velocity α^-1, acceleration α^-2, jerk α^-3, f_time α,
f_jerk α^-5. So for any shape of h the smallest feasible stretch is known in closed form,
α* = max(r_v, √r_a, ∛r_j), and an infeasible child is repaired by stretching it onto the limits, its
objectives following without another evaluation. NSGA-II then spends its generations on the shape of h.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from common.robot.ur16e import JointLimits
from common.runtime.clock import wall_monotonic
from common.runtime.errors import PlanningError
from common.trajectory import bspline as bs
from common.trajectory import nsga
from common.trajectory.task import Constraints, PathPlan, PlannerSettings

Array = NDArray[np.float64]

# Default number of generations, chosen with `cadence bench convergence` (docs/design.md): on the
# example task's longest path, 80 generations with both polishing steps reach 99.60-99.70 % (exact) and
# 99.45-99.65 % (hull) of a 1500-generation run's hypervolume over seeds 1-5; NSGA-II without the
# polishing reaches only 97.3-98.7 % (hull) after 80 generations and 98.2-99.4 % after 120.
DEFAULT_GENERATIONS = 80

# A repaired individual lands this far inside the limits, so round-off never makes it infeasible.
_REPAIR_MARGIN = 1.0 + 1e-9
# SLSQP aims this far inside the limits, as its own constraint tolerance may leave it a hair outside.
_POLISH_TARGET = 1.0 - 1e-8
# The shortest interval allowed, for a segment where no joint moves far (h_lb would be ~0).
H_MIN_S = 0.01
# Share of the generations before the ends are polished and fed back.
STAGE_SPLIT = 0.6


def interval_bounds(waypoints: Array, limits: JointLimits, kappa: float) -> tuple[Array, Array]:
    """h_lb and h_ub = κ·h_lb, each (W+1,) (paper eq. 9, DESIGN §5).

    h_l ≥ max_j |Δw_l^j| / v_max_j. The virtual knots split the first and last segments; each piece of a
    split segment gets its share of the displacement (half; a third when W = 2 and both virtual knots
    fall in the one segment).
    """
    w = len(waypoints)
    seg = np.max(np.abs(np.diff(waypoints, axis=0)) / limits.velocity, axis=1)  # (W-1,)
    if w == 2:
        lb = np.repeat(seg / 3.0, 3)
    else:
        lb = np.concatenate([[seg[0] / 2, seg[0] / 2], seg[1:-1], [seg[-1] / 2, seg[-1] / 2]])
    lb = np.maximum(lb, H_MIN_S)
    return lb, kappa * lb


@dataclass(frozen=True, slots=True)
class Evaluation:
    """Objectives and limit usage of a population: F (P, 2), ratio (P, 3, D) = max / limit."""

    f: Array
    ratio: Array


def evaluate(h: Array, path: PathPlan, limits: JointLimits, constraints: Constraints) -> Evaluation:
    """The whole population in one batched call: one solve for every A(h), no per-individual loop."""
    c = bs.control_points(h, path.waypoints, path.boundary)
    taylor = bs.span_taylor(h, c)
    d = path.waypoints.shape[1]
    f = np.stack([bs.time_cost(h, d), bs.jerk_cost(h, taylor)], axis=1)
    maxima = bs.span_maxima(h, taylor) if constraints == "exact" else bs.hull_maxima(h, c)
    return Evaluation(f, maxima / limits.kinematic()[None])


Evaluator = Callable[[Array, PathPlan, JointLimits, Constraints], Evaluation]


def limit_ratios(h: Array, path: PathPlan, limits: JointLimits, constraints: Constraints) -> Array:
    """Every piece's limit ratio, (P, K): per knot span (exact) or per control point (hull).

    Finer than ``evaluate``'s per-joint maxima, so that a gradient-based method sees smooth functions.
    """
    c = bs.control_points(h, path.waypoints, path.boundary)
    if constraints == "exact":
        r = bs.span_maxima(h, bs.span_taylor(h, c), per_span=True) / limits.kinematic()[None, :, None, :]
        return r.reshape(len(h), -1)
    cps = bs.derivative_control_points(h, c)
    lim = limits.kinematic()
    return np.concatenate([(np.abs(cd) / lim[d]).reshape(len(h), -1) for d, cd in enumerate(cps)], axis=1)


def polish(
    h0: Array,
    path: PathPlan,
    limits: JointLimits,
    constraints: Constraints,
    bounds: tuple[Array, Array],
    objective: str,
) -> Array | None:
    """Refine one end of the front with SLSQP: minimum t_f, or minimum f_jerk, under the limits.

    NSGA-II finds the middle of the front quickly but its ends slowly (only a few individuals are there).
    Gradients are forward differences, all n+1 points of one Jacobian evaluated in one batched call.
    Variables are h / h_lb, so every coordinate is of order one. Returns None when SLSQP found nothing
    better; the result is stretched onto the limits if SLSQP left it a hair outside.
    """
    from scipy.optimize import minimize  # half a second to import: only where it is used

    lb, ub = bounds
    n = len(h0)
    step = 1e-7
    d = path.waypoints.shape[1]
    memo: dict[bytes, tuple[Array, Array]] = {}

    def jac_data(x: Array) -> tuple[Array, Array]:
        key = x.tobytes()
        if key not in memo:
            pts = np.vstack([x, x + step * np.eye(n)]) * lb
            g = _POLISH_TARGET - limit_ratios(pts, path, limits, constraints)
            fj = evaluate(pts, path, limits, constraints).f[:, 1] if objective == "jerk" else np.zeros(n + 1)
            memo.clear()
            memo[key] = (g, fj)
        return memo[key]

    if objective == "time":
        fun = lambda x: float(d * np.dot(x, lb))  # noqa: E731
        grad = lambda x: d * lb  # noqa: E731
    else:
        scale = float(evaluate(h0[None], path, limits, constraints).f[0, 1])
        fun = lambda x: float(jac_data(x)[1][0]) / scale  # noqa: E731
        grad = lambda x: (jac_data(x)[1][1:] - jac_data(x)[1][0]) / step / scale  # noqa: E731
    cons = {
        "type": "ineq",
        "fun": lambda x: jac_data(x)[0][0],
        "jac": lambda x: ((jac_data(x)[0][1:] - jac_data(x)[0][0]) / step).T,
    }
    res = minimize(
        fun,
        h0 / lb,
        jac=grad,
        bounds=list(zip(np.ones(n), ub / lb, strict=True)),
        constraints=[cons],
        method="SLSQP",
        options={"maxiter": 60, "ftol": 1e-10},
    )
    h = np.clip(res.x * lb, lb, ub)
    alpha = feasible_stretch(evaluate(h[None], path, limits, constraints).ratio)[0] * _REPAIR_MARGIN
    if alpha > 1.0:
        # An interval at h_ub stays there: the optimum can lie on that bound.
        h = np.minimum(h * alpha, ub)
    ok = np.all(np.isfinite(h)) and evaluate(h[None], path, limits, constraints).ratio.max() <= 1.0
    return h if ok else None


def feasible_stretch(ratio: Array) -> Array:
    """α* per individual: the stretch that brings the worst limit ratio to exactly 1. (P,)."""
    r = ratio.max(axis=2)  # (P, 3): worst joint per derivative order
    alpha: Array = np.max(np.stack([r[:, 0], np.sqrt(r[:, 1]), np.cbrt(r[:, 2])], axis=1), axis=1)
    return alpha


def stretched(ev: Evaluation, alpha: Array) -> Evaluation:
    """The evaluation of α·h from that of h, with no new solve (see the module docstring)."""
    f = ev.f * np.stack([alpha, alpha**-5], axis=1)
    powers = np.array([1.0, 2.0, 3.0])[None, :, None]
    return Evaluation(f, ev.ratio * alpha[:, None, None] ** -powers)


def boundary_stretch(h: Array, path: PathPlan, limits: JointLimits, constraints: Constraints) -> Array:
    """For each row of h, the α that puts α·h exactly on the limits (fastest feasible along its ray)."""
    return feasible_stretch(evaluate(h, path, limits, constraints).ratio)


class TrajectoryProblem:
    """The problem of one path, in pymoo's terms (bounds xl/xu, ``_evaluate`` filling F and G); it keeps
    every feasible point it evaluates in a non-dominated archive."""

    def __init__(
        self,
        path: PathPlan,
        limits: JointLimits,
        constraints: Constraints,
        kappa: float,
        evaluator: Evaluator | None = None,
    ) -> None:
        self.evaluator = evaluator or evaluate
        self.path = path
        self.limits = limits
        self.constraints = constraints
        self.lb, self.ub = interval_bounds(path.waypoints, limits, kappa)
        d = path.waypoints.shape[1]
        self.n_var, self.n_obj, self.n_ieq_constr = len(self.lb), 2, 3 * d + 1
        self.xl, self.xu = self.lb, self.ub
        self._cache: dict[bytes, tuple[Array, Array]] = {}
        self.archive_h = np.empty((0, self.n_var))
        self.archive_f = np.empty((0, 2))
        self.n_evaluated = 0

    def constraint_values(self, h: Array, ev: Evaluation) -> Array:
        g_lim = (ev.ratio - 1.0).reshape(len(h), -1)
        g_ub = (h / self.ub).max(axis=1, keepdims=True) - 1.0
        return np.concatenate([g_lim, g_ub], axis=1)

    def repair(self, h: Array) -> Array:
        """Stretch infeasible rows onto the limits; remember their F and G for ``_evaluate``."""
        ev = self.evaluator(h, self.path, self.limits, self.constraints)
        alpha = feasible_stretch(ev.ratio) * _REPAIR_MARGIN
        alpha = np.where(alpha > 1.0, alpha, 1.0)
        h2 = h * alpha[:, None]
        ev2 = stretched(ev, alpha)
        g = self.constraint_values(h2, ev2)
        # A stretch past h_ub is clipped back (pymoo's operators need X within bounds); such a row is
        # evaluated afresh in _evaluate, and stays infeasible.
        inside = np.all(h2 <= self.ub, axis=1)
        for row, f_row, g_row in zip(h2[inside], ev2.f[inside], g[inside], strict=True):
            self._cache[row.tobytes()] = (f_row, g_row)
        return np.minimum(h2, self.ub)

    def _evaluate(self, x: Array, out: dict[str, Array], *args: object, **kwargs: object) -> None:
        f = np.empty((len(x), 2))
        g = np.empty((len(x), self.n_ieq_constr))
        missing = []
        for i, row in enumerate(x):
            hit = self._cache.pop(row.tobytes(), None)
            if hit is None:
                missing.append(i)
            else:
                f[i], g[i] = hit
        if missing:
            hm = x[missing]
            ev = self.evaluator(hm, self.path, self.limits, self.constraints)
            f[missing] = ev.f
            g[missing] = self.constraint_values(hm, ev)
        self._cache.clear()
        self.n_evaluated += len(x)
        ok = np.all(g <= 0.0, axis=1)
        self._merge(x[ok], f[ok])
        out["F"] = f
        out["G"] = g

    def _merge(self, h: Array, f: Array) -> None:
        if len(h) == 0:
            return
        hs = np.concatenate([self.archive_h, h])
        fs = np.concatenate([self.archive_f, f])
        keep = non_dominated(fs)
        self.archive_h, self.archive_f = hs[keep], fs[keep]

    def objectives(self, h: Array) -> tuple[Array, Array]:
        out: dict[str, Array] = {}
        self._evaluate(h, out)
        return out["F"], out["G"]


def non_dominated(f: Array) -> NDArray[np.intp]:
    """Indices of the non-dominated, distinct rows of a 2-objective F, sorted by f_time ascending.

    A sort and a sweep, O(n log n): with two objectives a point is non-dominated iff its f_jerk is below
    that of every point with a smaller f_time.
    """
    order = np.lexsort((f[:, 1], f[:, 0]))
    fj = f[order, 1]
    best_before = np.concatenate([[np.inf], np.minimum.accumulate(fj)[:-1]])
    front: NDArray[np.intp] = order[fj < best_before]
    return front


def hypervolume(f: Array, ideal: Array, nadir: Array, ref: float = 1.1) -> float:
    """2-D hypervolume of F normalised by (ideal, nadir), against the reference point (ref, ref)."""
    z = (f - ideal) / (nadir - ideal)
    z = z[np.all(z < ref, axis=1)]
    if len(z) == 0:
        return 0.0
    z = z[non_dominated(z)]  # f_time ascending, so f_jerk descending
    widths = np.diff(np.concatenate([z[:, 0], [ref]]))
    return float(np.sum(widths * (ref - z[:, 1])))


def downsample(front: Array, n: int) -> NDArray[np.intp]:
    """Choose n solutions of a front by ASF (paper §III-B): indices ordered k = 1 … n.

    The front (non-dominated, distinct) is normalised by its ideal and nadir points. k = 1 is the
    minimum-jerk point, k = n the minimum-time point; in between, ASF weights move step by step from
    jerk to time (pymoo's ASF divides by the weight: a small weight makes that objective count more).
    Each pick is restricted to points faster than the previous pick with enough faster points left for
    the picks to come, so the n solutions are distinct and ordered by strictly decreasing t_f. A front
    with fewer than n points is returned whole.
    """
    m = len(front)
    by_time_desc = np.argsort(-front[:, 0], kind="stable")
    if m <= n:
        return by_time_desc
    ideal, nadir = front.min(axis=0), front.max(axis=0)
    z = (front[by_time_desc] - ideal) / np.where(nadir > ideal, nadir - ideal, 1.0)
    picks = [0]
    for k in range(2, n):
        tau = (k - 1) / (n - 1)
        values = np.max(z / np.array([1.0 - tau, tau]), axis=1)  # ASF with the utopian point at 0
        lo, hi = picks[-1] + 1, m - 1 - (n - k)
        picks.append(lo + int(np.argmin(values[lo : hi + 1])))
    picks.append(m - 1)
    chosen: NDArray[np.intp] = by_time_desc[np.array(picks)]
    return chosen


@dataclass(frozen=True, slots=True)
class Solution:
    k: int
    h: Array
    f_time: float
    f_jerk: float

    @property
    def t_f(self) -> float:
        return float(np.sum(self.h))


@dataclass(frozen=True, slots=True)
class ParetoResult:
    """What ``plan_path`` found: the archive's front and the N chosen solutions (k = 1 … N)."""

    path: PathPlan
    limits: JointLimits
    settings: PlannerSettings
    generations: int
    front: Array  # (M, 2), f_time ascending
    front_h: Array  # (M, W+1)
    solutions: list[Solution]
    n_evaluated: int
    hypervolume_history: list[float] = field(default_factory=list)
    seconds: float = 0.0  # wall time of the planning, in the process that planned

    def to_json(self) -> dict[str, object]:
        """The contract of ``DIR/<path_id>.json`` (planner issue), plus the settings used."""
        b = self.path.boundary
        return {
            "path_id": self.path.id,
            "unit": "rad",
            "waypoints": self.path.waypoints.tolist(),
            "limits": self.limits.as_dict(),
            "boundary": {
                "start": {"velocity": b.v0.tolist(), "acceleration": b.a0.tolist(), "jerk": b.j0.tolist()},
                "end": {"velocity": b.v1.tolist(), "acceleration": b.a1.tolist(), "jerk": b.j1.tolist()},
            },
            "constraints": self.settings.constraints,
            "settings": {
                "population": self.settings.population,
                "generations": self.generations,
                "seed": self.settings.seed,
                "kappa": self.settings.kappa,
                "n_solutions": self.settings.n_solutions,
            },
            "front": self.front.tolist(),
            "solutions": [
                {"k": s.k, "h": s.h.tolist(), "t_f": s.t_f, "f_time": s.f_time, "f_jerk": s.f_jerk}
                for s in self.solutions
            ],
        }


def initial_population(lb: Array, ub: Array, size: int, rng: np.random.Generator) -> Array:
    """Log-uniform random shapes, plus the lower-bound shape stretched geometrically from h_lb to h_ub.

    The stretched seeds span the whole range of t_f from the first generation, so the front's ends are
    populated early; the random shapes give NSGA-II the diversity of shape it optimises.
    """
    n_seed = min(size // 6, 15)
    stretch = np.geomspace(1.0, ub[0] / lb[0], n_seed)
    seeds = lb[None, :] * stretch[:, None]
    rand = np.exp(rng.uniform(np.log(lb), np.log(ub), size=(size - n_seed, len(lb))))
    return np.concatenate([seeds, rand])


ProgressFn = Callable[[int, int], None]


def _polish_ends(problem: TrajectoryProblem, constraints: Constraints) -> list[Array]:
    """Polish the fastest and the smoothest point of the archive; they join the archive."""
    out = []
    # The fast end is multimodal in hull mode: start also from h_lb's shape stretched onto the limits.
    lb_shape = problem.lb * boundary_stretch(problem.lb[None], problem.path, problem.limits, constraints)[0]
    starts = [
        ("time", problem.archive_h[0]),
        ("time", np.minimum(lb_shape, problem.ub)),
        ("jerk", problem.archive_h[-1]),
    ]
    for objective, h0 in starts:
        h = polish(h0, problem.path, problem.limits, constraints, (problem.lb, problem.ub), objective)
        if h is not None:
            problem._evaluate(h[None], {})
            out.append(h)
    return out


Engine = Literal["numpy", "pymoo"]
# Generations after a waypoint edit, when the last set's solutions seed the search (``warm``): chosen
# with `cadence bench plan`, which reports the warm run's hypervolume against a cold default run.
WARM_GENERATIONS = 30


def warm_seeds(path: PathPlan, limits: JointLimits, kappa: float, previous: Sequence[Array]) -> Array:
    """The last set's interval vectors as seeds for the edited path, inside its new bounds. After an edit
    of a few degrees the old shapes are close to the new optimum; the repair stretches each onto the new
    limits. Empty when the number of waypoints changed (no interval maps onto another)."""
    lb, ub = interval_bounds(path.waypoints, limits, kappa)
    rows = [np.asarray(h, dtype=float) for h in previous]
    rows = [h for h in rows if h.shape == lb.shape and np.all(np.isfinite(h)) and np.all(h > 0)]
    if not rows:
        return np.empty((0, len(lb)))
    seeds: Array = np.clip(np.stack(rows), lb, ub)
    return seeds


def _pymoo_stage(
    problem: TrajectoryProblem, x: Array, generations: int, seed: int, on_generation: Callable[[], None]
) -> Array:
    """Today's engine until this one: pymoo's NSGA-II loop, kept as the reference of `cadence bench
    plan` and of the tests."""
    from pymoo.algorithms.moo.nsga2 import NSGA2
    from pymoo.core.problem import Problem
    from pymoo.core.repair import Repair

    class Adapter(Problem):  # type: ignore[misc]  # pymoo ships no type information
        def __init__(self) -> None:
            super().__init__(n_var=problem.n_var, n_obj=2, n_ieq_constr=problem.n_ieq_constr,
                             xl=problem.lb, xu=problem.ub)  # fmt: skip

        def _evaluate(self, x: Array, out: dict[str, Array], *args: object, **kwargs: object) -> None:
            problem._evaluate(x, out)

    class StretchRepair(Repair):  # type: ignore[misc]
        def _do(self, _: object, x: Array, **kwargs: object) -> Array:
            return problem.repair(x)

    algorithm = NSGA2(pop_size=len(x), sampling=x, repair=StretchRepair(), eliminate_duplicates=False)
    algorithm.setup(Adapter(), termination=("n_gen", generations), seed=seed, verbose=False)
    while algorithm.has_next():
        algorithm.next()
        on_generation()
    out = np.asarray(algorithm.pop.get("X"), dtype=float)
    return out


def plan_path(
    path: PathPlan,
    limits: JointLimits,
    settings: PlannerSettings,
    progress: ProgressFn | None = None,
    track_hypervolume: tuple[Array, Array] | None = None,
    evaluator: Evaluator | None = None,
    warm: Sequence[Array] = (),
    engine: Engine = "numpy",
) -> ParetoResult:
    """NSGA-II over h for one path, then ASF downsampling to N. Seeded: same inputs, same result.

    ``progress(gen, total)`` is called after each generation. ``track_hypervolume=(ideal, nadir)``
    records the archive's hypervolume after each generation (for convergence studies). ``evaluator``
    replaces the batched evaluation of the generations (the benchmark's straightforward baseline); the
    polishing of the ends always uses the batched functions. ``warm``: the interval vectors of the last
    set of this path before a waypoint edit; they seed the search, which then runs ``WARM_GENERATIONS``
    unless the settings name a number.
    """
    started = wall_monotonic()
    problem = TrajectoryProblem(path, limits, settings.constraints, settings.kappa, evaluator)
    rng = np.random.default_rng(settings.seed)
    seeds = warm_seeds(path, limits, settings.kappa, warm)
    generations = settings.generations or (WARM_GENERATIONS if len(seeds) else DEFAULT_GENERATIONS)
    x = initial_population(problem.lb, problem.ub, settings.population, rng)
    x[len(x) - min(len(seeds), len(x)) :] = seeds[: len(x)]  # in place of random shapes, not the stretched
    history: list[float] = []
    gen = 0

    def on_generation() -> None:
        nonlocal gen
        gen += 1
        if track_hypervolume is not None:
            history.append(hypervolume(problem.archive_f, *track_hypervolume))
        if progress is not None:
            progress(gen, generations)

    # Two stages: after the first, the ends of the archive's front are polished and put back into the
    # population, so the second stage fills in the front around them. Then the ends are polished again.
    first = max(1, round(generations * STAGE_SPLIT))
    for stage_gens in (first, generations - first):
        if stage_gens <= 0:
            continue
        if engine == "pymoo":
            x = _pymoo_stage(problem, x, stage_gens, settings.seed + gen, on_generation)
        else:
            x = nsga.evolve(x, problem.lb, problem.ub, problem.objectives, problem.repair, stage_gens, rng,
                            on_generation)  # fmt: skip
        if len(problem.archive_f) == 0:
            raise PlanningError(
                f"path '{path.id}': no trajectory within the limits is slower than κ·h_lb "
                f"(κ = {settings.kappa}); raise planner.kappa or the limits"
            )
        polished = _polish_ends(problem, settings.constraints)
        x = x.copy()
        x[: len(polished)] = polished
    front, front_h = problem.archive_f, problem.archive_h
    chosen = downsample(front, settings.n_solutions)
    solutions = [
        Solution(k=i + 1, h=front_h[j].copy(), f_time=float(front[j, 0]), f_jerk=float(front[j, 1]))
        for i, j in enumerate(chosen)
    ]
    return ParetoResult(
        path=path,
        limits=limits,
        settings=settings,
        generations=generations,
        front=front,
        front_h=front_h,
        solutions=solutions,
        n_evaluated=problem.n_evaluated,
        hypervolume_history=history,
        seconds=wall_monotonic() - started,
    )


# Bump when the planner's output for the same inputs changes, so stored sets are recomputed.
PLANNER_VERSION = 2


def content_hash(path: PathPlan, limits: JointLimits, settings: PlannerSettings) -> str:
    """Names a set by everything it was planned from: waypoints, limits, boundary conditions, settings.

    A changed task program never matches a stored set, so the store never serves a stale one.
    """
    b = path.boundary
    doc = {
        "version": PLANNER_VERSION,
        "waypoints": path.waypoints.tolist(),
        "limits": limits.as_dict(),
        "boundary": [v.tolist() for v in (b.v0, b.a0, b.j0, b.v1, b.a1, b.j1)],
        "settings": {
            "constraints": settings.constraints,
            "n_solutions": settings.n_solutions,
            "population": settings.population,
            "generations": settings.generations or DEFAULT_GENERATIONS,
            "seed": settings.seed,
            "kappa": settings.kappa,
        },
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:32]
