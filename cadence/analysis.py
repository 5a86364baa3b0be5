"""`cadence study analyse`: the paper's Table I and its tests (§IV) from session files, and nothing else.

Per subject and condition the measures of one session file (cadence/session.py): φ, ε, the mean of the
good windows' mean RR and that mean over the subject's RR_r. Per condition their mean ± sd over subjects
(Table I). Per pair of conditions and measure, a Wilcoxon signed-rank test paired by subject, over the
subjects that have both sessions: exact where scipy can be exact (no zero and no tied differences, at
most 50 pairs), the normal approximation otherwise, and the method is said beside the p-value.
"""

from __future__ import annotations

import html
import json
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np

from cadence.session import Session
from common.runtime.errors import InputError
from common.runtime.storage import write_readable
from schemas.session import CONDITION_NAMES

METRICS = ("productivity_per_min", "error_rate", "mean_rr_s", "mean_rr_norm")
LABELS = {
    "productivity_per_min": "φ [cycles/min]",
    "error_rate": "ε [errors/cycle]",
    "mean_rr_s": "mean RR [s]",
    "mean_rr_norm": "mean RR / RR_r",
}
COLUMNS = ("subject", "condition", "minutes", "complete", "cycles", "errors")
EXACT_MAX_N = 50  # scipy's own limit for the exact distribution


@dataclass(frozen=True, slots=True)
class PairedTest:
    n: int  # subjects with both sessions
    p: float
    method: str  # "exact", "normal approximation", or why there is no test
    median_difference: float  # second minus first condition


@dataclass(frozen=True, slots=True)
class Study:
    sessions: list[Session]
    conditions: list[str]  # those present, in the paper's order
    table: dict[str, dict[str, tuple[float, float, int]]]  # condition → metric → (mean, sd, n)
    tests: dict[str, dict[str, PairedTest]]  # "a-b" → metric → test
    simulated: bool


def paired_test(x: np.ndarray, y: np.ndarray) -> PairedTest:
    from scipy.stats import wilcoxon

    d = y - x
    n = len(d)
    if n == 0:
        return PairedTest(0, float("nan"), "no subject has both sessions", float("nan"))
    median = float(np.median(d))
    nonzero = d[d != 0]
    if len(nonzero) == 0:
        return PairedTest(n, 1.0, "none: every difference is zero", median)
    tied = len(np.unique(np.abs(nonzero))) < len(nonzero)
    if len(nonzero) == n and not tied and n <= EXACT_MAX_N:
        return PairedTest(n, float(wilcoxon(x, y, method="exact").pvalue), "exact", median)
    return PairedTest(n, float(wilcoxon(x, y, method="approx").pvalue), "normal approximation", median)


def metric(s: Session, name: str) -> float:
    return float(getattr(s, name))


def analyse(sessions: list[Session]) -> Study:
    """Table I and the tests; two sessions for one subject and condition is an error (which one counts?)."""
    if not sessions:
        raise InputError("no session files to analyse")
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
    table: dict[str, dict[str, tuple[float, float, int]]] = {}
    for c in conditions:
        rows = [s for s in sessions if s.info.condition == c]
        table[c] = {}
        for m in METRICS:
            v = np.array([metric(s, m) for s in rows])
            v = v[np.isfinite(v)]
            sd = float(np.std(v, ddof=1)) if len(v) > 1 else float("nan")
            table[c][m] = (float(np.mean(v)) if len(v) else float("nan"), sd, len(v))
    tests: dict[str, dict[str, PairedTest]] = {}
    for a, b in combinations(conditions, 2):
        both = sorted({s for s, c in seen if c == a} & {s for s, c in seen if c == b})
        tests[f"{a}-{b}"] = {}
        for m in METRICS:
            pairs = [(metric(seen[(s, a)], m), metric(seen[(s, b)], m)) for s in both]
            pairs = [p for p in pairs if np.isfinite(p).all()]
            x, y = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
            tests[f"{a}-{b}"][m] = paired_test(x, y)
    return Study(sessions, conditions, table, tests, all(s.info.simulated for s in sessions))


def stars(p: float) -> str:
    if not np.isfinite(p):
        return "–"
    return "***" if p < 0.001 else "**" if p < 0.01 else "*" if p < 0.05 else "n.s."


def to_json(study: Study) -> dict:
    return {
        "simulated": study.simulated,
        "subjects": len({s.info.subject for s in study.sessions}),
        "conditions": {c: CONDITION_NAMES[c] for c in study.conditions},
        "table": {
            c: {m: {"mean": v[0], "sd": v[1], "n": v[2]} for m, v in ms.items()}
            for c, ms in study.table.items()
        },
        "wilcoxon": {
            pair: {
                m: {"n": t.n, "p": t.p, "method": t.method, "median_difference": t.median_difference}
                for m, t in ms.items()
            }
            for pair, ms in study.tests.items()
        },
        "sessions": [session_row(s) for s in study.sessions],
    }


def session_row(s: Session) -> dict:
    return {
        "file": str(s.path),
        "subject": s.info.subject,
        "condition": s.info.condition,
        "simulated": s.info.simulated,
        "minutes": round(s.minutes, 3),
        "complete": s.end.complete,
        "cycles": s.n_cycles,
        "errors": s.n_errors,
        "rr_rest_s": s.rr_rest_s,
        "good_windows": len(s.good_rr_s),
        **{m: metric(s, m) for m in METRICS},
    }


def write_study(study: Study, out: Path) -> list[str]:
    """study.json, the figures (like the paper's Fig. 6 per subject and Fig. 7) and index.html."""
    from cadence.plots import study_figure, subject_figure

    out.mkdir(parents=True, exist_ok=True)
    write_readable(out / "study.json", json.dumps(to_json(study), indent=1).encode())
    written = ["study.json"]
    values = {c: {m: [metric(s, m) for s in study.sessions if s.info.condition == c] for m in METRICS}
              for c in study.conditions}  # fmt: skip
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


def _html(study: Study, files: list[str]) -> str:
    label = "SIMULATED (operator twins, not people)" if study.simulated else "sessions with people"
    head = "".join(f"<th>{html.escape(LABELS[m])}</th>" for m in METRICS)
    t1 = "\n".join(
        f"<tr><td>({c}) {CONDITION_NAMES[c]}</td>"
        + "".join(
            f"<td>{_fmt(mean)} ± {_fmt(sd)} (n = {n})</td>"
            for mean, sd, n in (study.table[c][m] for m in METRICS)
        )
        + "</tr>"
        for c in study.conditions
    )
    tests = "\n".join(
        f"<tr><td>{pair}</td>"
        + "".join(
            f"<td>p = {t.p:.3g} {stars(t.p)}<br><small>n = {t.n}, {html.escape(t.method)}, median Δ "
            f"{_fmt(t.median_difference, 4)}</small></td>"
            for t in ms.values()
        )
        + "</tr>"
        for pair, ms in study.tests.items()
    )
    ordered = sorted(study.sessions, key=lambda s: (s.info.subject, s.info.condition))
    per = "\n".join(
        "<tr>"
        + "".join(
            f"<td>{html.escape(str(r[k]) if not isinstance(r[k], float) else _fmt(r[k]))}</td>"
            for k in (*COLUMNS, *METRICS, "rr_rest_s")
        )
        + f"<td>{html.escape(Path(r['file']).name)}</td></tr>"
        for r in (session_row(s) for s in ordered)
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
<h2>Wilcoxon signed-rank tests, paired by subject</h2>
<table><tr><th>pair</th>{head}</tr>{tests}</table>
{figs}
<h2>Sessions</h2>
<table><tr><th>subject</th><th>condition</th><th>minutes</th><th>complete</th><th>cycles</th><th>errors</th>
{head}<th>RR_r [s]</th><th>file</th></tr>{per}</table>
</body></html>
"""
