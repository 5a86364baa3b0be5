"""Benchmark of the servo loop on the sim backend (`cadence bench executor` in short): tick error
percentiles, overruns and the time to prepare a path's samples. Figures are printed, not asserted:
the machines are shared and noisy."""

from __future__ import annotations

import json
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


@pytest.mark.bench
def test_bench_executor_under_load_prints_the_servo_beside_cyclictest_and_the_adoption() -> None:
    """The load mode (issue 73), 10 s: the figures are there and the executor ran; no timing is asserted."""
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "bench", "executor", "--load", "--seconds", "10"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    last = json.loads(r.stdout.strip().splitlines()[-1])
    servo, yardstick, adoption = last["servo"], last["cyclictest"], last["adoption"]
    assert servo["ticks"] > 1000  # the arm ran through the window
    for k in ("overruns", "longest_overrun_run", "p99_9_us", "max_us"):
        assert isinstance(servo[k], int), servo
    assert "error" in yardstick or {"ticks", "late", "p99_9_us"} <= yardstick.keys(), yardstick
    assert {"n", "p50_ms", "p99_9_ms", "max_ms"} <= adoption.keys() and adoption["readings"] > 100
    assert last["flood"]["signals"] > 0
    print(r.stdout)
