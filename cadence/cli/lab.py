"""The lab's commands: `cadence demo`, `cadence report`, `cadence study`."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from cadence.cli._common import SERVICES, err, out, positive_int
from common.runtime.errors import InputError
from common.runtime.resources import EXAMPLE_TASK
from common.trajectory.task import load_task


def cmd_demo(args: argparse.Namespace) -> int:
    import asyncio

    from cadence.demo import DemoOptions, run_demo

    kills = []
    for spec in args.kill:
        name, _, at = spec.partition("@")
        if name not in SERVICES or not at:
            raise InputError(
                f"--kill {spec}: expected SERVICE@SECONDS with SERVICE one of {', '.join(SERVICES)}"
            )
        kills.append((name, float(at)))
    opts = DemoOptions(
        duration_s=args.duration,
        speed=args.speed,
        out=Path(args.out),
        seed=args.seed,
        task=Path(args.task),
        kill=tuple(kills),
        live=not args.no_live,
    )
    t0 = time.monotonic()
    summary = asyncio.run(run_demo(opts, out))
    wall = time.monotonic() - t0
    table = Table(title=f"cadence demo: {args.duration:g} s of data time in {wall:.0f} s")
    for col in (
        "cycles",
        "φ [cycles/min]",
        "errors",
        "ε [errors/cycle]",
        "windows",
        "k steps ↓ / ↑",
        "restarts",
    ):
        table.add_column(col, justify="right")
    table.add_row(
        str(summary["cycles"]),
        f"{summary['productivity_per_min']:.2f}",
        str(summary["errors"]),
        f"{summary['error_rate']:.3f}",
        str(len(summary["windows"])),
        f"{summary['k_steps_down']} / {summary['k_steps_up']}",
        ", ".join(f"{k} {v}" for k, v in summary["restarts"].items() if v) or "none",
    )
    out.print(table)
    out.print(
        f"written: {args.out}/summary.json and a report (index.html, rr_k.png, pareto.png, cycles.png); "
        f"service logs in {args.out}/logs"
    )
    bad = {n: c for n, c in summary["exit_codes"].items() if c != 0}
    if bad:
        err.print(f"services that did not exit cleanly: {bad}")
        return 1
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from cadence.report import from_demo, from_mcap, write_report

    src = Path(args.source)
    if src.is_dir():
        run = from_demo(src)
    elif src.suffix == ".mcap" or src.is_file():
        run = from_mcap(src, Path(args.sets) if args.sets else None)
    else:
        raise InputError(f"{src}: neither a demo folder nor an MCAP recording")
    written = write_report(run, Path(args.out), args.rr_rest)
    table = Table(title=f"cadence report: {src}")
    for col in ("cycles", "φ [cycles/min]", "errors", "ε [errors/cycle]", "windows", "selections"):
        table.add_column(col, justify="right")
    table.add_row(
        str(len(run.cycles)),
        f"{run.productivity_per_min:.2f}",
        str(run.errors),
        f"{run.error_rate:.3f}",
        str(len(run.windows)),
        str(len(run.selections)),
    )
    out.print(table)
    if not run.sets:
        err.print("no Pareto sets in the source: pass --sets <data>/executor for the front and cycle figures")
    out.print(f"written to {args.out}: {', '.join(written)}")
    return 0


def cmd_study(args: argparse.Namespace) -> int:
    from cadence.plots import study_figure
    from cadence.study import CONDITIONS, METRICS, NAMES, compare, motions, simulate, subjects
    from common.runtime.storage import atomic_write
    from common.trajectory.planner import plan_path

    task = load_task(args.task)
    cohort = subjects(args.subjects, args.seed)
    outcomes = []
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=err
    ) as progress:
        plan = progress.add_task("planning the Pareto sets", total=len(task.paths))
        sols = {}
        for pid, path in task.paths.items():
            sols[pid] = [s.h for s in plan_path(path, task.limits, task.planner).solutions]
            progress.advance(plan)
        moves = motions(task, sols)
        n_per_path = {pid: len(v) for pid, v in sols.items()}
        runs = progress.add_task("simulating subjects × conditions", total=len(cohort) * len(CONDITIONS))
        for sub in cohort:
            for c in CONDITIONS:
                outcomes.append(simulate(task, moves, n_per_path, sub, c, args.minutes))
                progress.advance(runs)
    result = compare(outcomes)
    table = Table(
        title=f"SIMULATED study: {len(cohort)} operator twins × {args.minutes:g} min (like Table I)"
    )
    for col in ("condition", "φ [cycles/min]", "ε [errors/cycle]", "mean RR / rest"):
        table.add_column(col, justify="right" if col != "condition" else "left")
    for c in CONDITIONS:
        ms = result["means_sd"][c]
        table.add_row(f"({c}) {NAMES[c]}", *(f"{ms[m][0]:.3f} ± {ms[m][1]:.3f}" for m in METRICS))
    out.print(table)
    tests = Table(title="Wilcoxon signed-rank, paired by subject (simulated): p (median difference)")
    tests.add_column("pair")
    for col in ("φ", "ε", "mean RR / rest"):
        tests.add_column(col, justify="right")
    for pair, row in result["wilcoxon"].items():
        tests.add_row(pair, *(f"{row[m]['p']:.2g} ({row[m]['median_difference']:+.3f})" for m in METRICS))
    out.print(tests)
    dest = Path(args.out)
    dest.mkdir(parents=True, exist_ok=True)
    doc = {
        "simulated": True,
        "subjects": len(cohort),
        "minutes": args.minutes,
        "seed": args.seed,
        "conditions": NAMES,
        **result,
        "per_subject": [
            {"subject": o.subject, "condition": o.condition, "cycles": o.cycles, "errors": o.errors,
             **{m: getattr(o, m) for m in METRICS}}
            for o in outcomes
        ],
    }  # fmt: skip
    atomic_write(dest / "study.json", json.dumps(doc, indent=1).encode())
    values = {
        c: {m: [getattr(o, m) for o in outcomes if o.condition == c] for m in METRICS} for c in CONDITIONS
    }
    atomic_write(dest / "study.png", study_figure(values, NAMES))
    out.print(f"written: {dest}/study.json, {dest}/study.png")
    return 0


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    report = sub.add_parser(
        "report",
        help="figures and an index.html (φ, ε, cycle times, events) from a recording or a demo folder",
        description="Reads an MCAP recording or a `cadence demo` folder and writes to DIR: rr_k.png (mean RR "
        "per window and the selected k, like the paper's Fig. 6), pareto.png (each path's front, its N "
        "solutions and the k actually used), cycles.png (q, q̇, q̈ and jerk of the first and last cycle) "
        "and index.html with the production rate φ, the error rate ε, cycle times and events.",
    )
    report.add_argument("source", metavar="FILE.mcap|DEMO_DIR")
    report.add_argument("--out", required=True, metavar="DIR")
    report.add_argument(
        "--sets", metavar="FOLDER", help="Pareto sets cached by an executor (<data>/executor)"
    )
    report.add_argument("--rr-rest", type=float, help="the operator's resting mean RR for the figure, s")
    report.set_defaults(func=cmd_report)

    study = sub.add_parser(
        "study",
        help="the paper's comparison of conditions on simulated operators (labelled as simulated)",
        description="Conditions (a) minimum time, (b) minimum jerk and (c) tuned online, each run for every "
        "simulated subject (an operator twin with its own seed, resting RR and tolerance) in simulated time "
        "as fast as the machine allows. Prints a table like the paper's Table I (φ, ε, normalised mean RR) "
        "and Wilcoxon signed-rank p-values for a-b, a-c, b-c; writes DIR/study.json and DIR/study.png.",
    )
    study.add_argument("--subjects", type=positive_int(2), default=12, help="simulated subjects (default 12)")
    study.add_argument("--minutes", type=float, default=10.0, help="per condition and subject (default 10)")
    study.add_argument("--seed", type=int, default=1, help="the cohort's seed (default 1)")
    study.add_argument("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
    study.add_argument("--out", default="study-out", metavar="DIR", help="output folder (default study-out)")
    study.set_defaults(func=cmd_study)

    demo = sub.add_parser(
        "demo",
        help="the whole closed loop on this machine: operator twin, every service, simulated UR16e",
        description="Opens a Zenoh router on loopback, plans the task if its sets are not stored, starts "
        "every service as its own process (ECG gateway with the operator twin, HRV analyser, Pareto store, "
        "decision maker, executor with the simulated UR16e), restarts any that dies, shows a live view, "
        "stops them all with SIGTERM and writes DIR/summary.json, DIR/rr_k.png (mean RR and k over time) "
        "and DIR/cycles.png (joint positions of the first and last cycle).",
    )
    demo.add_argument("--duration", type=float, default=600.0, help="data time to run, s (default 600)")
    demo.add_argument("--speed", type=float, default=8.0, help="data time per wall time (default 8)")
    demo.add_argument("--out", default="demo-out", metavar="DIR", help="output folder (default demo-out)")
    demo.add_argument("--seed", type=int, default=1, help="the operator twin's seed (default 1)")
    demo.add_argument("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
    demo.add_argument(
        "--kill",
        action="append",
        default=[],
        metavar="SERVICE@S",
        help="SIGKILL a service at data time S (repeatable): shows the supervisor restarting it",
    )
    demo.add_argument("--no-live", action="store_true", help="no live view (for logs and CI)")
    demo.set_defaults(func=cmd_demo)
