"""Benchmark of the servo loop on the sim backend (`cadence bench executor` in short): tick error
percentiles, overruns and the time to prepare a path's samples. Figures are printed, not asserted:
the machines are shared and noisy."""

from __future__ import annotations

import json
import subprocess
import sys

EXPECTED = {
    "period_us",
    "ticks",
    "p50_err_us",
    "p99_err_us",
    "p999_err_us",
    "max_err_us",
    "overruns",
    "prepare_ms",
}


def test_bench_executor_prints_its_figures_as_the_last_json_line() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "bench", "executor", "--backend", "sim", "--seconds", "3"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    print("\n" + r.stdout)
    figures = json.loads(r.stdout.strip().splitlines()[-1])
    assert set(figures) == EXPECTED and figures["period_us"] == 2000
    assert figures["ticks"] >= 1500 and figures["prepare_ms"] > 0
    assert figures["p50_err_us"] <= figures["p99_err_us"] <= figures["p999_err_us"] <= figures["max_err_us"]


def test_an_unreachable_controller_is_one_clear_line_and_exit_1() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "bench", "executor", "--backend", "ur_rtde", "--host", "127.0.0.9"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 1 and "UR controller at 127.0.0.9" in r.stderr and "Traceback" not in r.stderr
