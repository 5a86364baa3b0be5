"""The robot's own stops in S_p (issue 74): the longest of the executor's ramp, the brake, the watchdog's
stop and the maker's (or the installed robot's) table, each budgeted with no credit for deceleration; a
table that does not reach full speed refused at start in one line; S_r at the speed in force."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.robot.stopping import UR16E_STOP_S, RobotStops, StopRow
from common.robot.ur16e import UR16E
from common.runtime.errors import ConfigError
from common.safety.separation import Figures, Ssm
from common.trajectory.scaling import Curve
from common.trajectory.task import load_task
from services.executor.settings import Settings
from tests.support.paths import EXAMPLE_TASK

TOP = UR16E.velocity


def test_a_row_counts_for_every_speed_up_to_its_own_and_an_unlisted_joint_takes_the_worst_of_any() -> None:
    stops = RobotStops((StopRow(1, 1, 0.5), StopRow(1, 1, 0.2, speed=0.33), StopRow(1, 0, 0.3)))
    third, half = np.zeros(6), np.zeros(6)
    third[1], half[1] = 0.3, 0.5
    assert stops.category(1, third) == 0.2  # the shoulder at 30 %: its 33 % row
    assert stops.category(1, half) == 0.5  # at 50 %: the next row up, full speed's
    wrist = np.zeros(6)
    wrist[4] = 0.1
    assert stops.category(1, wrist) == 0.3  # a wrist nobody measured: the worst listed joint at 10 % (base)
    assert stops.category(0, half) == 0.0  # no category 0 figures: none budgeted


def test_the_stop_budgeted_is_the_longest_the_brake_after_the_watchdogs_silence_included() -> None:
    peak = TOP.copy()
    brake = float(TOP.max()) / 4.0
    stops = RobotStops((), "", 4.0, 0.1)
    worst = stops.worst(peak, TOP)
    assert (worst.time_s, worst.by) == (pytest.approx(0.1 + brake), "the watchdog's stop")
    ur = Settings(backend="ur_rtde").stops().worst(peak * 0.1, TOP)
    assert ur.time_s == pytest.approx(0.1 + UR16E_STOP_S)  # the UR's protective stop, after the silence
    assert Settings().stops().worst(np.zeros(6), TOP).time_s == pytest.approx(0.1)  # at rest: the silence


def test_a_paths_figures_take_the_longer_of_the_executors_ramp_and_the_robots_stop() -> None:
    from common.runtime.resources import SHIPPED_SETS
    from common.safety.geometry import Arm
    from common.trajectory.shipped import read_shipped

    task = load_task(EXAMPLE_TASK)
    plan = read_shipped(SHIPPED_SETS / "box_filling.json").sets[0]
    curve = Curve.of(np.array(plan.solutions[0].h), task.paths[plan.path_id])
    own = Figures.of(curve, task.limits)
    slow = RobotStops(tuple(StopRow(1, j, 2.0) for j in range(6)), "a slow robot")
    with_robot = Figures.of(curve, task.limits, arm=Arm(stops=slow))
    assert own.stop_by == "the executor's ramp" and own.stop_time_s < 2.0
    assert (with_robot.stop_time_s, with_robot.stop_travel_s) == (2.0, 2.0)
    assert with_robot.stop_by == "the protective stop"
    assert with_robot.speed_m_s == own.speed_m_s


def test_a_stopping_table_that_does_not_reach_full_speed_is_refused_at_start_in_one_line() -> None:
    s = Settings(robot_stops=[StopRow(1, 1, 0.2, speed=0.33)])
    with pytest.raises(ConfigError) as e:
        s.arm()
    assert "category 1, joint 1 has no row at speed 1.0" in str(e.value)
    table = "[{ category = 1, joint = 1, time_s = 0.2, speed = 0.33 }]"
    r = subprocess.run([sys.executable, "-m", "services.executor"],
                       env={**os.environ, "CADENCE_EXECUTOR_ROBOT_STOPS": table},
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1, r.stderr
    assert "category 1, joint 1 has no row at speed 1.0" in r.stderr


@given(
    separation=st.floats(2.0, 8.0),
    in_force=st.floats(0.0, 2.0),
    reaction=st.floats(0.05, 1.0),
    travel=st.floats(0.05, 1.0),
)
def test_sr_counts_the_speed_in_force_through_tr_and_the_new_speeds_stop_fits_after_it(
    separation: float, in_force: float, reaction: float, travel: float
) -> None:
    """ISO/TS 15066: S_r is the speed in force over T_r. The speed chosen for an arm running at v_0 is
    one whose stop, after T_r at v_0, still fits S; it equals the constant-speed one where v_0 is slower."""
    ssm = Ssm(1.6, reaction, 2 * travel, 0.85, 0.1, stop_travel_s=travel)
    same = ssm.allowed_speed(separation)
    v = ssm.allowed_speed(separation, in_force)
    budget = ssm.protective_distance(0.0) + max(in_force, v) * reaction + v * travel
    assert budget <= separation + 1e-9 or v == 0.0
    assert v <= same + 1e-12
    if in_force <= same:
        assert v == pytest.approx(same)
