"""The wrist motions of issue 52, which tests/common/safety/test_geometry.py holds to their figures and
tests/cadence/test_docs_figures.py to what docs/robot.md says of them; and the arm's speed at a state
sample, which the wall-clock tests (walk-in, flood) judge a moving arm by, and the figures of the paths
they run."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from common.robot.ur16e import N_JOINTS, UR16E
from common.safety.geometry import Arm, Tool
from common.safety.separation import Figures
from common.trajectory.planner import content_hash
from common.trajectory.scaling import Curve
from common.trajectory.task import load_task
from schemas import RobotState
from services.executor.settings import Settings as ExecutorSettings
from services.pareto_store.store import SetStore
from tests.support.paths import EXAMPLE_TASK

DT, OMEGA = 0.002, math.radians(180.0)  # one controller step, at 180°/s


def wrist_speeds() -> dict[str, float]:
    """The top speed of arm and tool over one step: a wrist-3 spin read at the flange (bare arm) and at
    a gripper tip 0.1 m off its axis; a wrist-1 turn in the example tasks' working pose, at the flange
    and at the tip of a 0.2 m tool."""
    spin = np.zeros((2, N_JOINTS))
    spin[1, 5] = OMEGA * DT
    turn = np.radians([[0, -90, 90, -90, -90, 0]] * 2)
    turn[1, 3] += OMEGA * DT
    return {
        "spin_flange": Arm().top_speed(spin, DT),
        "spin_tip": Arm(tool=Tool.of([[0.1, 0.0, 0.0, 0.0]])).top_speed(spin, DT),
        "turn_flange": Arm().top_speed(turn, DT),
        "turn_tip": Arm(tool=Tool.of([[0.0, 0.0, 0.2, 0.0]])).top_speed(turn, DT),
    }


def speed(arm: Arm, s: RobotState) -> float:
    """The speed of the arm's (and tool's) fastest point at a sample, m/s."""
    q, qd = np.array(s.q), np.array(s.qd)
    return arm.top_speed(np.stack([q, q + qd * 1e-3]), 1e-3)


def figures_at_top_k(db: Path) -> tuple[Figures, dict[str, Figures]]:
    """The worst figures of the example task's paths at k = n (the executor's start here), and each's,
    with the executor's own arm and tool."""
    task = load_task(EXAMPLE_TASK)
    arm = ExecutorSettings().arm()
    store, _ = SetStore.open(db)
    each = {}
    for pid, path in task.paths.items():
        s = store.load(pid, content_hash(path, task.limits, task.planner))
        assert s is not None
        each[pid] = Figures.of(Curve.of(np.array(s.solutions[-1].h), path), UR16E, arm=arm)
    store.close()
    worst = Figures(0.0, 0.0)
    for f in each.values():
        worst = worst.worst(f)
    return worst, each
