"""`cadence bench hrv` and `bench decide`: the benchmarks on recordings of people (the shared data), in
the bench family of cadence/cli/bench.py."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING

from rich.progress import Progress
from rich.table import Table

from cadence.cli._common import arg, err, out
from cadence.cli.bench import SHARED_DATA, cli
from common.runtime.errors import InputError

if TYPE_CHECKING:
    from cadence.bench.hrv_scoring import WindowScore


def _bench_hrv_windows(args: argparse.Namespace) -> int:
    from cadence.bench.ecg_noise import variants_named
    from cadence.bench.hrv_scoring import window_table
    from cadence.bench.hrv_windows import bench_hrv_windows

    variants = variants_named(args.variants)
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
    print(json.dumps(window_table(title, scores, out)))
    return 0


def _bench_hrv_cv(args: argparse.Namespace) -> int:
    from cadence.bench.ecg_noise import variants_named
    from cadence.bench.hrv_cv import GRID, cross_validate, describe
    from cadence.bench.hrv_scoring import window_table
    from common.hrv.stream import RULES

    variants = variants_named(args.variants)
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
    figures = window_table(title, nested, out)
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
    from cadence.bench.hrv_peaks import bench_hrv

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
@arg(
    "--scenarios",
    action="store_true",
    help="instead: the personal mode on made-up people over hours (stress, rest, noise, drift, effort), "
    "each scenario's stated behaviour beside what the mode does (cadence/bench/scenarios.py)",
)
def cmd_bench_decide(args: argparse.Namespace) -> int:
    from cadence.bench import decide as bd
    from common.decision import Personal

    if args.scenarios:
        from cadence.bench.scenarios import table as scenario_table

        shown = Table(
            title=f"The personal mode as shipped {dataclasses.astuple(Personal())}, through the Decider"
        )
        for col in ("scenario", "stated (DESIGN §7)", "does"):
            shown.add_column(col)
        for row in scenario_table():
            shown.add_row(*row)
        out.print(shown)
        return 0

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
        if cv is not None:
            runs["personal, held out"], scores["personal, held out"] = cv.decisions, cv.held_out
        folder = Path(args.out)
        folder.mkdir(parents=True, exist_ok=True)
        for i, s in enumerate(scored):
            said(f"figure {i + 1} of {len(scored)}")
            png = bd.figure(s, {m: runs[m][i] for m in modes})
            (folder / f"{s.name.replace('/', '_')}.png").write_bytes(png)
        bd.write_decisions(folder / "decisions.csv", scored, {m.replace(", ", "_").replace(" ", "_"): r
                                                               for m, r in runs.items()})  # fmt: skip
    controls = {c: [bd.order(s, f(s)) for s in scored] for c, f in bd.CONTROLS.items()}
    table = Table(title="Per subject: order-balanced score (before / after pairs), Δk = k calm − k stress")
    cols = ("subject", "RR_r s", "windows", *(f"{m} b/a" for m in scores), *(f"{m} Δk" for m in scores),
            "mean RR b/a")  # fmt: skip
    for col in cols:
        table.add_column(col, justify="left" if col == "subject" else "right", no_wrap=col == "subject")

    def sides(o: bd.Order) -> str:
        return " / ".join("–" if x is None else f"{x:.2f}" for x in (o.before, o.after))

    for i, s in enumerate(scored):
        assert s.calibration is not None
        table.add_row(
            s.name + (" *" if s.note else ""),
            f"{s.calibration.rr_rest_s:.3f}",
            str(len(s.windows)),
            *(sides(scores[m][i].order) for m in scores),
            *(f"{scores[m][i].dk:+.1f}" for m in scores),
            sides(controls["mean RR"][i]),
        )
    out.print(table)
    if any(s.note for s in scored):
        out.print("* RR_r from the baseline's good windows, where " + "; ".join(
            f"{s.name}: {s.note}" for s in scored if s.note))  # fmt: skip
    figures: dict[str, object] = {m: bd.summary(v) for m, v in scores.items()}
    figures["controls"] = {c: bd.order_summary(v) for c, v in controls.items()}
    groups = sorted({s.dataset for s in scored})
    short = {"stress_predict": "SP", "gudb": "GUDB"}
    summary = Table(
        title="Order-balanced scores, medians over subjects (balanced: of those with calm blocks before and "
        "after a stressor), and in brackets controls from the same windows; old AUC: over all windows"
    )
    for col in ("mode", "data", "balanced", "> 0.5", "before", "> 0.5 ", "after", "Δk (95 % CI)", "old AUC"):
        summary.add_column(col, justify="left" if col in ("mode", "data") else "right")

    def cell(x: object, fmt: str = ".3f") -> str:
        return "–" if x is None else format(x, fmt)

    for g in [*groups, "all"]:
        for m, every in scores.items():
            f = bd.summary(every if g == "all" else [x for x in every if x.name.startswith(g + "/")])
            summary.add_row(
                m, short.get(g, g), cell(f["balanced_median"]), cell(f["balanced_above_half"], ".0%"),
                cell(f["before_median"]), cell(f["before_above_half"], ".0%"), cell(f["after_median"]),
                "{:+.1f} ({:.1f}–{:.1f})".format(f["dk_median"], *f["dk_ci95"]),  # type: ignore[str-format,misc]
                cell(f["auc_median"]),
            )  # fmt: skip
        for c, orders in controls.items():
            o = bd.order_summary(
                orders if g == "all" else [x for x, s in zip(orders, scored, strict=True) if s.dataset == g]
            )
            summary.add_row(
                f"({c})", short.get(g, g), cell(o["balanced_median"]), cell(o["balanced_above_half"], ".0%"),
                cell(o["before_median"]), cell(o["before_above_half"], ".0%"), cell(o["after_median"]),
                "", "", style="dim",
            )  # fmt: skip
        summary.add_section()
    out.print(summary)
    if cv is not None:
        shipped = Personal()
        out.print(
            f"Personal mode, chosen leaving each subject out (of {len(bd.grid())} settings that keep a "
            "steady person steady): "
            + ", ".join(
                f"{dataclasses.astuple(q)[:3]} in {cv.chosen.count(q)}" for q in dict.fromkeys(cv.chosen)
            )
            + f"; on all: {dataclasses.astuple(cv.on_all)[:3]}; shipped: {dataclasses.astuple(shipped)[:3]}"
        )
        if cv.on_all != shipped:
            out.print("[yellow]the shipped settings are not the ones chosen on all subjects[/yellow]")
        figures["chosen"] = dataclasses.asdict(cv.on_all)
    out.print(f"figures: {folder}/ (one per subject), decisions: {folder}/decisions.csv")
    print(json.dumps(figures))
    return 0
