"""Speed and separation monitoring (ISO/TS 15066 §5.5.4): how fast the robot may move with a person at a
given distance, as a time scale σ of the current trajectory (common/trajectory/scaling.py).

The protective separation distance (ISO/TS 15066 eq. 1, constant speeds):

    S_p = v_h (T_r + T_s) + v_r T_r + B + C + Z_d + Z_r,     B = v_r T_s / 2

v_h the person's speed toward the robot (1.6 m/s, ISO 13855's walking speed), T_r the time from the
person's move to the robot's reaction (sensor, adapter, bus, the executor's next ramp), T_s the time the
robot takes to stop (the scale's ramp from 1 to 0: the arm decelerates along its path, so the stopping
distance B at a linear ramp is v_r T_s / 2), C the intrusion distance (how far a body part reaches past
the point the sensor sees), Z_d and Z_r the uncertainties of the person's and the robot's position.
Solved for the largest v_r whose S_p fits the measured separation S:

    v_r ≤ (S − v_h (T_r + T_s) − C − Z_d − Z_r) / (T_r + T_s / 2)

v_r is the speed of the fastest point of the arm; the path's own top speed at σ = 1 (``path_speed``) turns
it into σ. Unknown separation (none yet, or older than ``max_age_s``) is read as a person at the robot:
σ = 0, the arm holds its place on the path until a fresh distance frees it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from common.sim.arm import DH_A, DH_ALPHA, DH_D

Array = NDArray[np.float64]
QUANTUM = 0.05  # σ is chosen in steps of this (rounded down: the safe side), so a walk is a few ramps


@dataclass(frozen=True, slots=True)
class Ssm:
    human_speed_m_s: float = 1.6  # v_h
    reaction_s: float = 0.2  # T_r
    stop_time_s: float = 0.5  # T_s: per path, the longest stop ramp found on it (scaling.stop_time)
    intrusion_m: float = 0.2  # C
    uncertainty_m: float = 0.1  # Z_d + Z_r
    max_age_s: float = 0.3

    def protective_distance(self, robot_speed_m_s: float) -> float:
        """S_p for a robot moving at ``robot_speed_m_s``."""
        tr, ts = self.reaction_s, self.stop_time_s
        return (self.human_speed_m_s * (tr + ts) + robot_speed_m_s * (tr + ts / 2)
                + self.intrusion_m + self.uncertainty_m)  # fmt: skip

    def allowed_speed(self, separation_m: float) -> float:
        """The largest robot speed whose S_p fits ``separation_m`` (0: too close even for a robot at rest)."""
        room = separation_m - self.protective_distance(0.0)
        return max(0.0, room / (self.reaction_s + self.stop_time_s / 2))

    def scale(self, separation_m: float | None, age_s: float, path_speed_m_s: float) -> float:
        """σ in [0, 1] for the path whose top speed at σ = 1 is ``path_speed_m_s``."""
        if separation_m is None or not math.isfinite(separation_m) or age_s > self.max_age_s:
            return 0.0
        if path_speed_m_s <= 0.0:
            return 1.0
        return min(1.0, self.allowed_speed(separation_m) / path_speed_m_s)


def stepped(sigma: float) -> float:
    """σ as the executor asks for it: 1, or rounded down to a step of ``QUANTUM``."""
    return 1.0 if sigma >= 1.0 else math.floor(sigma / QUANTUM + 1e-9) * QUANTUM


def link_points(q: Array) -> Array:
    """The origins of the UR16e's DH frames 1–6 (shoulder, elbow, wrists, flange) for joint rows q (m, 6):
    (m, 6, 3). The points a person can meet; the speed of the fastest is the arm's speed."""
    m = len(q)
    t = np.broadcast_to(np.eye(4), (m, 4, 4)).copy()
    out = np.empty((m, 6, 3))
    for j in range(6):
        ct, st = np.cos(q[:, j]), np.sin(q[:, j])
        ca, sa = math.cos(DH_ALPHA[j]), math.sin(DH_ALPHA[j])
        a = np.zeros((m, 4, 4))
        a[:, 0, 0], a[:, 0, 1], a[:, 0, 2], a[:, 0, 3] = ct, -st * ca, st * sa, DH_A[j] * ct
        a[:, 1, 0], a[:, 1, 1], a[:, 1, 2], a[:, 1, 3] = st, ct * ca, -ct * sa, DH_A[j] * st
        a[:, 2, 1], a[:, 2, 2], a[:, 2, 3] = sa, ca, DH_D[j]
        a[:, 3, 3] = 1.0
        t = t @ a
        out[:, j] = t[:, :3, 3]
    return out


def path_speed(q: Array, dt: float) -> float:
    """The top Cartesian speed of any link point along joint samples q (m, 6) taken every ``dt`` s."""
    if len(q) < 2:
        return 0.0
    p = link_points(q)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=2).max() / dt)
