"""`cadence plan`: the Pareto sets of a task program, as files and figures."""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from cadence.cli._common import Commands, add_planner_flags, arg, err, flags_from, out, task_with_overrides

cli = Commands()


@cli.command(
    "plan",
    help="compute the time/jerk Pareto set of every path of a task program",
    description="For every path of TASK: NSGA-II over the time intervals, ASF downsampling to N "
    "solutions; writes DIR/<path_id>.json and DIR/<path_id>.png.",
)
@arg("task", metavar="TASK.toml", help="task program (see deploy/tasks/box_filling.toml)")
@arg("--out", required=True, metavar="DIR", help="output folder (created if missing)")
@arg("--no-plots", action="store_true", help="write the JSON files only")
@arg("--ship", metavar="FILE.json", default=None,
     help="also write the sets as one file to ship (deploy/sets/): the store serves them and the simulated "
     "study runs on them instead of planning, the same bytes on every machine")  # fmt: skip
@arg("--workers", type=int, default=None, metavar="N",
     help="paths planned at once, one process each (default: the cores this process may use)")  # fmt: skip
@flags_from(add_planner_flags)
def cmd_plan(args: argparse.Namespace) -> int:
    began = time.perf_counter()  # the command's whole run is said beside the planning's (issue 76)
    from cadence.lab.plots import pareto_figure
    from common.runtime.storage import write_readable
    from common.trajectory.planner import content_hash
    from common.trajectory.pool import plan_paths
    from common.trajectory.shipped import as_message, write_shipped
    from common.trajectory.task import continuity_gaps

    task = task_with_overrides(args)
    for gap in continuity_gaps(task):
        err.print(f"[yellow]warning[/]: {task.source}: cycle: {gap} (the executor will refuse this cycle)")
    s = task.planner
    workers = args.workers or len(os.sched_getaffinity(0))
    started = time.perf_counter()
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=err,
        transient=False,
    ) as progress:
        bars = {p: progress.add_task(f"{p:<14} NSGA-II ({s.constraints})", total=None) for p in task.paths}

        def advance(pid: str, g: int, n: int) -> None:
            progress.update(bars[pid], completed=g, total=n)

        results = plan_paths(list(task.paths.values()), task.limits, s, workers, progress=advance)
    wall = time.perf_counter() - started

    # Everything is computed before anything is written: a failure leaves DIR as it was.
    outdir = Path(args.out)
    for result in results.values():
        write_readable(outdir / f"{result.path.id}.json", json.dumps(result.to_json(), indent=1).encode())
        if not args.no_plots:
            write_readable(outdir / f"{result.path.id}.png", pareto_figure(result))
    if args.ship:
        msgs = [as_message(r, content_hash(r.path, task.limits, s)) for r in results.values()]
        digest = write_shipped(Path(args.ship), task, msgs)
        out.print(f"shipped sets {digest[:12]} → {args.ship}")

    table = Table(
        title=f"{task.name}: Pareto sets ({s.constraints} limits) → {outdir}",
        caption=f"{wall:.2f} s planning on {workers} process{'es' if workers > 1 else ''}, "
        f"{time.perf_counter() - began:.2f} s in all (the plots and files too)",
    )
    for col in (
        "path",
        "W",
        "front",
        "N",
        "t_f k=1 [s]",
        f"t_f k={s.n_solutions} [s]",
        "f_jerk k=1",
        "time [s]",
    ):
        table.add_column(col, justify="right" if col != "path" else "left")
    for result in results.values():
        sols = result.solutions
        if len(sols) < s.n_solutions:
            err.print(f"[yellow]warning[/]: path '{result.path.id}': only {len(sols)} distinct solutions")
        table.add_row(
            result.path.id,
            str(len(result.path.waypoints)),
            str(len(result.front)),
            str(len(sols)),
            f"{sols[0].t_f:.3f}",
            f"{sols[-1].t_f:.3f}",
            f"{sols[0].f_jerk:.4g}",
            f"{result.seconds:.2f}",
        )
    out.print(table)
    return 0
