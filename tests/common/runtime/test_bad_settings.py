"""Every numeric setting has a range, checked at start: a bad value is exit 2 and one line naming the
file and the key, never a traceback, a hang or a flood (docs/operations.md). Task programs
likewise."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

from common.runtime.errors import TaskError
from common.trajectory.task import parse_task
from tests.support.tasks import GOOD

BAD = [
    ("decision_maker", "[decision_maker]\nn = 0"),
    ("decision_maker", "[decision_maker]\nrr_rest_s = nan"),
    ("decision_maker", "[decision_maker]\nrr_rest_s = -0.8"),
    ("decision_maker", "[decision_maker]\nrr_rest_s = inf"),
    ("decision_maker", "[decision_maker]\nrepublish_s = 0"),  # flooded the bus at 40-70k messages/s
    ("decision_maker", "[cadence]\nstatus_period_s = 0"),
    ("decision_maker", "[cadence]\nstatus_period_s = -1"),
    ("decision_maker", "[cadence]\nspeed = 0"),
    ("decision_maker", "[cadence]\ncell = 'a/b'"),  # a key chunk
    ("decision_maker", "[bus]\nlease_ms = 0"),
    ("decision_maker", "[decisionmaker]\nn = 15"),  # a typo in the section: was ignored in silence
    ("decision_maker", "decision_maker = 3"),
    ("pareto_store", "[pareto_store]\nworkers = 0"),
    ("hrv_analyser", "[hrv_analyser]\nwindow_s = 0"),  # hung
    ("executor", "[executor]\noverrun_limit = 0"),
    ("executor", "[executor]\ninitial_k = 0"),
    ("ecg_gateway", "[ecg_gateway]\nspeed = -1"),
    ("operator_twin", "[operator_twin.twin]\nrr_rest_s = 1e300"),
]


@pytest.mark.parametrize(("service", "text"), BAD, ids=[t.replace("\n", " ") for _, t in BAD])
def test_a_bad_setting_stops_the_service_at_start_with_one_line_and_exit_2(
    service: str, text: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "cadence.toml"
    cfg.write_text(text + "\n")
    module = importlib.import_module(f"services.{service}.__main__")
    assert module.run(["--config", str(cfg), "--data-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert "cadence.toml" in err, err
    section = text.split("]")[0].lstrip("[").split(".")[0] if text.startswith("[") else text.split()[0]
    key = text.split("\n")[-1].split("=")[0].strip() if "\n" in text else section
    assert section in err, err
    assert key in err or "unknown section" in err, err


def test_a_bad_value_from_the_environment_names_the_variable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from services.decision_maker.__main__ import run

    monkeypatch.setenv("CADENCE_DECISION_MAKER_REPUBLISH_S", "0")
    assert run(["--data-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "CADENCE_DECISION_MAKER_REPUBLISH_S" in err
    assert "republish_s" in err


def test_the_known_sections_are_the_graphs_services_and_the_common_tables(tmp_path: Path) -> None:
    """A table no service reads is refused, the UR emulator's too: it takes its options on its command
    line, and a ``[ur_emulator]`` table would look read while it is not."""
    from common.runtime.config import ConfigError, read_config
    from services.registry import IN_GRAPH, UR_EMULATOR

    cfg = tmp_path / "cadence.toml"
    cfg.write_text("".join(f"[{s.name}]\n" for s in IN_GRAPH) + "[cadence]\n[bus]\n")
    assert set(read_config(str(cfg))) == {"cadence", "bus", *(s.name for s in IN_GRAPH)}
    cfg.write_text(f"[{UR_EMULATOR.name}]\nhost = '127.0.0.2'\n")
    with pytest.raises(ConfigError, match=r"\[ur_emulator\]: unknown section"):
        read_config(str(cfg))


BAD_TASKS = [
    ("[planner]\nkappa = 1e300", "planner.kappa"),
    ("[planner]\npopulation = 100000000", "planner.population"),
    ("[planner]\nseed = -5", "planner.seed"),
    ("[planner]\nn_solutions = 5000", "planner.n_solutions"),
    ("[limits]\nunit = 'rad'\nvelocity = [1e-12, 1e-12, 1e-12, 1e-12, 1e-12, 1e-12]", "limits.velocity[0]"),
    # within the table's thousandth, but the slowest trajectory would take about 10 minutes
    ("[limits]\nunit = 'rad'\nvelocity = [0.01, 0.01, 0.01, 0.01, 0.01, 0.01]", "waypoints"),
    ("[[cycle]]\nmove = 'p1'\n[[cycle]]\nwait = 1e9", "cycle[1].wait"),
    ("[[cycle]]\nmove = 'p1'\n[[cycle]]\nwait_for = ''", "cycle[1].wait_for"),
]


@pytest.mark.parametrize(("extra", "field"), BAD_TASKS, ids=[f for _, f in BAD_TASKS])
def test_an_absurd_task_program_is_one_task_error_naming_the_field(extra: str, field: str) -> None:
    with pytest.raises(TaskError) as err:
        parse_task(GOOD + "\n" + extra + "\n", "t.toml")
    assert err.value.field == field
    assert "\n" not in str(err.value)


def test_the_automatic_resume_is_for_the_sim_only(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from services.executor.__main__ import run
    from tests.support.executor import TASK

    task_file = tmp_path / "shuttle.toml"
    task_file.write_text(TASK)
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[executor]\nbackend = 'ur_rtde'\nresume_policy = 'auto'\ntask = '{task_file}'\n")
    assert run(["--config", str(cfg), "--data-dir", str(tmp_path)]) == 2
    assert "resume_policy" in capsys.readouterr().err
