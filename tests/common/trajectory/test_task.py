"""Task programs: the example loads; every kind of bad file gets one line naming file, path and field."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from common.robot.ur16e import UR16E
from common.runtime.errors import TaskError
from common.trajectory.task import continuity_gaps, load_task, parse_task
from tests.support.paths import EXAMPLE_TASK
from tests.support.tasks import GOOD


def test_the_example_task_loads_with_six_chained_paths() -> None:
    task = load_task(EXAMPLE_TASK)
    assert len(task.paths) == 6
    assert continuity_gaps(task) == []
    assert any(s.wait_for for s in task.cycle)
    assert any(s.gripper for s in task.cycle)
    b1 = task.paths["b1_to_b2"]
    assert b1.waypoints.shape == (6, 6)
    assert b1.waypoints[0, 0] == pytest.approx(math.radians(-62.0))


def test_degrees_and_radians_are_both_read_as_radians() -> None:
    task = parse_task(GOOD, "good.toml")
    assert task.paths["p1"].waypoints[1, 0] == pytest.approx(math.radians(30))
    assert task.paths["p2"].waypoints[0, 0] == pytest.approx(0.785)
    assert [s.move for s in task.cycle] == ["p1", "p2"]


def test_a_task_may_lower_limits() -> None:
    task = parse_task(GOOD + '\n[limits]\nunit = "deg"\nvelocity = [60, 60, 90, 90, 90, 90]\n', "t.toml")
    np.testing.assert_allclose(task.limits.velocity, np.radians([60, 60, 90, 90, 90, 90]))
    np.testing.assert_allclose(task.limits.jerk, UR16E.jerk)


BAD = [
    ("missing field", GOOD.replace('unit = "deg"\n', "", 1), "path 'p1'", "unit"),
    ("unknown unit", GOOD.replace('unit = "deg"', 'unit = "grad"', 1), "path 'p1'", "unit"),
    (
        "outside the joint range",
        GOOD.replace("[30, -80, 100", "[400, -80, 100", 1),
        "path 'p1'",
        "waypoints[1][0]",
    ),
    (
        "limit above the UR16e table",
        GOOD + '\n[limits]\nunit = "deg"\nvelocity = [60, 200, 90, 90, 90, 90]\n',
        "",
        "limits.velocity[1]",
    ),
    (
        "fewer than 2 waypoints",
        GOOD.replace(
            "waypoints = [[0.785, -1.22, 1.66, -1.92, -1.571, 0.698], [0, -1.571, 1.571, -1.571, -1.571, 0]]",
            "waypoints = [[0.785, -1.22, 1.66, -1.92, -1.571, 0.698]]",
        ),
        "path 'p2'",
        "waypoints",
    ),
    ("NaN", GOOD.replace("[45, -70, 95", "[45, nan, 95", 1), "path 'p1'", "waypoints[2]"),
    ("duplicate path id", GOOD.replace('id = "p2"', 'id = "p1"'), "path 'p1'", "id"),
    ("wrong type", GOOD.replace("[30, -80, 100", '[30, "x", 100', 1), "path 'p1'", "waypoints[1][1]"),
    ("unknown key", GOOD.replace('id = "p2"', 'id = "p2"\nspeed = 3'), "path 'p2'", "speed"),
    (
        "five joints",
        GOOD.replace("[45, -70, 95, -110, -90, 40]", "[45, -70, 95, -110, -90]"),
        "path 'p1'",
        "waypoints[2]",
    ),
    ("syntax", GOOD + "\n[[paths]\n", "", "(syntax)"),
    ("unknown planner key", GOOD + "\n[planner]\npopsize = 30\n", "", "popsize"),
    ("planner value", GOOD + "\n[planner]\nkappa = 0.5\n", "", "planner.kappa"),
    ("unknown path in the cycle", GOOD + '\n[[cycle]]\nmove = "p9"\n', "", "cycle[0].move"),
    ("deadline not on a wait_for", GOOD + '\n[[cycle]]\nmove = "p1"\ndeadline = 2.0\n', "", "cycle[0]"),
    (
        "negative deadline",
        GOOD + '\n[[cycle]]\nmove = "p1"\n[[cycle]]\nwait_for = "part"\ndeadline = -1.0\n',
        "",
        "cycle[1].deadline",
    ),
    (
        "no such digital input",
        GOOD + '\n[[cycle]]\nmove = "p1"\n[[cycle]]\nwait_for = "part"\ninput = 8\n',
        "",
        "cycle[1].input",
    ),
    ("unknown on_late", GOOD + '\n[[cycle]]\nwait_for = "part"\non_late = "skip"\n', "", "on_late"),
]


@pytest.mark.parametrize(("what", "text", "path", "field"), BAD, ids=[b[0] for b in BAD])
def test_a_bad_task_file_names_the_file_the_path_and_the_field(
    what: str, text: str, path: str, field: str
) -> None:
    with pytest.raises(TaskError) as info:
        parse_task(text, "cell/bad.toml")
    msg = str(info.value)
    print(msg)
    assert msg.startswith("cell/bad.toml: ")
    assert path in msg
    assert field in msg
    assert "\n" not in msg


def test_a_missing_file_is_an_input_error(tmp_path: Path) -> None:
    with pytest.raises(TaskError, match=r"nope\.toml"):
        load_task(tmp_path / "nope.toml")


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cadence", *args], capture_output=True, text=True, timeout=120
    )


@pytest.mark.parametrize(("what", "text", "path", "field"), BAD[:7], ids=[b[0] for b in BAD[:7]])
def test_cadence_plan_exits_2_with_one_line_and_writes_nothing(
    tmp_path: Path, what: str, text: str, path: str, field: str
) -> None:
    task = tmp_path / "bad.toml"
    task.write_text(text)
    outdir = tmp_path / "out"
    proc = run_cli("plan", str(task), "--out", str(outdir))
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert str(task) in lines[0]
    assert field in lines[0]
    assert not outdir.exists()
