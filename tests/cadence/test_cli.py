"""The command line: `cadence plan` writes the JSON contract and a figure; every command has --help."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from common.trajectory.task import load_task
from common.trajectory.validate import trajectory_problems
from tests.support.cell import CELL
from tests.support.cli import run_cli
from tests.support.tasks import GOOD


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["plan"],
        ["bench"],
        ["bench", "plan"],
        ["bench", "decide"],
        ["session"],
        ["study"],
        ["study", "analyse"],
        ["study", "fit"],
    ],
)
def test_every_command_has_help(argv: list[str]) -> None:
    proc = run_cli(*argv, "--help")
    assert proc.returncode == 0
    assert "usage: cadence" in proc.stdout


def test_plan_writes_the_json_contract_and_a_png_per_path(tmp_path: Path) -> None:
    task_file = tmp_path / "t.toml"
    task_file.write_text(GOOD)
    began = time.perf_counter()
    proc = run_cli(
        "plan", str(task_file), "--out", str(tmp_path / "o"), "--generations", "15", "--n", "6", "--seed", "4"
    )
    took = time.perf_counter() - began
    assert proc.returncode == 0, proc.stderr
    # the times it prints are true: the planning within the whole, the whole within what the run took
    said = re.search(
        r"([\d.]+) s planning on \d+ process(?:es)?, ([\d.]+) s in all", " ".join(proc.stdout.split())
    )
    assert said is not None, proc.stdout
    planning, whole = map(float, said.groups())
    assert 0.0 < planning <= whole <= took
    task = load_task(task_file)
    for pid, path in task.paths.items():
        data = json.loads((tmp_path / "o" / f"{pid}.json").read_text())
        assert set(data) >= {
            "path_id",
            "unit",
            "waypoints",
            "limits",
            "boundary",
            "front",
            "solutions",
            "constraints",
        }
        assert data["path_id"] == pid
        assert data["unit"] == "rad"
        assert data["constraints"] == "exact"
        np.testing.assert_allclose(data["waypoints"], path.waypoints)
        assert set(data["boundary"]["start"]) == {"velocity", "acceleration", "jerk"}
        sols = data["solutions"]
        assert [s["k"] for s in sols] == list(range(1, 7))
        assert all(len(s["h"]) == len(path.waypoints) + 1 for s in sols)
        assert all(abs(s["t_f"] - sum(s["h"])) < 1e-12 for s in sols)
        assert all(trajectory_problems(np.array(s["h"]), path, task.limits) == [] for s in sols)
        png = (tmp_path / "o" / f"{pid}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        assert len(png) > 20_000


def test_a_bad_flag_value_exits_2(tmp_path: Path) -> None:
    proc = run_cli("plan", "x.toml", "--out", str(tmp_path), "--n", "1")
    assert proc.returncode == 2
    assert "--n" in proc.stderr


def test_an_unplannable_path_is_one_line_naming_it(tmp_path: Path) -> None:
    # κ barely above 1 leaves no room for the acceleration limits: nothing feasible exists
    task = tmp_path / "t.toml"
    task.write_text(GOOD + "\n[planner]\nkappa = 1.01\ngenerations = 3\n")
    proc = run_cli("plan", str(task), "--out", str(tmp_path / "o"))
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert "path 'p1'" in lines[-1]
    assert "kappa" in lines[-1]
    assert not (tmp_path / "o").exists()


@pytest.mark.asyncio
async def test_a_person_signals_a_part_and_marks_an_error_only_when_something_listens(endpoint: str) -> None:
    """`cadence signal` and `cadence mark error`: the message reaches a reader of its key with its source;
    with nobody reading, the command says so instead of losing it (Zenoh drops such a put)."""
    from cadence.tools.say import tell
    from common.runtime.bus import Bus, BusConfig
    from common.runtime.errors import BusError
    from schemas import OperatorError, OperatorSignal
    from schemas.topology import OPERATOR_ERROR, OPERATOR_SIGNAL

    async with (
        await Bus.open(BusConfig(listen=[endpoint]), CELL) as cell,
        await Bus.open(BusConfig(connect=[endpoint]), CELL, role="operator") as person,
    ):
        signals = cell.subscribe(cell.key("operator/signal"), OperatorSignal)
        sent = OperatorSignal(t_ns=1, seq=0, name="part_a2", source="cli")
        assert await tell(person, OPERATOR_SIGNAL, sent, 10.0) == f"cadence/{CELL}/operator/signal"
        assert (await signals.receive(10))[1] == sent
        with pytest.raises(BusError, match=f"nothing on the bus reads cadence/{CELL}/operator/error"):
            await tell(person, OPERATOR_ERROR, OperatorError(t_ns=1, seq=0, kind="late"), 0.5)
        errors = cell.subscribe(cell.key("operator/error"), OperatorError)
        mark = OperatorError(t_ns=2, seq=0, kind="wrong_object", source="experimenter")
        await tell(person, OPERATOR_ERROR, mark, 10.0)
        assert (await errors.receive(10))[1] == mark


def test_a_signal_name_the_schema_refuses_is_an_input_error(capsys: pytest.CaptureFixture[str]) -> None:
    from cadence.cli import main

    assert main(["signal", "x" * 65, "--timeout", "0.1"]) == 2
    assert "Expected `str` of length <= 64" in capsys.readouterr().err


@pytest.mark.asyncio
async def test_a_sensor_adapter_pipes_distances_in_and_a_bad_line_is_named_and_skipped(endpoint: str) -> None:
    """`cadence separation -`: a scanner driver's lines become operator/separation messages; a line that
    is not a distance (or is out of the schema's range) is reported by number and the others still go."""
    from common.runtime.bus import Bus, BusConfig
    from schemas import Separation

    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as cell:
        heard = cell.subscribe(cell.key("operator/separation/scanner_front"), Separation)  # its own key
        relay = ["separation", "-", "--source", "scanner:front", "--connect", endpoint]
        proc = subprocess.Popen([sys.executable, "-m", "cadence", *relay], stdin=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip
        assert proc.stdin is not None
        proc.stdin.write("near\n-3\n")
        got = None
        async with asyncio.timeout(30):
            while got is None:  # the relay's first puts may precede its session knowing the reader
                proc.stdin.write("1.25 0.04\n")
                proc.stdin.flush()
                with contextlib.suppress(TimeoutError):
                    got = (await heard.receive(0.2))[1]
        proc.stdin.close()
        rc = await asyncio.to_thread(proc.wait, 30)
    assert (got.distance_m, got.age_s, got.source) == (1.25, 0.04, "scanner:front")
    stderr = proc.stderr.read() if proc.stderr else ""
    assert "stdin line 1: 'near'" in stderr
    assert "stdin line 2: '-3'" in stderr
    assert rc == 1


@pytest.mark.asyncio
async def test_the_sensor_adapter_skips_a_bad_byte_a_huge_line_and_an_underscored_number(
    endpoint: str,
) -> None:
    """One invalid UTF-8 byte once killed the adapter, a 10 MB line stalled it for 35 s, and `1_0` was
    read as 10 m: each is now a line reported by number and skipped, and the lines after it still go."""
    from common.runtime.bus import Bus, BusConfig
    from schemas import Separation

    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as cell:
        heard = cell.subscribe(cell.key("operator/separation/scanner_front"), Separation)  # its own key
        relay = ["separation", "-", "--source", "scanner:front", "--connect", endpoint]
        proc = subprocess.Popen([sys.executable, "-m", "cadence", *relay], stdin=subprocess.PIPE,
                                stderr=subprocess.PIPE)  # fmt: skip
        assert proc.stdin is not None
        proc.stdin.write(b"2.5\xff\n" + b"7" * 10_000_000 + b"\n1_0\n")
        got = None
        async with asyncio.timeout(60):
            while got is None:  # the relay's first puts may precede its session knowing the reader
                proc.stdin.write(b"1.5\n")
                proc.stdin.flush()
                with contextlib.suppress(TimeoutError):
                    got = (await heard.receive(0.2))[1]
        proc.stdin.close()
        rc = await asyncio.to_thread(proc.wait, 30)
    stderr = (proc.stderr.read() if proc.stderr else b"").decode()
    assert got.distance_m == 1.5
    assert rc == 1
    assert "stdin line 1: not UTF-8" in stderr
    assert "stdin line 2:" in stderr
    assert "over 256 bytes" in stderr
    assert "stdin line 3: '1_0': not a decimal number" in stderr


def test_a_sensors_points_lines_are_placed_by_its_pose_and_a_bad_one_is_named() -> None:
    """`cadence separation --points`: 'X Y [Z]' in the sensor's frame, placed in the cell frame by --pose
    (the message says so), or left for the executor to place by the source's configured pose."""
    from cadence.tools.say import Form, parse_pose, separation_line
    from common.runtime.errors import InputError

    behind = Form(points=True, pose=parse_pose("3,0,180"))  # at x = 3 m, facing the robot's base
    m = separation_line("1.5 0 0.5", "cam", 7, 11, behind)
    assert m.points == ((pytest.approx(1.5), pytest.approx(0.0, abs=1e-12), 0.5),)
    assert (m.placed, m.to_robot, m.seq, m.t_ns) == (True, False, 7, 11)
    assert m.distance_m == pytest.approx(math.hypot(1.5, 0.5))  # the sensor's own range to it
    own = separation_line("1.5 0", "cam", 0, 0, Form(points=True))
    assert (own.points, own.placed) == (((1.5, 0.0, 0.0),), False)
    plain = separation_line("2.0", "scanner", 0, 0, Form(to_robot=True))
    assert (plain.distance_m, plain.to_robot, plain.points) == (2.0, True, ())
    with pytest.raises(InputError, match=r"expected X Y \[Z\]"):
        separation_line("1.5", "cam", 0, 0, Form(points=True))
    with pytest.raises(ValueError, match="X,Y,YAW"):
        parse_pose("3,0")
    r = subprocess.run([sys.executable, "-m", "cadence", "separation", "1", "--pose", "1,2,3"],
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == 2
    assert r.stderr.strip() == "cadence: error: --pose places points: it goes with --points"


def test_a_misspelled_bus_variable_stops_a_tool_as_it_stops_every_service() -> None:
    """`cadence top` ignored CADENCE_BUS_CONECT, which every service refuses (issue 43)."""
    import os

    env = {**os.environ, "CADENCE_BUS_CONECT": "['tcp/127.0.0.1:7447']"}
    proc = subprocess.run([sys.executable, "-m", "cadence", "top"], env=env, capture_output=True, text=True,
                          timeout=60)  # fmt: skip
    assert proc.returncode == 2
    assert "CADENCE_BUS_CONECT" in proc.stderr
    assert "conect" in proc.stderr


def test_a_demo_speed_every_service_would_refuse_is_refused_at_the_command() -> None:
    """`cadence demo --speed 2000` was accepted, and every service refused it at start: a silent restart
    loop (issue 43). One check, at the command, with the range."""
    proc = subprocess.run([sys.executable, "-m", "cadence", "demo", "--speed", "2000"], capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2
    assert "--speed: must be at most 1000" in proc.stderr


def test_what_only_the_process_cell_has_is_refused_in_lockstep_with_the_flag_that_gives_it() -> None:
    """The lockstep demo has no process to kill and no router to join: said at the command, not found out
    from a run that ignored them."""
    proc = subprocess.run([sys.executable, "-m", "cadence", "demo", "--kill", "executor@30", "--listen",
                           "tcp/127.0.0.1:7447"], capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2
    assert "--kill and --listen need --processes" in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "cadence", "demo", "--processes", "--speed", "max"],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2
    assert "--speed max runs the cell in lockstep" in proc.stderr


def test_a_misspelt_option_is_said_with_the_commands_own_usage() -> None:
    """`cadence demo --duraton 10` showed the top-level usage, which names no option of the demo."""
    r = subprocess.run([sys.executable, "-m", "cadence", "demo", "--duraton", "10"], capture_output=True,
                       text=True, timeout=60)  # fmt: skip
    assert r.returncode == 2
    assert r.stderr.startswith("usage: cadence demo")
    assert "--duration" in r.stderr  # its usage names the option meant
    assert r.stderr.strip().endswith("cadence demo: error: unrecognized arguments: --duraton 10")
