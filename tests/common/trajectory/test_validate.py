"""The executor's last check refuses what would exceed a limit or leave the path, and says why."""

from __future__ import annotations

import numpy as np
import pytest

from common.robot.ur16e import UR16E
from common.runtime.errors import TrajectoryRejected
from common.trajectory.planner import boundary_stretch
from common.trajectory.validate import check_trajectory, trajectory_problems
from tests.support.paths import random_path


@pytest.fixture
def on_the_limits() -> tuple:
    path = random_path(61, 6)
    h = np.array([0.3, 0.3, 0.8, 0.9, 0.7, 0.3, 0.3])
    return path, h * boundary_stretch(h[None], path, UR16E, "exact")[0] * (1 + 1e-9)


def test_a_trajectory_on_its_limits_passes(on_the_limits: tuple) -> None:
    path, h = on_the_limits
    assert trajectory_problems(h, path, UR16E) == []
    check_trajectory(h, path, UR16E, claimed_waypoints=path.waypoints.copy())


def test_one_percent_faster_is_refused_naming_joint_and_quantity(on_the_limits: tuple) -> None:
    path, h = on_the_limits
    with pytest.raises(TrajectoryRejected) as info:
        check_trajectory(h * 0.99, path, UR16E)
    assert any("over its limit" in p for p in info.value.problems)
    assert path.id in str(info.value)


def test_other_waypoints_than_the_executors_copy_are_refused(on_the_limits: tuple) -> None:
    path, h = on_the_limits
    forged = path.waypoints.copy()
    forged[3, 2] += 0.05
    problems = trajectory_problems(h, path, UR16E, claimed_waypoints=forged)
    assert problems == ["waypoint 3 differs from the executor's copy of path 'random61'"]


@pytest.mark.parametrize("h", [np.ones(3), np.array([1.0, 1, 1, -1, 1, 1, 1]), np.full(7, np.nan)])
def test_malformed_intervals_are_refused(on_the_limits: tuple, h: np.ndarray) -> None:
    path, _ = on_the_limits
    assert trajectory_problems(h, path, UR16E) != []
