"""Reacting within a path: time scaling along the trajectory, and a switch to another solution mid-path.

**Time scaling.** The executor runs the path's curve q(s) at path time s(t) with ṡ = σ(t), σ ∈ [0, 1].
The commanded motion's derivatives follow by the chain rule:

    q̇ = q'σ,   q̈ = q''σ² + q'σ̇,   q⃛ = q'''σ³ + 3q''σσ̇ + q'σ̈.

With σ constant these are the planned ones times σ, σ², σ³: inside the limits whenever the plan is. While
σ changes, the terms in σ̇ and σ̈ add to them, so every change of σ is a ``Ramp`` (a quintic in time, from
the σ, σ̇, σ̈ in force to a new σ at rest) whose commanded samples are checked against the limits before it
is handed to the servo loop (``plan_ramp``); σ̈ is continuous, so the commanded jerk is. A plan that is at a
limit somewhere leaves no room there, so a ramp is tried at a few start times and durations, the first
that keeps every sample inside wins.

**A switch of solution (k) mid-path.** The rest of the path is planned again from the switch instant: a
quintic B-spline from the point reached to the remaining waypoints, its start velocity, acceleration and
jerk those of the current curve there (so the joined curve is continuous to the jerk), its intervals the new
solution's for the same segments, stretched as little as the limits need (``switch_curve``). The switch
is in path time, so it composes with the scaling: the commanded motion stays continuous through both.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from common.robot.ur16e import JointLimits
from common.trajectory import bspline as bs
from common.trajectory.task import PathPlan
from common.trajectory.validate import trajectory_problems

Array = NDArray[np.float64]
_X = TypeVar("_X", float, Array)
DT = 0.002  # one controller step: the playback's time step
LIMIT_RTOL = 1e-6  # slack on a commanded sample's limit (round-off of the chain rule)


@dataclass(frozen=True, slots=True)
class Curve:
    """A piecewise quintic q(s) on [0, t_f]: span start instants (S,) and power-basis coefficients (S, 6, D).
    Joining two curves is concatenating their spans (``joined``)."""

    starts: Array
    taylor: Array
    t_f: float
    sites: Array  # the path times at which the path's waypoints are passed, (W,)
    speed: Array  # max |q'| per joint, (D,)

    @classmethod
    def of(cls, h: Array, path: PathPlan) -> Curve:
        h2 = np.atleast_2d(np.asarray(h, dtype=float))
        c = bs.control_points(h2, path.waypoints, path.boundary)
        taylor = bs.span_taylor(h2, c)
        speed = bs.span_maxima(h2, taylor)[0, 0]
        return cls(bs.instants(h2)[0][:-1], taylor[0], float(h2.sum()), bs.waypoint_sites(h2)[0], speed)

    def span(self, s: Array) -> NDArray[np.intp]:
        i: NDArray[np.intp] = np.clip(
            np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.starts) - 1
        )
        return i

    def at(self, s: Array, order: int = 3) -> Array:
        """q, q', …, q^(order) at path times s (clipped to [0, t_f]): (order+1, m, D)."""
        s = np.clip(np.asarray(s, dtype=float), 0.0, self.t_f)
        i = self.span(s)
        tau = (s - self.starts[i])[:, None]
        coeffs = self.taylor[i]
        return np.stack([bs.poly_eval(bs.poly_derivative(coeffs, d), tau) for d in range(order + 1)])

    def joined(self, s_switch: float, rest: Curve) -> Curve:
        """This curve up to ``s_switch``, then ``rest`` (whose s = 0 is ``s_switch``, and whose first
        waypoint is the point there, not one of the path's)."""
        keep = self.starts < s_switch
        return Curve(
            np.concatenate([self.starts[keep], rest.starts + s_switch]),
            np.concatenate([self.taylor[keep], rest.taylor]),
            s_switch + rest.t_f,
            np.concatenate([self.sites[self.sites < s_switch], rest.sites[1:] + s_switch]),
            np.maximum(self.speed, rest.speed),
        )


Coefficients = tuple[float, float, float, float, float, float]


def _sigma(c: Coefficients, x: _X) -> _X:
    """σ at ramp time x (a float for the servo loop, an array for the checks: the same arithmetic)."""
    return ((((c[5] * x + c[4]) * x + c[3]) * x + c[2]) * x + c[1]) * x + c[0]


def _integral(c: Coefficients, x: _X) -> _X:
    """∫₀ˣ σ: the path time gained during the ramp."""
    return x * (c[0] + x * (c[1] / 2 + x * (c[2] / 3 + x * (c[3] / 4 + x * (c[4] / 5 + x * c[5] / 6)))))


@dataclass(frozen=True, slots=True)
class Ramp:
    """σ(τ) = Σ c_k τ^k on [0, duration] from t0 (the playback's time), then σ(end) for ever; s(t0) = s0.

    A quintic from (σ0, σ̇0, σ̈0) to (σ1, 0, 0): the σ-state in force when it starts, so σ, σ̇ and σ̈ are
    continuous at every change. Its jerk (the scale's) is bounded: a quadratic on a finite interval."""

    t0: float
    duration: float
    s0: float
    c: Coefficients
    target: float  # σ at the end and after: exactly, not the quintic's round-off of it

    @classmethod
    def hold(cls, t0: float, s0: float, sigma: float) -> Ramp:
        return cls(t0, 0.0, s0, (sigma, 0.0, 0.0, 0.0, 0.0, 0.0), sigma)

    @classmethod
    def between(
        cls, t0: float, s0: float, start: tuple[float, float, float], sigma1: float, duration: float
    ) -> Ramp:
        sig0, sd0, sdd0 = start
        t = duration
        c0, c1, c2 = sig0, sd0, sdd0 / 2.0
        d = sigma1 - (c0 + c1 * t + c2 * t * t)
        e = -(c1 + 2.0 * c2 * t)
        f = -2.0 * c2
        m = np.array([[t**3, t**4, t**5], [3 * t**2, 4 * t**3, 5 * t**4], [6 * t, 12 * t**2, 20 * t**3]])
        c3, c4, c5 = np.linalg.solve(m, [d, e, f])
        return cls(t0, duration, s0, (c0, c1, c2, float(c3), float(c4), float(c5)), sigma1)

    @property
    def end(self) -> float:
        return self.t0 + self.duration

    def at(self, t: float) -> tuple[float, float]:
        """s and σ at one playback time, in plain floats: what the servo loop asks every step."""
        tau = t - self.t0
        inside = min(max(tau, 0.0), self.duration)
        sig = self.target if tau >= self.duration else _sigma(self.c, inside)
        return self.s0 + _integral(self.c, inside) + sig * (tau - inside), sig

    def state(self, t: Array) -> tuple[Array, Array, Array, Array]:
        """s, σ, σ̇, σ̈ at playback times t ≥ t0."""
        tau = np.clip(np.asarray(t, dtype=float) - self.t0, 0.0, None)
        inside = np.minimum(tau, self.duration)
        c = self.c
        sd = (((5 * c[5] * inside + 4 * c[4]) * inside + 3 * c[3]) * inside + 2 * c[2]) * inside + c[1]
        sdd = ((20 * c[5] * inside + 12 * c[4]) * inside + 6 * c[3]) * inside + 2 * c[2]
        after = tau >= self.duration
        s = self.s0 + _integral(c, inside) + self.target * (tau - inside)
        return (
            s,
            np.where(after, self.target, _sigma(c, inside)),
            np.where(after, 0.0, sd),
            np.where(after, 0.0, sdd),
        )

    def rebased(self, t: float) -> Ramp:
        """The same σ-state at playback time ``t``, as a ramp of a new playback that starts there with
        s = 0: the scale carries from one path to the next."""
        _, sig, sd, sdd = (float(x[0]) for x in self.state(np.array([t])))
        if t >= self.end:
            return Ramp.hold(0.0, 0.0, sig)
        return Ramp.between(0.0, 0.0, (sig, sd, sdd), self.target, self.end - t)


def commanded(curve: Curve, s: Array, sig: Array, sd: Array, sdd: Array) -> Array:
    """q, q̇, q̈, q⃛ of the commanded motion (chain rule): (4, m, D)."""
    q, d1, d2, d3 = curve.at(s)
    sg, sdv, sddv = sig[:, None], sd[:, None], sdd[:, None]
    return np.stack([q, d1 * sg, d2 * sg**2 + d1 * sdv, d3 * sg**3 + 3 * d2 * sg * sdv + d1 * sddv])


def ramp_ratio(curve: Curve, ramp: Ramp, limits: JointLimits) -> float:
    """The largest ratio of a commanded velocity, acceleration or jerk to its limit during the ramp,
    sampled at every controller step (and its end); σ outside [0, 1] counts as over (2.0)."""
    n = max(2, int(np.ceil(ramp.duration / DT)) + 1)
    t = ramp.t0 + np.arange(n, dtype=np.float64) * DT
    s, sig, sd, sdd = ramp.state(t)
    if np.any(sig < -1e-9) or np.any(sig > 1.0 + 1e-9):
        return 2.0
    moving = s < curve.t_f  # past the end the arm holds the last point
    if not np.any(moving):
        return 0.0
    _, v, a, j = commanded(curve, s[moving], sig[moving], sd[moving], sdd[moving])
    lim = limits.kinematic()
    return float(max((np.abs(x) / lim[i]).max() for i, x in enumerate((v, a, j))))


# Start delays and stretches of the shortest duration tried for a ramp, earliest finish first.
DELAYS_S = (0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5)
STRETCH = (1.0, 1.5, 2.0, 3.0, 4.0)
# The quintic smoothstep's largest slope and curvature: σ̇ ≤ 1.875 Δσ/T, σ̈ ≤ (10/√3) Δσ/T².
_P1, _P2 = 1.875, 10.0 / np.sqrt(3.0)


def ramp_duration(curve: Curve, limits: JointLimits, delta: float) -> float:
    """The shortest ramp worth trying for a change of σ by ``delta``: the one whose own terms q'σ̇ and
    q'σ̈ alone reach the acceleration and jerk limits at the path's top joint speeds (the planned terms
    come on top, so the search stretches it from there). At least 4 controller steps."""
    d = abs(delta)
    return float(max(4 * DT, _P1 * d * np.max(curve.speed / limits.acceleration),
                     np.sqrt(_P2 * d * np.max(curve.speed / limits.jerk))))  # fmt: skip


def plan_ramp(
    curve: Curve, current: Ramp, t_min: float, sigma1: float, limits: JointLimits, also: Sequence[Curve] = ()
) -> Ramp | None:
    """The earliest-finishing ramp to ``sigma1`` starting at or after ``t_min`` (a controller step) whose
    commanded samples stay inside the limits, on ``curve`` and on each of ``also`` (a switched curve the
    loop may take during the ramp); None when none of the candidates does."""
    curves = [curve, *also]
    candidates = []
    for delay in DELAYS_S:
        t0 = float(np.ceil((t_min + delay) / DT - 1e-9) * DT)
        s0, sig, sd, sdd = (float(x[0]) for x in current.state(np.array([t0])))
        base = max(ramp_duration(c, limits, sigma1 - sig) for c in curves)
        for stretch in STRETCH:
            candidates.append((t0 + base * stretch, t0, s0, (sig, sd, sdd), base * stretch))
    for _, t0, s0, start, duration in sorted(candidates, key=lambda c: c[0]):
        ramp = Ramp.between(t0, s0, start, sigma1, duration)
        if all(ramp_ratio(c, ramp, limits) <= 1.0 + LIMIT_RTOL for c in curves):
            return ramp
    return None


def resume_at(curve: Curve, q: Array, s_last: float, ahead_s: float = 0.5) -> float:
    """The path time a path cut short by a stop goes on from: the point of the curve nearest the arm at
    ``q`` (by the largest joint's difference), from the last sample sent (``s_last``) up to ``ahead_s``
    further on. A controller's braking stop carries the arm on past that sample, along the path's
    direction at first; going on from the sample itself would move it back first."""
    s = np.arange(s_last, min(s_last + ahead_s, curve.t_f), DT)
    if s.size == 0:
        return s_last
    off = np.max(np.abs(curve.at(s, order=0)[0] - np.asarray(q, dtype=float)), axis=1)
    return float(s[np.argmin(off)])


def resume_ramp(curve: Curve, s0: float, sigma1: float, limits: JointLimits) -> Ramp | None:
    """The scale of a path going on from rest at path time ``s0``: from σ = 0 up to ``sigma1``, inside the
    limits (a path's own start is at rest by its boundary conditions; a point within it is not, so the
    scale must rise from 0). None when no ramp fits; held at 0 when 0 is what is allowed."""
    held = Ramp.hold(0.0, s0, 0.0)
    return held if sigma1 <= 0.0 else plan_ramp(curve, held, 0.0, sigma1, limits)


def _derivatives(curve: Curve, s: Array) -> tuple[Array, Array, Array]:
    """q', q'', q''' at path times s (n,), span by span: a span's coefficients broadcast over its points
    instead of gathered per point (``Curve.at``): four times faster, where the stop-time scan needs
    millions."""
    d = np.empty((3, len(s), curve.taylor.shape[2]))
    i = curve.span(s)
    for j in np.unique(i):
        at = np.nonzero(i == j)[0]
        tau = (s[at] - curve.starts[j])[:, None]
        a = curve.taylor[j]
        d[0, at] = (((5 * a[5] * tau + 4 * a[4]) * tau + 3 * a[3]) * tau + 2 * a[2]) * tau + a[1]
        d[1, at] = ((20 * a[5] * tau + 12 * a[4]) * tau + 6 * a[3]) * tau + 2 * a[2]
        d[2, at] = (60 * a[5] * tau + 24 * a[4]) * tau + 6 * a[3]
    return d[0], d[1], d[2]


@dataclass(frozen=True, slots=True)
class Stop:
    """The worst stop from σ = 1 on a curve: how long it takes (T_s), and how much path time the arm
    covers meanwhile (at σ = 1 path time is time: the stopping distance over the top speed). A ramp alone
    covers half its duration (the smoothstep's integral); a start delayed by a look or a candidate's
    delay covers all of the delay: more than ISO/TS 15066's v_r T_s / 2 assumes, so it is kept apart."""

    time_s: float
    travel_s: float


def _ramp_fits(
    curve: Curve, lim: Array, s0: Array, s_r: Array, state: tuple[Array, Array, Array]
) -> NDArray[np.bool_]:
    """For each start s0 (path time), whether the ramp whose path times past its start are ``s_r`` and
    whose σ, σ̇, σ̈ are ``state`` keeps every commanded sample inside the limits ``lim``."""
    g, gd, gdd = (x[None, :, None] for x in state)
    out = np.zeros(len(s0), dtype=bool)
    per = max(1, 400_000 // max(1, len(s_r)))  # starts per block: some tens of MB
    for a in range(0, len(s0), per):
        s = s0[a : a + per, None] + s_r[None, :]
        moving = s < curve.t_f  # past the end the arm holds the last point
        d1, d2, d3 = (x.reshape(*s.shape, -1) for x in _derivatives(curve, np.minimum(s, curve.t_f).ravel()))
        ratio = np.maximum.reduce(
            [
                np.abs(d1 * g) / lim[0],
                np.abs(d2 * g**2 + d1 * gd) / lim[1],
                np.abs(d3 * g**3 + 3 * d2 * g * gd + d1 * gdd) / lim[2],
            ]
        ).max(axis=2)
        out[a : a + per] = np.where(moving, ratio, 0.0).max(axis=1) <= 1.0 + LIMIT_RTOL
    return out


def _span_range_maxima(curve: Curve) -> Array:
    """max |q'|, |q''|, |q'''| per joint over the spans i to j, for every i and j ≥ i: (S, S, 3, D), from
    the spans' own exact maxima (``bspline.span_maxima``)."""
    h = np.diff(np.append(curve.starts, curve.t_f))[None]
    per = bs.span_maxima(h, curve.taylor[None], per_span=True)[0]  # (3, S, D)
    n = per.shape[1]
    table = np.zeros((n, n, 3, per.shape[2]))
    for i in range(n):
        table[i, i:] = np.maximum.accumulate(np.moveaxis(per[:, i:], 1, 0), axis=0)
    return table


def _bound_fits(
    curve: Curve, lim: Array, table: Array, s0: Array, reach: float, state: tuple[Array, Array, Array]
) -> NDArray[np.bool_]:
    """A sufficient test of ``_ramp_fits`` at a fraction of its cost: with the largest |q'|, |q''|, |q'''|
    over the spans the ramp can reach (path times s0 to s0 + ``reach``), every sample's terms at their
    worst still fit. True: it fits; False: look closer."""
    g, gd, gdd = (np.abs(x) for x in state)
    m = table[curve.span(s0), curve.span(s0 + reach)]  # (n, 3, D)
    v1, v2, v3 = (m[:, i, :, None] for i in range(3))  # (n, D, 1), against the samples' (m,)
    acc = (v2 * g**2 + v1 * gd).max(axis=2) / lim[1][None]
    jerk = (v3 * g**3 + 3 * v2 * g * gd + v1 * gdd).max(axis=2) / lim[2][None]
    worst = np.maximum(np.maximum(acc, jerk), m[:, 0] / lim[0][None]).max(axis=1)
    fits: NDArray[np.bool_] = worst <= 1.0 + LIMIT_RTOL
    return fits


def stop_time(curve: Curve, limits: JointLimits, s_from: float = 0.0, look_s: float = 0.02) -> Stop:
    """T_s of the separation distance, and the travel with it: the longest a stop from σ = 1 takes on this
    curve when it is asked for at any controller step from path time ``s_from`` on, planned as the
    executor plans it (``plan_ramp`` from the σ-state (1, 0, 0) to 0: the earliest-finishing candidate
    inside the limits).

    Every start is a multiple of DT (a ramp starts at a controller step), so checking each is the exact
    worst case, not a sample of it (plus one step: a request between two steps waits for the next). At
    σ = 1 playback time is path time, and one candidate's ramp is the same σ(τ) from every start, so a
    candidate is checked for all the starts still without a stop at once, a (starts × ramp samples)
    array, the earliest-finishing candidate first. Where none fits, the next
    look (``look_s`` later) asks again: that start's stop is a look longer than the worst stop within it
    (the looks' phase is not known).
    """
    n = int(np.floor(max(0.0, curve.t_f - s_from) / DT)) + 1
    starts = np.ceil(s_from / DT - 1e-9) * DT + np.arange(n) * DT
    base = ramp_duration(curve, limits, 1.0)
    candidates = sorted(
        (np.ceil(d / DT - 1e-9) * DT + base * k, np.ceil(d / DT - 1e-9) * DT, base * k)
        for d in DELAYS_S
        for k in STRETCH
    )
    lim = limits.kinematic()
    table = _span_range_maxima(curve)
    took = np.full(n, np.inf)  # each start's stop: from the request to σ = 0
    travel = np.full(n, np.inf)  # and the path time covered meanwhile
    left = np.arange(n)
    for finish, delay, duration in candidates:
        if not len(left):
            break
        m = max(2, int(np.ceil(duration / DT)) + 1)
        tau = np.arange(m, dtype=np.float64) * DT
        s_r, sig, sd, sdd = Ramp.between(0.0, 0.0, (1.0, 0.0, 0.0), 0.0, duration).state(tau)
        state = (sig, sd, sdd)
        sure = _bound_fits(curve, lim, table, starts[left] + delay, float(s_r[-1]), state)
        fits = ~sure
        # the others sample by sample, every 8th first: most fail an early candidate, and fail on those
        for samples in (np.arange(0, m, 8), np.arange(m)):
            rows = np.nonzero(fits)[0]
            fits[rows] = _ramp_fits(curve, lim, starts[left[rows]] + delay, s_r[samples],
                                    (sig[samples], sd[samples], sdd[samples]))  # fmt: skip
        fits |= sure
        took[left[fits]] = finish
        travel[left[fits]] = delay + duration / 2
        left = left[~fits]
    look = max(1, round(look_s / DT))
    for i in left[::-1]:  # no candidate fits: the next look asks again
        later = slice(i + 1, i + 1 + look)
        took[i] = look * DT + (float(took[later].max()) if i + 1 < n else 0.0)
        travel[i] = look * DT + (float(travel[later].max()) if i + 1 < n else 0.0)
    # a request between two steps waits for the next: one step more than the worst from a step
    return Stop(float(took.max()) + DT, float(travel.max()) + DT)


def next_waypoint(curve: Curve, s_switch: float) -> int:
    """The index of the first waypoint after ``s_switch`` (never the first waypoint)."""
    m = int(np.searchsorted(curve.sites, s_switch, side="right"))
    return min(max(m, 1), len(curve.sites) - 1)


def _layout(segments: Array) -> Array:
    """Segment durations → the B-spline's intervals (the virtual knots split the end segments: halves,
    or thirds of a single segment), as planner.interval_bounds lays them out."""
    if len(segments) == 1:
        return np.repeat(segments / 3.0, 3)
    return np.concatenate([[segments[0] / 2] * 2, segments[1:-1], [segments[-1] / 2] * 2])


def segment_durations(h: Array) -> Array:
    """The time between consecutive waypoints of a solution h (W+1 intervals → W-1 segments)."""
    sites = bs.waypoint_sites(np.atleast_2d(h))[0]
    durations: Array = np.diff(sites)
    return durations


@dataclass(frozen=True, slots=True)
class Switch:
    """The rest of a path from ``s_switch`` on, as its own path and intervals (checked), and the joined
    curve."""

    s_switch: float
    rest: PathPlan
    h: Array
    stretch: float
    curve: Curve


# Stretches of the new solution's rest tried, nearest to 1 first: from a fast solution to a slow one the
# arm arrives with more speed than the slow rest has room for, and a shorter rest is the smooth way out.
STRETCHES = np.geomspace(0.25, 4.0, 49)
_NEAREST_FIRST = np.argsort(np.abs(np.log(STRETCHES)), kind="stable")
BETAS = (1.25, 1.5, 2.0, 3.0)  # the way to the next waypoint made longer, when the pace there is too fast


def switch_curve(
    curve: Curve, path: PathPlan, h_new: Array, s_switch: float, limits: JointLimits
) -> Switch | None:
    """The joined curve that leaves the current one at ``s_switch`` for the new solution ``h_new``.

    The rest starts at the current point with its velocity, acceleration and jerk (path time), passes the
    remaining waypoints of the executor's own copy and ends as the path does. Its segments last as long as
    the new solution's (the first: the share of it still ahead), stretched by the least α ≥ 1 that keeps
    the exact maxima inside the limits; the whole rest is then checked as any trajectory is. None when no
    stretch up to 4 does, or the switch is too close to the end to matter.
    """
    if not 0.0 < s_switch < curve.t_f - 4 * DT:
        return None
    q, d1, d2, d3 = (x[0] for x in curve.at(np.array([s_switch])))
    m = next_waypoint(curve, s_switch)
    waypoints = np.concatenate([q[None], path.waypoints[m:]])
    b = path.boundary
    rest = PathPlan(id=path.id, waypoints=waypoints, boundary=bs.Boundary(d1, d2, d3, b.v1, b.a1, b.j1))
    seg = segment_durations(h_new)[m - 1 :].copy()
    seg[0] = curve.sites[m] - s_switch  # to the next waypoint at the pace the arm is at
    lay = _layout(seg)
    first = 3 if len(seg) == 1 else 2  # intervals of the first segment
    # rows: the rest stretched by α (nearest 1 first), then with the first segment also stretched by β
    alphas = STRETCHES[_NEAREST_FIRST]
    betas = np.array([1.0, *BETAS])
    hs = np.repeat(alphas, len(betas))[:, None] * lay[None, :]
    hs[:, :first] *= np.tile(betas, len(alphas))[:, None] / np.repeat(alphas, len(betas))[:, None]
    cps = bs.control_points(hs, rest.waypoints, rest.boundary)
    maxima = bs.span_maxima(hs, bs.span_taylor(hs, cps))
    ok = np.all(maxima <= limits.kinematic()[None] * (1 + 1e-9), axis=(1, 2))
    for i in np.nonzero(ok)[0]:
        h = hs[i]
        if not trajectory_problems(h, rest, limits):
            alpha = float(alphas[i // len(betas)])
            return Switch(s_switch, rest, h, alpha, curve.joined(s_switch, Curve.of(h, rest)))
    return None
