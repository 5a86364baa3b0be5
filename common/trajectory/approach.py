"""The slow move to a path's start (the arm stands elsewhere: a start-up, a resume after a stop mid-path)
as a path of its own: two waypoints, at rest at both ends, timed so that no joint passes the move's speed
and acceleration (nor the task's jerk).

Why a path and not the controller's moveJ: a path is played by the servo loop, so the move is under the
same guards as every other motion: the controller's watchdog (an executor that stalls stops the arm), the
lease on the scale (looks that stop coming stop the arm), and the scale itself (a person who comes near
slows it smoothly, and it goes on when they leave). A moveJ runs on the controller whatever the executor
does: an executor stalled for 2.7 s on a loaded host left it moving inside the person's reach.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from common.robot.ur16e import JointLimits
from common.trajectory import bspline as bs
from common.trajectory.task import PathPlan

Array = NDArray[np.float64]
SPANS = bs.n_intervals(2)


def approach(
    q0: Array, q1: Array, speed: float, acceleration: float, limits: JointLimits, path_id: str
) -> tuple[PathPlan, Array]:
    """The path from ``q0`` to ``q1`` and its span durations ``h`` (SPANS,): the shortest uniform timing
    whose joint speeds stay within ``speed`` rad/s and accelerations within ``acceleration`` rad/s² (and
    within the task's limits, jerk included). Its motion is a straight line in joint space."""
    q0, q1 = np.asarray(q0, dtype=float), np.asarray(q1, dtype=float)
    path = PathPlan(
        path_id, np.stack([q0, q1]), bs.Boundary.at_rest(len(q0)), "the slow move to a path's start"
    )
    unit = np.full((1, SPANS), 1.0 / SPANS)  # a 1 s move: speed scales as 1/T, acceleration 1/T², jerk 1/T³
    taylor = bs.span_taylor(unit, bs.control_points(unit, path.waypoints, path.boundary))
    v, a, j = bs.span_maxima(unit, taylor)[0]  # (D,) each
    top = limits.kinematic()
    v_max = np.minimum(top[0], speed)
    a_max = np.minimum(top[1], acceleration)
    t_f = max(
        float(np.max(v / v_max)),
        float(np.sqrt(np.max(a / a_max))),
        float(np.cbrt(np.max(j / top[2]))),
        1e-3,  # q0 = q1: a move of one step, at rest
    )
    return path, np.full(SPANS, t_f / SPANS)
