"""The UR16e's joint limits: the one table in Cadence. A task program may only lower them (DESIGN §5).

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
