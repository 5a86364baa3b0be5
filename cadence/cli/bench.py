"""`cadence bench …`: benchmarks that print their figures, and the ratio to a baseline measured in the
same run."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from rich.table import Table

from cadence.cli._common import (
    Commands,
    add_planner_flags,
    arg,
    err,
    flags_from,
    out,
    positive_int,
    task_with_overrides,
)
from common.runtime.resources import EXAMPLE_TASK

if TYPE_CHECKING:
    from cadence.bench.planning import Replanning


cli = Commands()
SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"  # the recordings beside a checkout


cli.group(
    "bench",
    steps={"dest": "bench", "metavar": "BENCH"},
    help="benchmarks that print their figures and ratios to baselines",
)


@cli.command(
    "bench plan",
    help="planning time vs the straightforward evaluation; hull vs exact vs Ruckig",
    description="On the longest path of TASK: full planning time, the same NSGA-II generations "
    "evaluated the straightforward way, both hypervolumes, and the fastest t_f under hull and exact "
    "limits and as Ruckig stop-at-every-waypoint moves. The last line is the figures as JSON.",
)
@arg(
    "--repeat",
    type=positive_int(1),
    default=3,
    help="tries of each side, interleaved; medians are shown (default 3)",
)
@arg("--workers", type=positive_int(1), default=2, help="processes for the whole task (default 2)")
@flags_from(add_planner_flags, task_option=True)
def cmd_bench_plan(args: argparse.Namespace) -> int:
    from cadence.bench.planning import bench_plan, bench_replanning
    from cadence.bench.protocol import sides_json

    task = task_with_overrides(args)
    with err.status("today's planner and the fast one, path by path and the whole task …"):
        rp = bench_replanning(task, task.planner, workers=args.workers, repeat=args.repeat)
    replanning_table(rp)
    r = bench_plan(task, task.planner, repeat=args.repeat)
    table = Table(
        title=f"bench plan: {task.name}, path '{r.path_id}' (W = {r.n_waypoints}), "
        f"pop {r.population}, {r.generations} generations"
    )
    table.add_column("figure")
    table.add_column("Cadence", justify="right")
    table.add_column("straightforward", justify="right")
    table.add_column("ratio", justify="right")
    table.caption = (
        f"CPU seconds, medians of {r.protocol['tries']} tries each, interleaved; load {r.protocol['load']}"
    )
    table.add_row("full planning (CPU s)", f"{r.plan_s:.3f}", f"{r.naive_plan_s:.3f}", f"{r.plan_ratio:.1f}×")
    table.add_row(
        "one generation's evaluation (CPU ms)",
        f"{r.eval_ms:.2f}",
        f"{r.naive_eval_ms:.1f}",
        f"{r.eval_ratio:.1f}×",
    )
    table.add_row(
        "hypervolume (same normalisation)", f"{r.hv:.4f}", f"{r.naive_hv:.4f}", f"{r.hv / r.naive_hv:.4f}"
    )
    out.print(table)
    limits = Table(title="fastest t_f of the same path")
    limits.add_column("method")
    limits.add_column("t_f (s)", justify="right")
    limits.add_row("hull limits (paper's control-point bounds)", f"{r.tf_hull:.3f}")
    limits.add_row("exact limits (Cadence default)", f"{r.tf_exact:.3f}")
    ruckig = "ruckig not installed (uv sync --extra bench)" if r.tf_ruckig is None else f"{r.tf_ruckig:.3f}"
    limits.add_row("Ruckig, stopping at every waypoint", ruckig)
    out.print(limits)
    out.print(
        "straightforward = the same NSGA-II (population, generations, seed, repair) with one "
        "make_interp_spline per individual and jerk² sampled at 1000 points; end polishing shared."
    )
    figures = {
        "path_id": r.path_id,
        "plan_s": r.plan_s,
        "naive_plan_s": r.naive_plan_s,
        "plan_ratio": r.plan_ratio,
        "eval_ms": r.eval_ms,
        "naive_eval_ms": r.naive_eval_ms,
        "eval_ratio": r.eval_ratio,
        "plan": sides_json(r.plan),
        "evaluation": sides_json(r.evaluation),
        "hv": r.hv,
        "naive_hv": r.naive_hv,
        "tf_hull": r.tf_hull,
        "tf_exact": r.tf_exact,
        "tf_ruckig": r.tf_ruckig,
    }
    figures["replanning"] = rp.to_json()
    one = rp.one_path
    figures["one_path"] = {"path": rp.path_id, "cadence_cpu_s": one["cadence"].cpu,
                           "pymoo_cpu_s": one["pymoo"].cpu, "cadence_wall_s": one["cadence"].wall,
                           "pymoo_wall_s": one["pymoo"].wall,
                           "hv_ratio": rp.hv[rp.path_id] / rp.pymoo_hv[rp.path_id]}  # fmt: skip
    figures["protocol"] = rp.protocol
    print(json.dumps(figures))
    return 0


def replanning_table(r: Replanning) -> None:
    t = Table(title=f"replanning: fast engine vs today's (pymoo's loop), same run; hypervolume as a share "
                    f"of a {r.reference_generations}-generation reference",
              caption=f"medians of {r.tries} tries each, interleaved; load {r.protocol['load']}")  # fmt: skip
    t.add_column("figure")
    t.add_column("fast", justify="right")
    t.add_column("today", justify="right")
    t.add_column("ratio", justify="right")
    for name, sides, ratio in ((f"one path '{r.path_id}'", r.one_path, r.path_ratio),
                               ("whole task, one process each", r.whole_task, r.task_ratio)):  # fmt: skip
        fast, today = sides["cadence"], sides["pymoo"]
        t.add_row(f"{name}: CPU s (wall s)", f"{fast.cpu:.3f} ({fast.wall:.3f})",
                  f"{today.cpu:.3f} ({today.wall:.3f})", f"{ratio:.1f}×")  # fmt: skip
    t.add_row(f"whole task on {r.workers} processes, the fast engine alone (wall s)",
              f"{r.task_parallel_s:.3f}", "", "")  # fmt: skip
    t.add_row(f"whole task after a {r.edit_deg:g}° edit, warm (s)", f"{r.warm_s:.3f}", "", "")
    for pid in r.hv:
        t.add_row(f"hypervolume '{pid}' (warm after the edit)", f"{r.hv[pid]:.4f} ({r.warm_hv[pid]:.4f})",
                  f"{r.pymoo_hv[pid]:.4f}", f"{r.hv[pid] / r.pymoo_hv[pid]:.4f}")  # fmt: skip
    out.print(t)


@cli.command(
    "bench convergence",
    help="hypervolume against generations, as a share of a long reference run's",
    description="How the default number of NSGA-II generations was chosen: for the longest path of "
    "TASK, the archive's hypervolume after each checkpoint for several seeds, as a share of a long "
    "reference run's, under the reference front's normalisation.",
)
@arg("--seeds", type=positive_int(1), default=5, help="number of seeds (default 5)")
@arg("--reference", type=positive_int(10), default=1500, help="reference generations (1500)")
@flags_from(add_planner_flags, task_option=True)
def cmd_bench_convergence(args: argparse.Namespace) -> int:
    from cadence.bench.planning import convergence
    from common.trajectory.planner import DEFAULT_GENERATIONS

    task = task_with_overrides(args)
    checkpoints = [10, 20, 40, 60, 80, 120, 200]
    seeds = list(range(1, args.seeds + 1))
    with err.status(f"reference run: {args.reference} generations …"):
        c = convergence(task, task.planner, seeds, args.reference, checkpoints)
    table = Table(
        title=f"hypervolume as a share of a {c.reference_generations}-generation run's, path '{c.path_id}' "
        f"({task.planner.constraints} limits)"
    )
    table.add_column("seed")
    for g in checkpoints:
        table.add_column(f"gen {g}", justify="right")
    table.add_column(
        f"default ({task.planner.generations or DEFAULT_GENERATIONS}, polished)", justify="right"
    )
    for seed in seeds:
        table.add_row(str(seed), *(f"{x:.4f}" for x in c.shares[seed]), f"{c.final[seed]:.4f}")
    out.print(table)
    print(
        json.dumps({"path_id": c.path_id, "checkpoints": checkpoints, "shares": c.shares, "final": c.final})
    )
    return 0


@cli.command(
    "bench store",
    help="query latency of the Pareto store on loopback, stored and while planning",
    description="Starts pareto_store as a process on a fresh data folder, queries it while it plans "
    "TASK's paths and then for a stored set; prints the latency percentiles.",
)
@arg("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
@arg("--queries", type=positive_int(1), default=500, help="queries of the stored set")
def cmd_bench_store(args: argparse.Namespace) -> int:
    import asyncio

    from cadence.bench.store import StoreBench, bench_store

    r = asyncio.run(bench_store(args.task, args.queries))
    p = StoreBench.pct
    table = Table(title="pareto_store query latency on loopback (store as a process)")
    for col in ("queries", "n", "p50 (ms)", "p99 (ms)", "p99.9 (ms)", "max (ms)"):
        table.add_column(col, justify="right" if col != "queries" else "left")
    for name, v in (("stored set", r.stored_ms), ("while planning", r.during_planning_ms)):
        table.add_row(
            name, str(len(v)), f"{p(v, 50):.2f}", f"{p(v, 99):.2f}", f"{p(v, 99.9):.2f}", f"{max(v):.2f}"
        )
    out.print(table)
    return 0


@cli.command(
    "bench plant",
    help="a plant of N cells as deployed (one real), each its own router, behind line and plant routers",
    description="Per N: N cells, each its own router (mTLS, its own CA and access control) and its "
    "services' accounts putting a cell's traffic at speed 1; a line router per 10 cells and the plant's "
    "router over them; the first cell a real one (its services as `cadence demo --processes` runs them, "
    "at speed 1, on its own accounts); the cells' routers send the plant its share on this host's "
    "network interface when it has one. Rounds of two phases: the cells alone, then with the plant "
    "monitor and `cadence record --plant` (the plant's processes at its priority, nice 10). Prints the "
    "in-cell robot/state and separation p50/p99 of each kind of phase and the shift (the real cell's "
    "apart), beside how late a thread of the host woke in the same phases (the host's own delay), "
    "each phase's p99, every process group's CPU, what was delivered, how far behind the plant view "
    "was, and the plant recording's bytes per cell and day. The last line is the figures as JSON.",
)
@arg("--cells", type=positive_int(1), action="append", metavar="N", help="cells (repeatable; default 50)")
@arg("--seconds", type=float, default=20.0, help="each phase's length (default 20)")
@arg("--per-line", type=positive_int(1), default=10, help="cells behind one line router (default 10)")
@arg("--rounds", type=positive_int(1), default=3, help="pairs of phases, alone then read (default 3)")
@arg("--no-real-cell", action="store_true", help="every cell synthetic (by default the first is a real one)")
def cmd_bench_plant(args: argparse.Namespace) -> int:
    import asyncio

    from rich.console import Console

    from cadence.bench.plant import PlantFigures, bench_plant, plant_table

    figures: list[PlantFigures] = []
    for n in args.cells or [50]:
        with err.status(f"bench plant: {n} cells"):
            run = bench_plant(
                n, args.seconds, args.per_line, args.rounds, not args.no_real_cell, progress=err
            )
            figures.append(asyncio.run(run))
    wide = Console(width=max(out.width, 170))  # thirteen columns: narrower, each folds to nothing
    for table in plant_table(figures):
        wide.print(table)
    print(json.dumps([f.to_dict() for f in figures]))
    return 0


@cli.command(
    "bench executor",
    help="tick timing of the 500 Hz servo loop, and the time to prepare a path's samples",
    description="Runs the executor's servo loop (pinned, SCHED_FIFO when permitted) on a backend for "
    "SECONDS, servoing the longest path of TASK forward and back while the state is read at 50 Hz, and "
    "prints the tick error percentiles (|tick time - deadline|), the overruns and prepare_ms (h to "
    "validated 500 Hz samples for the slowest trajectory of that path). The last line is JSON. With "
    "--load: the executor itself, as a cell runs it (its servo in a process of its own, the sim arm), kept "
    "busy (5,000 messages every 50 ms to decode, two busy loops, a sensor at 20 Hz whose readings' adoption "
    "it measures), beside cyclictest on the servo's core in the same window; the servo's period error and "
    "overruns are printed beside cyclictest's, and the adoption.",
)
@arg("--backend", choices=("sim", "ur_rtde"), default="sim")
@arg("--seconds", type=float, default=20.0, help="how long to servo (default 20)")
@arg("--host", default="127.0.0.1", help="ur_rtde: the controller's address")
@arg("--core", type=int, default=None, help="core for the servo thread (default: the last)")
@arg("--fifo-priority", type=int, default=80, help="SCHED_FIFO priority; 0 for none")
@arg("--task", default=None, metavar="TASK.toml", help="default: box_filling")
@arg("--load", action="store_true", help="the whole executor under load, beside cyclictest (sim only)")
@arg("--busy", type=int, default=2, help="--load: busy loops beside it (default 2)")
@arg("--json", action="store_true", help="print only the JSON line")
def cmd_bench_executor(args: argparse.Namespace) -> int:
    from cadence.bench.servo_loop import bench_executor
    from services.executor import RobotUnavailable

    if args.load:
        return bench_executor_load(args)
    if not args.json:
        out.print(f"[dim]servo loop on the {args.backend} backend for {args.seconds:g} s …[/dim]")
    try:
        r = bench_executor(args.backend, args.seconds, args.host, args.core, args.fifo_priority, args.task)
    except RobotUnavailable as exc:
        print(f"cadence bench executor: {exc}", file=sys.stderr)
        return 1
    if not args.json:
        for w in r.warnings:
            out.print(f"[yellow]warning:[/yellow] {w}")
        t = r.timing
        table = Table(title=f"servo loop, {r.backend} backend, {t['ticks']} ticks ({r.motions} motions)")
        for col in ("period", "p50", "p99", "p99.9", "max", "overruns", "prepare"):
            table.add_column(col, justify="right")
        table.add_row(
            f"{t['period_us']} µs",
            *(f"{t[k]:.1f} µs" for k in ("p50_err_us", "p99_err_us", "p999_err_us", "max_err_us")),
            str(t["overruns"]),
            f"{r.prepare_ms:.2f} ms",
        )
        out.print(table)
    print(json.dumps(r.as_json()))
    if r.aborted:
        print(f"cadence bench executor: {r.aborted}", file=sys.stderr)
        return 1
    return 0


def bench_executor_load(args: argparse.Namespace) -> int:
    from cadence.bench.executor_load import bench_executor_load

    if args.backend != "sim":
        print("cadence bench executor: --load runs on the sim backend only", file=sys.stderr)
        return 2
    if not args.json:
        out.print(f"[dim]the executor under load for {args.seconds:g} s, beside cyclictest …[/dim]")
    r = bench_executor_load(args.seconds, args.busy)
    if not args.json:
        for w in r.warnings:
            out.print(f"[yellow]warning:[/yellow] {w}")
        s, ct, a = r.servo, r.cyclictest, r.adoption
        table = Table(title=f"period error on the servo's core, {args.busy} busy loops, load {r.load[0]:.1f}")
        for col in ("", "ticks", "late", "longest run", "p50", "p99", "p99.9", "max"):
            table.add_column(col, justify="right")

        def us(x: object) -> str:
            return "—" if x is None else f"{x:g} µs"

        table.add_row("servo process", str(s["ticks"]), str(s["overruns"]), str(s["longest_overrun_run"]),
                      *(us(s[k]) for k in ("p50_us", "p99_us", "p99_9_us", "max_us")))  # fmt: skip
        if "error" in ct:
            table.add_row("cyclictest", ct["error"], *([""] * 6))
        else:
            table.add_row("cyclictest", str(ct["ticks"]), str(ct["late"]), "",
                          *(us(ct[k]) for k in ("p50_us", "p99_us", "p99_9_us", "max_us")))  # fmt: skip
        out.print(table)
        lk = a["looks"]
        out.print(f"{a['readings']} readings sent (refused by the executor: {a['refused'] or 'none'}). The "
                  f"reaction, a fall of the guard's σ → the servo playing it, {a['n']} times: p50 "
                  f"{a['p50_ms']} ms, p99.9 {a['p99_9_ms']} ms, max {a['max_ms']} ms ({a['cuts']} taken by "
                  f"the servo itself). The executor's looks alone: p50 {lk['p50_ms']} ms, p99.9 "
                  f"{lk['p99_9_ms']} ms, max {lk['max_ms']} ms, late {lk['late']}. Lease lapses "
                  f"{a['lease_lapses']}; the flood: {r.flood}")  # fmt: skip
    print(json.dumps(r.as_json()))
    return 0
