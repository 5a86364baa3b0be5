"""The wearer's movement, from the strap's accelerometer (DESIGN §6, §7): what tells physical effort from
mental load, both of which lower mean RR.

Gravity is each axis's exponential mean over ``GRAVITY_TAU_S`` (it follows posture, which changes slowly);
what is left is the dynamic acceleration, whose magnitude (mg) is the movement. Per second of data time
the analyser keeps its sum and count, so a window's figures are read off whatever seconds arrived: the
mean dynamic acceleration over the window, and the share of its seconds spent moving (a second's mean
over ``MOVING_MG``). A window with accelerometer data for less than ``MIN_COVERAGE`` of it has no movement
figure: it is read as if the strap had no accelerometer.

The numbers are physical, not tuned on people: 1 s follows a change of posture within seconds and keeps
a step (about 2 Hz) out of the gravity estimate; 50 mg is above what a still wearer's strap shows (4–25 mg
per 3 s on the shared Polar export of a seated person, who moves once, at 100–320 mg for 10 s) and below a
walk's trunk acceleration.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

GRAVITY_TAU_S = 1.0
MOVING_MG = 50.0
MIN_COVERAGE = 0.5
KEEP_S = 1800  # seconds of movement kept: far more than a window (30 s by default, at most 600 s)
_NS = 1_000_000_000


def dynamic_mg(
    xyz_mg: NDArray[np.float64], fs_hz: float, gravity: NDArray[np.float64] | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per sample, the magnitude of the acceleration less gravity; and gravity after the last sample,
    which continues the estimate into the next chunk (None: start from the first sample)."""
    x = np.asarray(xyz_mg, dtype=float).reshape(-1, 3)
    a = 1.0 - math.exp(-1.0 / (fs_hz * GRAVITY_TAU_S))
    g0 = x[0] if gravity is None else gravity
    g, _ = lfilter([a], [1.0, a - 1.0], x, axis=0, zi=((1.0 - a) * g0)[None, :])
    return np.linalg.norm(x - g, axis=1), g[-1]


class Movement:
    """Movement per second of data time, fed chunk by chunk; a gap or a new rate restarts gravity."""

    def __init__(self) -> None:
        self.gravity: NDArray[np.float64] | None = None
        self.fs_hz = 0.0
        self.seconds: dict[int, list[float]] = {}  # whole second of data time: [sum, count]

    def feed(self, t_ns: int, fs_hz: float, xyz_mg: NDArray[np.float64], gap: bool = False) -> None:
        if len(xyz_mg) == 0:
            return
        if gap or fs_hz != self.fs_hz:
            self.gravity = None
        self.fs_hz = fs_hz
        dyn, self.gravity = dynamic_mg(xyz_mg, fs_hz, self.gravity)
        second = (t_ns + np.round(np.arange(len(dyn)) * _NS / fs_hz).astype(np.int64)) // _NS
        for s in np.unique(second):
            cell = self.seconds.setdefault(int(s), [0.0, 0.0])
            cell[0] += float(dyn[second == s].sum())
            cell[1] += float(np.count_nonzero(second == s))
        if len(self.seconds) > 2 * KEEP_S:  # now and then, not at every chunk
            old = int(second[-1]) - KEEP_S
            self.seconds = {s: c for s, c in self.seconds.items() if s >= old}

    def over(self, start_ns: int, end_ns: int) -> tuple[float | None, float | None]:
        """The window's mean dynamic acceleration (mg) and the share of its seconds spent moving; None,
        None when too little of it has accelerometer data."""
        cells = [self.seconds[s] for s in range(start_ns // _NS, -(-end_ns // _NS)) if s in self.seconds]
        n = sum(c[1] for c in cells)
        if not cells or n < MIN_COVERAGE * (end_ns - start_ns) / _NS * self.fs_hz:
            return None, None
        moving = sum(1 for c in cells if c[0] / c[1] > MOVING_MG)
        return round(sum(c[0] for c in cells) / n, 1), round(moving / len(cells), 3)


class Baseline(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """What the decision knows of the wearer's movement at work: the level (mg) and spread of their
    windows' movement, from a working calibration or learnt from their first windows of work, and until
    when a movement above it holds the decision (data time, ns; -1: none yet)."""

    level_mg: float | None = None
    sd_mg: float = 0.0
    learning: tuple[float, ...] = ()  # the first windows' movement, while the level is learnt
    moved_until_ns: int = -1


def baseline_of(level_mg: float | None, sd_mg: float | None) -> Baseline:
    return Baseline(level_mg, sd_mg or 0.0)


def learnt(learning: tuple[float, ...], margin_mg: float, moved_until_ns: int = -1) -> Baseline:
    """The level at work from the first windows: their median and spread, leaving out those over the
    lower quartile by more than ``margin_mg``. A stretch of effort among the first windows (a busy host
    that starts the decision late, a worker who starts with the heavy parts) once made the level the
    effort's, and no window after it was held."""
    x = np.asarray(learning, dtype=float)
    calm = x[x <= np.percentile(x, 25) + margin_mg]
    return Baseline(float(np.median(calm)), float(np.std(calm)), (), moved_until_ns)


def moved(
    b: Baseline, movement_mg: float | None, start_ns: int, end_ns: int, rr_s: float | None,
    rr_before_s: float, margin_mg: float, back_s: float, max_hold_s: float, learn_windows: int,
) -> tuple[bool, Baseline, bool]:  # fmt: skip
    """Whether a window is held for movement, the baseline after it, and whether the hold ended at its
    maximum (the decision then re-anchors: RR_{i-1} becomes this window's, with no step).

    A window without a movement figure (no accelerometer) is never held: Alg. 1 reads it as it always did.
    Held: a window whose movement is over the level by more than ``margin_mg`` (or three spreads, if
    more), and after one every window until the heart is back near where it was before the effort
    (``rr_s`` within ``back_s`` of ``rr_before_s``, RR_{i-1}, which a held window leaves as it was), or
    ``max_hold_s`` after the last moving one. A fixed minute once released a heart still recovering, read
    against the RR before the effort: k fell for the effort alone (3 steps at a recovery of 120 s)."""
    if movement_mg is None:
        return False, b, False
    if b.level_mg is None:
        learning = (*b.learning, movement_mg)
        if len(learning) < learn_windows:
            b = msgspec.structs.replace(b, learning=learning)
        else:
            b = learnt(learning, margin_mg, b.moved_until_ns)
    # while the level is learnt, the calmest window so far stands for it: an effort among the first
    # windows (a busy host that starts the decision late) is held, not read as stress
    level, sd = (b.level_mg, b.sd_mg) if b.level_mg is not None else (min(b.learning), 0.0)
    if movement_mg > level + max(3.0 * sd, margin_mg):
        return True, msgspec.structs.replace(b, moved_until_ns=end_ns), False
    if b.moved_until_ns < 0:
        return False, b, False
    ended = msgspec.structs.replace(b, moved_until_ns=-1)
    if start_ns >= b.moved_until_ns + max_hold_s * 1e9:
        return False, ended, True
    if rr_s is not None and rr_s >= rr_before_s - back_s:
        return False, ended, False  # back near where it was: read as ever
    return True, b, False
