"""The lab's commands: `cadence demo`, `report`, `session`, `study analyse|simulate|fit`."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from rich.table import Table

from cadence.cli._common import (
    Commands,
    arg,
    err,
    flags_from,
    out,
    positive_int,
)
from common.runtime.errors import InputError
from common.runtime.resources import EXAMPLE_TASK

if TYPE_CHECKING:
    from cadence.lab.simulate import Cohort


cli = Commands()


def cohort(args: argparse.Namespace) -> Cohort:
    from cadence.lab.simulate import Cohort

    return Cohort(Path(args.task), args.subjects, args.minutes, args.calibrate, args.seed, Path(args.out))


def add_cohort_flags(p: argparse.ArgumentParser, out_default: str) -> None:
    p.add_argument("--subjects", type=positive_int(2), default=12, help="simulated subjects (default 12)")
    p.add_argument("--minutes", type=float, default=10.0, help="per condition and subject (default 10)")
    p.add_argument("--calibrate", type=float, default=5.0, help="minutes at rest per subject (default 5)")
    p.add_argument("--seed", type=int, default=1, help="the cohort's seed (default 1)")
    p.add_argument("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
    p.add_argument("--out", default=out_default, metavar="DIR", help=f"output folder (default {out_default})")


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
    from cadence.lab.report import from_demo, from_mcap, write_report
    from cadence.lab.tables import report_table

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
    out.print(report_table(run, src))
    if not run.sets:
        err.print(
            f"no Pareto sets in {args.sets}"
            if args.sets
            else "no Pareto sets in the source: pass --sets <data>/executor for the front and cycle figures"
        )
    out.print(f"written to {args.out}: {', '.join(written)}")
    return 0


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
    from cadence.lab.design import make_plan, write_plan
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
    written = write_plan(plan, path)  # both or neither: run it again once there is room
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
    from cadence.lab.analysis import MARGINS, analyse, write_csv, write_study
    from cadence.lab.session_file import load_session

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
    from cadence.lab.analysis import session_files
    from cadence.lab.tables import print_study

    study = analyse([load_session(f) for f in session_files(args.sessions)], args.include_incomplete, margins)
    print_study(study)
    written = write_study(study, Path(args.out))
    out.print(f"written to {args.out}: {', '.join(written)}")
    if args.csv:
        out.print(f"written to {args.csv}: {', '.join(write_csv(study, Path(args.csv)))}")
    return 0


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
    from cadence.lab.simulate import simulate_study

    simulate_study(cohort(args))
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
    from cadence.lab.fit import write_fit
    from cadence.lab.simulate import simulate_study
    from cadence.lab.tables import fit_table

    study, fitted = simulate_study(cohort(args), fit_subjects=args.fit_subjects)
    assert fitted is not None
    twin = {c: (study.table[c]["productivity_per_min"][0], study.table[c]["error_rate"][0]) for c in "abc"}
    rr_p = {pair: t["mean_rr_norm"].p for pair, t in study.tests.items()}
    write_fit(fitted, twin, rr_p, Path(args.out))
    out.print(fit_table(twin, rr_p))
    out.print(f"fitted: {', '.join(f'{k} = {v:.4g}' for k, v in fitted.model.items())}; "
              f"written: {args.out}/fit.json, {args.out}/fit.png")  # fmt: skip
    return 0
