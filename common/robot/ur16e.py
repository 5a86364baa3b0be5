"""The UR16e: its kinematics (standard DH, the TCP pose, the points a person can meet) and its joint limits,
the one model and the one table in Cadence, used alike by the planner, the simulator and the safety code.
The joint limits: A task program may only lower them (DESIGN §5).

Sources (see shared/reference/ur-rtde-wire.md):
- position ±360° every joint, speed 120°/s base and shoulder, 180°/s elbow and wrists: Universal Robots'
  UR16e user manual, as carried in Universal_Robots_ROS2_Description `config/ur16e/joint_limits.yaml`.
- acceleration and jerk: Universal Robots publishes none. Cadence's defaults, 5 rad/s² and 50 rad/s³ on
  every joint, are the values the planner issues were measured with; they are well inside what servoJ
  tracks on an e-Series arm carrying the paper's EPick gripper and a box. Lower them in the task program
  for heavier payloads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

JOINT_NAMES = ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3")
N_JOINTS = len(JOINT_NAMES)


@dataclass(frozen=True, slots=True)
class JointLimits:
    """Per-joint limits in SI units (rad, rad/s, rad/s², rad/s³), each shape (6,)."""

    position: NDArray[np.float64]
    velocity: NDArray[np.float64]
    acceleration: NDArray[np.float64]
    jerk: NDArray[np.float64]

    def kinematic(self) -> NDArray[np.float64]:
        """(3, D): velocity, acceleration, jerk rows, the order of ``bspline.span_maxima``."""
        return np.stack([self.velocity, self.acceleration, self.jerk])

    def as_dict(self) -> dict[str, list[float]]:
        return {
            "velocity": self.velocity.tolist(),
            "acceleration": self.acceleration.tolist(),
            "jerk": self.jerk.tolist(),
        }


UR16E = JointLimits(
    position=np.full(N_JOINTS, 2 * math.pi),
    velocity=np.radians([120.0, 120.0, 180.0, 180.0, 180.0, 180.0]),
    acceleration=np.full(N_JOINTS, 5.0),
    jerk=np.full(N_JOINTS, 50.0),
)

DT = 0.002  # one e-Series controller step

# standard DH of the UR16e (ROS-Industrial ur_description, default_kinematics.yaml)
DH_D = np.array([0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655])
DH_A = np.array([0.0, -0.4784, -0.36, 0.0, 0.0, 0.0])
DH_ALPHA = np.array([math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0])


def forward_kinematics(q: Array) -> Array:
    """TCP pose (x, y, z in m; rx, ry, rz as a rotation vector, UR's convention) at joint angles q."""
    t = np.eye(4)
    for theta, d, a, alpha in zip(q, DH_D, DH_A, DH_ALPHA, strict=True):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        t = t @ np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]]
        )
    return np.concatenate([t[:3, 3], rotation_vector(t[:3, :3])])


def rotation_vector(r: Array) -> Array:
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0)))
    if angle < 1e-12:
        return np.zeros(3)
    if math.pi - angle < 1e-6:  # 180°: the axis from the diagonal
        axis = np.sqrt(np.maximum((np.diag(r) + 1.0) / 2.0, 0.0))
        i = int(np.argmax(axis))
        axis = r[:, i] / math.sqrt(2.0 * (1.0 + r[i, i])) if axis[i] > 0 else axis
        return axis / np.linalg.norm(axis) * angle
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2.0 * math.sin(angle))
    return axis * angle


def frames(q: Array) -> Array:
    """The DH frames 1–6 of the UR16e for joint rows q (m, 6): (m, 6, 4, 4), in the base frame."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    m = len(q)
    t = np.broadcast_to(np.eye(4), (m, 4, 4)).copy()
    out = np.empty((m, 6, 4, 4))
    for j in range(6):
        ct, st = np.cos(q[:, j]), np.sin(q[:, j])
        ca, sa = math.cos(DH_ALPHA[j]), math.sin(DH_ALPHA[j])
        a = np.zeros((m, 4, 4))
        a[:, 0, 0], a[:, 0, 1], a[:, 0, 2], a[:, 0, 3] = ct, -st * ca, st * sa, DH_A[j] * ct
        a[:, 1, 0], a[:, 1, 1], a[:, 1, 2], a[:, 1, 3] = st, ct * ca, -ct * sa, DH_A[j] * st
        a[:, 2, 1], a[:, 2, 2], a[:, 2, 3] = sa, ca, DH_D[j]
        a[:, 3, 3] = 1.0
        t = t @ a
        out[:, j] = t
    return out


def link_points(q: Array) -> Array:
    """The origins of the UR16e's DH frames 1–6 (shoulder, elbow, wrists, flange) for joint rows q (m, 6):
    (m, 6, 3). The arm's joints; its tool is common/safety/geometry.py's."""
    return frames(q)[:, :, :3, 3]
