"""RR intervals from R peaks, cleaned, and tumbling windows on data time (paper §II-C; DESIGN §6).

Why cleaning is not optional: one missed or extra beat moves a 30 s window's mean RR by about 20 ms,
the size of Δ_rs, so one detection error could move k. An interval is excluded when it departs from the
median of its neighbours by more than ``TOLERANCE``; its kind says why (``missed``: about twice the
median, ``extra``: a fragment, ``ectopic``: a premature beat and its compensatory pause). An interval
that spans a gap in the data is never formed.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

TOLERANCE = 0.2  # relative departure from the local median that excludes an interval
NEIGHBOURS = 5  # on each side, for the local median
MIN_RR_S, MAX_RR_S = 0.25, 2.5  # physiological bounds (240 and 24 beats per minute)
MAX_EXCLUDED = 0.2  # a window with more excluded intervals than this is low quality
MIN_COVERAGE = 0.6  # clean intervals must cover this share of the window

Kind = Literal["ok", "missed", "extra", "ectopic", "implausible"]
Gaps = tuple[tuple[float, float], ...] | list[tuple[float, float]]  # (start, end) of missing data, s
Quality = Literal["good", "low", "none"]


@dataclass(frozen=True, slots=True)
class Intervals:
    """``t_s[i]`` is the time of the beat that ends interval ``rr_s[i]``."""

    t_s: NDArray[np.float64]
    rr_s: NDArray[np.float64]
    kind: list[Kind]

    @property
    def excluded(self) -> NDArray[np.bool_]:
        return np.array([k != "ok" for k in self.kind], dtype=bool)


def intervals(peaks_s: NDArray[np.float64], gaps_s: Gaps = ()) -> Intervals:
    """RR intervals between consecutive peaks, classified; none across a gap (start, end) in the data."""
    peaks_s = np.asarray(peaks_s, dtype=float)
    if len(peaks_s) < 2:
        return Intervals(np.empty(0), np.empty(0), [])
    rr = np.diff(peaks_s)
    t = peaks_s[1:]
    keep = np.ones(len(rr), dtype=bool)
    for g0, g1 in gaps_s:
        keep &= ~((peaks_s[:-1] < g1) & (peaks_s[1:] > g0))
    rr, t = rr[keep], t[keep]
    return Intervals(t, rr, classify(rr))


def classify(rr: NDArray[np.float64]) -> list[Kind]:
    kinds: list[Kind] = []
    for i, x in enumerate(rr):
        if not MIN_RR_S <= x <= MAX_RR_S:
            kinds.append("implausible")
            continue
        lo, hi = max(0, i - NEIGHBOURS), min(len(rr), i + NEIGHBOURS + 1)
        neigh = np.concatenate([rr[lo:i], rr[i + 1 : hi]])
        neigh = neigh[(neigh >= MIN_RR_S) & (neigh <= MAX_RR_S)]
        if neigh.size < 2:
            kinds.append("ok")
            continue
        med = float(np.median(neigh))
        dev = x / med - 1.0
        if abs(dev) <= TOLERANCE:
            kinds.append("ok")
        elif 1.6 <= x / med <= 2.4:
            kinds.append("missed")
        elif x / med <= 0.6:
            kinds.append("extra")
        else:
            kinds.append("ectopic")
    return kinds


@dataclass(frozen=True, slots=True)
class Window:
    start_s: float
    end_s: float
    mean_rr_s: float | None
    n_beats: int
    excluded: float
    quality: Quality
    rmssd_s: float | None
    sdnn_s: float | None


def window_stats(start_s: float, end_s: float, iv: Intervals, gaps_s: Gaps = ()) -> Window:
    """One window [start, end): the intervals whose ending beat falls inside it. A window that a gap in
    the data overlaps is low quality whatever is left of it (DESIGN §6)."""
    sel = (iv.t_s >= start_s) & (iv.t_s < end_s)
    rr = iv.rr_s[sel]
    bad = iv.excluded[sel]
    clean = rr[~bad]
    n = int(rr.size)
    excluded = float(bad.mean()) if n else 1.0
    if clean.size == 0:
        return Window(start_s, end_s, None, n, excluded, "none", None, None)
    coverage = float(clean.sum()) / (end_s - start_s)
    gapped = any(g0 < end_s and g1 > start_s for g0, g1 in gaps_s)
    good = excluded <= MAX_EXCLUDED and coverage >= MIN_COVERAGE and not gapped
    # successive differences only between intervals that are next to each other and both clean
    idx = np.nonzero(sel)[0]
    pairs = [
        (iv.rr_s[a], iv.rr_s[b])
        for a, b in itertools.pairwise(idx)
        if b == a + 1 and not iv.excluded[a] and not iv.excluded[b]
    ]
    rmssd = float(np.sqrt(np.mean([(b - a) ** 2 for a, b in pairs]))) if pairs else None
    return Window(
        start_s,
        end_s,
        float(clean.mean()),
        n,
        excluded,
        "good" if good else "low",
        rmssd,
        float(clean.std(ddof=1)) if clean.size > 1 else None,
    )


def windows(
    iv: Intervals, length_s: float = 30.0, start_s: float = 0.0, end_s: float | None = None, gaps_s: Gaps = ()
) -> list[Window]:
    """Tumbling windows of ``length_s`` from ``start_s``; the last one ends at or before ``end_s``."""
    end = end_s if end_s is not None else (float(iv.t_s[-1]) if iv.t_s.size else start_s)
    out = []
    t = start_s
    while t + length_s <= end + 1e-9:
        out.append(window_stats(t, t + length_s, iv, gaps_s))
        t += length_s
    return out


def match_beats(
    ref_s: NDArray[np.float64], found_s: NDArray[np.float64], tol_s: float = 0.15
) -> tuple[int, int, int]:
    """(TP, FP, FN): detected beats matched one-to-one to reference beats within ``tol_s`` (the usual
    150 ms of ANSI/AAMI EC57), each reference taking the nearest unused detection."""
    found_s = np.asarray(found_s, dtype=float)
    used = np.zeros(len(found_s), dtype=bool)
    tp = 0
    idx = np.searchsorted(found_s, ref_s)
    for k, t in enumerate(ref_s):
        cands = [
            c
            for c in (idx[k] - 1, idx[k])
            if 0 <= c < len(found_s) and not used[c] and abs(found_s[c] - t) <= tol_s
        ]
        if cands:
            used[min(cands, key=lambda c: abs(found_s[c] - t))] = True
            tp += 1
    return tp, len(found_s) - tp, len(ref_s) - tp
