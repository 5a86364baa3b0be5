"""A run's folder (cadence/demo/folder.py): a second demo into a finished folder keeps the first's report
and logs, moved aside, and the services' data stays for it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from cadence.demo.folder import keep_previous
from common.runtime.errors import InputError


def finished_run(folder: Path, summary: str, when: float) -> None:
    (folder / "logs").mkdir(parents=True, exist_ok=True)
    (folder / "logs" / "executor.log").write_text(f"log of {summary}")
    (folder / "data").mkdir(exist_ok=True)
    (folder / "data" / "pareto.sqlite").write_text("sets")
    (folder / "index.html").write_text(f"report of {summary}")
    (folder / "separation.png").write_text(f"figure of {summary}")
    (folder / "summary.json").write_text(summary)
    os.utime(folder / "summary.json", (when, when))


def test_a_finished_runs_report_and_logs_are_kept_aside_and_its_data_stays(tmp_path: Path) -> None:
    assert keep_previous(tmp_path) is None  # nothing finished there: nothing moved
    finished_run(tmp_path, "first", 1_700_000_000)
    first = keep_previous(tmp_path)
    finished_run(tmp_path, "second", 1_700_000_000)  # ended within the same second
    second = keep_previous(tmp_path)
    assert first is not None and second is not None and first != second
    assert (first / "summary.json").read_text() == "first"
    assert (first / "logs" / "executor.log").read_text() == "log of first"
    assert (second / "index.html").read_text() == "report of second"
    assert (second / "separation.png").read_text() == "figure of second"
    assert not (tmp_path / "summary.json").exists() and not (tmp_path / "logs").exists()
    assert (tmp_path / "data" / "pareto.sqlite").read_text() == "sets"  # the next run starts from it


def test_a_folder_that_cannot_keep_them_is_one_clear_error(tmp_path: Path) -> None:
    finished_run(tmp_path, "first", 1_700_000_000)
    (tmp_path / "previous").write_text("a file where the folder would go")
    with pytest.raises(InputError, match="cannot be kept"):
        keep_previous(tmp_path)
    assert (tmp_path / "summary.json").read_text() == "first"  # nothing lost
