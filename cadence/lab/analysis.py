"""`cadence study analyse`: the paper's Table I and its tests (§IV) from session files, with what reviewers
ask for beside them, and nothing else.

Per subject and condition the measures of one session file (cadence/lab/session_file.py): φ, ε, the mean
of the good windows' mean RR, that mean over the subject's RR_r, and the raw NASA-TLX when it was asked.
Per condition their mean ± sd over subjects (Table I). Then (cadence/lab/stats.py):

- Friedman's test per measure over the subjects with every condition, before any pair;
- per pair of conditions and measure a Wilcoxon signed-rank test paired by subject (exact where scipy can
  be exact: no zero and no tied differences, at most 50 pairs; the normal approximation otherwise, said
  beside the p-value), Holm-adjusted over all the pairs and measures, with the matched-pairs
  rank-biserial correlation and d_z and their 95 % bootstrap CIs;
- TOST for "(b) ≈ (c)" per measure, with a declared margin (``--margin``);
- period effects: the measures by the place of the session in each subject's order (a study plan
  records it), with Friedman's test over the subjects with every period.

Sessions cut short are left out unless asked (``include_incomplete``), and listed with their reason; a
task file that differs between sessions is refused (the sessions did not run the same task), and
differing software versions and planned sets are said.
"""

from __future__ import annotations

import html
import json
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from itertools import combinations
from pathlib import Path

import numpy as np

from cadence.lab.session_file import Session
from cadence.lab.stats import (
    Equivalence,
    Omnibus,
    bootstrap_ci,
    d_z,
    friedman,
    holm,
    rank_biserial,
    tost_paired,
)
from common.runtime.errors import InputError
from common.runtime.storage import write_readable
from schemas.session import CONDITION_NAMES, Tlx

METRICS = ("productivity_per_min", "error_rate", "mean_rr_s", "mean_rr_norm")
TLX = "tlx_raw"
RESTING = "mean_rr_resting_norm"  # beside mean RR / RR_r when a calibration was at work
LABELS = {
    "productivity_per_min": "φ [cycles/min]",
    "error_rate": "ε [errors/cycle]",
    "mean_rr_s": "mean RR [s]",
    "mean_rr_norm": "mean RR / RR_r",
    RESTING: "mean RR / RR at rest",
    TLX: "NASA-TLX (raw, 0-100)",
}
# TOST margins for "(b) ≈ (c)" unless given: about one decision step of RR, a tenth of a cycle a minute,
# two errors in a hundred cycles, ten TLX points
MARGINS = {
    "productivity_per_min": 0.1,
    "error_rate": 0.02,
    "mean_rr_s": 0.02,
    "mean_rr_norm": 0.025,
    RESTING: 0.025,
    TLX: 10.0,
}
COLUMNS = ("subject", "condition", "minutes", "complete", "cycles", "errors")
EXACT_MAX_N = 50  # scipy's own limit for the exact distribution


@dataclass(frozen=True, slots=True)
class PairedTest:
    n: int  # subjects with both sessions
    p: float
    method: str  # "exact", "normal approximation", or why there is no test
    median_difference: float  # second minus first condition
    p_holm: float = float("nan")  # over every pair and measure of the study
    rank_biserial: float = float("nan")
    rank_biserial_ci: tuple[float, float] = (float("nan"), float("nan"))
    d_z: float = float("nan")
    d_z_ci: tuple[float, float] = (float("nan"), float("nan"))


@dataclass(frozen=True, slots=True)
class Study:
    sessions: list[Session]
    conditions: list[str]  # those present, in the paper's order
    table: dict[str, dict[str, tuple[float, float, int]]]  # condition → metric → (mean, sd, n)
    tests: dict[str, dict[str, PairedTest]]  # "a-b" → metric → test
    simulated: bool
    metrics: tuple[str, ...] = METRICS
    friedman: dict[str, Omnibus] = field(default_factory=dict)  # metric → over every condition
    equivalence: dict[str, Equivalence] = field(default_factory=dict)  # metric → TOST of b ≈ c
    periods: dict[str, dict[str, object]] = field(default_factory=dict)  # metric → means by period, test
    excluded: list[tuple[Path, str]] = field(default_factory=list)  # left out, and why
    notes: list[str] = field(default_factory=list)


def paired_test(x: np.ndarray, y: np.ndarray) -> PairedTest:
    from scipy.stats import wilcoxon

    d = y - x
    n = len(d)
    if n == 0:
        return PairedTest(0, float("nan"), "no subject has both sessions", float("nan"))
    median = float(np.median(d))
    sizes = {"rank_biserial": rank_biserial(d), "rank_biserial_ci": bootstrap_ci(d, "rank_biserial"),
             "d_z": d_z(d), "d_z_ci": bootstrap_ci(d, "d_z")}  # fmt: skip
    nonzero = d[d != 0]
    if len(nonzero) == 0:
        return PairedTest(n, 1.0, "none: every difference is zero", median, **sizes)  # type: ignore[arg-type]
    tied = len(np.unique(np.abs(nonzero))) < len(nonzero)
    exact = len(nonzero) == n and not tied and n <= EXACT_MAX_N
    p = float(wilcoxon(x, y, method="exact" if exact else "approx").pvalue)
    return PairedTest(n, p, "exact" if exact else "normal approximation", median, **sizes)  # type: ignore[arg-type]


def metric(s: Session, name: str) -> float:
    return float(getattr(s, name))


def by_subject(
    sessions: list[Session], key: Callable[[Session], object], levels: list, m: str
) -> list[np.ndarray]:
    """One column per level (condition, period) of ``m``, over the subjects that have every level."""
    cell = {(s.info.subject, key(s)): metric(s, m) for s in sessions}
    subjects = sorted({s.info.subject for s in sessions})
    full = [x for x in subjects if all(np.isfinite(cell.get((x, lv), np.nan)) for lv in levels)]
    return [np.array([cell[(x, lv)] for x in full]) for lv in levels]


def select(sessions: list[Session], include_incomplete: bool) -> tuple[list[Session], list[tuple[Path, str]]]:
    """The sessions that count; those cut short are left out, with their reason, unless included."""
    if include_incomplete:
        return sessions, []
    kept = [s for s in sessions if s.end.complete]
    return kept, [(s.path, f"cut short: {s.end.reason}") for s in sessions if not s.end.complete]


def agreement(sessions: list[Session]) -> list[str]:
    """The sessions ran one task (else InputError); the software versions and planned sets they ran on,
    if more than one."""
    tasks: dict[str, list[str]] = {}
    for s in sessions:
        tasks.setdefault(s.info.task_sha256, []).append(s.path.name)
    if len(tasks) > 1:
        which = "; ".join(f"{h[:12]}: {', '.join(files)}" for h, files in tasks.items())
        raise InputError(f"the sessions ran different task files (by SHA-256): {which}")
    notes = []
    versions = sorted({s.info.software for s in sessions})
    if len(versions) > 1:
        notes.append(f"sessions ran different software: {', '.join(versions)}")
    sets = sorted({s.info.sets_sha256[:12] for s in sessions if s.info.sets_sha256})
    if len(sets) > 1:  # planned again between sessions (an edited task, another machine's planner)
        notes.append(f"sessions ran on different planned sets: {', '.join(sets)}")
    return notes


def analyse(
    sessions: list[Session], include_incomplete: bool = False, margins: dict[str, float] | None = None
) -> Study:
    """Table I and the tests; two sessions for one subject and condition is an error (which one counts?)."""
    if not sessions:
        raise InputError("no session files to analyse")
    notes = agreement(sessions)
    sessions, excluded = select(sessions, include_incomplete)
    if not sessions:
        raise InputError("every session was cut short: none to analyse (--include-incomplete counts them)")
    seen: dict[tuple[str, str], Session] = {}
    for s in sessions:
        k = (s.info.subject, s.info.condition)
        if k in seen:
            raise InputError(
                f"two sessions of subject {k[0]} in condition {k[1]}: {seen[k].path} and {s.path}; "
                "pass the one that counts"
            )
        seen[k] = s
    conditions = [c for c in CONDITION_NAMES if any(s.info.condition == c for s in sessions)]
    working = any(s.working_calibration for s in sessions)
    metrics = (
        METRICS
        + ((RESTING,) if working else ())
        + ((TLX,) if any(s.end.tlx is not None for s in sessions) else ())
    )
    if working:
        notes.append(
            "calibrated at work: RR_r is the working level (k = 1), so mean RR / RR_r is about 1 in (b) by "
            "construction; mean RR / RR at rest (the level kept beside it) is reported too"
        )
    table: dict[str, dict[str, tuple[float, float, int]]] = {}
    for c in conditions:
        rows = [s for s in sessions if s.info.condition == c]
        table[c] = {}
        for m in metrics:
            v = np.array([metric(s, m) for s in rows])
            v = v[np.isfinite(v)]
            sd = float(np.std(v, ddof=1)) if len(v) > 1 else float("nan")
            table[c][m] = (float(np.mean(v)) if len(v) else float("nan"), sd, len(v))
    tests: dict[str, dict[str, PairedTest]] = {}
    pairs_of: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}
    for a, b in combinations(conditions, 2):
        both = sorted({s for s, c in seen if c == a} & {s for s, c in seen if c == b})
        tests[f"{a}-{b}"] = {}
        for m in metrics:
            pairs = [(metric(seen[(s, a)], m), metric(seen[(s, b)], m)) for s in both]
            pairs = [p for p in pairs if np.isfinite(p).all()]
            x, y = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
            pairs_of[(f"{a}-{b}", m)] = (x, y)
            tests[f"{a}-{b}"][m] = paired_test(x, y)
    family = [(pair, m) for pair in tests for m in metrics]
    adjusted = holm([tests[pair][m].p for pair, m in family])
    for (pair, m), p in zip(family, adjusted, strict=True):
        tests[pair][m] = replace(tests[pair][m], p_holm=float(p))
    margins = {**MARGINS, **(margins or {})}
    bc = ("b-c", metrics[0]) in pairs_of
    equivalence = {m: tost_paired(*pairs_of[("b-c", m)], margins[m]) for m in metrics} if bc else {}
    friedman_of = {
        m: friedman(by_subject(sessions, lambda s: s.info.condition, conditions, m)) for m in metrics
    }
    return Study(sessions, conditions, table, tests, all(s.info.simulated for s in sessions), metrics,
                 friedman_of, equivalence, period_effects(sessions, metrics), excluded, notes)  # fmt: skip


def period_effects(sessions: list[Session], metrics: tuple[str, ...]) -> dict[str, dict[str, object]]:
    """Per measure: its mean by the session's place in the subject's order, and Friedman's test over
    the subjects with every place (learning, fatigue). Nothing without a study plan's periods."""
    periods = sorted({s.info.period for s in sessions if s.info.period is not None})
    if len(periods) < 2:
        return {}
    placed = [s for s in sessions if s.info.period is not None]
    out: dict[str, dict[str, object]] = {}
    for m in metrics:
        means = {str(p): _mean_of_some([metric(s, m) for s in placed if s.info.period == p]) for p in periods}
        test = friedman(by_subject(placed, lambda s: s.info.period, periods, m))
        out[m] = {"means": means, "n": test.n, "statistic": test.statistic, "p": test.p}
    return out


def _mean_of_some(values: list[float]) -> float:
    """The mean of the finite values; NaN, said by the caller, where there are none (numpy's own
    "Mean of empty slice" warning once leaked to the user here)."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def stars(p: float) -> str:
    if not np.isfinite(p):
        return "–"
    return "***" if p < 0.001 else "**" if p < 0.01 else "*" if p < 0.05 else "n.s."


def to_json(study: Study) -> dict:
    return {
        "simulated": study.simulated,
        "subjects": len({s.info.subject for s in study.sessions}),
        "conditions": {c: CONDITION_NAMES[c] for c in study.conditions},
        "sets_sha256": sorted({s.info.sets_sha256 for s in study.sessions if s.info.sets_sha256}),
        "builds": sorted({s.info.build for s in study.sessions if s.info.build}),
        "table": {
            c: {m: {"mean": v[0], "sd": v[1], "n": v[2]} for m, v in ms.items()}
            for c, ms in study.table.items()
        },
        "friedman": {m: {"n": f.n, "statistic": f.statistic, "p": f.p} for m, f in study.friedman.items()},
        "wilcoxon": {
            pair: {
                m: {
                    "n": t.n,
                    "p": t.p,
                    "method": t.method,
                    "median_difference": t.median_difference,
                    "p_holm": t.p_holm,
                    "rank_biserial": t.rank_biserial,
                    "rank_biserial_ci": list(t.rank_biserial_ci),
                    "d_z": t.d_z,
                    "d_z_ci": list(t.d_z_ci),
                }
                for m, t in ms.items()
            }
            for pair, ms in study.tests.items()
        },
        "equivalence_b_c": {
            m: {
                "n": e.n,
                "margin": e.margin,
                "mean_difference": e.mean_difference,
                "p_lower": e.p_lower,
                "p_upper": e.p_upper,
                "p": e.p,
            }
            for m, e in study.equivalence.items()
        },
        "periods": study.periods,
        "excluded": [{"file": str(f), "why": why} for f, why in study.excluded],
        "notes": study.notes,
        "sessions": [session_row(s, study.metrics) for s in study.sessions],
    }


def session_row(s: Session, metrics: tuple[str, ...] = METRICS) -> dict:
    return {
        "file": str(s.path),
        "subject": s.info.subject,
        "condition": s.info.condition,
        "period": s.info.period,
        "break_s": s.info.break_s,
        "simulated": s.info.simulated,
        "minutes": round(s.minutes, 3),
        "complete": s.end.complete,
        "cycles": s.n_cycles,
        "errors": s.n_errors,
        "rr_rest_s": s.rr_rest_s,
        "good_windows": len(s.good_rr_s),
        **{m: metric(s, m) for m in metrics},
    }


def write_csv(study: Study, folder: Path) -> list[str]:
    """Long format for R, JASP or SPSS: sessions.csv, one row per subject × condition (with the TLX items),
    and windows.csv, one row per window of each session (data time from the session's start)."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for s in study.sessions:
        row = session_row(s, study.metrics) | {
            "file": s.path.name,
            "training": s.info.training_start_ns is not None,
        }
        tlx = s.end.tlx
        rows.append(row | {f"tlx_{i}": getattr(tlx, i) if tlx else "" for i in Tlx.__struct_fields__})
    _csv(folder / "sessions.csv", rows)
    windows = []
    for s in study.sessions:
        for w in s.windows:
            if not s.inside(w.end_ns):
                continue
            k = s.k_at(w.end_ns)
            at = round((w.end_ns - s.info.start_ns) / 1e9, 3)
            windows.append({"subject": s.info.subject, "condition": s.info.condition, "period": s.info.period,
                            "end_s": at, "mean_rr_s": w.mean_rr_s, "quality": w.quality, "reason": w.reason,
                            "movement_mg": w.movement_mg, "k": k})  # fmt: skip
    _csv(folder / "windows.csv", windows)
    return ["sessions.csv", "windows.csv"]


def _csv(path: Path, rows: list[dict]) -> None:
    import csv
    import io

    text = io.StringIO()
    if rows:
        w = csv.DictWriter(text, fieldnames=list(rows[0]), lineterminator="\n")
        w.writeheader()
        w.writerows({k: "" if v is None else v for k, v in r.items()} for r in rows)
    write_readable(path, text.getvalue().encode())


def write_study(study: Study, out: Path) -> list[str]:
    """study.json, the figures (like the paper's Fig. 6 per subject and Fig. 7) and index.html."""
    from cadence.lab.plots import study_figure, subject_figure

    out.mkdir(parents=True, exist_ok=True)
    write_readable(out / "study.json", json.dumps(to_json(study), indent=1).encode())
    written = ["study.json"]
    values = {
        c: {m: [metric(s, m) for s in study.sessions if s.info.condition == c] for m in METRICS}
        for c in study.conditions
    }  # fmt: skip  (the figure: the paper's measures)
    marks = {pair: {m: stars(t.p) for m, t in ms.items()} for pair, ms in study.tests.items()}
    write_readable(out / "conditions.png", study_figure(values, CONDITION_NAMES, marks, study.simulated))
    written.append("conditions.png")
    for subject in sorted({s.info.subject for s in study.sessions}):
        mine = [s for s in study.sessions if s.info.subject == subject]
        mine.sort(key=lambda s: s.info.condition)
        name = f"subject_{_safe(subject)}.png"
        write_readable(out / name, subject_figure(mine))
        written.append(name)
    write_readable(out / "index.html", _html(study, written).encode())
    written.append("index.html")
    return written


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


def _fmt(v: float, digits: int = 3) -> str:
    return f"{v:.{digits}f}" if np.isfinite(v) else "–"


def _with_ci(value: float, ci: tuple[float, float]) -> str:
    return f"{_fmt(value, 2)} [{_fmt(ci[0], 2)}, {_fmt(ci[1], 2)}]"


def _html(study: Study, files: list[str]) -> str:
    label = "SIMULATED (operator twins, not people)" if study.simulated else "sessions with people"
    ms = study.metrics
    head = "".join(f"<th>{html.escape(LABELS[m])}</th>" for m in ms)
    t1 = "\n".join(
        f"<tr><td>({c}) {CONDITION_NAMES[c]}</td>"
        + "".join(
            f"<td>{_fmt(mean)} ± {_fmt(sd)} (n = {n})</td>" for mean, sd, n in (study.table[c][m] for m in ms)
        )
        + "</tr>"
        for c in study.conditions
    )
    omnibus = (
        "<tr><td>Friedman (every condition)</td>"
        + "".join(
            f"<td>χ² = {_fmt(f.statistic, 2)}, p = {f.p:.3g}<br><small>n = {f.n}</small></td>"
            for f in (study.friedman[m] for m in ms)
        )
        + "</tr>"
    )
    tests = omnibus + "\n".join(
        f"<tr><td>{pair}</td>"
        + "".join(
            f"<td>p = {t.p:.3g} {stars(t.p)}, Holm {t.p_holm:.3g} {stars(t.p_holm)}<br><small>n = {t.n}, "
            f"{html.escape(t.method)}, median Δ {_fmt(t.median_difference, 4)}<br>"
            f"r_rb {_with_ci(t.rank_biserial, t.rank_biserial_ci)}, "
            f"d_z {_with_ci(t.d_z, t.d_z_ci)}</small></td>"
            for t in (tests_of[m] for m in ms)
        )
        + "</tr>"
        for pair, tests_of in study.tests.items()
    )
    tost = "".join(
        f"<td>±{e.margin:g}: p = {e.p:.3g} ({'equivalent' if e.p < 0.05 else 'not shown equivalent'})<br>"
        f"<small>n = {e.n}, mean Δ {_fmt(e.mean_difference, 4)}</small></td>"
        for e in (study.equivalence[m] for m in ms if m in study.equivalence)
    )
    periods = "\n".join(
        f"<tr><td>{html.escape(LABELS[m])}</td><td>"
        + ", ".join(f"{k}: {_fmt(v)}" for k, v in row["means"].items())  # type: ignore[attr-defined]
        + f"</td><td>p = {row['p']:.3g} (n = {row['n']})</td></tr>"
        for m, row in study.periods.items()
    )
    left_out = "".join(f"<li>{html.escape(f.name)}: {html.escape(why)}</li>" for f, why in study.excluded)
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in study.notes)
    ordered = sorted(study.sessions, key=lambda s: (s.info.subject, s.info.condition))
    per = "\n".join(
        "<tr>"
        + "".join(
            f"<td>{html.escape(str(r[k]) if not isinstance(r[k], float) else _fmt(r[k]))}</td>"
            for k in (*COLUMNS, *ms, "rr_rest_s")
        )
        + f"<td>{html.escape(Path(r['file']).name)}</td></tr>"
        for r in (session_row(s, ms) for s in ordered)
    )
    captions = {
        "conditions.png": "Per condition, one point per subject: mean RR over RR_r (like the paper's "
        "Fig. 7), φ and ε; brackets mark the Wilcoxon signed-rank test of each pair (* p < 0.05, "
        "** p < 0.01, *** p < 0.001, n.s. not significant).",
    }
    figs = "\n".join(
        f'<figure><img src="{f}" alt="{f}"><figcaption>'
        + html.escape(
            captions.get(
                f,
                f"{f[8:-4]}: per condition, each window's mean RR (filled: good, hollow: held), RR_r and the "
                "decision thresholds, the selected k (right axis), cycle ends (ticks) and errors (red ×), "
                "over the session's minutes (like the paper's Fig. 6).",
            )
        )
        + "</figcaption></figure>"
        for f in files
        if f.endswith(".png")
    )
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Cadence study</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}} img{{max-width:100%}}
table{{border-collapse:collapse;margin:1em 0}} td,th{{border:1px solid #ccc;padding:4px 8px;text-align:left}}
figcaption{{color:#444;font-size:90%}}</style></head><body>
<h1>Cadence study: {label}</h1>
<p>{len({s.info.subject for s in study.sessions})} subjects, {len(study.sessions)} sessions.
φ = cycles per minute, ε = errors per cycle, mean RR over the good windows; RR_r from each subject's
calibration at rest. Means ± sd over subjects.</p>
<h2>Table I</h2>
<table><tr><th>condition</th>{head}</tr>{t1}</table>
<h2>Tests: Friedman over every condition, then Wilcoxon signed-rank paired by subject</h2>
<p>p as tested, and Holm-adjusted over every pair and measure; effect sizes (second condition minus first):
the matched-pairs rank-biserial correlation r_rb and d_z, with 95 % percentile bootstrap CIs over
subjects.</p>
<table><tr><th>pair</th>{head}</tr>{tests}</table>
<h2>(b) ≈ (c)? Two one-sided paired t-tests (TOST) within the margin</h2>
<table><tr><th></th>{head}</tr><tr><td>c − b</td>{tost}</tr></table>
<h2>Period effects: the measures by the session's place in each subject's order</h2>
<table><tr><th>measure</th><th>mean by period</th><th>Friedman</th></tr>{periods}</table>
<h2>Left out</h2><ul>{left_out or "<li>none</li>"}</ul>
<ul>{notes}</ul>
{figs}
<h2>Sessions</h2>
<table><tr><th>subject</th><th>condition</th><th>minutes</th><th>complete</th><th>cycles</th><th>errors</th>
{head}<th>RR_r [s]</th><th>file</th></tr>{per}</table>
</body></html>
"""


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
