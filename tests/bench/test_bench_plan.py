"""Benchmark of the planner (issue: planner; exact limits). It prints its figures and the ratios to the
straightforward baseline measured in the same run; the assertions are on quality, never on time."""

from __future__ import annotations

import pytest

from cadence.bench import bench_plan
from common.trajectory.task import load_task
from tests.conftest import BENCH_QUICK, EXAMPLE_TASK

pytestmark = pytest.mark.bench


def test_bench_plan_prints_times_ratios_and_fronts() -> None:
    task = load_task(EXAMPLE_TASK)
    r = bench_plan(task, task.planner, repeat=1 if BENCH_QUICK else 2)
    print(
        f"\npath {r.path_id} (W={r.n_waypoints}, pop {r.population}, {r.generations} generations)\n"
        f"full planning   {r.plan_s:.3f} s  naive {r.naive_plan_s:.3f} s  ratio {r.plan_ratio:.1f}x\n"
        f"one evaluation  {r.eval_ms:.2f} ms naive {r.naive_eval_ms:.1f} ms  ratio {r.eval_ratio:.1f}x\n"
        f"hypervolume        {r.hv:.4f}     naive {r.naive_hv:.4f}\n"
        f"fastest t_f        exact {r.tf_exact:.3f} s, hull {r.tf_hull:.3f} s, Ruckig {r.tf_ruckig} s"
    )
    assert r.hv >= 0.99 * r.naive_hv
    assert r.tf_exact < r.tf_hull
    if r.tf_ruckig is not None:
        assert r.tf_exact < r.tf_ruckig
