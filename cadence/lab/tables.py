"""What the lab's commands print: a study's Table I and its tests, the fitted twin beside the paper, a
session's figures. Rich tables, built here so that a command module only parses and calls."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console
from rich.table import Table

if TYPE_CHECKING:
    from cadence.lab.analysis import Study
    from cadence.lab.report import Run
    from cadence.lab.session_file import Session
    from schemas.session import SessionEnd

out = Console()
err = Console(stderr=True)


def print_study(study: Study) -> None:
    from cadence.lab.analysis import LABELS
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
            "—"  # no session of the condition has the measure (a TLX not taken): nothing, not nan
            if not math.isfinite(mean)
            else f"{mean:.3f} ± {sd:.3f}"
            if math.isfinite(sd)
            else f"{mean:.3f} ± —"
            for mean, sd, _ in study.table[c].values()
        )
        table.add_row(f"({c}) {CONDITION_NAMES[c]}", *cells)
    out.print(table)
    if subjects >= 2:  # with one, each "test" would print nan and p = 1: said above instead
        print_tests(study)
    for f, why in study.excluded:
        out.print(f"left out: {f.name}: {why}")
    for note in study.notes:
        out.print(f"note: {note}")


def print_tests(study: Study) -> None:
    from cadence.lab.analysis import LABELS, stars

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


def fit_table(twin: dict[str, tuple[float, float]], rr_p: dict[str, float]) -> Table:
    """The twin fitted on (a) and (b) beside the paper's Table I; (c) and the RR tests predicted."""
    from cadence.lab.fit import PAPER, PAPER_RR_P

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
    return table


def session_table(s: Session, end: SessionEnd) -> Table:
    """One session's figures, as the paper's Table I counts them."""
    table = Table(title=f"session {s.path}: {'complete' if end.complete else 'CUT SHORT: ' + end.reason}")
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
    return table


def report_table(run: Run, src: Path) -> Table:
    """A recording's or a demo's figures (`cadence report`)."""
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
    return table
