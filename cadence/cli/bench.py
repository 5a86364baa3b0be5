"""`cadence bench …`: benchmarks that print their figures, and the ratio to a baseline measured in the
same run."""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from rich.progress import Progress
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
from common.runtime.errors import InputError
from common.runtime.resources import EXAMPLE_TASK

if TYPE_CHECKING:
    from cadence.bench import Replanning
    from cadence.bench.ecg_noise import Variant
    from cadence.bench.hrv_scoring import WindowScore


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
@arg("--repeat", type=positive_int(1), default=3, help="timed repetitions (best is kept)")
@arg("--workers", type=positive_int(1), default=2, help="processes for the whole task (default 2)")
@flags_from(add_planner_flags, task_option=True)
def cmd_bench_plan(args: argparse.Namespace) -> int:
    from cadence.bench import bench_plan, bench_replanning

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
    table.add_row("full planning (s)", f"{r.plan_s:.3f}", f"{r.naive_plan_s:.3f}", f"{r.plan_ratio:.1f}×")
    table.add_row(
        "one generation's evaluation (ms)",
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
        "hv": r.hv,
        "naive_hv": r.naive_hv,
        "tf_hull": r.tf_hull,
        "tf_exact": r.tf_exact,
        "tf_ruckig": r.tf_ruckig,
    }
    figures["replanning"] = dataclasses.asdict(rp)
    print(json.dumps(figures))
    return 0


def replanning_table(r: Replanning) -> None:
    t = Table(title=f"replanning: fast engine vs today's (pymoo's loop), same run; hypervolume as a share "
                    f"of a {r.reference_generations}-generation reference")  # fmt: skip
    t.add_column("figure")
    t.add_column("fast", justify="right")
    t.add_column("today", justify="right")
    t.add_column("ratio", justify="right")
    t.add_row(f"one path '{r.path_id}' (s)", f"{r.path_s:.3f}", f"{r.pymoo_path_s:.3f}",
              f"{r.path_ratio:.1f}×")  # fmt: skip
    t.add_row(f"whole task (s, {r.workers} processes vs 1)", f"{r.task_s:.3f}", f"{r.pymoo_task_s:.3f}",
              f"{r.task_ratio:.1f}×")  # fmt: skip
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
    from cadence.bench import convergence
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

    from cadence.bench import StoreBench, bench_store

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
    "bench executor",
    help="tick timing of the 500 Hz servo loop, and the time to prepare a path's samples",
    description="Runs the executor's servo loop (pinned, SCHED_FIFO when permitted) on a backend for "
    "SECONDS, servoing the longest path of TASK forward and back while the state is read at 50 Hz, and "
    "prints the tick error percentiles (|tick time - deadline|), the overruns and prepare_ms (h to "
    "validated 500 Hz samples for the slowest trajectory of that path). The last line is JSON.",
)
@arg("--backend", choices=("sim", "ur_rtde"), default="sim")
@arg("--seconds", type=float, default=20.0, help="how long to servo (default 20)")
@arg("--host", default="127.0.0.1", help="ur_rtde: the controller's address")
@arg("--core", type=int, default=None, help="core for the servo thread (default: the last)")
@arg("--fifo-priority", type=int, default=80, help="SCHED_FIFO priority; 0 for none")
@arg("--task", default=None, metavar="TASK.toml", help="default: box_filling")
@arg("--json", action="store_true", help="print only the JSON line")
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


def _window_table(title: str, scores: dict[str, dict[str, WindowScore]]) -> dict[str, object]:
    """The window scores as a table on stdout; the worst records of Cadence's under it; the figures."""
    table = Table(title=title)
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
            if f["worst_records"] and name != "neurokit2":
                notes.append(f"{v} {name}: {f['worst_records']}")
    out.print(table)
    out.print("* the share held on the records without arrhythmia runs (GUDB: every window)")
    if notes:
        out.print("Cadence's windows over 10 ms, worst first: " + "; ".join(notes))
    return dict(figures)


def _variants(args: argparse.Namespace) -> tuple[Variant, ...]:
    from cadence.bench.ecg_noise import VARIANTS

    asked = args.variants.split(",") if args.variants else list(VARIANTS)
    unknown = [v for v in asked if v not in VARIANTS]
    if unknown:
        raise InputError(f"--variants: unknown {', '.join(unknown)} (known: {', '.join(VARIANTS)})")
    return tuple(v for v in VARIANTS if v in asked)


def _bench_hrv_windows(args: argparse.Namespace) -> int:
    from cadence.bench import bench_hrv_windows

    variants = _variants(args)
    records = tuple(r for r in (args.records or "").split(",") if r)
    with Progress(console=err, transient=True) as bar:
        task = bar.add_task("scoring windows", total=None)
        scores = bench_hrv_windows(
            args.data,
            args.fs,
            variants,
            records,
            progress=lambda what: bar.update(task, description=what),
            gudb_dir=args.gudb,
        )
    title = f"30 s windows marked good vs the annotated NN mean, {args.fs:g} Hz; errors in ms"
    print(json.dumps(_window_table(title, scores)))
    return 0


def _bench_hrv_cv(args: argparse.Namespace) -> int:
    from cadence.bench.hrv_cv import GRID, cross_validate, describe
    from common.hrv.stream import RULES

    variants = _variants(args)
    with Progress(console=err, transient=True) as bar:
        task = bar.add_task("detecting and scoring every unit under every rule set", total=None)
        cv = cross_validate(
            args.data, args.gudb, args.fs, variants, progress=lambda what: bar.update(task, description=what)
        )
    if not cv.units:
        raise InputError(f"{args.data}, {args.gudb}: no annotated record nor GUDB subject to cross-validate")
    held_out, picks = cv.held_out()
    nested: dict[str, dict[str, WindowScore]] = {}
    for (v, name), sc in held_out.items():
        nested.setdefault(v, {})[name] = sc
    title = f"Held out: each unit scored with the thresholds chosen on the others ({len(cv.units)} units)"
    figures = _window_table(title, nested)
    best = cv.chosen()
    counts: dict[int, list[str]] = {}
    for u, g in picks.items():
        counts.setdefault(g, []).append(u)
    out.print(f"Grid: {len(cv.rules)} rule sets over " + ", ".join(f"{k} {v}" for k, v in GRID.items()))
    for g, units in sorted(counts.items(), key=lambda kv: -len(kv[1])):
        out.print(f"  chosen in {len(units)} of {len(cv.units)} folds: {describe(cv.rules[g])}")
    shipped = describe(RULES)
    out.print(
        f"Chosen on all units: {describe(cv.rules[best])}; shipped (common/hrv/stream.py Rules): {shipped}"
    )
    if describe(cv.rules[best]) != shipped:
        out.print("[yellow]the shipped thresholds are not the ones chosen on all units[/yellow]")
    print(json.dumps({"held_out": figures, "chosen": describe(cv.rules[best]), "shipped": shipped}))
    return 0


@cli.command(
    "bench hrv",
    help="R-peak detection vs established detectors on the annotated recordings",
    description="On every annotated record of DATA, resampled to --fs: sensitivity, PPV and F1 (150 ms) "
    "of Cadence's detector and of NeuroKit2's and py-ecg-detectors' (optional: uv sync --extra bench), "
    "throughput, Cadence's publication latency and its 30 s window mean-RR error.",
)
@arg(
    "--data",
    default=str(SHARED_DATA / "ecg"),
    metavar="DIR",
    help="annotated WFDB records (default ../shared/data/ecg)",
)
@arg("--fs", type=float, default=130.0, help="sample rate to resample to (default 130, the H10's)")
@arg(
    "--windows",
    action="store_true",
    help="score the 30 s windows instead: how far each window marked good is from the annotated NN "
    "mean (p95, over 10 and 20 ms, the share held), for Cadence and NeuroKit2, per noise variant",
)
@arg(
    "--variants",
    metavar="V,…",
    help="with --windows: noise variants (clean, white12, white6, wander, motion; default all)",
)
@arg("--records", metavar="R,…", help="with --windows: only these records (default all)")
@arg(
    "--gudb",
    default=str(SHARED_DATA / "gudb"),
    metavar="DIR",
    help="with --windows or --cv: GUDB subjects' annotated chest-strap beats, scored as a strap's RR "
    "(default ../shared/data/gudb; skipped when absent)",
)
@arg(
    "--cv",
    action="store_true",
    help="cross-validate the cleaning's thresholds: leave one record (or GUDB subject) out, choose on "
    "the rest from a grid, score the one left out; prints the held-out figures and the choices "
    "(a few minutes)",
)
def cmd_bench_hrv(args: argparse.Namespace) -> int:
    from cadence.bench import bench_hrv

    if not Path(args.data).is_dir():
        raise InputError(f"{args.data}: no such folder (the annotated recordings, e.g. ../shared/data/ecg)")
    if args.cv:
        return _bench_hrv_cv(args)
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


@cli.command(
    "bench decide",
    help="decisions on real people: does k fall under stress, per decision mode",
    description="For every subject of DATA (SNN/ Empatica E4 exports and DATA/blocks.csv) and of GUDB "
    "(seated, then a maths test): calibrate on the calm start, run the session's 30 s windows through "
    "the decision maker's own code in the paper's mode (Alg. 1) and the personal mode, and score each: "
    "the within-subject AUC of k (calm windows above stress windows), the subjects whose mean k is "
    "lower in stress, the median k per block type, the held share; hyperventilation apart. A figure per "
    "subject in --out; the last line is JSON.",
)
@arg(
    "--data",
    default=str(SHARED_DATA / "stress_predict"),
    metavar="DIR",
    help="SNN/ E4 exports and blocks.csv (default ../shared/data/stress_predict)",
)
@arg(
    "--gudb",
    default=str(SHARED_DATA / "gudb"),
    metavar="DIR",
    help="GUDB subjects, seated then maths (default ../shared/data/gudb; skipped when absent; '' for none)",
)
@arg("--out", default="bench-decide", metavar="DIR", help="where the figures go (default ./bench-decide)")
@arg(
    "--cv",
    action="store_true",
    help="also choose the personal mode's settings leaving one subject out, and score each subject with "
    "the settings chosen on the others (held-out figures)",
)
@arg(
    "--wrist-movement",
    action="store_true",
    help="feed the wristband's accelerometer to the movement hold (off: the hold is built for a chest "
    "strap's trunk acceleration; a wrist's is the hands typing and gesturing)",
)
def cmd_bench_decide(args: argparse.Namespace) -> int:
    from cadence.bench import decide as bd
    from common.decision import Personal

    data, gudb_dir = Path(args.data), Path(args.gudb) if args.gudb else None
    if not data.is_dir():
        raise InputError(f"{data}: no such folder (SNN/ Empatica E4 exports and blocks.csv)")
    with Progress(console=err, transient=True) as bar:
        task = bar.add_task("reading", total=None)

        def said(what: str) -> None:
            bar.update(task, description=what)

        sessions = bd.stress_predict(data, args.wrist_movement, said)
        if gudb_dir is not None and gudb_dir.is_dir():
            sessions += bd.gudb(gudb_dir, said)
        for s in sessions:
            if s.problem:
                err.print(f"[yellow]{s.name}: not scored: {s.problem}[/yellow]")
        scored = [s for s in sessions if s.problem is None]
        if not scored:
            raise InputError(f"{data}: no subject could be scored (see above)")
        modes: dict[str, Personal | None] = {"paper": None, "personal": Personal()}
        runs = {m: [bd.run(s, q) for s in scored] for m, q in modes.items()}
        scores = {m: [bd.score(s, d) for s, d in zip(scored, runs[m], strict=True)] for m in modes}
        cv = bd.cross_validate(scored, progress=said) if args.cv else None
        folder = Path(args.out)
        folder.mkdir(parents=True, exist_ok=True)
        for i, s in enumerate(scored):
            said(f"figure {i + 1} of {len(scored)}")
            png = bd.figure(s, {m: runs[m][i] for m in modes})
            (folder / f"{s.name.replace('/', '_')}.png").write_bytes(png)
    table = Table(title="Per subject: mean k in stress / calm, AUC of k (calm above stress)")
    for col in ("subject", "RR_r s", "windows", *(f"{m} k s/c" for m in modes), *(f"{m} AUC" for m in modes)):
        table.add_column(col, justify="left" if col == "subject" else "right", no_wrap=col == "subject")
    for i, s in enumerate(scored):
        assert s.calibration is not None
        table.add_row(
            s.name + (" *" if s.note else ""),
            f"{s.calibration.rr_rest_s:.3f}",
            str(len(s.windows)),
            *(f"{scores[m][i].k_stress:.1f} / {scores[m][i].k_calm:.1f}" for m in modes),
            *(f"{scores[m][i].auc:.2f}" for m in modes),
        )
    out.print(table)
    if any(s.note for s in scored):
        out.print("* RR_r from the baseline's good windows, where " + "; ".join(
            f"{s.name}: {s.note}" for s in scored if s.note))  # fmt: skip
    figures: dict[str, object] = {m: bd.summary(scores[m]) for m in modes}
    groups = sorted({s.name.split("/")[0] for s in scored})
    summary = Table(title="Per mode (medians over subjects)")
    for col in (
        "mode",
        "data",
        "subjects",
        "AUC",
        "lower in stress",
        "k stress",
        "k calm",
        "k hypervent.",
        "held",
    ):
        summary.add_column(col, justify="left" if col in ("mode", "data") else "right")
    sets = [(m, scores[m]) for m in modes] + ([("personal, held out", cv.held_out)] if cv else [])
    for (m, every), g in itertools.product(sets, [*groups, "all"]):
        f = bd.summary(every if g == "all" else [x for x in every if x.name.startswith(g + "/")])
        if not f["subjects"]:
            continue
        summary.add_row(
            m, g, str(f["subjects"]), f"{f['auc_median']:.3f}",
            f"{f['lower_in_stress_n']} ({f['lower_in_stress']:.0%})",
            f"{f['k_stress_median']:.1f}", f"{f['k_relax_median']:.1f}",
            "" if f["k_hyperventilation_median"] is None else f"{f['k_hyperventilation_median']:.1f}",
            f"{f['held_share']:.0%}",
        )  # fmt: skip
    out.print(summary)
    if cv is not None:
        shipped = Personal()
        out.print(
            f"Personal mode, chosen leaving each subject out (grid {len(bd.grid())} settings): "
            + ", ".join(f"{dataclasses.astuple(q)} in {cv.chosen.count(q)}" for q in dict.fromkeys(cv.chosen))
            + f"; on all: {dataclasses.astuple(cv.on_all)}; shipped: {dataclasses.astuple(shipped)}"
        )
        if cv.on_all != shipped:
            out.print("[yellow]the shipped settings are not the ones chosen on all subjects[/yellow]")
        figures["personal_held_out"] = bd.summary(cv.held_out)
        figures["chosen"] = dataclasses.asdict(cv.on_all)
    out.print(f"figures: {folder}/ (one per subject)")
    print(json.dumps(figures))
    return 0
