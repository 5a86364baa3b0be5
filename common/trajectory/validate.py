"""The last check before a trajectory reaches the robot (DESIGN §8): whatever arrives on the bus, the
executor rebuilds the curve from *its own* copy of the path's waypoints and checks it against *its own*
limits table. The check is on the curve itself (exact maxima), whatever mode planned it.
"""

from __future__ import annotations

import numpy as np

from common.robot.ur16e import JOINT_NAMES, JointLimits
from common.runtime.errors import TrajectoryRejected
from common.trajectory import bspline as bs
from common.trajectory.task import PathPlan
from schemas.pareto import MAX_PATH_S, ParetoSet

WAYPOINT_TOL_RAD = 1e-9
# Relative slack on a limit: exact maxima carry round-off of ~1e-12; a real excess is far larger.
LIMIT_RTOL = 1e-9
_QUANTITIES = ("velocity", "acceleration", "jerk")


def trajectory_problems(
    h: np.ndarray,
    path: PathPlan,
    limits: JointLimits,
    claimed_waypoints: np.ndarray | None = None,
    position_rate_hz: float = 2000.0,
) -> list[str]:
    """Every reason to refuse the trajectory h along ``path`` (empty: it may run)."""
    h = np.asarray(h, dtype=float)
    w = len(path.waypoints)
    if h.shape != (w + 1,):
        return [f"h has shape {h.shape}, expected ({w + 1},) for {w} waypoints"]
    if not np.all(np.isfinite(h)) or np.any(h <= 0):
        return ["h must be finite and positive"]
    if h.sum() > MAX_PATH_S:  # before anything is sampled: memory grows with the duration
        return [f"the path takes {h.sum():.6g} s, over the {MAX_PATH_S:g} s any path may take"]
    problems = []
    if claimed_waypoints is not None:
        claimed = np.asarray(claimed_waypoints, dtype=float)
        if claimed.shape != path.waypoints.shape:
            problems.append(
                f"waypoints have shape {claimed.shape}, the executor's copy {path.waypoints.shape}"
            )
        elif not np.allclose(claimed, path.waypoints, rtol=0.0, atol=WAYPOINT_TOL_RAD):
            i = int(np.argmax(np.max(np.abs(claimed - path.waypoints), axis=1)))
            problems.append(f"waypoint {i} differs from the executor's copy of path '{path.id}'")
    h2 = h[None, :]
    c = bs.control_points(h2, path.waypoints, path.boundary)
    sites = bs.waypoint_sites(h2)[0]
    q_sites = bs.evaluate_dense(h, path.waypoints, path.boundary, sites)[0]
    off = np.max(np.abs(q_sites - path.waypoints))
    if not off <= WAYPOINT_TOL_RAD:
        problems.append(f"the curve misses a waypoint by {off:.3g} rad (ill-conditioned h)")
    maxima = bs.span_maxima(h2, bs.span_taylor(h2, c))[0]  # (3, D)
    lim = limits.kinematic()
    for d, j in zip(*np.nonzero(maxima > lim * (1 + LIMIT_RTOL)), strict=True):
        problems.append(
            f"{JOINT_NAMES[j]} {_QUANTITIES[d]} {maxima[d, j]:.6g} over its limit {lim[d, j]:.6g}"
        )
    t = np.linspace(0.0, float(h.sum()), max(2, int(h.sum() * position_rate_hz) + 1))
    q = bs.evaluate_dense(h, path.waypoints, path.boundary, t)[0]
    for j in np.nonzero(np.max(np.abs(q), axis=0) > limits.position)[0]:
        problems.append(f"{JOINT_NAMES[j]} leaves its position range ±{limits.position[j]:.4g} rad")
    return problems


def check_trajectory(
    h: np.ndarray, path: PathPlan, limits: JointLimits, claimed_waypoints: np.ndarray | None = None
) -> None:
    """Raise ``TrajectoryRejected`` with every problem found; return quietly when it may run."""
    problems = trajectory_problems(h, path, limits, claimed_waypoints)
    if problems:
        raise TrajectoryRejected(path.id, problems)


def validated_samples(
    h: np.ndarray,
    path: PathPlan,
    limits: JointLimits,
    claimed_waypoints: np.ndarray | None = None,
    rate_hz: float = 500.0,
) -> np.ndarray:
    """What the executor servos: the checked trajectory as joint positions at ``rate_hz``, (m, D), the
    first row the path's first waypoint and the last its last. Raises ``TrajectoryRejected``."""
    check_trajectory(h, path, limits, claimed_waypoints)
    _, q, _, _ = bs.sample(np.asarray(h, dtype=float), path.waypoints, path.boundary, rate_hz)
    return q


def set_problems(s: ParetoSet, path: PathPlan, limits: JointLimits, digest: str) -> list[str]:
    """Every reason not to serve ``s``, a set another cell answered for ``path`` (sets by hash): it must
    name this path's content hash, carry this path's waypoints, and every solution must pass
    the check the executor applies before any trajectory runs (``trajectory_problems``), on this
    store's own copy of the path and limits. A hash is a claim; the trajectories are checked."""
    if s.content_hash != digest:
        return [f"it was planned from other inputs ({s.content_hash[:12]}…, this path's {digest[:12]}…)"]
    problems = []
    claimed = np.asarray(s.waypoints, dtype=float)
    for sol in s.solutions:
        problems += [
            f"k = {sol.k}: {p}" for p in trajectory_problems(np.asarray(sol.h), path, limits, claimed)
        ]
    return problems
