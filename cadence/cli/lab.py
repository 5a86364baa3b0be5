"""The lab's commands: `cadence demo`, `report`, `session`, `study analyse|simulate|fit`."""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import sys
import time
import tomllib
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from cadence.cli._common import (
    Commands,
    add_bus_flags,
    arg,
    err,
    flags_from,
    out,
    positive_float,
    positive_int,
    speed,
)
from cadence.cli.hrv import add_posture
from common.runtime.errors import InputError
from common.runtime.resources import EXAMPLE_TASK
from common.trajectory.task import load_task

if TYPE_CHECKING:
    from cadence.analysis import Study
    from cadence.fit import Fit
    from cadence.registry import StudyPlan
    from cadence.session import SessionOptions, Watch
    from cadence.study import Model
    from schemas import Calibration
    from schemas.session import SessionEnd, Tlx


cli = Commands()


def add_cohort_flags(p: argparse.ArgumentParser, out_default: str) -> None:
    p.add_argument("--subjects", type=positive_int(2), default=12, help="simulated subjects (default 12)")
    p.add_argument("--minutes", type=float, default=10.0, help="per condition and subject (default 10)")
    p.add_argument("--calibrate", type=float, default=5.0, help="minutes at rest per subject (default 5)")
    p.add_argument("--seed", type=int, default=1, help="the cohort's seed (default 1)")
    p.add_argument("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
    p.add_argument("--out", default=out_default, metavar="DIR", help=f"output folder (default {out_default})")


@cli.command(
    "demo",
    help="the whole closed loop on this machine: operator twin, every service, simulated UR16e",
    description="Opens a Zenoh router on loopback, plans the task if its sets are not stored, starts "
    "every service as its own process (ECG gateway with the operator twin, HRV analyser, Pareto store, "
    "decision maker, executor with the simulated UR16e), restarts any that dies, shows a live view, "
    "stops them all with SIGTERM and writes DIR/summary.json, DIR/rr_k.png (mean RR and k over time), "
    "DIR/cycles.png (joint positions of the first and last cycle), DIR/pareto.png (the sets) and "
    "DIR/index.html (the report that shows them).",
)
@arg("--duration", type=positive_float, default=600.0, help="data time to run, s (default 600)")
@arg("--speed", type=speed, default=8.0, help="data time per wall time, above 0 and at most 1000 (default 8)")
@arg("--out", default="demo-out", metavar="DIR", help="output folder (default demo-out)")
@arg("--seed", type=int, default=1, help="the operator twin's seed (default 1)")
@arg("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
@arg(
    "--kill",
    action="append",
    default=[],
    metavar="SERVICE@S",
    help="SIGKILL a service at data time S (repeatable): shows the supervisor restarting it",
)
@arg("--no-live", action="store_true", help="no live view (for logs and CI)")
@arg("--listen", metavar="ENDPOINT", help="the router's endpoint (default: a free port on 127.0.0.1)")
@arg(
    "--twin",
    action="append",
    default=[],
    metavar="KEY=VALUE",
    help="a parameter of the operator twin (common/sim/twin.py; repeatable), e.g. heavy_from_s=120 "
    "heavy_until_s=300 (a stretch of heavier parts) or accelerometer=false (a strap without one)",
)
@arg(
    "--decide",
    choices=("paper", "personal"),
    default="paper",
    help="the decision maker's mode: paper (Alg. 1, default) or personal (k from this person's own "
    "scale; README, Decisions on real people)",
)
def cmd_demo(args: argparse.Namespace) -> int:
    from cadence.demo import ORDER, DemoOptions, run_demo, twin_table
    from common.sim.twin import TwinParams

    kills = []
    for spec in args.kill:
        name, _, at = spec.partition("@")
        if name not in ORDER or not at:
            raise InputError(
                f"--kill {spec}: expected SERVICE@SECONDS with SERVICE one of {', '.join(ORDER)}"
            )
        kills.append((name, float(at)))
    twin = []
    for spec in args.twin:
        key, _, text = spec.partition("=")
        try:
            twin.append((key.strip(), tomllib.loads(f"v = {text}")["v"]))
        except tomllib.TOMLDecodeError:
            raise InputError(f"--twin {spec}: expected KEY=VALUE, the value a number or true/false") from None
    opts = DemoOptions(
        duration_s=args.duration,
        speed=args.speed,
        out=Path(args.out),
        seed=args.seed,
        task=Path(args.task),
        kill=tuple(kills),
        live=not args.no_live,
        listen=args.listen,
        twin=tuple(twin),
        decide=args.decide,
    )
    try:  # a parameter the twin does not have, or out of its range: said now, not by a service at start
        msgspec.convert(twin_table(opts), TwinParams)
    except msgspec.ValidationError as exc:
        raise InputError(f"--twin: {exc}") from None
    t0 = time.monotonic()
    summary = asyncio.run(run_demo(opts, out))
    wall = time.monotonic() - t0
    cut = " (cut short)" if summary["cut_short"] else ""
    table = Table(title=f"cadence demo: {summary['duration_s']:g} s of data time in {wall:.0f} s{cut}")
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
        f"written: {args.out}/summary.json and a report (index.html, rr_k.png, pareto.png, cycles.png, "
        "separation.png); "
        f"service logs in {args.out}/logs"
    )
    bad = {n: c for n, c in summary["exit_codes"].items() if c != 0}
    if bad:
        err.print(f"services that did not exit cleanly: {bad}")
        return 1
    return 130 if summary["cut_short"] else 0  # as a shell reports an interrupted command


@cli.command(
    "report",
    help="figures and an index.html (φ, ε, cycle times, events) from a recording or a demo folder",
    description="Reads an MCAP recording or a `cadence demo` folder and writes to DIR: rr_k.png (mean RR "
    "per window and the selected k, like the paper's Fig. 6), pareto.png (each path's front, its N "
    "solutions and the k actually used), cycles.png (q, q̇, q̈ and jerk of the first and last cycle) "
    "and index.html with the production rate φ, the error rate ε, cycle times and events.",
)
@arg("source", metavar="FILE.mcap|DEMO_DIR")
@arg("--out", required=True, metavar="DIR")
@arg("--sets", metavar="FOLDER", help="Pareto sets cached by an executor (<data>/executor)")
@arg("--rr-rest", type=float, help="the operator's resting mean RR for the figure, s")
def cmd_report(args: argparse.Namespace) -> int:
    from cadence.report import from_demo, from_mcap, write_report

    src = Path(args.source)
    if args.sets and not Path(args.sets).is_dir():
        raise InputError(f"--sets {args.sets}: no such folder (the executor's cached sets: <data>/executor)")
    if src.is_dir():
        run = from_demo(src)
    elif src.suffix == ".mcap" or src.is_file():
        run = from_mcap(src, Path(args.sets) if args.sets else None)
    else:
        raise InputError(f"{src}: neither a demo folder nor an MCAP recording")
    for note in run.notes:
        err.print(note, markup=False)
    try:
        written = write_report(run, Path(args.out), args.rr_rest)
    except OSError as exc:  # a full disk, a folder not ours: one line; each file is whole or as it was
        where = exc.filename or args.out
        raise InputError(f"{where}: the report cannot be written there ({exc.strerror or exc}); the files "
                         "already there are left as they were") from None  # fmt: skip
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
        err.print(
            f"no Pareto sets in {args.sets}"
            if args.sets
            else "no Pareto sets in the source: pass --sets <data>/executor for the front and cycle figures"
        )
    out.print(f"written to {args.out}: {', '.join(written)}")
    return 0


def print_study(study: Study) -> None:
    from cadence.analysis import LABELS, stars
    from schemas.session import CONDITION_NAMES

    what = "SIMULATED study (operator twins, not people)" if study.simulated else "study"
    subjects = len({s.info.subject for s in study.sessions})
    if subjects < 2:  # said first: the tables below have no spread and no tests to give
        err.print(f"{subjects} subject: the tables have no spread (± —) and no tests (Friedman and Wilcoxon "
                  "pair subjects: they need at least 2, and an exact p below 0.05 needs 6)")  # fmt: skip
    table = Table(title=f"{what}: {subjects} subjects, {len(study.sessions)} sessions (like Table I)")
    table.add_column("condition")
    for m in study.metrics:
        table.add_column(LABELS[m], justify="right")
    for c in study.conditions:
        cells = (
            f"{mean:.3f} ± {sd:.3f}" if math.isfinite(sd) else f"{mean:.3f} ± —"
            for mean, sd, _ in study.table[c].values()
        )
        table.add_row(f"({c}) {CONDITION_NAMES[c]}", *cells)
    out.print(table)
    tests = Table(
        title="Friedman, then Wilcoxon signed-rank paired by subject: p, Holm-adjusted p, r_rb [95 % CI]"
    )
    tests.add_column("pair")
    for m in study.metrics:
        tests.add_column(LABELS[m], justify="right")
    tests.add_row("Friedman", *(f"{f.p:.2g} {stars(f.p)} (n {f.n})" for f in study.friedman.values()))
    for pair, row in study.tests.items():
        tests.add_row(pair, *(f"{t.p:.2g}, Holm {t.p_holm:.2g} {stars(t.p_holm)}\nr_rb {t.rank_biserial:.2f} "
                              f"[{t.rank_biserial_ci[0]:.2f}, {t.rank_biserial_ci[1]:.2f}] (n {t.n})"
                              for t in row.values()))  # fmt: skip
    if study.equivalence:
        tests.add_row("b ≈ c (TOST)", *(f"±{e.margin:g}: p {e.p:.2g}" + (" equivalent" if e.p < 0.05 else "")
                                        for e in study.equivalence.values()))  # fmt: skip
    out.print(tests)
    for f, why in study.excluded:
        out.print(f"left out: {f.name}: {why}")
    for note in study.notes:
        out.print(f"note: {note}")


def session_files(sources: list[str]) -> list[Path]:
    """Files as given, and a folder's ``*.mcap`` files."""
    files: list[Path] = []
    for src in map(Path, sources):
        if src.is_dir():
            found = sorted(src.glob("*.mcap"))
            if not found:
                raise InputError(f"{src}: a folder with no session files (*.mcap)")
            files += found
        else:
            files.append(src)
    return files


cli.group(
    "study",
    steps={"dest": "study", "metavar": "STEP"},
    help="the paper's study: analyse session files; simulate one with operator twins",
    description="`analyse` reads session files (from `cadence session`) and writes the paper's Table I, "
    "Wilcoxon signed-rank tests paired by subject, figures and index.html; `simulate` writes session "
    "files for simulated subjects (labelled so) and analyses them the same way.",
)


@cli.command(
    "study plan",
    help="a study's plan: pseudonymous subjects, a counterbalanced order of conditions each, a registry",
    description="Writes PLAN.toml: subjects S01…SNN, each with an order of the conditions from a Williams "
    "design (every condition equally often in each place and after each other; 6 sequences for three "
    "conditions, dealt out in seeded shuffled blocks of 6), the minutes per session, the training before "
    "a subject's first session, the least break between two, and the sessions folder beside it. Beside "
    "it, demographics.csv, one row per ID to fill in by hand: who is who stays out of the session files. "
    "`cadence session --study PLAN.toml --subject S01` runs that subject's next session.",
)
@arg("--subjects", type=positive_int(1), required=True, help="how many")
@arg("--out", required=True, metavar="PLAN.toml")
@arg("--name", help="the study's name (default: the file's stem)")
@arg(
    "--conditions",
    default="abc",
    help="the conditions, in letters: abc (the paper's) or abcy (with the yoked control, which holds the "
    "subject's own mean k of (c): it comes last, after the counterbalanced others)",
)
@arg("--seed", type=int, default=1, help="the deal of sequences to subjects (default 1)")
def cmd_study_plan(args: argparse.Namespace) -> int:
    from cadence.registry import make_plan, write_plan
    from schemas.session import CONDITION_NAMES

    conditions = list(dict.fromkeys(args.conditions))
    if (
        not conditions
        or any(c not in CONDITION_NAMES for c in conditions)
        or len(conditions) != len(args.conditions)
    ):
        raise InputError(f"--conditions {args.conditions}: distinct letters of {''.join(CONDITION_NAMES)}")
    path = Path(args.out)
    if path.exists():
        raise InputError(f"{path}: exists; a study's plan is never overwritten (subjects may have run)")
    plan = make_plan(args.name or path.stem, args.subjects, conditions, args.seed)
    try:
        written = write_plan(plan, path)
    except OSError as exc:  # each file whole or not at all: run it again once there is room
        raise InputError(f"{exc.filename or path}: cannot be written ({exc.strerror or exc})") from None
    table = Table(title=f"study {plan.name}: {len(plan.subjects)} subjects")
    for col in ("subject", *(f"period {i + 1}" for i in range(len(conditions)))):
        table.add_column(col)
    for subject in plan.subjects:
        table.add_row(subject.id, *(f"({c}) {CONDITION_NAMES[c]}" for c in subject.order))
    out.print(table)
    out.print(f"written: {', '.join(map(str, written))}; sessions go to {path.parent / plan.sessions}")
    return 0


@cli.command(
    "study analyse",
    help="Table I, Friedman and Wilcoxon tests (Holm, effect sizes, TOST), figures, index.html, CSV",
    description="Per subject and condition: φ (cycles per minute), ε (errors per cycle), mean RR of the "
    "good windows, mean RR over the subject's RR_r and the raw NASA-TLX, between the session's start and "
    "end. Per condition their mean ± sd over subjects; per measure Friedman's test; per pair of "
    "conditions and measure a Wilcoxon signed-rank test paired by subject (scipy; exact where possible, "
    "else the normal approximation, said beside the p-value), Holm-adjusted over all of them, with the "
    "rank-biserial correlation and d_z and their bootstrap CIs; a TOST for (b) ≈ (c); period effects "
    "with a study plan. Sessions cut short are left out and listed unless --include-incomplete. Writes "
    "DIR/study.json, DIR/conditions.png (like Fig. 7), one "
    "DIR/subject_<id>.png per subject (like Fig. 6) and DIR/index.html. A file that was not closed, has "
    "no calibration, mixes cells or mixes clocks is refused with the reason.",
)
@arg("sessions", nargs="+", metavar="SESSION.mcap|FOLDER")
@arg("--out", required=True, metavar="DIR")
@arg("--csv", metavar="DIR", help="also long-format CSV for R, JASP or SPSS: sessions.csv and windows.csv")
@arg("--include-incomplete", action="store_true", help="count sessions cut short (default: left out, listed)")
@arg(
    "--margin",
    action="append",
    default=[],
    metavar="MEASURE=VALUE",
    help="the equivalence margin of the TOST for (b) ≈ (c), per measure (productivity_per_min, error_rate, "
    "mean_rr_s, mean_rr_norm, tlx_raw); default 0.1, 0.02, 0.02, 0.025, 10",
)
def cmd_study_analyse(args: argparse.Namespace) -> int:
    from cadence.analysis import MARGINS, analyse, write_csv, write_study
    from cadence.session import load_session

    margins = {}
    for spec in args.margin:
        name, _, value = spec.partition("=")
        try:
            margins[name] = float(value)
        except ValueError:
            margins[name] = float("nan")
        if name not in MARGINS or not margins[name] > 0:
            raise InputError(
                f"--margin {spec}: expected MEASURE=VALUE above 0, MEASURE one of {', '.join(MARGINS)}"
            )
    study = analyse([load_session(f) for f in session_files(args.sessions)], args.include_incomplete, margins)
    print_study(study)
    written = write_study(study, Path(args.out))
    out.print(f"written to {args.out}: {', '.join(written)}")
    if args.csv:
        out.print(f"written to {args.csv}: {', '.join(write_csv(study, Path(args.csv)))}")
    return 0


def _simulated_study(
    args: argparse.Namespace, model: Model | None = None, fit_subjects: int = 0
) -> tuple[Study, Fit | None]:
    """Plan, then (with ``fit_subjects``) fit the twin on a cohort of that size, then write a session file
    per subject and condition under ``--out``/sessions and analyse them as `study analyse` does."""
    from cadence.analysis import analyse, write_study
    from cadence.fit import cohort_for, fit
    from cadence.session import load_session
    from cadence.study import calibrate_twin, motions, simulate_session, subjects
    from common.trajectory.planner import plan_path
    from schemas.session import Condition

    conditions: tuple[Condition, ...] = ("a", "b", "c")
    task_path = Path(args.task)
    task = load_task(task_path)
    cohort = subjects(args.subjects, args.seed)
    folder = Path(args.out) / "sessions"
    folder.mkdir(parents=True, exist_ok=True)
    files, fitted = [], None
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
        if fit_subjects:
            bar = progress.add_task("fitting the twin to Table I (a), (b)", total=None)
            few = cohort[:fit_subjects]
            fit_cohort = cohort_for(task, moves, n_per_path, few, args.minutes, args.calibrate)
            fitted = fit(fit_cohort, lambda what: progress.update(bar, description=f"fitting: {what}"))
            progress.update(bar, description="fitted the twin to Table I (a), (b)", total=1, completed=1)
            model = fitted.model
        runs = progress.add_task("simulating subjects × conditions", total=len(cohort) * len(conditions))
        for sub in cohort:
            cal = calibrate_twin(sub, args.calibrate, model)
            for c in conditions:
                f = folder / f"{sub.name}_{c}.mcap"
                simulate_session(task, task_path, moves, n_per_path, sub, cal, c, args.minutes, f, model)
                files.append(f)
                progress.advance(runs)
    study = analyse([load_session(f) for f in files])
    print_study(study)
    written = write_study(study, Path(args.out))
    out.print(f"written: {len(files)} session files in {folder}; {', '.join(written)} in {args.out}")
    return study, fitted


@cli.command(
    "study simulate",
    help="session files for simulated subjects (operator twins), then their analysis",
    description="Each subject is an operator twin with its own seed, resting RR and tolerance. It is "
    "calibrated at rest, then runs conditions (a) minimum time, (b) minimum jerk and (c) tuned online "
    "in simulated time, as fast as the machine allows; each run is written as a session file (the "
    "message types and metadata of a live session, marked simulated) to DIR/sessions and analysed "
    "as `cadence study analyse` would.",
)
@flags_from(add_cohort_flags, "study-out")
def cmd_study_simulate(args: argparse.Namespace) -> int:
    _simulated_study(args)
    return 0


@cli.command(
    "study fit",
    help="fit the operator twin to the paper's Table I on (a) and (b); predict (c) and the RR tests",
    description="Fits the twin's handling time to φ_b/φ_a and its error model (error_base, "
    "error_stress) to ε_a and ε_b of the paper's Table I, on a cohort of --fit-subjects, then runs "
    "`study simulate` with the fitted twin and sets its (c) and RR tests beside the paper's. Writes "
    "DIR/fit.json, DIR/fit.png and the simulated study. A simulation, labelled so.",
)
@flags_from(add_cohort_flags, "fit-out")
@arg("--fit-subjects", type=positive_int(1), default=6, help="of them, fit on (default 6)")
def cmd_study_fit(args: argparse.Namespace) -> int:
    from cadence.fit import PAPER, PAPER_RR_P, write_fit

    study, fitted = _simulated_study(args, fit_subjects=args.fit_subjects)
    assert fitted is not None
    twin = {c: (study.table[c]["productivity_per_min"][0], study.table[c]["error_rate"][0]) for c in "abc"}
    rr_p = {pair: t["mean_rr_norm"].p for pair, t in study.tests.items()}
    write_fit(fitted, twin, rr_p, Path(args.out))
    table = Table(title="The operator twin fitted to Table I on (a) and (b), SIMULATED; (c) and RR predicted")
    for col in ("measure", "paper (people)", "twin", ""):
        table.add_column(col, justify="right" if col else "left")
    rows = [
        ("φ_b / φ_a", PAPER["b"][0] / PAPER["a"][0], twin["b"][0] / twin["a"][0], "fitted"),
        ("ε_a", PAPER["a"][1], twin["a"][1], "fitted"),
        ("ε_b", PAPER["b"][1], twin["b"][1], "fitted"),
        ("φ_c / φ_a", PAPER["c"][0] / PAPER["a"][0], twin["c"][0] / twin["a"][0], "predicted"),
        ("ε_c", PAPER["c"][1], twin["c"][1], "predicted"),
        *((f"RR p, {pair}", PAPER_RR_P[pair], rr_p[pair], "predicted") for pair in ("a-b", "a-c", "b-c")),
    ]
    for name, paper, got, what in rows:
        table.add_row(name, f"{paper:.3g}", f"{got:.3g}", what)
    out.print(table)
    out.print(f"fitted: {', '.join(f'{k} = {v:.4g}' for k, v in fitted.model.items())}; "
              f"written: {args.out}/fit.json, {args.out}/fit.png")  # fmt: skip
    return 0


def tty_keys(q: asyncio.Queue[str]) -> Callable[[], None] | None:
    """Single keys from the terminal into ``q`` (cbreak mode: no Enter needed); the returned function
    gives the terminal back. None when standard input is not a terminal."""
    import termios
    import threading
    import tty

    if not sys.stdin.isatty():
        return None
    loop = asyncio.get_running_loop()
    fd = sys.stdin.fileno()
    saved = termios.tcgetattr(fd)
    tty.setcbreak(fd)

    def read() -> None:
        while ch := sys.stdin.read(1):
            loop.call_soon_threadsafe(q.put_nowait, ch)

    threading.Thread(target=read, daemon=True).start()
    return lambda: termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def planned(args: argparse.Namespace) -> StudyPlan | None:
    """With --study: the subject's next session by the plan, filled into ``args`` (condition, minutes,
    training, place, the last session's end); the plan. Without: the defaults, and no plan."""
    from cadence.registry import load_plan, next_session
    from schemas.session import CONDITION_NAMES

    args.period = args.previous_end_ns = None
    if not args.study:
        if args.condition is None:
            raise InputError("--condition: required without --study")
        args.minutes = args.minutes or 10.0
        return None
    plan = load_plan(Path(args.study))
    nxt = next_session(plan, sessions_folder(plan, args), args.subject)
    if nxt is None:
        raise InputError(f"subject {args.subject} has a complete session in every condition of {args.study}")
    if args.condition not in (None, nxt.condition):
        raise InputError(
            f"subject {args.subject}'s next session in {args.study} is ({nxt.condition}), period "
            f"{nxt.period}, not ({args.condition}): the order is the study's design"
        )
    args.condition, args.period = nxt.condition, nxt.period
    args.minutes = args.minutes or plan.minutes
    if args.training is None:
        args.training = plan.training_minutes if nxt.training else 0.0
    if nxt.previous is not None:
        args.previous_end_ns = nxt.previous.end.end_ns
    periods = len(plan.subject(args.subject).order)
    err.print(f"study {plan.name}: subject {args.subject}, period {nxt.period} of {periods}: condition "
              f"({nxt.condition}) {CONDITION_NAMES[nxt.condition]}"
              + (f", {args.training:g} min of training first" if args.training else ""))  # fmt: skip
    return plan


def sessions_folder(plan: StudyPlan, args: argparse.Namespace) -> Path:
    return Path(args.study).parent / plan.sessions


def fresh_path(folder: Path, subject: str, condition: str) -> Path:
    """SUBJECT_CONDITION.mcap in ``folder``: a run after a cut-short one gets _2, _3, …"""
    path, n = folder / f"{subject}_{condition}.mcap", 1
    while path.exists():
        n += 1
        path = folder / f"{subject}_{condition}_{n}.mcap"
    return path


def yoked_k(args: argparse.Namespace, plan: StudyPlan | None) -> int | None:
    """Condition y: the subject's mean k of (c), rounded, from their (c) session."""
    from cadence.registry import sessions_of
    from cadence.session import load_session

    if args.condition != "y":
        return None
    if args.yoked_to:
        source = Path(args.yoked_to)
    else:
        done = (
            [d for d in sessions_of(plan, sessions_folder(plan, args), args.subject)
             if d.info.condition == "c" and d.end.complete] if plan else []
        )  # fmt: skip
        if not done:
            raise InputError(f"condition y: no complete (c) session of subject {args.subject} to yoke to")
        source = done[-1].path
    s = load_session(source)
    if s.info.subject != args.subject or s.info.condition != "c":
        raise InputError(f"{source}: not subject {args.subject}'s (c) session")
    k = round(s.mean_k)
    err.print(f"condition y: k = {k}, the mean k of {source.name} ({s.mean_k:.2f})")
    return k


def parse_tlx(text: str) -> Tlx:
    from schemas.session import Tlx

    try:
        values = [int(v) for v in text.split(",")]
        return msgspec.convert(dict(zip(Tlx.__struct_fields__, values, strict=True)), Tlx)
    except (ValueError, msgspec.ValidationError) as exc:
        raise InputError(f"--tlx {text}: six integers 0-100, mental to frustration ({exc})") from None


def ask_tlx(given: Tlx | None) -> Callable[[], Awaitable[Tlx | None]]:
    """The questionnaire at the end: the scores given, or each item asked on the terminal."""

    async def ask() -> Tlx | None:
        if given is not None:
            return given
        from schemas.session import Tlx

        answers = []
        for item in Tlx.__struct_fields__:
            while True:
                text = await asyncio.to_thread(
                    input, f"NASA-TLX {item} (0-100, empty: skip the questionnaire): "
                )
                if not text.strip():
                    return None
                if text.strip().isdecimal() and 0 <= int(text) <= 100:
                    answers.append(text.strip())
                    break
        return parse_tlx(",".join(answers))

    return ask


def session_view(phase: str, w: Watch, opts: SessionOptions) -> Table:
    """The experimenter's view: the checks until the cell is ready, then RR, k, cycles, errors, time left."""
    from cadence.session import STALE_S

    t = Table(
        title=f"cadence session — subject {opts.subject}, condition ({opts.condition}): {phase}",
        caption="keys: e wrong object, l late, o other error, u undo the last mark · 1…9 the task's n-th "
        "signal · Ctrl-C ends",
    )
    if w.start_ns is None:
        t.add_column("check")
        t.add_column("state")
        for what, why in w.readiness().items():
            t.add_row(what, "[green]ok[/green]" if why is None else why)
        return t
    for col in ("time left", "mean RR (last window)", "k", "cycles", "φ so far", "errors", "robot"):
        t.add_column(col, justify="right")
    done_s = max(0.0, (w.data_ns - w.start_ns) / 1e9)
    win = w.window
    quiet = time.monotonic() - w.data_wall
    t.add_row(
        f"{max(0.0, opts.minutes * 60 - done_s):.0f} s" + (f" [red](no data for {quiet:.0f} s)[/red]"
                                                           if quiet > STALE_S else ""),
        f"{win.mean_rr_s:.3f} s ({win.quality})" if win and win.mean_rr_s else "—",
        str(w.selection.k) if w.selection else "—",
        str(w.cycles),
        f"{w.cycles / (done_s / 60):.2f}/min" if done_s > 0 else "—",
        str(w.errors),
        w.robot.state if w.robot else "—",
    )  # fmt: skip
    return t


@cli.command(
    "session",
    help="one subject's session in one condition on a running cell, recorded to one MCAP",
    description="Checks the cell first (a status from every service, the robot ready, a good HRV "
    "window), calibrates the subject at rest or at work if asked (--calibrate, --posture; stored and "
    "published as `cadence calibrate` does) or takes the stored calibration, waits until the person's "
    "windows are good and near the baseline (--settle-timeout), sets the condition on the decision maker "
    "((a) minimum time: k = N; (b) minimum jerk: k = 1; (c) tuned online: Alg. 1 from the initial k), "
    "and records the cell's traffic for MINUTES of data time, with a live view. The file carries the "
    "session's description (subject, condition, calibration, task hash, software, start and end in "
    "data time); Ctrl-C ends it early, complete and marked cut short (exit 1). For the study: "
    "`cadence study analyse`.",
)
@arg("--subject", required=True, help="the subject's ID (as in the calibration, and the study plan)")
@arg(
    "--study",
    metavar="PLAN.toml",
    help="the study plan (`cadence study plan`): refuses a subject not in it, runs the subject's next "
    "condition, records its place and the break before it, trains before their first session, and files "
    "the session in the plan's sessions folder",
)
@arg(
    "--condition",
    choices=("a", "b", "c", "y"),
    help="(a), (b), (c), or (y) yoked: k fixed at the subject's mean k of their (c) session; with "
    "--study, the plan's next one (another is refused)",
)
@arg("--minutes", type=float, help="data time to record (default: the plan's, else 10)")
@arg(
    "--training",
    type=float,
    metavar="MINUTES",
    help="familiarisation in the condition before it counts, recorded and not analysed (default: the "
    "plan's training_minutes before a subject's first session, else none)",
)
@arg(
    "--tlx",
    metavar="M,P,T,P,E,F",
    help="the subject's NASA-TLX, six scores 0-100 (mental, physical, temporal, performance, effort, "
    "frustration); without it a session of a study asks at the end when run in a terminal",
)
@arg("--yoked-to", metavar="C_SESSION.mcap", help="condition y without a plan: the subject's (c) session")
@arg(
    "--calibrate",
    type=float,
    metavar="MINUTES",
    help="calibrate first, for MINUTES (the paper: 5 at rest; not the 5-minute familiarisation)",
)
@flags_from(add_posture)
@arg(
    "--settle-timeout",
    type=float,
    default=600.0,
    metavar="S",
    help="before the condition starts, wait up to S wall seconds for two good windows within 40 ms of "
    "RR_r (the person settled where the calibration put them); 0: no wait (default 600)",
)
@arg("--measured-sigma", action="store_true", help="as `cadence calibrate`")
@arg("--out", metavar="FILE.mcap", help="default: SUBJECT_CONDITION.mcap")
@arg("--data-dir", help="where the calibration is stored (default CADENCE_DATA_DIR)")
@arg("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="the executor's task")
@arg("--note", default="", help="free text kept in the file (e.g. the experimenter)")
@flags_from(add_bus_flags, 120.0)
def cmd_session(args: argparse.Namespace) -> int:
    from rich.live import Live

    from cadence.cli._common import joining, stop_on_signals
    from cadence.cli.hrv import calibrate, calibration_screen
    from cadence.session import SessionOptions, load_session, run_session, task_digest
    from common.runtime.bus import Bus
    from common.runtime.config import CommonSettings

    plan = planned(args)
    folder = sessions_folder(plan, args) if plan else Path(".")
    out_path = Path(args.out) if args.out else fresh_path(folder, args.subject, args.condition)
    if out_path.exists():
        raise InputError(f"{out_path}: exists; a session file is evidence and is never overwritten")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    data_dir = Path(args.data_dir or os.environ.get("CADENCE_DATA_DIR") or CommonSettings().data_dir)
    tlx = parse_tlx(args.tlx) if args.tlx else None
    opts = SessionOptions(
        subject=args.subject,
        condition=args.condition,
        minutes=args.minutes,
        out=out_path,
        data_dir=data_dir.expanduser(),
        task=Path(args.task),
        cell=args.cell,
        calibrate_minutes=args.calibrate,
        measured_sigma=args.measured_sigma,
        ready_timeout_s=args.timeout,
        notes=args.note,
        posture=args.posture,
        settle_timeout_s=None if args.settle_timeout == 0 else args.settle_timeout,
        training_minutes=args.training or 0.0,
        yoked_k=yoked_k(args, plan),
        study=plan.name if plan else "",
        period=args.period,
        previous_end_ns=args.previous_end_ns,
    )
    task_digest(opts.task)  # a task file that is not there is said before the session starts
    ask = None if tlx is None and not (plan and sys.stdin.isatty()) else ask_tlx(tlx)

    async def go() -> SessionEnd:
        stop = stop_on_signals()
        cfg = joining(args)
        async with await Bus.open(cfg, args.cell, role="operator") as bus:
            with Live(console=err, refresh_per_second=4, transient=False) as live:

                def show(phase: str, w: Watch, o: SessionOptions) -> None:
                    live.update(session_view(phase, w, o))

                async def calib() -> Calibration:
                    minutes = args.calibrate
                    cal, level = await calibrate(
                        bus, minutes, args.subject, opts.data_dir, args.measured_sigma, posture=args.posture
                    )
                    for line in calibration_screen(cal, level, args.measured_sigma):
                        live.console.print(line)
                    return cal

                keys: asyncio.Queue[str] = asyncio.Queue()
                restore = tty_keys(keys)
                try:
                    return await run_session(bus, opts, stop, show, calib, keys, ask)
                finally:
                    if restore is not None:
                        restore()

    end = asyncio.run(go())
    if not out_path.exists():
        err.print("stopped before the condition took effect: no session file written")
        return 1
    s = load_session(out_path)
    table = Table(title=f"session {out_path}: {'complete' if end.complete else 'CUT SHORT: ' + end.reason}")
    for col in ("minutes", "cycles", "φ [cycles/min]", "errors", "ε [errors/cycle]", "mean RR / RR_r"):
        table.add_column(col, justify="right")
    table.add_row(
        f"{s.minutes:.2f}",
        str(s.n_cycles),
        f"{s.productivity_per_min:.3f}",
        str(s.n_errors),
        f"{s.error_rate:.3f}",
        f"{s.mean_rr_s:.3f} / {s.rr_rest_s:.3f} s",
    )
    out.print(table)
    if s.info.break_s is not None:
        least = f" (the plan asks at least {plan.break_minutes:g})" if plan else ""
        out.print(f"break before it: {s.info.break_s / 60:.1f} min of data time{least}")
    if s.end.tlx is not None:
        out.print(f"NASA-TLX raw: {s.end.tlx.raw:.1f}")
    return 0 if end.complete else 1
