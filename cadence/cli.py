"""`cadence`: the one console script (DESIGN §10). Every subcommand has --help; bad input exits 2 with
one line naming the file and field; nothing is written when the input is bad."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

from msgspec import structs
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from common.cell import SERVICES as CELL_SERVICES
from common.errors import BusError, CadenceError, InputError
from common.resources import EXAMPLE_TASK
from common.task import Task, continuity_gaps, load_task

out = Console()
err = Console(stderr=True)


def _positive_int(minimum: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from exc
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return parse


def _task_with_overrides(args: argparse.Namespace) -> Task:
    task = load_task(args.task)
    overrides = {
        "seed": args.seed,
        "n_solutions": args.n,
        "population": args.pop,
        "generations": args.generations,
        "constraints": args.constraints,
    }
    settings = structs.replace(task.planner, **{k: v for k, v in overrides.items() if v is not None})
    return replace(task, planner=settings)


def cmd_plan(args: argparse.Namespace) -> int:
    from cadence.plots import pareto_figure
    from common.planner import plan_path
    from common.storage import atomic_write

    task = _task_with_overrides(args)
    for gap in continuity_gaps(task):
        err.print(f"[yellow]warning[/]: {task.source}: cycle: {gap} (the executor will refuse this cycle)")
    s = task.planner
    results = []
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=err,
        transient=False,
    ) as progress:
        for path in task.paths.values():
            bar = progress.add_task(f"{path.id:<14} NSGA-II ({s.constraints})", total=None)
            t0 = time.perf_counter()
            result = plan_path(
                path, task.limits, s, progress=lambda g, n, b=bar: progress.update(b, completed=g, total=n)
            )
            results.append((result, time.perf_counter() - t0))

    # Everything is computed before anything is written: a failure leaves DIR as it was.
    outdir = Path(args.out)
    for result, _ in results:
        atomic_write(outdir / f"{result.path.id}.json", json.dumps(result.to_json(), indent=1).encode())
        if not args.no_plots:
            atomic_write(outdir / f"{result.path.id}.png", pareto_figure(result))

    table = Table(title=f"{task.name}: Pareto sets ({s.constraints} limits) → {outdir}")
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
    for result, secs in results:
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
            f"{secs:.2f}",
        )
    out.print(table)
    return 0


def cmd_bench_plan(args: argparse.Namespace) -> int:
    from cadence.bench import bench_plan

    task = _task_with_overrides(args)
    r = bench_plan(task, task.planner, repeat=args.repeat)
    table = Table(
        title=f"bench plan: {task.name}, path '{r.path_id}' (W = {r.n_waypoints}), "
        f"pop {r.population}, {r.generations} generations"
    )
    table.add_column("figure")
    table.add_column("Cadence", justify="right")
    table.add_column("straightforward", justify="right")
    table.add_column("ratio", justify="right")
    table.add_row("full planning [s]", f"{r.plan_s:.3f}", f"{r.naive_plan_s:.3f}", f"{r.plan_ratio:.1f}×")
    table.add_row(
        "one generation's evaluation [ms]",
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
    limits.add_column("t_f [s]", justify="right")
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
        "hv": r.hv,
        "naive_hv": r.naive_hv,
        "tf_hull": r.tf_hull,
        "tf_exact": r.tf_exact,
        "tf_ruckig": r.tf_ruckig,
    }
    print(json.dumps(figures))
    return 0


def cmd_bench_convergence(args: argparse.Namespace) -> int:
    from cadence.bench import convergence
    from common.planner import DEFAULT_GENERATIONS

    task = _task_with_overrides(args)
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


def cmd_bench_store(args: argparse.Namespace) -> int:
    import asyncio

    from cadence.bench import StoreBench, bench_store

    r = asyncio.run(bench_store(args.task, args.queries))
    p = StoreBench.pct
    table = Table(title="pareto_store query latency on loopback (store as a process)")
    for col in ("queries", "n", "p50 [ms]", "p99 [ms]", "p99.9 [ms]", "max [ms]"):
        table.add_column(col, justify="right" if col != "queries" else "left")
    for name, v in (("stored set", r.stored_ms), ("while planning", r.during_planning_ms)):
        table.add_row(
            name, str(len(v)), f"{p(v, 50):.2f}", f"{p(v, 99):.2f}", f"{p(v, 99.9):.2f}", f"{max(v):.2f}"
        )
    out.print(table)
    return 0


def cmd_bench_executor(args: argparse.Namespace) -> int:
    from cadence.bench import bench_executor
    from services.executor.backends import RobotUnavailable

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


def _stop_on_signals():
    """An event set by SIGTERM or SIGINT (Ctrl-C), for the commands that run until stopped."""
    import asyncio

    from common.service import on_stop_signals

    stop = asyncio.Event()
    on_stop_signals(asyncio.get_running_loop(), stop.set)
    return stop


def cmd_record(args: argparse.Namespace) -> int:
    import asyncio

    from cadence.recording import record
    from common.bus import Bus

    async def go() -> int:
        stop = _stop_on_signals()
        if args.duration is not None:
            asyncio.get_running_loop().call_later(args.duration, stop.set)
        async with await Bus.open(_bus_config(args, "peer"), args.cell) as bus:
            keys = args.keys or [bus.key("**")]
            err.print(f"recording {', '.join(keys)} to {args.output} (Ctrl-C to stop)")
            bus.token(bus.key("health/recorder"))  # a recorder is running (zenoh liveliness)
            rec = await record(
                bus,
                Path(args.output),
                keys,
                stop,
                json=args.json,
                on_first=lambda key: err.print(f"first message: {key}", markup=False, highlight=False),
            )
        err.print(f"{rec.count} messages written to {args.output}")
        return 0

    return asyncio.run(go())


def cmd_replay(args: argparse.Namespace) -> int:
    import asyncio

    from cadence.recording import replay
    from common.bus import Bus

    async def go() -> int:
        async with await Bus.open(_bus_config(args, "peer"), "cell1") as bus:
            if args.wait is not None:
                await asyncio.sleep(args.wait)  # let subscribers on other hosts discover this session
            n = await replay(bus, Path(args.recording), args.speed, args.keys)
        err.print(f"{n} messages replayed from {args.recording}")
        return 0

    return asyncio.run(go())


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
    from common.planner import plan_path
    from common.storage import atomic_write
    from common.study import CONDITIONS, METRICS, NAMES, compare, motions, simulate, subjects

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


def _record_peaks(args: argparse.Namespace):
    from common.ecg_records import read_record
    from common.rpeaks import detect

    rec = read_record(args.record, fs=args.fs)
    return rec, detect(rec.uv, rec.fs, chunk=round(rec.fs)) / rec.fs


def cmd_hrv_peaks(args: argparse.Namespace) -> int:
    rec, peaks = _record_peaks(args)
    print(json.dumps({"fs": rec.fs, "peaks_s": [round(float(t), 6) for t in peaks]}))
    return 0


def cmd_hrv_windows(args: argparse.Namespace) -> int:
    from common.hrv import intervals, windows

    rec, peaks = _record_peaks(args)
    for w in windows(intervals(peaks), args.window, end_s=len(rec.uv) / rec.fs):
        print(
            json.dumps(
                {
                    "start_s": w.start_s,
                    "end_s": w.end_s,
                    "mean_rr_s": w.mean_rr_s,
                    "n_beats": w.n_beats,
                    "excluded": w.excluded,
                    "quality": w.quality,
                    "reason": w.reason,
                }
            )
        )
    return 0


def cmd_decide(args: argparse.Namespace) -> int:
    from common.decision import Params, State, dec, step

    try:
        params = Params.of(args.rr_rest, args.n, args.sigma_r, args.rr_s_offset, args.sigma_s)
    except (ValueError, ArithmeticError) as exc:
        raise InputError(f"decide: {exc}") from exc
    values = []
    for lineno, line in enumerate(sys.stdin, start=1):
        text = line.strip()
        try:
            value = dec(text)
            ok = value.is_finite() and value > 0
        except ArithmeticError:
            ok = False
        if not ok:
            raise InputError(f"<stdin>:{lineno}: expected a positive number of seconds, got {text!r}")
        values.append(value)
    state = State.initial(params)
    lines = []
    for value in values:
        state = step(params, state, value).state
        lines.append(str(state.k))
    sys.stdout.write("".join(f"{x}\n" for x in lines))
    return 0


def _bench_hrv_windows(args: argparse.Namespace) -> int:
    from cadence.bench import bench_hrv_windows
    from common.ecg_noise import VARIANTS

    variants = tuple(args.variants.split(",")) if args.variants else VARIANTS
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise InputError(f"--variants: unknown {', '.join(unknown)} (known: {', '.join(VARIANTS)})")
    records = tuple(r for r in (args.records or "").split(",") if r)
    with Progress(console=err, transient=True) as bar:
        task = bar.add_task("scoring windows", total=None)
        scores = bench_hrv_windows(
            args.data, args.fs, variants, records, progress=lambda what: bar.update(task, description=what)
        )
    table = Table(title=f"30 s windows marked good vs the annotated NN mean, {args.fs:g} Hz; errors in ms")
    for col in ("variant", "pipeline", "good", "held", "held %*", "p95", ">10", ">20", "worst"):
        table.add_column(col, justify="left" if col in ("variant", "pipeline") else "right", no_wrap=True)
    figures: dict[str, dict[str, dict[str, float | int | str]]] = {}
    notes = []
    for v, by_name in scores.items():
        for name, sc in by_name.items():
            f = figures.setdefault(v, {})[name] = sc.figures()
            table.add_row(
                v,
                name,
                str(f["good"]),
                str(f["held"]),
                f"{float(f['held_share_sinus']) * 100:.1f}",
                f"{f['p95_ms']:.2f}",
                str(f["over_10_ms"]),
                str(f["over_20_ms"]),
                f"{f['worst_ms']}",
            )
            if f["worst_records"] and name == "cadence":
                notes.append(f"{v}: {f['worst_records']}")
    out.print(table)
    out.print("* the share held on the records without arrhythmia runs")
    if notes:
        out.print("Cadence's windows over 10 ms, worst first: " + "; ".join(notes))
    print(json.dumps(figures))
    return 0


def cmd_bench_hrv(args: argparse.Namespace) -> int:
    from cadence.bench import bench_hrv

    if not Path(args.data).is_dir():
        raise InputError(f"{args.data}: no such folder (the annotated recordings, e.g. ../shared/data/ecg)")
    if args.windows:
        return _bench_hrv_windows(args)
    with err.status("detecting beats on every record …"):
        scores, extra = bench_hrv(args.data, args.fs)
    table = Table(
        title=f"R-peak detection at {args.fs:g} Hz, {int(extra['records'])} annotated records, 150 ms"
    )
    for col in ("detector", "Se %", "PPV %", "F1 %", "FP", "FN", "× real time"):
        table.add_column(col, justify="left" if col == "detector" else "right")
    for sc in sorted(scores, key=lambda x: -x.f1):
        table.add_row(
            sc.name,
            f"{sc.se * 100:.2f}",
            f"{sc.ppv * 100:.2f}",
            f"{sc.f1 * 100:.2f}",
            str(sc.fp),
            str(sc.fn),
            f"{sc.realtime:.0f}",
        )
    out.print(table)
    out.print(
        f"Cadence: a peak is published p99 {extra['latency_p99_s']:.3f} s after it occurs (max "
        f"{extra['latency_max_s']:.2f} s; {extra['latency_over_0_5_s'] * 100:.2f} % later than 0.5 s: "
        "search-back and the first 2 s); "
        f"30 s window mean-RR error vs annotations over {int(extra['good_windows'])} good windows: median "
        f"{extra['window_err_median_ms']:.2f} ms, p95 {extra['window_err_p95_ms']:.2f} ms"
    )
    best = max((s for s in scores if s.name != "cadence"), key=lambda x: x.f1, default=None)
    ours = next(s for s in scores if s.name == "cadence")
    print(
        json.dumps(
            {
                "cadence_f1": ours.f1,
                "best_other": best.name if best else None,
                "best_other_f1": best.f1 if best else None,
                "cadence_realtime": ours.realtime,
                **extra,
            }
        )
    )
    return 0


async def calibrate(
    bus,
    minutes: float,
    subject: str,
    data_dir: Path,
    measured_sigma: bool,
    progress=None,
) -> tuple[object, object]:
    """Collect `minutes` of data time of resting windows from the bus; store and publish the calibration."""
    import time

    import msgspec

    from common.hrv import Window, resting_level
    from common.storage import atomic_write
    from schemas import Calibration, HrvWindow

    wins: list[Window] = []
    first = None
    async for _, w in bus.subscribe(bus.key("hrv/window"), HrvWindow, maxsize=1000):
        first = w.start_ns if first is None else first
        wins.append(
            Window(
                (w.start_ns - first) / 1e9,
                (w.end_ns - first) / 1e9,
                w.mean_rr_s,
                w.n_beats,
                w.excluded_fraction,
                w.quality,
                w.rmssd_s,
                w.sdnn_s,
            )
        )
        covered = (w.end_ns - first) / 60e9
        if progress is not None:
            progress(min(covered, minutes), minutes)
        if covered >= minutes - 1e-9:
            break
    try:
        level = resting_level(wins)
    except ValueError as exc:
        raise InputError(f"calibrate: {exc}") from exc
    cal = Calibration(
        t_ns=time.time_ns(),
        seq=0,
        subject=subject,
        rr_rest_s=round(level.rr_rest_s, 6),
        **({"sigma_rest_s": round(level.sigma_s, 6)} if measured_sigma and level.sigma_s > 0 else {}),
    )
    atomic_write(data_dir / "calibration.json", msgspec.json.encode(cal))
    bus.put(bus.key("operator/calibration"), cal, block=True)
    return cal, level


def cmd_calibrate(args: argparse.Namespace) -> int:
    import asyncio

    from common.bus import Bus, BusConfig
    from common.service import CommonSettings, read_config, section

    raw = read_config(args.config)
    common = section(raw, "cadence", CommonSettings, args.config or "<defaults>")
    bus_cfg = section(raw, "bus", BusConfig, args.config or "<defaults>")
    data_dir = Path(args.data_dir or os.environ.get("CADENCE_DATA_DIR") or common.data_path).expanduser()
    cell = args.cell or common.cell

    async def go() -> tuple[object, object]:
        async with await Bus.open(bus_cfg, cell) as bus:
            with Progress(
                TextColumn("resting windows"),
                BarColumn(),
                TextColumn("{task.completed:.1f}/{task.total:.1f} min"),
                console=err,
            ) as prog:
                bar = prog.add_task("", total=args.minutes)
                return await calibrate(
                    bus,
                    args.minutes,
                    args.subject,
                    data_dir,
                    args.measured_sigma,
                    lambda done, total: prog.update(bar, completed=done),
                )

    cal, level = asyncio.run(go())
    out.print(
        f"subject {cal.subject}: RR_r = {cal.rr_rest_s:.3f} s over {level.good}/{level.total} good windows; "
        f"σ_r = {cal.sigma_rest_s:.3f} s ({'measured' if args.measured_sigma else 'the paper default'}); "
        f"stored in {data_dir / 'calibration.json'} and published on operator/calibration"
    )
    return 0


SERVICES = {
    "decision_maker": "services.decision_maker.__main__",
    "ecg_gateway": "services.ecg_gateway.__main__",
    "hrv_analyser": "services.hrv_analyser.__main__",
    "executor": "services.executor.__main__",
    "pareto_store": "services.pareto_store.__main__",
    "ur_emulator": "services.ur_emulator.__main__",
}


def cmd_run(args: argparse.Namespace) -> int:
    import importlib

    module = importlib.import_module(SERVICES[args.service])
    return int(module.run(args.args))


def _bus_config(args: argparse.Namespace, mode: str):
    from common.bus import BusConfig

    return BusConfig(
        mode=None if args.zenoh_config else mode,  # a config file says its own mode
        connect=args.connect or [],
        listen=getattr(args, "listen", None) or [],
        config_file=args.zenoh_config,
    )


def cmd_get(args: argparse.Namespace) -> int:
    import asyncio

    import msgspec

    from common.bus import Bus
    from schemas.topology import AnyMessage

    async def go() -> int:
        async with await Bus.open(
            _bus_config(args, "peer" if not args.connect else "client"), "cell1"
        ) as bus:
            replies = await bus.get(args.key, AnyMessage, timeout=args.timeout)
        ok = 0
        for r in replies:
            if r.message is not None:
                ok += 1
                print(msgspec.json.encode(r.message).decode())
            else:
                err.print(f"{r.key}: error: {r.error}", markup=False, highlight=False)
        if not replies:
            err.print(f"no reply for {args.key} within {args.timeout} s", markup=False)
        return 0 if ok else 1

    return asyncio.run(go())


def cmd_robot_resume(args: argparse.Namespace) -> int:
    """Clear a latched stop: ask the executor of the cell on ``robot/resume`` and print what it did."""
    import asyncio
    import getpass

    from common.bus import Bus
    from schemas import RobotEvent

    by = args.by or getpass.getuser()

    async def go() -> int:
        async with await Bus.open(
            _bus_config(args, "peer" if not args.connect else "client"), args.cell
        ) as bus:
            replies = await bus.get(f"{bus.key('robot/resume')}?by={by}", RobotEvent, timeout=args.timeout)
        for r in replies:
            if r.message is not None:
                print(r.message.message)
                return 1 if r.message.message.startswith("stopped") else 0
            err.print(f"cadence robot resume: {r.error}", markup=False, highlight=False)
            return 1
        err.print(
            f"cadence robot resume: no executor answered on cadence/{args.cell}/robot/resume within "
            f"{args.timeout:g} s (is it running, and is this host on its bus? --connect ENDPOINT)",
            markup=False,
        )
        return 1

    return asyncio.run(go())


def cmd_install(args: argparse.Namespace) -> int:
    from cadence.install import Options, install

    opts = Options(
        robot=args.robot,
        strap=args.strap,
        cell_name=args.cell,
        prefix=Path(args.prefix),
        services=tuple(s.strip() for s in args.services.split(",") if s.strip()),
        router_host=args.router_host,
        port=args.port,
        join=Path(args.join) if args.join else None,
        python=args.python,
        source=args.source,
        venv=not args.no_venv,
        systemctl=not args.no_systemctl,
    )
    for line in install(opts, dry_run=args.dry_run):
        print(line)
    return 0


def cmd_uninstall(args: argparse.Namespace) -> int:
    from cadence.install import uninstall

    for line in uninstall(keep_venv=args.keep_venv):
        print(line)
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    import asyncio

    from common.bus import Bus
    from common.service import sd_notify, watchdog_period_s

    async def go() -> None:
        stop = _stop_on_signals()
        async with await Bus.open(_bus_config(args, "router"), "cell1"):
            err.print(f"Zenoh router listening on {', '.join(args.listen or ['its config file'])}")
            sd_notify("READY=1")  # under systemd (Type=notify); a no-op elsewhere
            period = watchdog_period_s()
            while not stop.is_set():
                if period is not None:
                    sd_notify("WATCHDOG=1")
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), period or 3600.0)

    asyncio.run(go())
    return 0


def _add_planner_flags(p: argparse.ArgumentParser, task_option: bool = False) -> None:
    if task_option:
        p.add_argument("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
    p.add_argument("--seed", type=int, help="NSGA-II seed (default: the task's, else 1)")
    p.add_argument("--n", type=_positive_int(2), help="number of solutions N (default 15)")
    p.add_argument("--pop", type=_positive_int(8), help="NSGA-II population (default 90)")
    p.add_argument(
        "--generations", type=_positive_int(1), help="NSGA-II generations (default: tuned, see README)"
    )
    p.add_argument(
        "--constraints",
        choices=("exact", "hull"),
        help="limits on the curve itself (exact, default) or on the control points (hull, the paper's)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cadence",
        description="Cadence: a cobot that keeps a pace its human co-worker can sustain.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    plan = sub.add_parser(
        "plan",
        help="compute the time/jerk Pareto set of every path of a task program",
        description="For every path of TASK: NSGA-II over the time intervals, ASF downsampling to N "
        "solutions; writes DIR/<path_id>.json and DIR/<path_id>.png.",
    )
    plan.add_argument("task", metavar="TASK.toml", help="task program (see deploy/tasks/box_filling.toml)")
    plan.add_argument("--out", required=True, metavar="DIR", help="output folder (created if missing)")
    plan.add_argument("--no-plots", action="store_true", help="write the JSON files only")
    _add_planner_flags(plan)
    plan.set_defaults(func=cmd_plan)

    bench = sub.add_parser("bench", help="benchmarks that print their figures and ratios to baselines")
    bench_sub = bench.add_subparsers(dest="bench", required=True, metavar="BENCH")
    bp = bench_sub.add_parser(
        "plan",
        help="planning time vs the straightforward evaluation; hull vs exact vs Ruckig",
        description="On the longest path of TASK: full planning time, the same NSGA-II generations "
        "evaluated the straightforward way, both hypervolumes, and the fastest t_f under hull and exact "
        "limits and as Ruckig stop-at-every-waypoint moves. The last line is the figures as JSON.",
    )
    bp.add_argument("--repeat", type=_positive_int(1), default=3, help="timed repetitions (best is kept)")
    _add_planner_flags(bp, task_option=True)
    bp.set_defaults(func=cmd_bench_plan)
    bc = bench_sub.add_parser(
        "convergence",
        help="hypervolume against generations, as a share of a long reference run's",
        description="How the default number of NSGA-II generations was chosen: for the longest path of "
        "TASK, the archive's hypervolume after each checkpoint for several seeds, as a share of a long "
        "reference run's, under the reference front's normalisation.",
    )
    bc.add_argument("--seeds", type=_positive_int(1), default=5, help="number of seeds (default 5)")
    bc.add_argument("--reference", type=_positive_int(10), default=1500, help="reference generations (1500)")
    _add_planner_flags(bc, task_option=True)
    bc.set_defaults(func=cmd_bench_convergence)
    bs = bench_sub.add_parser(
        "store",
        help="query latency of the Pareto store on loopback, stored and while planning",
        description="Starts pareto_store as a process on a fresh data folder, queries it while it plans "
        "TASK's paths and then for a stored set; prints the latency percentiles.",
    )
    bs.add_argument("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
    bs.add_argument("--queries", type=_positive_int(1), default=500, help="queries of the stored set")
    bs.set_defaults(func=cmd_bench_store)

    be = bench_sub.add_parser(
        "executor",
        help="tick timing of the 500 Hz servo loop, and the time to prepare a path's samples",
        description="Runs the executor's servo loop (pinned, SCHED_FIFO when permitted) on a backend for "
        "SECONDS, servoing the longest path of TASK forward and back while the state is read at 50 Hz, and "
        "prints the tick error percentiles (|tick time - deadline|), the overruns and prepare_ms (h to "
        "validated 500 Hz samples for the slowest trajectory of that path). The last line is JSON.",
    )
    be.add_argument("--backend", choices=("sim", "ur_rtde"), default="sim")
    be.add_argument("--seconds", type=float, default=20.0, help="how long to servo (default 20)")
    be.add_argument("--host", default="127.0.0.1", help="ur_rtde: the controller's address")
    be.add_argument("--core", type=int, default=None, help="core for the servo thread (default: the last)")
    be.add_argument("--fifo-priority", type=int, default=80, help="SCHED_FIFO priority; 0 for none")
    be.add_argument("--task", default=None, metavar="TASK.toml", help="default: box_filling")
    be.add_argument("--json", action="store_true", help="print only the JSON line")
    be.set_defaults(func=cmd_bench_executor)

    rec = sub.add_parser(
        "record",
        help="record bus traffic into an MCAP file",
        description="Records every message under the key expressions (default cadence/<cell>/**) into "
        "FILE.mcap, one channel per key with the message type's JSON schema. Stops on Ctrl-C, SIGTERM or "
        "after --duration; the file is complete in every case.",
    )
    rec.add_argument("keys", nargs="*", metavar="KEYEXPR", help="key expressions (default cadence/<cell>/**)")
    rec.add_argument("-o", "--output", required=True, metavar="FILE.mcap")
    rec.add_argument("--duration", type=float, help="stop after this many seconds")
    rec.add_argument(
        "--json", action="store_true", help="JSON channels (for Foxglove) instead of MessagePack"
    )
    rec.add_argument("--cell", default="cell1", help="robot cell (default cell1)")
    rec.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    rec.add_argument("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
    rec.set_defaults(func=cmd_record)
    rep = sub.add_parser(
        "replay",
        help="republish a recording with its original data time",
        description="Republishes the recorded payloads on their keys, paced by the recorded arrival times "
        "divided by --speed. Services work on data time, so they give what they gave live.",
    )
    rep.add_argument("recording", metavar="FILE.mcap")
    rep.add_argument("--speed", type=float, default=1.0, help="× the recorded pace; 0 as fast as possible")
    rep.add_argument("--keys", nargs="+", metavar="KEYEXPR", help="replay only these key expressions")
    rep.add_argument("--wait", type=float, help="seconds to wait after joining the bus before replaying")
    rep.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    rep.add_argument("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
    rep.set_defaults(func=cmd_replay)

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
    study.add_argument(
        "--subjects", type=_positive_int(2), default=12, help="simulated subjects (default 12)"
    )
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

    hrv = sub.add_parser("hrv", help="offline heart-rate tools on a recording")
    hrv_sub = hrv.add_subparsers(dest="hrv", required=True, metavar="TOOL")
    for name, func, what in (
        ("peaks", cmd_hrv_peaks, 'one JSON object {"fs", "peaks_s"}: R-peak times from the record start'),
        ("windows", cmd_hrv_windows, "one JSON line per tumbling window: mean RR, beats, excluded, quality"),
    ):
        p = hrv_sub.add_parser(name, help=what, description=f"Prints {what}.")
        p.add_argument(
            "record", metavar="RECORD", help="WFDB record path without extension, or a CSV (s, µV)"
        )
        p.add_argument("--fs", type=float, default=None, help="resample to this rate first (130: as the H10)")
        if name == "windows":
            p.add_argument("--window", type=float, default=30.0, help="window length [s] (default 30)")
        p.set_defaults(func=func)

    cal = sub.add_parser(
        "calibrate",
        help="record resting windows, compute RR_r, store and publish the subject's calibration",
        description="Listens to hrv/window for MINUTES of data time (the ECG gateway and HRV analyser must "
        "run), averages the good windows' mean RR into RR_r, writes DATA_DIR/calibration.json and publishes "
        "it on operator/calibration.",
    )
    cal.add_argument("--minutes", type=float, default=5.0, help="resting time to record (default 5)")
    cal.add_argument("--subject", default="subject", help="who is calibrated")
    cal.add_argument(
        "--measured-sigma",
        action="store_true",
        help="use the measured RR spread as σ_r instead of the paper's 0.14 s (moves the initial k)",
    )
    cal.add_argument("--config", metavar="FILE.toml", help="deployment config ([cadence], [bus])")
    cal.add_argument("--data-dir", help="data folder (default from the config or CADENCE_DATA_DIR)")
    cal.add_argument("--cell", help="robot cell name")
    cal.set_defaults(func=cmd_calibrate)

    decide = sub.add_parser(
        "decide",
        help="the decision rule (paper Alg. 1) on mean RR values read from standard input",
        description="Reads one mean RR per line (seconds) from standard input and prints the selected k "
        "after each window, one per line. RR_s = RR_r - offset. Exact on decimal values.",
    )
    decide.add_argument(
        "--rr-rest", required=True, type=str, metavar="S", help="RR_r: the resting mean RR [s]"
    )
    decide.add_argument("--n", type=_positive_int(1), default=15, help="number of solutions N (default 15)")
    decide.add_argument("--sigma-r", type=str, default="0.14", metavar="S", help="σ_r [s] (default 0.14)")
    decide.add_argument("--rr-s-offset", type=str, default="0.08", metavar="S", help="RR_r − RR_s [s] (0.08)")
    decide.add_argument("--sigma-s", type=str, default="0.08", metavar="S", help="σ_s [s] (default 0.08)")
    decide.set_defaults(func=cmd_decide)

    bh = bench_sub.add_parser(
        "hrv",
        help="R-peak detection vs established detectors on the annotated recordings",
        description="On every annotated record of DATA, resampled to --fs: sensitivity, PPV and F1 (150 ms) "
        "of Cadence's detector and of NeuroKit2's and py-ecg-detectors' (optional: uv sync --extra bench), "
        "throughput, Cadence's publication latency and its 30 s window mean-RR error.",
    )
    bh.add_argument(
        "--data",
        default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "ecg"),
        metavar="DIR",
        help="annotated WFDB records (default ../shared/data/ecg)",
    )
    bh.add_argument(
        "--fs", type=float, default=130.0, help="sample rate to resample to (default 130, the H10's)"
    )
    bh.add_argument(
        "--windows",
        action="store_true",
        help="score the 30 s windows instead: how far each window marked good is from the annotated NN "
        "mean (p95, over 10 and 20 ms, the share held), for Cadence and NeuroKit2, per noise variant",
    )
    bh.add_argument(
        "--variants",
        metavar="V,…",
        help="with --windows: noise variants (clean, white12, white6, wander, motion; default all)",
    )
    bh.add_argument("--records", metavar="R,…", help="with --windows: only these records (default all)")
    bh.set_defaults(func=cmd_bench_hrv)

    run = sub.add_parser("run", help="run one service (production: one systemd unit each)")
    run.add_argument("service", choices=sorted(SERVICES))
    run.add_argument(
        "args", nargs=argparse.REMAINDER, help="the service's options (--config, --data-dir, --cell)"
    )
    run.set_defaults(func=cmd_run)

    get = sub.add_parser("get", help="query a key (e.g. cadence/cell1/pareto/b1_to_b2) and print JSON")
    get.add_argument("key", help="key expression or selector")
    get.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    get.add_argument("--timeout", type=float, default=5.0, help="seconds (default 5)")
    get.add_argument("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
    get.set_defaults(func=cmd_get)

    robot = sub.add_parser("robot", help="the robot's executor: clear a latched stop")
    robot_sub = robot.add_subparsers(dest="robot_command", required=True)
    resume = robot_sub.add_parser(
        "resume",
        help="clear a latched stop (protective stop, overruns, lost controller) once its cause is seen to",
        description="Ask the cell's executor to clear its latched stop. On a real UR16e this also unlocks "
        "the controller's protective stop (its dashboard refuses within 5 s of the stop). Prints the "
        "state it reached; exit 1 when the robot is still stopped after it.",
    )
    resume.add_argument("--cell", default="cell1", help="robot cell (default cell1)")
    resume.add_argument("--by", help="who resumes, for the record (default: your user name)")
    resume.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    resume.add_argument("--timeout", type=float, default=15.0, help="seconds (default 15)")
    resume.add_argument("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
    resume.set_defaults(func=cmd_robot_resume)

    router = sub.add_parser("router", help="run a Zenoh router (no zenohd binary needed)")
    router.add_argument(
        "--listen",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="default: the config file's, else tcp/127.0.0.1:7447 (loopback only)",
    )
    router.add_argument("--connect", action="append", metavar="ENDPOINT", help="other routers")
    router.add_argument("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
    router.set_defaults(func=cmd_router)

    inst = sub.add_parser(
        "install",
        help="install this host's part of a robot cell under systemd (root)",
        description="Creates the cadence user, /etc/cadence/cadence.toml (every key, commented), one bus "
        "account per service (random password, its own certificate from the cell's CA), the router's "
        "mTLS config with the ACL generated from the topology, a Python the service user can run and the "
        "venv on it under the prefix, and installs and enables the units. Re-running keeps the config, "
        "the CA and the passwords.",
    )
    inst.add_argument(
        "--robot", required=True, metavar="HOST|sim", help="the UR controller's address, or sim"
    )
    inst.add_argument(
        "--strap",
        default="Polar H10",
        metavar="ADDRESS|NAME|twin|replay",
        help="the Polar H10 (MAC address or part of its name; default 'Polar H10'), or twin/replay",
    )
    inst.add_argument("--cell", default="cell1", help="the cell's name (default cell1)")
    inst.add_argument(
        "--prefix", default="/opt/cadence", help="where the venv and Python go (default /opt/cadence)"
    )
    inst.add_argument(
        "--services",
        default=",".join((*CELL_SERVICES, "router")),
        help="what runs on this host, comma-separated (default: all of them and the router)",
    )
    inst.add_argument(
        "--router-host", default="", help="where other hosts reach the router (default: hostname)"
    )
    inst.add_argument(
        "--port", type=_positive_int(1), default=7447, help="the router's TLS port (default 7447)"
    )
    inst.add_argument(
        "--join", metavar="CELL.json", help="the first host's /etc/cadence/credentials/cell.json"
    )
    inst.add_argument("--python", metavar="PATH", help="the interpreter for the venv (default: see README)")
    inst.add_argument(
        "--from", dest="source", metavar="SPEC", help="what to install (default: this checkout)"
    )
    inst.add_argument("--no-venv", action="store_true", help="files and units only")
    inst.add_argument("--no-systemctl", action="store_true", help="no daemon-reload or enable")
    inst.add_argument("--dry-run", action="store_true", help="print every file it would write, and stop")
    inst.set_defaults(func=cmd_install)

    uninst = sub.add_parser(
        "uninstall", help="remove what `cadence install` wrote (keeps /var/lib/cadence, the data)"
    )
    uninst.add_argument("--keep-venv", action="store_true", help="leave the venv and Python under the prefix")
    uninst.set_defaults(func=cmd_uninstall)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except InputError as exc:
        err.print(f"cadence: error: {exc}", markup=False, highlight=False, soft_wrap=True)
        return 2
    except BusError as exc:
        err.print(f"cadence: bus error: {exc}", markup=False, highlight=False, soft_wrap=True)
        return 1
    except CadenceError as exc:
        err.print(f"cadence: error: {exc}", markup=False, highlight=False, soft_wrap=True)
        return 1
    except KeyboardInterrupt:
        err.print("cadence: interrupted")
        return 130
    except BrokenPipeError:  # `cadence hrv peaks … | head`: the reader has had enough
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
