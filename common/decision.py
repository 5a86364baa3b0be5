"""The paper's Alg. 1 as a pure step function (paper §II-C, §III-B; DESIGN §7).

Exactness: thresholds and steps are decimal numbers (Δ_rs = 0.02 s, Δ_sr = 0.01 s), and a mean RR of
0.80 s that drops by 0.04 s must move k by exactly one step. In binary floating point 0.76 - 0.80 is
-0.04000000000000004 and floor((ΔRR + 0.02) / 0.02) would give -2. So every value is taken as the
decimal it was written as (the shortest repr of the float that carries it) and the arithmetic is done in
``decimal.Decimal``, where these subtractions and divisions are exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import ROUND_CEILING, ROUND_FLOOR, ROUND_HALF_UP, Decimal

from schemas.decision import Reason


def dec(x: float | str | Decimal) -> Decimal:
    """The decimal value a number was written as: 0.1 → Decimal('0.1'), not 0.1000000000000000055…"""
    if isinstance(x, Decimal):
        return x
    if isinstance(x, float):
        if not math.isfinite(x):
            raise ValueError(f"not a finite number: {x}")
        return Decimal(repr(float(x)))  # a numpy float prints its type too
    return Decimal(x)


@dataclass(frozen=True, slots=True)
class Params:
    """Per subject (DESIGN §7): RR_r from calibration; the rest default as in the paper."""

    rr_rest: Decimal
    n: int = 15
    sigma_rest: Decimal = Decimal("0.14")
    rr_stress_offset: Decimal = Decimal("0.08")
    sigma_stress: Decimal = Decimal("0.08")
    d_rs: Decimal = Decimal("0.02")  # rest → stress threshold and step
    d_sr: Decimal = Decimal("0.01")  # stress → rest step

    @classmethod
    def of(
        cls,
        rr_rest: float | str,
        n: int = 15,
        sigma_rest: float | str = "0.14",
        rr_stress_offset: float | str = "0.08",
        sigma_stress: float | str = "0.08",
    ) -> Params:
        if n < 1:
            raise ValueError(f"n must be at least 1, got {n}")
        p = cls(dec(rr_rest), n, dec(sigma_rest), dec(rr_stress_offset), dec(sigma_stress))
        if p.rr_rest <= 0 or p.sigma_rest <= 0 or p.sigma_stress <= 0 or p.rr_stress_offset <= 0:
            raise ValueError("RR_r, σ_r, σ_s and the RR_s offset must be positive")
        return p

    @property
    def rr_stress(self) -> Decimal:
        return self.rr_rest - self.rr_stress_offset

    @property
    def rr_stress_max(self) -> Decimal:
        """RR_s^max = RR_s − σ_s: below it, stress accumulates (branch 3)."""
        return self.rr_stress - self.sigma_stress

    @property
    def k0(self) -> int:
        """N − round(σ_r / Δ_rs): 15 − 7 = 8 with the defaults, as in the paper (half rounds up)."""
        steps = (self.sigma_rest / self.d_rs).to_integral_value(rounding=ROUND_HALF_UP)
        return clamp(self.n - int(steps), 1, self.n)


@dataclass(frozen=True, slots=True)
class State:
    k: int
    rr_prev: Decimal  # RR_{i-1}

    @classmethod
    def initial(cls, p: Params) -> State:
        return cls(p.k0, p.rr_rest)


@dataclass(frozen=True, slots=True)
class Step:
    state: State
    delta: int
    reason: Reason


def clamp(k: int, lo: int, hi: int) -> int:
    return max(lo, min(hi, k))


def step(p: Params, s: State, rr: float | str | Decimal | None, good_quality: bool = True) -> Step:
    """One window of Alg. 1. A low-quality window (or none: no clean beat) holds k and leaves RR_{i-1}."""
    if rr is None or not good_quality:
        return Step(s, 0, "low-quality")
    rr_i = dec(rr)
    d_rr = rr_i - s.rr_prev
    if d_rr < -p.d_rs and rr_i < p.rr_rest:
        # eq. (6): floor, exact on decimal values; ΔRR_r measured from the lower of RR_r and RR_{i-1}
        d_rr_r = rr_i - min(p.rr_rest, s.rr_prev)
        delta = int(((d_rr_r + p.d_rs) / p.d_rs).to_integral_value(rounding=ROUND_FLOOR))
        reason: Reason = "stress"
    elif d_rr > 0 and rr_i >= p.rr_stress:
        # eq. (7): ceil, exact on decimal values; ΔRR_s measured from the higher of RR_s and RR_{i-1}
        d_rr_s = rr_i - max(p.rr_stress, s.rr_prev)
        delta = int((d_rr_s / p.d_sr).to_integral_value(rounding=ROUND_CEILING))
        reason = "rest"
    elif rr_i < p.rr_stress_max:
        delta, reason = -1, "cumulative"
    else:
        delta, reason = 0, "hold"
    return Step(State(clamp(s.k + delta, 1, p.n), rr_i), delta, reason)


# The paper's conditions that hold k (§III-B): (a) minimum time is the fastest solution, k = N; (b)
# minimum jerk the smoothest, k = 1. Condition (c) is Alg. 1 itself.
FIXED_PRESETS = ("a", "b")


def fixed_k(preset: int | str, n: int) -> int:
    """The k a fixed condition holds: a preset's (``"a"``, ``"b"``) or a number within 1 … n."""
    if preset == "a":
        return n
    if preset == "b":
        return 1
    if isinstance(preset, str):
        raise ValueError(f"unknown preset {preset!r}; expected one of {', '.join(FIXED_PRESETS)} or a k")
    if not 1 <= preset <= n:
        raise ValueError(f"k = {preset} is outside 1 … n = {n}")
    return preset


def k_for_path(k: int, n_path: int) -> int:
    """The selection for a path whose set has n_path solutions (sets may differ in size)."""
    return clamp(k, 1, n_path)


# --- the personal mode (DESIGN §7): beyond the paper, beside it -----------------------------------------


@dataclass(frozen=True, slots=True)
class Personal:
    """The personal mode's settings (DESIGN §7; docs/decision.md). k is a position: how
    far this person's recent mean RR lies from their own reference, in steps of ``step_s``, counted from
    the paper's k0 at the reference.

    Why not Alg. 1's thresholds: they are the spread between people (σ ≈ 0.1 s), wide against one person's
    stress drop (about 50 ms), and after a stressed baseline a relaxed heart sits above RR_r where Alg. 1
    saturates at N.

    Chosen by leave-one-subject-out cross-validation on the order-balanced score (``cadence bench decide
    --cv``), among the settings that keep a steady person steady (``steady``): ``step_s``; ``keep``, how much
    the past weighs in the recent mean RR, a window (each window weighed by its beats: a wrist or a strap
    that read few counts for few); ``hysteresis``, how far past the middle between two k, in steps, the
    recent mean must go before k moves, and then k moves only that far behind it (a play: noise that
    pushed k over does not push it back at once).

    Set from the behaviour they must give (DESIGN §7 states it;
    tests/services/decision_maker/test_personal.py plays it), not from the data, whose sessions last an hour:
    ``ref_tau_s``, how slowly the reference follows the person's recent mean, either way (two hours: a day's
    slow drift is followed, a stress of minutes is not); ``freeze_s``, how far below the reference the recent
    mean must be for the person to read as stressed, when the reference does not follow at all (a drift
    slower than ``freeze_s / ref_tau_s``, 22 ms an hour, is followed; a faster fall is load, held for as long
    as it lasts); ``effort_tau_s``, how long after a movement hold that timed out the remaining drop is taken
    for the effort's recovery rather than for load (``reanchored``)."""

    step_s: float = 0.015
    keep: float = 0.7
    hysteresis: float = 0.5
    ref_tau_s: float = 7200.0
    freeze_s: float = 0.045
    effort_tau_s: float = 600.0


@dataclass(frozen=True, slots=True)
class PersonalState:
    k: int
    ref: float  # the person's reference mean RR
    sum_rr: float = 0.0  # Σ beats × mean RR, the past weighed down by ``keep`` a window
    sum_n: float = 0.0  # Σ beats, likewise
    effort: float = 0.0  # ≤ 0: the part of the drop below the reference still put down to an effort

    @classmethod
    def initial(cls, p: Params) -> PersonalState:
        return cls(p.k0, float(p.rr_rest))


def personal_step(
    p: Params,
    q: Personal,
    s: PersonalState,
    rr: float | None,
    n_beats: int,
    usable: bool,
    dt_s: float = 30.0,
) -> tuple[PersonalState, int, Reason]:
    """One window of the personal mode: (state, δ, reason). ``usable``: a good window, or one held only
    for how few beats it has, each clean (a wrist's); any other (noise, a gap, no clean beat) holds k and
    the state, as Alg. 1 holds. ``dt_s``: the window's length, for the time constants. Bounds as Alg. 1:
    1 ≤ k ≤ N."""
    if rr is None or not usable or n_beats < 1 or not math.isfinite(rr):
        return s, 0, "low-quality"
    sum_rr, sum_n = q.keep * s.sum_rr + n_beats * rr, q.keep * s.sum_n + n_beats
    recent = sum_rr / sum_n
    # an effort's recovery: forgiven while the heart comes back, and less so with time
    effort = min(0.0, max(s.effort * math.exp(-dt_s / q.effort_tau_s), recent - s.ref)) if s.effort else 0.0
    level = recent - effort
    x = (level - s.ref) / q.step_s  # where the person is, in steps from the reference
    # a play (backlash): k moves only when x is more than half a step and the hysteresis from it, and then
    # only as far as brings it back within that, so noise that pushed it over does not push it back at once
    band, at = 0.5 + q.hysteresis, s.k - p.k0
    if x > at + band:
        at = math.ceil(x - band)
    elif x < at - band:
        at = math.floor(x + band)
    k = clamp(p.k0 + at, 1, p.n)
    ref = s.ref
    if level >= s.ref - q.freeze_s:  # not reading as stressed: the reference follows, slowly
        ref += (level - s.ref) * -math.expm1(-dt_s / q.ref_tau_s)
    delta = k - s.k
    reason: Reason = "stress" if delta < 0 else "rest" if delta > 0 else "hold"
    return PersonalState(k, ref, sum_rr, sum_n, effort), delta, reason


def reanchored(s: PersonalState, rr: float, n_beats: int) -> PersonalState:
    """After a movement hold that timed out with the heart still below where it was (Alg. 1 re-anchors
    RR_{i-1} there): the recent mean starts from this window, and the drop below the reference is put
    down to the effort, forgiven as the heart recovers and fading over ``effort_tau_s``, so a slow
    recovery is not read as load and never lowers the reference. k stays."""
    return PersonalState(s.k, s.ref, n_beats * rr, float(n_beats), min(0.0, rr - s.ref))
