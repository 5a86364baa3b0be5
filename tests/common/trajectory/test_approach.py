"""The move to a path's start as a path of its own (common/trajectory/approach.py): within the move's own
speed and acceleration and the task's limits, a straight line in joint space, at rest at both ends."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.robot.ur16e import UR16E
from common.trajectory import bspline as bs
from common.trajectory.approach import approach
from common.trajectory.scaling import Curve

joints = st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6).map(np.array)


@settings(max_examples=60, deadline=None)
@given(joints, joints, st.floats(0.01, 1.0), st.floats(0.01, 2.0))
def test_an_approach_keeps_its_speed_and_acceleration_on_a_straight_line_at_rest_at_both_ends(
    q0: np.ndarray, q1: np.ndarray, speed: float, acceleration: float
) -> None:
    path, h = approach(q0, q1, speed, acceleration, UR16E, "approach to there")
    curve = Curve.of(h, path)
    v, a, j = bs.span_maxima(h[None], curve.taylor[None])[0]
    assert np.all(v <= speed * (1 + 1e-9) + 1e-12)
    assert np.all(a <= acceleration * (1 + 1e-9) + 1e-12)
    assert np.all(j <= UR16E.jerk * (1 + 1e-9))
    # as short as that allows: one of the three binds (speed, acceleration, the task's jerk)
    assert max(np.max(v) / speed, np.max(a) / acceleration, np.max(j / UR16E.jerk)) == pytest.approx(1.0) or (
        h.sum() == pytest.approx(1e-3)
    )
    s = np.linspace(0.0, curve.t_f, 41)
    q, qd, qdd, _ = curve.at(s)
    np.testing.assert_allclose(q[0], q0, atol=1e-9)
    np.testing.assert_allclose(q[-1], q1, atol=1e-9)
    np.testing.assert_allclose(qd[[0, -1]], 0.0, atol=1e-6)  # the spline solve's round-off
    np.testing.assert_allclose(qdd[[0, -1]], 0.0, atol=1e-6)
    # every point on the segment from q0 to q1, in order
    d = q1 - q0
    if np.linalg.norm(d) > 1e-9:
        part = (q - q0) @ d / (d @ d)
        np.testing.assert_allclose(q, q0 + part[:, None] * d, atol=1e-9)
        assert (
            np.all(np.diff(part) >= -1e-12)
            and part[0] == pytest.approx(0.0)
            and part[-1] == pytest.approx(1.0)
        )


def test_an_arm_already_there_has_a_move_of_a_step_that_goes_nowhere() -> None:
    q = np.array([0.1, -1.5, 1.5, -1.5, -1.5, 0.0])
    path, h = approach(q, q, 0.3, 0.6, UR16E, "approach to there")
    assert h.sum() == pytest.approx(1e-3)
    np.testing.assert_allclose(Curve.of(h, path).at(np.linspace(0, h.sum(), 5), 0)[0], np.tile(q, (5, 1)))


@pytest.mark.asyncio
async def test_two_moves_to_one_start_that_share_an_h_have_each_its_own_figures_and_neither_is_kept(
    tmp_path,
) -> None:
    """The executor remembers a path's figures (top speed, stop) by its id and its h; a move to a path's
    start is named after the path and its h is the move's length in time, so two of them from two places
    can share both and not the motion: one's figures must never stand for the other's. Nor are they kept,
    each made once, where they would push the paths' own out."""
    import asyncio

    from common.runtime.config import CommonSettings
    from common.runtime.memory import MemoryNetwork
    from common.runtime.service import ServiceContext
    from services.executor.__main__ import Executor
    from tests.support.executor import sim_settings, tracked
    from tests.support.paths import EXAMPLE_TASK

    settings = sim_settings(EXAMPLE_TASK, separation=True, separation_sources=tracked("test"),
                            lock_dir=str(tmp_path / "locks"))  # fmt: skip
    bus = MemoryNetwork().bus(role="executor")
    node = Executor(ServiceContext("executor", bus, CommonSettings(data_dir=str(tmp_path)), settings,
                                   asyncio.Event()))  # fmt: skip
    await node.setup()
    try:
        q1 = np.zeros(6)
        base = approach(np.array([1.0, 0, 0, 0, 0, 0]), q1, 0.5, 1.0, UR16E, "approach to b1_to_b2")
        wrist = approach(np.array([0, 0, 0, 1.0, 0, 0]), q1, 0.5, 1.0, UR16E, "approach to b1_to_b2")
        np.testing.assert_array_equal(base[1], wrist[1])  # the same h: one joint 1 rad, either way
        each = [node.figures.of(p, h, Curve.of(h, p), keep=False) for p, h in (base, wrist)]
        assert each[0].speed_m_s > 1.5 * each[1].speed_m_s  # the base swings the whole arm
        assert not node.figures.known(*base) and not node.figures.known(*wrist)
        kept = node.figures.of(*base, Curve.of(base[1], base[0]))
        assert node.figures.known(*base) and not node.figures.known(*wrist)
        assert node.figures.of(*wrist, Curve.of(wrist[1], wrist[0])) != kept
    finally:
        await node.close()
        await bus.close()
