"""The batched quintic B-spline against scipy's make_interp_spline and dense numerics."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from common.trajectory import bspline as bs
from tests.support.paths import random_path
from tests.support.trajectory import scipy_reference


def random_h(rng: np.random.Generator, w: int, n: int) -> np.ndarray:
    return rng.uniform(0.05, 2.0, (n, w + 1))


@pytest.mark.parametrize("w", [2, 3, 4, 6, 9])
@pytest.mark.parametrize("with_boundary", [False, True])
def test_control_points_match_make_interp_spline_to_1e9(w: int, with_boundary: bool) -> None:
    path = random_path(100 + w, w, with_boundary)
    h = random_h(np.random.default_rng(w), w, 12)
    c = bs.control_points(h, path.waypoints, path.boundary)
    for i in range(len(h)):
        ref = scipy_reference(h[i], path)
        assert np.max(np.abs(ref.c - c[i])) < 1e-9


def test_the_curve_passes_every_waypoint_at_its_knot_and_meets_the_boundary_conditions() -> None:
    path = random_path(7, 7, boundary=True)
    h = random_h(np.random.default_rng(1), 7, 5)
    b = path.boundary
    for row in h:
        q = bs.evaluate_dense(row, path.waypoints, path.boundary, bs.waypoint_sites(row[None])[0])[0]
        assert np.max(np.abs(q - path.waypoints)) < 1e-9
        ends = bs.evaluate_dense(row, path.waypoints, path.boundary, np.array([0.0, row.sum()]))
        for d, (start, end) in enumerate([(b.v0, b.v1), (b.a0, b.a1), (b.j0, b.j1)], start=1):
            np.testing.assert_allclose(ends[d, 0], start, atol=1e-8)
            np.testing.assert_allclose(ends[d, 1], end, atol=1e-8)


def test_span_polynomials_agree_with_scipy_derivatives_everywhere() -> None:
    path = random_path(3, 6, boundary=True)
    h = random_h(np.random.default_rng(3), 6, 3)
    for row in h:
        ref = scipy_reference(row, path)
        t = np.linspace(0.0, row.sum(), 777)
        vals = bs.evaluate_dense(row, path.waypoints, path.boundary, t)
        for d in range(4):
            scale = max(1.0, np.max(np.abs(ref(t, d))))
            assert np.max(np.abs(vals[d] - ref(t, d))) / scale < 1e-9


def test_f_jerk_equals_a_dense_numerical_integral_to_1e6_relative() -> None:
    path = random_path(11, 6)
    h = random_h(np.random.default_rng(11), 6, 6)
    c = bs.control_points(h, path.waypoints, path.boundary)
    exact = bs.jerk_cost(h, bs.span_taylor(h, c))
    for i, row in enumerate(h):
        ref = scipy_reference(row, path)
        # Simpson on each knot span separately (the jerk is smooth inside a span, kinked at knots).
        s = bs.instants(row[None])[0]
        total = 0.0
        for a, b in itertools.pairwise(s):
            t = np.linspace(a, b, 2001)
            y = np.sum(ref(t, 3) ** 2, axis=1)
            total += (b - a) / 6000 * (y[0] + y[-1] + 4 * y[1:-1:2].sum() + 2 * y[2:-1:2].sum())
        assert abs(exact[i] - total) / total < 1e-6


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_exact_maxima_bound_a_2khz_sampling_and_are_attained(seed: int) -> None:
    path = random_path(seed, 6, boundary=seed % 2 == 1)
    h = random_h(np.random.default_rng(seed), 6, 8)
    c = bs.control_points(h, path.waypoints, path.boundary)
    maxima = bs.span_maxima(h, bs.span_taylor(h, c))
    hull = bs.hull_maxima(h, c)
    for i, row in enumerate(h):
        t = np.linspace(0.0, row.sum(), int(row.sum() * 20000) + 2)  # 20 kHz, ten times the bar
        dense = np.stack(
            [np.abs(v).max(axis=0) for v in bs.evaluate_dense(row, path.waypoints, path.boundary, t)[1:]]
        )
        assert np.all(dense <= maxima[i] * (1 + 1e-9) + 1e-12), "a sample exceeds the exact maximum"
        assert np.all(maxima[i] <= dense * (1 + 1e-5) + 1e-9), "the exact maximum is not attained"
        assert np.all(hull[i] >= maxima[i] * (1 - 1e-9)), "the control-point hull must bound the curve"


def test_samples_at_500_hz_step_2_ms_and_end_exactly_at_t_f() -> None:
    path = random_path(5, 5)
    h = np.array([0.3, 0.3, 0.7, 0.9, 0.4, 0.2123])
    t, q, qd, qdd = bs.sample(h, path.waypoints, path.boundary, 500.0)
    assert t[-1] == pytest.approx(h.sum(), abs=1e-12)
    assert np.allclose(np.diff(t)[:-1], 0.002)
    assert np.diff(t)[-1] <= 0.002 + 1e-12
    np.testing.assert_allclose(q[0], path.waypoints[0], atol=1e-12)
    np.testing.assert_allclose(q[-1], path.waypoints[-1], atol=1e-9)
    assert q.shape == qd.shape == qdd.shape == (len(t), 6)
    np.testing.assert_allclose(qd[[0, -1]], 0.0, atol=1e-9)
