"""Benchmark of the servo loop on the sim backend (`cadence bench executor` in short): tick error
percentiles, overruns and the time to prepare a path's samples. Figures are printed, not asserted:
the machines are shared and noisy."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.support.emulator import check_bench_executor_output


@pytest.mark.bench
def test_bench_executor_prints_its_figures_as_the_last_json_line() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "bench", "executor", "--backend", "sim", "--seconds", "3"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    check_bench_executor_output(r)


def test_an_unreachable_controller_is_one_clear_line_and_exit_1() -> None:
    """Not a benchmark: its refusal, in every run."""
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "bench", "executor", "--backend", "ur_rtde", "--host", "127.0.0.9"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 1
    assert "UR controller at 127.0.0.9" in r.stderr
    assert "Traceback" not in r.stderr
