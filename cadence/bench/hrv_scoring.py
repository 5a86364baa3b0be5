"""How far the windows a pipeline marks good are from the truth, on annotated records.

Alg. 1 moves k one step for each Δ_rs = 20 ms of mean RR, so what matters is not the F1 of the beats but
the error of each window that is allowed to move k. The truth of a window is the mean of the annotated
NN intervals (both beats normal: N L R e j) whose closing beat lies in it. A window is not scored when it
has fewer than ``MIN_NN`` of them (there is no truth to compare with) or touches ventricular flutter or
fibrillation (no RR interval means anything there). An NN interval that spans a stretch the annotators
marked unreadable in every lead is not in the truth: a beat hidden there could not be annotated (101 at
320 s: an "NN interval" of 1.89 s between beats 1 s apart, across 1 s marked unreadable).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from rich.console import Console
from rich.table import Table

from common.hrv.records import BEAT_SYMBOLS, Annotations
from common.hrv.stream import Window

NN_SYMBOLS = frozenset("NLRej")  # normal beats of MIT-BIH's beat labels
SINUS = "(N"  # MIT-BIH's rhythm annotation of normal sinus rhythm
MIN_NN = 10


def has_arrhythmia_runs(ann: Annotations) -> bool:
    """Any rhythm other than normal sinus annotated (bigeminy, trigeminy, AF, tachycardia, …): the held
    share is judged on records without them, where a window has no reason to be held but noise."""
    return any(
        s == "+" and a.strip("\x00 ") not in ("", "(N") for s, a in zip(ann.symbol, ann.aux, strict=True)
    )


@dataclass(frozen=True, slots=True)
class Truth:
    start_s: float
    end_s: float
    mean_nn_s: float | None  # None: not scored
    rhythm: str = SINUS  # the annotated rhythm: the non-sinus one that covers most of the window, if any


def rhythm_spans(ann: Annotations, end_s: float) -> list[tuple[float, float, str]]:
    """(from, to, rhythm) for each annotated rhythm (``(N``, ``(AFIB``, ``(SVTA``, ``(NOD``, ``(BII`` …),
    from its ``+`` annotation to the next one."""
    out: list[tuple[float, float, str]] = []
    for t, sym, aux in zip(ann.t_s, ann.symbol, ann.aux, strict=True):
        rhythm = aux.strip("\x00 ")
        if sym == "+" and rhythm.startswith("("):
            if out:
                out[-1] = (out[-1][0], float(t), out[-1][2])
            out.append((float(t), end_s, rhythm))
    return out


def rhythm_of(spans: Sequence[tuple[float, float, str]], start_s: float, end_s: float) -> str:
    """The non-sinus rhythm that covers most of [start, end), else sinus: a window with a run of SVT in it
    is not a window of sinus rhythm, however short the run."""
    cover: dict[str, float] = {}
    for a, b, r in spans:
        if r != SINUS and (o := min(b, end_s) - max(a, start_s)) > 0:
            cover[r] = cover.get(r, 0.0) + o
    return max(cover, key=lambda r: cover[r]) if cover else SINUS


def unreadable_spans(ann: Annotations, end_s: float) -> list[tuple[float, float]]:
    """Where every lead is unreadable: from a ``~`` of subtype -1 to the next ``~``."""
    spans: list[tuple[float, float]] = []
    open_at: float | None = None
    for t, sym, sub in zip(ann.t_s, ann.symbol, ann.subtype, strict=False):
        if sym != "~":
            continue
        if open_at is not None:
            spans.append((open_at, float(t)))
            open_at = None
        if sub == -1:
            open_at = float(t)
    if open_at is not None:
        spans.append((open_at, end_s))
    return spans


def flutter_spans(ann: Annotations, end_s: float) -> list[tuple[float, float]]:
    """Where the rhythm is ventricular flutter or fibrillation: a ``(VFL``/``(VF`` rhythm until the next
    rhythm annotation, and each ``[`` … ``]`` episode."""
    spans: list[tuple[float, float]] = []
    open_at: float | None = None
    for t, sym, aux in zip(ann.t_s, ann.symbol, ann.aux, strict=True):
        rhythm = aux.strip("\x00 ")
        if sym == "+" and rhythm.startswith("("):
            if open_at is not None:
                spans.append((open_at, float(t)))
                open_at = None
            if rhythm in ("(VFL", "(VF"):
                open_at = float(t)
        elif sym == "[":
            open_at = float(t) if open_at is None else open_at
        elif sym == "]" and open_at is not None:
            spans.append((open_at, float(t)))
            open_at = None
    if open_at is not None:
        spans.append((open_at, end_s))
    return spans


def truth(ann: Annotations, starts_s: Sequence[float], length_s: float, end_s: float) -> list[Truth]:
    """The reference mean NN of each window [start, start + length)."""
    beats = [(float(t), s) for t, s in zip(ann.t_s, ann.symbol, strict=True) if s in BEAT_SYMBOLS]
    t_end = np.array([b[0] for b in beats[1:]])
    nn = np.array(
        [a[1] in NN_SYMBOLS and b[1] in NN_SYMBOLS for a, b in itertools.pairwise(beats)], dtype=bool
    )
    rr = np.diff([b[0] for b in beats]) if beats else np.empty(0)
    spans = flutter_spans(ann, end_s)
    hidden = unreadable_spans(ann, end_s)
    rhythms = rhythm_spans(ann, end_s)
    t_start = np.array([b[0] for b in beats[:-1]])
    for a, b in hidden:
        nn &= ~((t_start < b) & (t_end > a))
    out = []
    for s in starts_s:
        e = s + length_s
        sel = (t_end >= s) & (t_end < e) & nn
        touched = any(a < e and b > s for a, b in spans)
        mean = float(rr[sel].mean()) if sel.sum() >= MIN_NN and not touched else None
        out.append(Truth(s, e, mean, rhythm_of(rhythms, s, e)))
    return out


@dataclass(frozen=True, slots=True)
class WindowError:
    record: str
    start_s: float
    error_s: float  # |pipeline's mean RR − truth|
    reason: str = ""


@dataclass
class WindowScore:
    """The figures of the windows table (docs/decision.md) for one pipeline over a set of records."""

    name: str
    good: list[WindowError] = field(default_factory=list)
    held: int = 0  # scored windows the pipeline marked low (it would hold k)
    held_reasons: dict[str, int] = field(default_factory=dict)
    sinus_scored: int = 0  # scored windows of records without arrhythmia runs
    sinus_held: int = 0
    held_by_record: dict[str, int] = field(default_factory=dict)
    by_rhythm: dict[str, list[int]] = field(default_factory=dict)  # rhythm → [scored windows, held, passed]

    def add(
        self,
        record: str,
        truths: Iterable[Truth],
        means: Iterable[float | None],
        reasons: Iterable[str],
        sinus: bool = False,
    ) -> None:
        """``means[i]`` is the pipeline's mean RR for ``truths[i]``'s window when it marks it good, else
        None; ``reasons[i]`` says why it held the window; ``sinus``: the record has no arrhythmia runs."""
        for t, m, why in zip(truths, means, reasons, strict=True):
            if t.mean_nn_s is None:
                continue
            counts = self.by_rhythm.setdefault(t.rhythm, [0, 0, 0])
            counts[0] += 1
            counts[1 if m is None else 2] += 1
            self.sinus_scored += sinus
            if m is None:
                self.held += 1
                self.sinus_held += sinus
                self.held_reasons[why] = self.held_reasons.get(why, 0) + 1
                self.held_by_record[record] = self.held_by_record.get(record, 0) + 1
            else:
                self.good.append(WindowError(record, t.start_s, abs(m - t.mean_nn_s)))

    def add_windows(self, record: str, truths: Sequence[Truth], wins: Sequence[Window], sinus: bool) -> None:
        """A Cadence pipeline's windows: the mean RR of those it marks good, the reason of the others."""
        means = [w.mean_rr_s if w.quality == "good" else None for w in wins]
        self.add(record, truths, means, [w.reason or "" for w in wins], sinus)

    def merge(self, other: WindowScore) -> None:
        """Another part of the same pipeline's run (another record) added to this one."""
        self.good += other.good
        self.held += other.held
        for why, n in other.held_reasons.items():
            self.held_reasons[why] = self.held_reasons.get(why, 0) + n
        self.sinus_scored += other.sinus_scored
        self.sinus_held += other.sinus_held
        for record, n in other.held_by_record.items():
            self.held_by_record[record] = self.held_by_record.get(record, 0) + n
        for rhythm, counts in other.by_rhythm.items():
            mine = self.by_rhythm.setdefault(rhythm, [0, 0, 0])
            mine[:] = [a + b for a, b in zip(mine, counts, strict=True)]

    @property
    def errors_ms(self) -> NDArray[np.float64]:
        return np.array([w.error_s for w in self.good]) * 1e3

    @property
    def held_share(self) -> float:
        n = len(self.good) + self.held
        return self.held / n if n else 0.0

    def figures(self) -> dict[str, float | int | str]:
        e = self.errors_ms
        worst = sorted(self.good, key=lambda w: -w.error_s)
        return {
            "good": len(self.good),
            "held": self.held,
            "held_share": round(self.held_share, 3),
            "held_share_sinus": round(self.sinus_held / self.sinus_scored, 3) if self.sinus_scored else 0.0,
            "p95_ms": round(float(np.percentile(e, 95)), 2) if e.size else 0.0,
            "over_10_ms": int((e > 10).sum()),
            "over_20_ms": int((e > 20).sum()),
            "worst_ms": round(float(e.max()), 1) if e.size else 0.0,
            # the records of the windows over 10 ms, worst first
            "worst_records": ", ".join(dict.fromkeys(w.record for w in worst if w.error_s > 0.01)),
            # windows passed as good inside an annotated rhythm other than sinus: read as if they were
            "passed_not_sinus": sum(c[2] for r, c in self.by_rhythm.items() if r != SINUS),
        }


def window_table(title: str, scores: dict[str, dict[str, WindowScore]], out: Console) -> dict[str, object]:
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
    rhythms = Table(title="Scored windows per annotated rhythm: windows / held / passed as good")
    pipelines = [(v, n, sc) for v, by_name in scores.items() for n, sc in by_name.items() if n != "neurokit2"]
    names = sorted({r for _, _, sc in pipelines for r in sc.by_rhythm}, key=lambda r: (r != SINUS, r))
    rhythms.add_column("variant")
    rhythms.add_column("pipeline")
    for r in names:
        rhythms.add_column(r.lstrip("(") + (" (sinus)" if r == SINUS else ""), justify="right")
    for v, n, sc in pipelines:
        rhythms.add_row(
            v, n, *("/".join(map(str, sc.by_rhythm[r])) if r in sc.by_rhythm else "" for r in names)
        )
        figures[v][n]["by_rhythm"] = {r: dict(zip(("windows", "held", "passed"), c, strict=True))
                                      for r, c in sc.by_rhythm.items()}  # type: ignore[assignment]  # fmt: skip
    out.print(rhythms)
    return dict(figures)
