"""The statistics a within-subjects study is asked for beyond the paper's Wilcoxon tests: the omnibus test
before the pairwise ones, the correction over them, effect sizes with confidence intervals, and an
equivalence test. Pure functions on arrays; every one is checked in tests/cadence/lab/test_stats.py
against scipy, statsmodels or a published worked example, not against itself.

- Friedman's test over subjects × conditions (scipy): is there any difference at all, before the pairs.
- Holm's step-down correction of the pairwise p-values (Holm 1979): controls the family-wise error over
  the 12 tests (3 pairs × 4 measures) without Bonferroni's loss of power.
- Effect sizes of a paired difference d = y − x: the matched-pairs rank-biserial correlation (Kerby 2014:
  the share of rank sum on the positive side minus the share on the negative side, zeros left out as in
  Wilcoxon's test) and Cohen's d_z (mean over sd of d). Percentile bootstrap CIs, resampling subjects,
  seeded so a table is reproducible.
- TOST (Schuirmann 1987): "b ≈ c" needs evidence of equivalence, not a non-significant difference. Two
  one-sided paired t-tests against ±margin; equivalent at α when both reject, so p = the larger of the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

BOOTSTRAP_RESAMPLES = 4000
BOOTSTRAP_SEED = 20_260_101


def holm(ps: ArrayLike) -> NDArray[np.float64]:
    """Holm-adjusted p-values, in the given order; NaN (no test) stays NaN and does not count."""
    p = np.asarray(ps, dtype=float)
    out = np.full_like(p, np.nan)
    idx = np.flatnonzero(np.isfinite(p))
    m = len(idx)
    running = 0.0
    for rank, i in enumerate(idx[np.argsort(p[idx], kind="stable")]):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out


def _rank_biserial_rows(d: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per row of differences: zeros are left out, the rest ranked by size (ties averaged)."""
    from scipy.stats import rankdata

    ranks = rankdata(np.where(d == 0, np.nan, np.abs(d)), axis=1, nan_policy="omit")
    pos = np.nansum(np.where(d > 0, ranks, 0.0), axis=1)
    neg = np.nansum(np.where(d < 0, ranks, 0.0), axis=1)
    total = pos + neg
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, (pos - neg) / total, np.nan)


def _d_z_rows(d: NDArray[np.float64]) -> NDArray[np.float64]:
    sd = np.std(d, axis=1, ddof=1) if d.shape[1] > 1 else np.zeros(len(d))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(sd > 0, np.mean(d, axis=1) / sd, np.nan)


_ROWS = {"rank_biserial": _rank_biserial_rows, "d_z": _d_z_rows}


def rank_biserial(diff: ArrayLike) -> float:
    """Matched-pairs rank-biserial correlation of the differences (zeros left out); NaN if none is left."""
    return float(_rank_biserial_rows(np.asarray(diff, dtype=float)[None, :])[0])


def d_z(diff: ArrayLike) -> float:
    """Cohen's d_z: the mean difference over its standard deviation (n − 1)."""
    return float(_d_z_rows(np.asarray(diff, dtype=float)[None, :])[0])


def bootstrap_ci(diff: ArrayLike, stat: str, level: float = 0.95) -> tuple[float, float]:
    """Percentile bootstrap CI of ``stat`` ("rank_biserial" or "d_z") over resampled subjects."""
    d = np.asarray(diff, dtype=float)
    if len(d) < 3:
        return float("nan"), float("nan")
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    draws = _ROWS[stat](d[rng.integers(0, len(d), (BOOTSTRAP_RESAMPLES, len(d)))])
    draws = draws[np.isfinite(draws)]
    if len(draws) < BOOTSTRAP_RESAMPLES // 2:
        return float("nan"), float("nan")
    tail = (1.0 - level) / 2.0 * 100.0
    lo, hi = np.percentile(draws, [tail, 100.0 - tail])
    return float(lo), float(hi)


@dataclass(frozen=True, slots=True)
class Omnibus:
    n: int  # subjects with every condition
    statistic: float
    p: float


def friedman(columns: list[NDArray[np.float64]]) -> Omnibus:
    """Friedman's chi-square over subjects (rows) × conditions (columns); NaN with fewer than 3
    conditions or 2 subjects."""
    from scipy.stats import friedmanchisquare

    n = len(columns[0]) if columns else 0
    if len(columns) < 3 or n < 2:
        return Omnibus(n, float("nan"), float("nan"))
    r = friedmanchisquare(*columns)
    return Omnibus(n, float(r.statistic), float(r.pvalue))


@dataclass(frozen=True, slots=True)
class Equivalence:
    n: int
    margin: float
    mean_difference: float
    p_lower: float  # H0: the difference is at or below −margin
    p_upper: float  # H0: at or above +margin
    p: float  # max of the two: equivalent at α when p < α


def tost_paired(x: ArrayLike, y: ArrayLike, margin: float) -> Equivalence:
    """Two one-sided paired t-tests of y − x against (−margin, +margin)."""
    from scipy.stats import ttest_1samp

    d = np.asarray(y, dtype=float) - np.asarray(x, dtype=float)
    if len(d) < 2:
        return Equivalence(len(d), margin, float("nan"), float("nan"), float("nan"), float("nan"))
    lower = float(ttest_1samp(d, -margin, alternative="greater").pvalue)
    upper = float(ttest_1samp(d, margin, alternative="less").pvalue)
    return Equivalence(len(d), margin, float(np.mean(d)), lower, upper, max(lower, upper))
