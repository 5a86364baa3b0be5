"""Benchmark of the planner (issue: planner; exact limits). It prints its figures and the ratios to the
straightforward baseline measured in the same run; the assertions are on quality, never on time."""

from __future__ import annotations

import pytest

from cadence.bench.planning import bench_plan, bench_replanning
from common.trajectory.task import load_task
from tests.support.paths import BENCH_QUICK, EXAMPLE_TASK

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
    # docs/design.md's table of the fastest t_f (the same to the ms on any machine: k = N's last bits
    # move by 1e-7 s between kernels, docs/development.md)
    from tests.support.paths import DOCS

    text = (DOCS / "design.md").read_text()
    rows = {"hull limits (the paper's)": r.tf_hull, "exact limits (Cadence's default)": r.tf_exact}
    if r.tf_ruckig is not None:
        rows["Ruckig, stopping at every waypoint"] = r.tf_ruckig
    for name, tf in rows.items():
        row = f"| {name} | {tf:.3f} |"
        assert row in text, f"docs/design.md, the fastest t_f: expected the row {row}"


def test_bench_replanning_prints_today_beside_the_fast_engine() -> None:
    task = load_task(EXAMPLE_TASK)
    r = bench_replanning(task, task.planner, workers=2, reference_generations=300 if BENCH_QUICK else 600,
                         repeat=1 if BENCH_QUICK else 2)  # fmt: skip
    for name, sides, ratio in (("one path " + r.path_id, r.one_path, r.path_ratio),
                               ("whole task, one process each", r.whole_task, r.task_ratio)):  # fmt: skip
        fast, today = sides["cadence"], sides["pymoo"]
        print(f"\n{name}: CPU {fast.cpu:.3f} s (wall {fast.wall:.3f}), today {today.cpu:.3f} s "
              f"(wall {today.wall:.3f}), ratio {ratio:.1f}x; tries {r.tries}, interleaved")  # fmt: skip
        assert len(fast.cpu_s) == len(today.cpu_s) == r.tries  # equal tries on both sides
    print(f"whole task on {r.workers} processes (the fast engine): {r.task_parallel_s:.3f} s wall; "
          f"warm after a {r.edit_deg:g} deg edit: {r.warm_s:.3f} s; protocol {r.protocol}")  # fmt: skip
    assert set(r.protocol) == {"tries", "interleaved", "workers", "load"}
    assert set(r.to_json()["one_path"]["cadence"]) >= {"cpu_s", "wall_s", "cpu_spread"}
    for pid in r.hv:
        print(f"hypervolume {pid}: {r.hv[pid]:.4f} (today {r.pymoo_hv[pid]:.4f}, warm {r.warm_hv[pid]:.4f})")
    assert min(r.hv.values()) >= 0.99
    assert min(r.warm_hv.values()) >= 0.99
