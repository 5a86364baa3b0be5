"""The study's statistics (cadence/lab/stats.py) checked against scipy, statsmodels and published examples."""

from __future__ import annotations

import numpy as np
import pytest
from statsmodels.stats.multitest import multipletests
from statsmodels.stats.weightstats import ttost_paired

from cadence.lab.stats import bootstrap_ci, d_z, friedman, holm, rank_biserial, tost_paired

RNG = np.random.default_rng(7)


def test_holm_matches_statsmodels_and_leaves_missing_tests_out() -> None:
    for _ in range(20):
        p = RNG.uniform(0, 0.2, 12)
        assert np.allclose(holm(p), multipletests(p, method="holm")[1])
    # Holm (1979)'s rule by hand: sorted p 0.01, 0.04, 0.03 → 3·0.01, max(0.03, 2·0.03), max(0.06, 0.04)
    assert np.allclose(holm([0.01, 0.04, 0.03]), [0.03, 0.06, 0.06])
    out = holm([0.01, np.nan, 0.04])  # a test that could not be run is not one of the family
    assert np.isnan(out[1])
    assert np.allclose(out[[0, 2]], multipletests([0.01, 0.04], method="holm")[1])


def test_the_rank_biserial_correlation_is_scipys_signed_rank_sum_rescaled() -> None:
    from scipy.stats import wilcoxon

    for n in (6, 12, 20):
        d = np.round(RNG.normal(0.3, 1.0, n), 1)  # rounded: ties among |d|, and zeros
        nz = d[d != 0]
        t_plus = wilcoxon(nz, alternative="greater").statistic  # the rank sum of the positive differences
        total = len(nz) * (len(nz) + 1) / 2
        assert rank_biserial(d) == pytest.approx((t_plus - (total - t_plus)) / total)
    # Kerby (2014): 4 of 5 pairs favour one side with ranks 5, 4, 3, 1 against 2: r = (13 − 2) / 15
    assert rank_biserial([5.0, 4.0, 3.0, -2.0, 1.0]) == pytest.approx(11 / 15)
    assert np.isnan(rank_biserial([0.0, 0.0]))


def test_d_z_is_the_paired_t_over_root_n() -> None:
    from scipy.stats import ttest_rel

    x, y = RNG.normal(0, 1, 12), RNG.normal(0.5, 1, 12)
    assert d_z(y - x) == pytest.approx(ttest_rel(y, x).statistic / np.sqrt(12))


def test_the_bootstrap_ci_brackets_the_estimate_and_narrows_with_more_subjects() -> None:
    few, many = RNG.normal(0.5, 1.0, 8), RNG.normal(0.5, 1.0, 200)
    lo, hi = bootstrap_ci(few, "d_z")
    assert lo < d_z(few) < hi
    lo2, hi2 = bootstrap_ci(many, "d_z")
    assert hi2 - lo2 < (hi - lo) / 2
    assert lo2 < 0.5 < hi2  # the true d_z is 0.5
    assert bootstrap_ci(few, "d_z") == (lo, hi)  # seeded: the same table every time
    assert all(np.isnan(bootstrap_ci([1.0, 2.0], "rank_biserial")))


def test_friedman_is_the_textbook_statistic_and_needs_three_conditions() -> None:
    from scipy.stats import chi2, rankdata

    cols = [RNG.normal(m, 1, 12) for m in (0.0, 0.3, 1.0)]
    r = friedman(cols)
    ranks = np.array([rankdata(row) for row in np.column_stack(cols)])  # within each subject
    n, k = ranks.shape
    q = 12 / (n * k * (k + 1)) * (ranks.sum(axis=0) ** 2).sum() - 3 * n * (k + 1)  # no ties: the formula
    assert (r.n, r.statistic, r.p) == (12, pytest.approx(q), pytest.approx(chi2.sf(q, k - 1)))
    assert np.isnan(friedman(cols[:2]).p)


def test_tost_matches_statsmodels_and_says_equivalent_only_within_the_margin() -> None:
    x = RNG.normal(10.0, 1.0, 12)
    near, far = x + RNG.normal(0.02, 0.1, 12), x + RNG.normal(0.8, 0.1, 12)
    for y in (near, far):
        p, lower, upper = ttost_paired(y, x, -0.3, 0.3)
        got = tost_paired(x, y, 0.3)
        assert (got.p, got.p_lower, got.p_upper) == pytest.approx((p, lower[1], upper[1]))
    assert tost_paired(x, near, 0.3).p < 0.05 < tost_paired(x, far, 0.3).p
