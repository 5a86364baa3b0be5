"""The planner on paths it has never seen: every solution valid, the front good, the ends optimal."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from pymoo.indicators.hv import HV
from pymoo.util.nds.non_dominated_sorting import NonDominatedSorting
from scipy.optimize import minimize

from cadence.bench.naive import evaluate_naive
from common.robot.ur16e import UR16E
from common.trajectory import bspline as bs
from common.trajectory import nsga
from common.trajectory.planner import (
    WARM_GENERATIONS,
    ParetoResult,
    downsample,
    evaluate,
    hypervolume,
    interval_bounds,
    non_dominated,
    plan_path,
    warm_seeds,
)
from common.trajectory.pool import plan_paths
from common.trajectory.task import PathPlan, PlannerSettings
from common.trajectory.validate import trajectory_problems
from tests.support.paths import random_path
from tests.support.trajectory import scipy_reference


def test_interval_bounds_split_the_end_segments_between_the_virtual_knots() -> None:
    path = random_path(1, 5)
    lb, ub = interval_bounds(path.waypoints, UR16E, kappa=10.0)
    seg = np.max(np.abs(np.diff(path.waypoints, axis=0)) / UR16E.velocity, axis=1)
    np.testing.assert_allclose(
        lb, np.maximum([seg[0] / 2, seg[0] / 2, seg[1], seg[2], seg[3] / 2, seg[3] / 2], 0.01)
    )
    np.testing.assert_allclose(ub, 10 * lb)


def test_two_waypoints_give_three_intervals_of_a_third_each() -> None:
    wp = np.array([[0.0] * 6, [1.0, 0, 0, 0, 0, 0]])
    lb, _ = interval_bounds(wp, UR16E, kappa=10.0)
    np.testing.assert_allclose(lb, [1.0 / UR16E.velocity[0] / 3] * 3)


def test_non_dominated_agrees_with_pymoo_sorting() -> None:
    rng = np.random.default_rng(0)
    f = rng.uniform(size=(400, 2))
    f[:, 1] = 1.0 / (f[:, 0] + 0.1) + rng.uniform(0, 2, 400)
    ours = set(non_dominated(f).tolist())
    theirs = set(NonDominatedSorting().do(f, only_non_dominated_front=True).tolist())
    assert ours == theirs
    assert np.all(np.diff(f[non_dominated(f), 0]) > 0)


def test_hypervolume_agrees_with_pymoo() -> None:
    rng = np.random.default_rng(1)
    x = np.sort(rng.uniform(size=30))
    f = np.stack([x, (1 - x) ** 2], axis=1)
    ideal, nadir = np.zeros(2), np.ones(2)
    assert hypervolume(f, ideal, nadir) == pytest.approx(HV(ref_point=np.array([1.1, 1.1])).do(f), rel=1e-12)


def test_downsampling_is_distinct_and_ordered_from_smoothest_to_fastest() -> None:
    x = np.linspace(1.0, 10.0, 200)
    front = np.stack([x, 1.0 / x**5], axis=1)
    idx = downsample(front, 15)
    chosen = front[idx]
    assert len(set(idx.tolist())) == 15
    assert np.all(np.diff(chosen[:, 0]) < 0), "t_f must strictly decrease with k"
    assert idx[0] == np.argmin(front[:, 1])
    assert idx[-1] == np.argmin(front[:, 0])


def test_a_front_smaller_than_n_is_returned_whole_slowest_first() -> None:
    front = np.array([[1.0, 5.0], [2.0, 3.0], [3.0, 1.0]])
    assert downsample(front, 15).tolist() == [2, 1, 0]


def check_solutions(result: ParetoResult, path: PathPlan, mode: str) -> None:
    lim = UR16E.kinematic()
    sols = result.solutions
    assert len(sols) == 15
    t_f = np.array([s.t_f for s in sols])
    jerk = np.array([s.f_jerk for s in sols])
    assert np.all(np.diff(t_f) < 0), "k = 1 slowest … k = N fastest, all distinct"
    assert jerk[0] == pytest.approx(result.front[:, 1].min())
    assert t_f[-1] == pytest.approx(result.front[:, 0].min() / 6)
    lb, ub = interval_bounds(path.waypoints, UR16E, result.settings.kappa)
    for s in sols:
        assert np.all(s.h >= lb * (1 - 1e-12))
        assert np.all(s.h <= ub * (1 + 1e-12))
        ref = scipy_reference(s.h, path)
        sites = bs.waypoint_sites(s.h[None])[0]
        assert np.max(np.abs(ref(sites) - path.waypoints)) < 1e-9
        b = path.boundary
        for d, (v0, v1) in enumerate([(b.v0, b.v1), (b.a0, b.a1), (b.j0, b.j1)], start=1):
            np.testing.assert_allclose(ref(0.0, d), v0, atol=1e-8)
            np.testing.assert_allclose(ref(s.t_f, d), v1, atol=1e-8)
        t = np.linspace(0.0, s.t_f, int(s.t_f * 2000) + 2)  # ≥ 2 kHz
        dense = np.stack([np.abs(ref(t, d)).max(axis=0) for d in (1, 2, 3)])
        assert np.all(dense <= lim * (1 + 1e-6)), f"k={s.k} exceeds a limit ({mode})"
        assert trajectory_problems(s.h, path, UR16E) == []
        # f_jerk against an independent integral (dense Simpson per span on scipy's spline)
        knots_s = bs.instants(s.h[None])[0]
        total = 0.0
        for a, bb in itertools.pairwise(knots_s):
            tt = np.linspace(a, bb, 1001)
            y = np.sum(ref(tt, 3) ** 2, axis=1)
            total += (bb - a) / 3000 * (y[0] + y[-1] + 4 * y[1:-1:2].sum() + 2 * y[2:-1:2].sum())
        assert s.f_jerk == pytest.approx(total, rel=1e-6)


@pytest.mark.parametrize(
    ("seed", "mode", "w"), [(21, "exact", 6), (22, "hull", 6), (23, "exact", 3), (24, "exact", 8)]
)
def test_every_solution_of_an_unseen_path_is_valid(seed: int, mode: str, w: int) -> None:
    path = random_path(seed, w, boundary=seed == 23)
    result = plan_path(path, UR16E, PlannerSettings(constraints=mode, seed=seed))
    check_solutions(result, path, mode)


def test_the_same_seed_gives_the_same_set() -> None:
    path = random_path(5, 5)
    a = plan_path(path, UR16E, PlannerSettings(seed=7, generations=20))
    b = plan_path(path, UR16E, PlannerSettings(seed=7, generations=20))
    assert [s.h.tolist() for s in a.solutions] == [s.h.tolist() for s in b.solutions]


@pytest.mark.bench  # an 800-generation reference run per mode: it runs with the benchmarks (CI runs both)
@pytest.mark.parametrize("mode", ["exact", "hull"])
def test_front_hypervolume_is_at_least_99_percent_of_a_long_run(mode: str) -> None:
    path = random_path(31, 6)
    long = plan_path(path, UR16E, PlannerSettings(constraints=mode, seed=1000, generations=800))
    default = plan_path(path, UR16E, PlannerSettings(constraints=mode, seed=3))
    both = np.concatenate([long.front, default.front])
    ideal, nadir = both.min(axis=0), both.max(axis=0)
    ratio = hypervolume(default.front, ideal, nadir) / hypervolume(long.front, ideal, nadir)
    print(f"{mode}: hypervolume {ratio:.4f} of an 800-generation run's")
    assert ratio >= 0.99


def gradient_min_tf(path: PathPlan, starts: int = 3) -> float:
    """An independent minimum of t_f: SLSQP on scipy splines, limits from dense sampling (5 kHz)."""
    lb, _ = interval_bounds(path.waypoints, UR16E, 10.0)
    lim = UR16E.kinematic()

    def cons(x: np.ndarray) -> np.ndarray:
        h = x * lb
        ref = scipy_reference(h, path)
        t = np.linspace(0.0, h.sum(), int(h.sum() * 5000) + 2)
        return np.concatenate([1.0 - np.abs(ref(t, d)).max(axis=0) / lim[d - 1] for d in (1, 2, 3)])

    best = np.inf
    rng = np.random.default_rng(0)
    for _ in range(starts):
        x0 = rng.uniform(2.0, 6.0, len(lb))
        # start feasible: stretch until the sampled limits hold
        while np.any(cons(x0) < 0):
            x0 = x0 * 1.2
        res = minimize(
            lambda x: float(np.dot(x, lb)),
            x0,
            jac=lambda x: lb,
            method="SLSQP",
            bounds=[(1.0, 10.0)] * len(lb),
            constraints=[{"type": "ineq", "fun": cons}],
            options={"maxiter": 200},
        )
        if np.all(cons(res.x) >= -1e-6):
            best = min(best, float(np.dot(res.x, lb)))
    return best


def test_the_fastest_exact_solution_is_within_3_percent_of_a_gradient_based_minimum() -> None:
    path = random_path(41, 6)
    result = plan_path(path, UR16E, PlannerSettings(constraints="exact", seed=1))
    reference = gradient_min_tf(path)
    print(f"planner {result.solutions[-1].t_f:.4f} s, gradient-based {reference:.4f} s")
    assert result.solutions[-1].t_f <= 1.03 * reference


def test_exact_limits_give_faster_trajectories_than_the_hull() -> None:
    path = random_path(42, 6)
    exact = plan_path(path, UR16E, PlannerSettings(constraints="exact", seed=1))
    hull = plan_path(path, UR16E, PlannerSettings(constraints="hull", seed=1))
    print(f"fastest t_f: exact {exact.solutions[-1].t_f:.3f} s, hull {hull.solutions[-1].t_f:.3f} s")
    assert exact.solutions[-1].t_f < 0.9 * hull.solutions[-1].t_f


def test_batched_and_straightforward_evaluations_agree() -> None:
    path = random_path(9, 6)
    h = np.random.default_rng(9).uniform(0.2, 1.5, (10, 7))
    for mode in ("exact", "hull"):
        fast, slow = evaluate(h, path, UR16E, mode), evaluate_naive(h, path, UR16E, mode)
        np.testing.assert_allclose(fast.f[:, 0], slow.f[:, 0])
        np.testing.assert_allclose(fast.f[:, 1], slow.f[:, 1], rtol=1e-3)  # trapezoid on 1000 samples
        np.testing.assert_allclose(fast.ratio, slow.ratio, rtol=1e-3, atol=1e-9)


def test_fronts_agree_with_pymoo_sorting_front_by_front() -> None:
    rng = np.random.default_rng(3)
    f = np.round(rng.uniform(size=(300, 2)), 2)  # rounded: ties and duplicates on purpose
    ours = nsga.fronts(f)
    theirs = NonDominatedSorting().do(f)
    # pymoo keeps duplicates on one front, ours moves a copy one front down; on distinct rows they agree
    distinct = np.unique(f, axis=0, return_index=True)[1]
    g = f[np.sort(distinct)]
    assert [set(x.tolist()) for x in nsga.fronts(g)] == [set(x.tolist()) for x in NonDominatedSorting().do(g)]
    assert sum(len(x) for x in ours) == len(f)
    assert len(ours) >= len(theirs)


def test_crowding_gives_the_ends_infinity_and_the_middle_its_neighbours_gap() -> None:
    f = np.array([[0.0, 4.0], [1.0, 2.0], [3.0, 1.0], [4.0, 0.0]])
    d = nsga.crowding(f)
    assert np.isinf(d[0])
    assert np.isinf(d[-1])
    np.testing.assert_allclose(d[1:-1], [3 / 4 + 3 / 4, 3 / 4 + 2 / 4])


def test_crossover_and_mutation_stay_in_bounds_and_change_something() -> None:
    rng = np.random.default_rng(4)
    xl, xu = np.full(5, 0.1), np.full(5, 2.0)
    a, b = rng.uniform(0.1, 2.0, (2, 200, 5))
    kids = nsga.mutate(nsga.crossover(a, b, xl, xu, rng), xl, xu, rng)
    assert kids.shape == (400, 5)
    assert np.all((kids >= xl) & (kids <= xu))
    assert np.mean(~np.isin(kids, np.concatenate([a, b]))) > 0.2


@pytest.mark.parametrize("seed", [51, 52])
def test_the_array_engine_finds_fronts_as_good_as_pymoos_loop(seed: int) -> None:
    path = random_path(seed, 5)
    ours = plan_path(path, UR16E, PlannerSettings(seed=seed))
    theirs = plan_path(path, UR16E, PlannerSettings(seed=seed), engine="pymoo")
    both = np.concatenate([ours.front, theirs.front])
    ideal, nadir = both.min(axis=0), both.max(axis=0)
    ratio = hypervolume(ours.front, ideal, nadir) / hypervolume(theirs.front, ideal, nadir)
    print(f"hypervolume ratio array engine / pymoo: {ratio:.4f}")
    assert ratio >= 0.995
    check_solutions(ours, path, "exact")


def test_a_warm_start_after_a_waypoint_edit_is_valid_and_as_good_in_fewer_generations() -> None:
    path = random_path(61, 6)
    before = plan_path(path, UR16E, PlannerSettings(seed=1))
    wp = path.waypoints.copy()
    wp[3] += np.radians(3.0)
    edited = dataclasses.replace(path, waypoints=wp)
    seeds = warm_seeds(edited, UR16E, 10.0, [s.h for s in before.solutions])
    lb, ub = interval_bounds(wp, UR16E, 10.0)
    assert seeds.shape == (15, len(lb))
    assert np.all((seeds >= lb) & (seeds <= ub))
    warm = plan_path(edited, UR16E, PlannerSettings(seed=1), warm=[s.h for s in before.solutions])
    cold = plan_path(edited, UR16E, PlannerSettings(seed=1))
    assert warm.generations == WARM_GENERATIONS < cold.generations
    both = np.concatenate([warm.front, cold.front])
    ideal, nadir = both.min(axis=0), both.max(axis=0)
    assert hypervolume(warm.front, ideal, nadir) >= 0.99 * hypervolume(cold.front, ideal, nadir)
    check_solutions(warm, edited, "exact")
    # a path whose number of waypoints changed has no seeds: it is planned cold
    assert len(warm_seeds(edited, UR16E, 10.0, [np.ones(3)])) == 0


def test_paths_planned_in_forked_processes_equal_those_planned_here() -> None:
    paths = [dataclasses.replace(random_path(s, 4), id=f"p{s}") for s in (71, 72, 73)]
    settings = PlannerSettings(seed=2, generations=12)
    seen: list[tuple[str, int, int]] = []
    apart = plan_paths(paths, UR16E, settings, workers=2, progress=lambda *a: seen.append(a))
    here = plan_paths(paths, UR16E, settings, workers=1)
    for p in paths:
        assert [s.h.tolist() for s in apart[p.id].solutions] == [s.h.tolist() for s in here[p.id].solutions]
    assert {(pid, g) for pid, g, _ in seen} == {(p.id, g) for p in paths for g in range(1, 13)}
