"""The simulated UR16e (common/sim/arm.py): kinematics, servoJ tracking, limits as protective stops."""

from __future__ import annotations

import numpy as np
import pytest

from common.robot.ur16e import DT, UR16E, forward_kinematics
from common.sim.arm import SimArm, move_j_profile


def test_forward_kinematics_at_zero_and_with_the_base_turned() -> None:
    # the standard-DH UR arm stretched out: x = a2 + a3, y = -(d4 + d6), z = d1 - d5
    np.testing.assert_allclose(forward_kinematics(np.zeros(6))[:3], [-0.8384, -0.2907, 0.06085], atol=1e-9)
    turned = forward_kinematics(np.array([np.pi / 2, 0, 0, 0, 0, 0]))[:3]
    np.testing.assert_allclose(turned, [0.2907, -0.8384, 0.06085], atol=1e-9)


def test_servo_tracks_a_smooth_target_and_settles_on_its_end() -> None:
    arm = SimArm(np.zeros(6))
    t = np.arange(0, 2.0, DT)
    target = 0.5 * (1 - np.cos(np.pi * t / 2.0))[:, None] * np.ones(6)  # 0 → 1 rad in 2 s, rest to rest
    lag = [float(np.max(np.abs(arm.q - row))) for row in target if arm.servo(row)]
    assert len(lag) == len(t)
    assert 0.0 < max(lag) < 0.05  # tens of ms behind at ≤ 0.8 rad/s
    for _ in range(250):
        arm.servo(target[-1])
    assert np.max(np.abs(arm.q - target[-1])) < 1e-4
    assert not arm.stopped


def test_a_jump_over_the_speed_limit_is_a_protective_stop_and_the_arm_does_not_move() -> None:
    arm = SimArm(np.zeros(6))
    assert not arm.servo(np.full(6, 0.5), lookahead=0.03, gain=2000)  # 0.5 rad in one step
    assert arm.stopped
    assert "speed" in arm.fault
    assert np.all(arm.q == 0.0)
    assert not arm.servo(np.zeros(6))  # commands are ignored until unlocked
    arm.unlock()
    assert arm.servo(np.full(6, 1e-4))


def test_leaving_the_position_range_is_a_protective_stop() -> None:
    arm = SimArm(np.array([2 * np.pi - 1e-4, 0, 0, 0, 0, 0]))
    assert not arm.jump_to(arm.q + np.array([1e-3, 0, 0, 0, 0, 0]))
    assert "position range" in arm.fault
    assert arm.q[0] == pytest.approx(2 * np.pi - 1e-4)


def test_brake_decelerates_at_the_given_rate() -> None:
    arm = SimArm(np.zeros(6))
    for v in np.linspace(0, 1.0, 200):  # accelerate base to 1 rad/s
        arm.jump_to(arm.q + np.array([v * DT, 0, 0, 0, 0, 0]))
    steps = 0
    while not arm.brake(4.0):
        steps += 1
    assert steps * DT == pytest.approx(0.25, abs=3 * DT)
    assert np.all(arm.qd == 0.0)


def test_move_j_profile_is_synchronised_and_within_speed_and_acceleration() -> None:
    q0, q1 = np.zeros(6), np.array([1.0, -0.5, 0.25, 0, 0, 0.1])
    p = move_j_profile(q0, q1, speed=0.3, acceleration=0.6)
    np.testing.assert_allclose(p[-1], q1)
    v = np.diff(np.vstack([q0, p]), axis=0) / DT
    assert np.max(np.abs(v[:, 0])) <= 0.3 + 1e-9
    assert np.max(np.abs(np.diff(v[:, 0]))) / DT <= 0.6 + 1e-6
    np.testing.assert_allclose(v[:, 1], -0.5 * v[:, 0], atol=1e-12)  # every joint on the same schedule
    assert np.all(np.abs(v) <= UR16E.velocity)


def test_a_sim_arm_at_rest_between_motions_reports_no_speed() -> None:
    """A `ready` sim arm reported joint speeds up to 0.0032 rad/s: its last step's, never zeroed
    (issue 40). After a servo motion and after a moveJ it reports 0, as a real arm at rest does."""
    from services.executor.backends import SimBackend

    b = SimBackend(np.zeros(6), speed=1000.0)
    for i in range(50):
        b.servo(np.full(6, 0.0002 * i))
    assert np.abs(b.actual_qd()).max() > 0.05
    b.motion_ended()
    assert np.abs(b.actual_qd()).max() == 0.0
    assert b.move_j(np.full(6, 0.02), 0.3, 0.6)
    assert np.abs(b.actual_qd()).max() == 0.0
