"""Quintic B-spline joint trajectories through waypoints, batched over a population (paper §II-A, §II-D).

Layout (DESIGN §5): W waypoints, two virtual knots, W+2 instants s_0 = 0 < s_1 < … < s_{W+1} = t_f,
W+1 intervals h. Waypoints sit at s_0, s_2, …, s_{W-1}, s_{W+1}; s_1 and s_W carry no condition. Knots:
0 six times, s_1 … s_W, t_f six times (W+12 knots, n = W+6 control points per joint).

Every function takes ``h`` with shape (P, W+1): rows are individuals of a population, so NSGA-II evaluates
a whole generation in one call (pymoo's vectorised ``_evaluate``). One matrix A(h) per row serves all
D joints, so one batched ``np.linalg.solve`` gives every control point of the generation.

Why not one ``scipy.interpolate.make_interp_spline`` per individual: it is the reference (the tests check
this module against it to 1e-9), but a Python loop over 90 individuals × 200 generations costs seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.pareto import PathEnd

P_DEG = 5  # quintic: C^4, so velocity, acceleration and jerk are continuous (paper §II-A)

# 3-node Gauss–Legendre on [0, 1]: exact for polynomials up to degree 5, and jerk² of a quintic is
# degree 4 on each knot span, so f_jerk has no quadrature error (DESIGN §5).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(3)
GL_NODES = (_GL_X + 1.0) / 2.0
GL_WEIGHTS = _GL_W / 2.0

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Boundary:
    """Velocity, acceleration and jerk at the start and end of a path, each shape (D,)."""

    v0: Array
    a0: Array
    j0: Array
    v1: Array
    a1: Array
    j1: Array

    @classmethod
    def at_rest(cls, d: int) -> Boundary:
        z = np.zeros(d)
        return cls(z, z, z, z, z, z)

    @classmethod
    def from_ends(cls, start: PathEnd, end: PathEnd) -> Boundary:
        """From a ``ParetoSet``'s ends: the one converter between the wire and the spline code."""
        a = [np.array(x, dtype=float) for x in (start.velocity, start.acceleration, start.jerk)]
        b = [np.array(x, dtype=float) for x in (end.velocity, end.acceleration, end.jerk)]
        return cls(*a, *b)

    def ends(self) -> tuple[PathEnd, PathEnd]:
        """For a ``ParetoSet``: (start, end)."""
        return (
            PathEnd(velocity=self.v0.tolist(), acceleration=self.a0.tolist(), jerk=self.j0.tolist()),
            PathEnd(velocity=self.v1.tolist(), acceleration=self.a1.tolist(), jerk=self.j1.tolist()),
        )

    def as_rows(self) -> Array:
        """RHS rows in the order of ``design_matrix``'s derivative rows: (6, D)."""
        return np.stack([self.v0, self.a0, self.j0, self.j1, self.a1, self.v1])


def n_intervals(n_waypoints: int) -> int:
    return n_waypoints + 1


def instants(h: Array) -> Array:
    """s_0 … s_{W+1}: (P, W+2)."""
    return np.concatenate([np.zeros((h.shape[0], 1)), np.cumsum(h, axis=1)], axis=1)


def knots(h: Array) -> Array:
    """Clamped knot vector (P, W+12): 0 and t_f with multiplicity p+1 = 6, s_1 … s_W simple."""
    s = instants(h)
    p = h.shape[0]
    return np.concatenate([np.zeros((p, P_DEG)), s, np.repeat(s[:, -1:], P_DEG, axis=1)], axis=1)


def waypoint_sites(h: Array) -> Array:
    """The instants at which the W waypoints are passed: s_0, s_2, …, s_{W-1}, s_{W+1}. (P, W)."""
    s = instants(h)
    w = h.shape[1] - 1
    idx = [0, *range(2, w), w + 1]
    return s[:, idx]


def basis_funs(t: Array, span: NDArray[np.intp], x: Array, p: int) -> Array:
    """Non-zero B-spline basis values at x (The NURBS Book, A2.2), batched.

    t: knots (P, M); span: static knot-span indices (m,) with t[span] <= x <= t[span+1]; x: (P, m).
    Returns (P, m, p+1); entry r belongs to control point span - p + r. Spans are static because every
    evaluation site of this module is a knot or lies in a known interval, so nothing is searched.
    """
    n_pts = x.shape[1]
    out = np.zeros((p + 1, x.shape[0], n_pts))
    out[0] = 1.0
    left = np.empty((p + 1, x.shape[0], n_pts))
    right = np.empty((p + 1, x.shape[0], n_pts))
    for j in range(1, p + 1):
        left[j] = x - t[:, span + 1 - j]
        right[j] = t[:, span + j] - x
        saved = np.zeros_like(x)
        for r in range(j):
            temp = out[r] / (right[r + 1] + left[j - r])
            out[r] = saved + right[r + 1] * temp
            saved = left[j - r] * temp
        out[j] = saved
    return np.moveaxis(out, 0, -1)


def _edge_derivative_rows(t: Array) -> tuple[list[Array], list[Array]]:
    """Rows mapping the control points to q'(0), q''(0), q'''(0) and to q'(t_f), q''(t_f), q'''(t_f).

    A clamped spline's d-th derivative at an end is the first/last control point of its derivative
    spline, c_d[i] = (p-d+1)(c_{d-1}[i+1] - c_{d-1}[i]) / (t[i+p+1] - t[i+d]) (paper eq. 5); it depends
    on the d+1 control points nearest that end, so only four rows are carried per end. Each (P, n).
    """
    n_pop, m_knots = t.shape
    n = m_knots - P_DEG - 1
    eye = np.eye(n)
    start = np.broadcast_to(eye[:4], (n_pop, 4, n))
    end = np.broadcast_to(eye[n - 4 :], (n_pop, 4, n))
    starts, ends = [], []
    for d in (1, 2, 3):
        i0 = np.arange(4 - d)
        i1 = np.arange(n - 4, n - d)
        s0 = (P_DEG - d + 1) / (t[:, i0 + P_DEG + 1] - t[:, i0 + d])
        s1 = (P_DEG - d + 1) / (t[:, i1 + P_DEG + 1] - t[:, i1 + d])
        start = (start[:, 1:, :] - start[:, :-1, :]) * s0[:, :, None]
        end = (end[:, 1:, :] - end[:, :-1, :]) * s1[:, :, None]
        starts.append(start[:, 0, :])
        ends.append(end[:, -1, :])
    return starts, ends


def design_matrix(h: Array) -> Array:
    """A(h) of paper eq. (10), (P, n, n): W position rows and six boundary-derivative rows.

    Row order: q(s_0), q'(0), q''(0), q'''(0), q(s_2) … q(s_{W-1}), q'''(t_f), q''(t_f), q'(t_f), q(t_f).
    The derivative rows come from ``_edge_derivative_rows``.
    """
    t = knots(h)
    n_pop, w1 = h.shape
    w = w1 - 1
    n = w + 6
    a = np.zeros((n_pop, n, n))
    starts, ends = _edge_derivative_rows(t)
    a[:, 0, 0] = 1.0
    for d in range(3):
        a[:, 1 + d, :] = starts[d]
        a[:, n - 2 - d, :] = ends[d]
    a[:, n - 1, n - 1] = 1.0
    if w > 2:
        interior = np.arange(2, w)  # waypoints 2 … W-1 at s_l, knot t[5+l], span 5+l
        spans = interior + P_DEG
        vals = basis_funs(t, spans, t[:, spans], P_DEG)  # (P, W-2, 6)
        rows = 4 + np.arange(w - 2)
        cols = spans[:, None] - P_DEG + np.arange(P_DEG + 1)[None, :]
        a[:, rows[:, None], cols] = vals
    return a


def rhs(waypoints: Array, boundary: Boundary) -> Array:
    """B of paper eq. (10), (n, D), in the row order of ``design_matrix``; it does not depend on h."""
    b = boundary.as_rows()
    return np.concatenate([waypoints[:1], b[:3], waypoints[1:-1], b[3:], waypoints[-1:]])


def control_points(h: Array, waypoints: Array, boundary: Boundary) -> Array:
    """Solve A(h) Θ = B for every individual and every joint at once: (P, n, D)."""
    b = rhs(waypoints, boundary)
    theta = np.linalg.solve(design_matrix(h), np.broadcast_to(b, (h.shape[0], *b.shape)))
    return np.asarray(theta, dtype=np.float64)


def derivative_control_points(h: Array, c: Array) -> list[Array]:
    """[c_1, c_2, c_3]: control points of the velocity, acceleration and jerk splines, (P, n-d, D)."""
    return _derivative_chain(h, c, 3)[1:]


_FACT = np.array([1.0, 1.0, 2.0, 6.0, 24.0, 120.0])
_SHIFT_POW = np.arange(6)[None, :] - np.arange(4)[:, None]  # k - m
_SHIFT_FACT = _FACT[None, :] / _FACT[_SHIFT_POW.clip(0)]  # k!/(k-m)!


def _derivative_chain(h: Array, c: Array, upto: int) -> list[Array]:
    """[c_0, c_1, …, c_upto]: control points of q and its derivative splines (paper eq. 5), (P, n-d, D)."""
    t = knots(h)
    out = [c]
    for k in range(1, upto + 1):
        ck = out[-1]
        i = np.arange(ck.shape[1] - 1)
        scale = (P_DEG - k + 1) / (t[:, i + P_DEG + 1] - t[:, i + k])
        out.append((ck[:, 1:, :] - ck[:, :-1, :]) * scale[:, :, None])
    return out


def span_taylor(h: Array, c: Array) -> Array:
    """Power-basis coefficients of every knot span: (P, W+1, 6, D), q(s_{l-1}+τ) = Σ_k a_k τ^k.

    Why: on a span the quintic is a polynomial, so the maxima of |q'|, |q''|, |q'''| are found exactly
    from its coefficients (exact-limit mode) and jerk² is integrated exactly. a_k = q^(k)(s_{l-1}) / k!.
    The 5th derivative is constant on a span (the degree-0 control point c_5[l-1]); the 4th is linear and
    equals c_4[l-1] at the span start (a degree-1 spline equals its control point at the knot). Orders
    0–3 are carried from t = 0 span by span (q is C^4: each span starts where the last one ended), W+1
    Horner steps instead of a basis evaluation per order.
    """
    chain = _derivative_chain(h, c, P_DEG)
    n_pop, w1 = h.shape
    coeffs = np.empty((n_pop, w1, P_DEG + 1, c.shape[2]))
    coeffs[:, :, 5, :] = chain[5] / _FACT[5]
    coeffs[:, :, 4, :] = chain[4][:, :-1, :] / _FACT[4]
    # Orders 0–3 at t = 0: the first control point of each derivative spline (clamped knots).
    vals = np.stack([chain[k][:, 0, :] for k in range(4)], axis=1)  # (P, 4, D)
    # q^(m)(s_l) = Σ_{k≥m} a_k k!/(k-m)! h_l^(k-m): one (4, 6) matrix per individual and span.
    powers = h[:, :, None, None] ** _SHIFT_POW.clip(0)  # (P, S, 4, 6)
    shift = np.where(_SHIFT_POW >= 0, _SHIFT_FACT, 0.0) * powers
    for span in range(w1):
        coeffs[:, span, :4, :] = vals / _FACT[:4, None]
        if span + 1 < w1:
            vals = shift[:, span] @ coeffs[:, span]
    return coeffs


def poly_derivative(coeffs: Array, order: int) -> Array:
    """Coefficients (…, K+1 - order, D) of the order-th derivative of Σ a_k τ^k given as (…, K+1, D)."""
    k = np.arange(coeffs.shape[-2])
    out = coeffs
    for _ in range(order):
        k = k[1:]
        out = out[..., 1:, :] * k[:, None]
        k = k - 1
    return out


def poly_eval(coeffs: Array, tau: Array) -> Array:
    """Horner: coeffs (…, K+1, D), tau broadcastable to (…, D)."""
    out = np.zeros(np.broadcast_shapes(coeffs[..., 0, :].shape, np.shape(tau)))
    for i in range(coeffs.shape[-2] - 1, -1, -1):
        out = out * tau + coeffs[..., i, :]
    return out


def jerk_cost(h: Array, taylor: Array) -> Array:
    """f_jerk = Σ_j ∫ q_j'''² dt (paper eq. 7), exact with 3-node Gauss–Legendre per span: (P,)."""
    j0, j1, j2 = 6.0 * taylor[:, :, 3, :], 24.0 * taylor[:, :, 4, :], 60.0 * taylor[:, :, 5, :]  # (P, S, D)
    total = np.zeros(j0.shape)
    for node, weight in zip(GL_NODES, GL_WEIGHTS, strict=True):
        tau = (h * node)[:, :, None]
        total += weight * ((j2 * tau + j1) * tau + j0) ** 2
    cost: Array = np.einsum("psd,ps->p", total, h)
    return cost


def time_cost(h: Array, n_joints: int) -> Array:
    """f_time = D Σ h (paper eq. 7): (P,)."""
    cost: Array = n_joints * h.sum(axis=1)
    return cost


def _quadratic_roots(c0: Array, c1: Array, c2: Array, h: Array) -> tuple[Array, Array]:
    """The real roots in (0, h) of c0 + c1 τ + c2 τ², NaN where absent. Flat arrays."""
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = c1 * c1 - 4.0 * c2 * c0
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        # Stable form: q = -(c1 + sign(c1)·√disc)/2, roots q/c2 and c0/q; linear when c2 = 0.
        q = -0.5 * (c1 + np.copysign(sq, c1))
        quad = c2 != 0
        r1 = np.where(quad, q / c2, -c0 / c1)
        r2 = np.where(quad, c0 / q, np.nan)
    r1 = np.where((r1 > 0) & (r1 < h), r1, np.nan)
    r2 = np.where((r2 > 0) & (r2 < h), r2, np.nan)
    return r1, r2


_BISECT_STEPS = 8
_NEWTON_STEPS = 4


def _cubic_root_in_bracket(c0: Array, c1: Array, c2: Array, c3: Array, a: Array, b: Array) -> Array:
    """The root of c0 + c1 τ + c2 τ² + c3 τ³ in [a, b], where it is monotone and changes sign.

    Bisection first (safe), then Newton clipped to the bracket (fast). The root is where |q'| is
    stationary, so an error Δτ in it changes the maximum only by about |jerk|·Δτ²/2. The cubic is
    monotone on the bracket, so the sign at its left end never changes and the left end is all that
    bisection has to move; the loops work in place, as their cost is the number of numpy calls.
    """
    left_positive = (((c3 * a + c2) * a + c1) * a + c0) > 0
    width = b - a
    lo = a.copy()
    mid = np.empty_like(a)
    f = np.empty_like(a)
    for _ in range(_BISECT_STEPS):
        width *= 0.5
        np.add(lo, width, out=mid)
        np.multiply(c3, mid, out=f)
        f += c2
        f *= mid
        f += c1
        f *= mid
        f += c0
        np.copyto(lo, mid, where=(f > 0) == left_positive)
    hi = lo + width
    x = lo + 0.5 * width
    for _ in range(_NEWTON_STEPS):
        f = ((c3 * x + c2) * x + c1) * x + c0
        df = (3.0 * c3 * x + 2.0 * c2) * x + c1
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.clip(np.where(df != 0, x - f / df, x), lo, hi)
    return x


def span_maxima(h: Array, taylor: Array, per_span: bool = False) -> Array:
    """Exact max over t of |q'|, |q''|, |q'''| per joint: (P, 3, D), or (P, 3, S, D) per knot span
    with ``per_span``. No sampling.

    On a span the maximum of |p| is at an end or at a root of p' inside it. Jerk (quadratic): its
    vertex. Acceleration (cubic): the real roots of the jerk, closed form. Velocity (quartic): the roots
    of the cubic acceleration, at most one in each piece where the acceleration is monotone (pieces cut
    at the jerk's roots), found by bisection and Newton on the few pieces that bracket one.
    Works on flat arrays of every (individual, span, joint): numpy is fastest on long contiguous rows.
    """
    shape = taylor[:, :, 0, :].shape  # (P, S, D)
    a1, a2, a3, a4, a5 = (np.ascontiguousarray(taylor[:, :, k, :]).ravel() for k in range(1, 6))
    hh = np.broadcast_to(h[:, :, None], shape).ravel()
    # velocity v = a1 + 2a2 τ + 3a3 τ² + 4a4 τ³ + 5a5 τ⁴; acceleration = v'; jerk = v''.
    v1, v2, v3, v4 = 2 * a2, 3 * a3, 4 * a4, 5 * a5
    c0, c1, c2, c3 = 2 * a2, 6 * a3, 12 * a4, 20 * a5  # acceleration
    j0, j1, j2 = 6 * a3, 24 * a4, 60 * a5  # jerk

    def vel(x: Array) -> Array:
        return (((v4 * x + v3) * x + v2) * x + v1) * x + a1

    def acc(x: Array) -> Array:
        return ((c3 * x + c2) * x + c1) * x + c0

    def jerk(x: Array) -> Array:
        return (j2 * x + j1) * x + j0

    with np.errstate(divide="ignore", invalid="ignore"):
        vtx = -j1 / (2.0 * j2)
    vtx = np.where((vtx > 0) & (vtx < hh), vtx, hh)  # absent → an end, which is counted anyway
    jmax = np.maximum(np.maximum(np.abs(j0), np.abs(jerk(hh))), np.abs(jerk(vtx)))

    r1, r2 = _quadratic_roots(j0, j1, j2, hh)
    acc_h = acc(hh)
    amax = np.maximum(np.abs(c0), np.abs(acc_h))
    amax = np.fmax(amax, np.abs(acc(r1)))
    amax = np.fmax(amax, np.abs(acc(r2)))

    # velocity: pieces [0, p], [p, q], [q, h] with p ≤ q the jerk roots (absent roots → h)
    p = np.fmin(r1, r2)
    q = np.fmax(r1, r2)
    p = np.where(np.isnan(p), hh, p)
    q = np.where(np.isnan(q), hh, q)
    vmax = np.maximum(np.abs(a1), np.abs(vel(hh)))
    # All bracketing pieces of all spans in one root-finding call: the arrays are short, so the cost is
    # the number of numpy calls, not their length.
    lo = np.concatenate([0.0 * hh, p, q])
    hi = np.concatenate([p, q, hh])
    flo = np.concatenate([c0, acc(p), acc(q)])
    fhi = np.concatenate([flo[hh.size :], acc_h])
    idx = np.nonzero(((flo > 0) != (fhi > 0)) & (flo != 0) & (fhi != 0) & (hi > lo))[0]
    if idx.size:
        e = idx % hh.size  # the (individual, span, joint) each piece belongs to
        x = _cubic_root_in_bracket(c0[e], c1[e], c2[e], c3[e], lo[idx], hi[idx])
        v_root = np.abs((((v4[e] * x + v3[e]) * x + v2[e]) * x + v1[e]) * x + a1[e])
        np.maximum.at(vmax, e, v_root)

    out = np.stack([vmax.reshape(shape), amax.reshape(shape), jmax.reshape(shape)], axis=1)  # (P, 3, S, D)
    return out if per_span else out.max(axis=2)


def hull_maxima(h: Array, c: Array) -> Array:
    """max |control point| of the 1st–3rd derivative splines per joint (paper eq. 8): (P, 3, D).

    The convex-hull bound: sufficient, conservative (the curve stays inside its control polygon).
    """
    return np.stack([np.abs(cd).max(axis=1) for cd in derivative_control_points(h, c)], axis=1)


def sample(
    h: Array, waypoints: Array, boundary: Boundary, rate_hz: float
) -> tuple[Array, Array, Array, Array]:
    """One solution as samples at ``rate_hz``: t (m,), q, q̇, q̈ (m, D); the last sample is t_f exactly.

    Why from the span polynomials: the executor needs a few thousand samples once per path start, and
    Horner on the span's quintic is exact and allocation-light; the servo loop then only indexes.
    """
    t_f = float(np.sum(h))
    n = int(np.floor(t_f * rate_hz + 1e-9)) + 1
    t = np.arange(n) / rate_hz
    if t[-1] < t_f - 1e-12:
        t = np.append(t, t_f)
    q, qd, qdd, _ = evaluate_dense(h, waypoints, boundary, t)
    return t, q, qd, qdd


def evaluate_dense(h: Array, waypoints: Array, boundary: Boundary, t: Array) -> Array:
    """q and its first three derivatives at arbitrary times: (4, m, D). For plots and checks."""
    h2 = np.atleast_2d(np.asarray(h, dtype=float))
    c = control_points(h2, waypoints, boundary)
    taylor = span_taylor(h2, c)[0]
    s = instants(h2)[0]
    span = np.clip(np.searchsorted(s, t, side="right") - 1, 0, h2.shape[1] - 1)
    tau = (t - s[span])[:, None]
    coeffs = taylor[span]
    return np.stack([poly_eval(poly_derivative(coeffs, d), tau) for d in range(4)])
