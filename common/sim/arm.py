"""A simulated UR16e: what the executor's ``sim`` backend drives, and what the UR controller emulator
will drive (one model, not two). Kinematics and limits from shared/reference/ur-rtde-wire.md.

The model is a kinematic one, the controller's view of the arm rather than its dynamics:
- servoJ tracking: each 2 ms step the joints move a fraction ``dt / τ`` of the way to the target, with
  ``τ = lookahead · GAIN_REF / gain``. Like the real servoj, a longer lookahead or a lower gain gives a
  smoother, later arm (tens of ms of lag at the defaults), and an arm that keeps converging on the last
  target after the stream ends.
- limits are safety limits: a step that would exceed a joint's speed limit or leave its position range is
  not taken; the arm enters a protective stop and ignores commands until it is unlocked, as the real arm
  does.
- ``brake`` decelerates every joint at a given rate (stopJ, servoStop).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from common.robot.ur16e import DT, JOINT_NAMES, UR16E, JointLimits

Array = NDArray[np.float64]

GAIN_REF = 100.0  # gain at which τ equals the lookahead time
SPEED_TOL = 1e-6  # relative slack on the speed limit (round-off only)


class SimArm:
    """The arm's state and one controller step at a time. Preallocated: ``servo`` allocates no arrays,
    so the servo loop can call it every tick."""

    def __init__(self, q0: Array, limits: JointLimits = UR16E, dt: float = DT) -> None:
        self.limits = limits
        self.dt = dt
        self.q = np.array(q0, dtype=float)
        self.qd = np.zeros(6)
        self.target = self.q.copy()
        self.digital_out = 0
        self.digital_in = 0  # standard digital inputs 0–7, a bit each: the cell's buttons
        self.fault = ""  # why the arm is in a protective stop; "" while it runs
        self.steps = 0
        self._d = np.zeros(6)
        self._abs = np.zeros(6)

    @property
    def stopped(self) -> bool:
        return bool(self.fault)

    def servo(self, target: Array, lookahead: float = 0.1, gain: float = 300.0) -> bool:
        """One step toward ``target``; False (and no motion) in or into a protective stop."""
        if self.fault:
            self.qd.fill(0.0)
            return False
        self.steps += 1
        self.target[:] = target
        np.subtract(target, self.q, out=self._d)
        self._d *= min(1.0, self.dt * gain / (lookahead * GAIN_REF))
        return self._move(self._d)

    def brake(self, deceleration: float) -> bool:
        """One step of a decelerating stop (stopJ, servoStop); True once every joint is at rest."""
        self.steps += 1
        dv = deceleration * self.dt
        np.abs(self.qd, out=self._abs)
        if float(self._abs.max()) <= dv:
            self.qd.fill(0.0)
            return True
        scale = np.maximum(self._abs - dv, 0.0) / np.where(self._abs > 0.0, self._abs, 1.0)
        self.qd *= scale
        self.q += self.qd * self.dt
        return False

    def halt(self, deceleration: float) -> int:
        """The braking stop a controller takes on its own when the commands stop (its watchdog), taken
        all at once: the steps it took while nobody sent any. How many it took."""
        n = 0
        while not self.brake(deceleration):
            n += 1
        return n

    def jump_to(self, q: Array) -> bool:
        """One step of a controller-side motion (moveJ) already planned within the limits."""
        np.subtract(q, self.q, out=self._d)
        return self._move(self._d)

    def _move(self, dq: Array) -> bool:
        np.abs(dq, out=self._abs)
        over = self._abs > self.limits.velocity * self.dt * (1.0 + SPEED_TOL)
        if over.any():
            j = int(np.argmax(over))
            return self.protect(
                f"{JOINT_NAMES[j]} speed {self._abs[j] / self.dt:.3f} rad/s over its limit "
                f"{self.limits.velocity[j]:.3f} rad/s"
            )
        self.q += dq
        np.abs(self.q, out=self._abs)
        if (self._abs > self.limits.position).any():
            self.q -= dq
            j = int(np.argmax(self._abs > self.limits.position))
            return self.protect(f"{JOINT_NAMES[j]} at the edge of its position range")
        np.multiply(dq, 1.0 / self.dt, out=self.qd)
        return True

    def protect(self, reason: str) -> bool:
        self.fault = reason
        self.qd.fill(0.0)
        return False

    def rest(self) -> None:
        """No command comes (between motions): the arm holds where it is, and says it is still. Its last
        step's speed once stayed in ``qd`` (up to 0.0032 rad/s reported by a ``ready`` arm)."""
        self.qd.fill(0.0)

    def unlock(self) -> None:
        """Clear a protective stop (the operator's 'unlock' on the teach pendant)."""
        self.fault = ""


def move_j_profile(q0: Array, q1: Array, speed: float, acceleration: float, dt: float = DT) -> Array:
    """Samples of a synchronised trapezoidal joint move (moveJ): every joint starts and stops together,
    the one with the longest way at ``speed`` and ``acceleration``. (m, 6), the last row is q1."""
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
    dist = float(np.max(np.abs(q1 - q0)))
    if dist < 1e-12:
        return q1[None, :].copy()
    t_acc = speed / acceleration
    if acceleration * t_acc**2 >= dist:  # never reaches speed: a triangle
        t_acc = math.sqrt(dist / acceleration)
        speed = acceleration * t_acc
    t_total = 2.0 * t_acc + (dist - acceleration * t_acc**2) / speed
    t = np.arange(1, math.ceil(t_total / dt) + 1) * dt
    t = np.minimum(t, t_total)
    s = np.where(
        t < t_acc,
        0.5 * acceleration * t**2,
        np.where(
            t <= t_total - t_acc,
            0.5 * acceleration * t_acc**2 + speed * (t - t_acc),
            dist - 0.5 * acceleration * (t_total - t) ** 2,
        ),
    )
    return q0 + np.outer(s / dist, q1 - q0)
