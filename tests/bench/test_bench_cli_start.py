"""How fast the command line starts (issue 56): `cadence --version` and `--help` beside `python -c pass`
in the same run, the median of several starts each. Prints the figures and the ratio; asserts what does
not depend on the host's speed: a start that parses nothing imports neither scipy nor matplotlib."""

from __future__ import annotations

import statistics
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.bench

RUNS = 5


def median_start_s(args: list[str]) -> float:
    times = []
    for _ in range(RUNS):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, *args], capture_output=True, check=True, timeout=120)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def test_bench_the_command_line_starts_without_importing_the_world() -> None:
    base = median_start_s(["-c", "pass"])
    figures = {what: median_start_s(["-m", "cadence", *what.split()]) for what in ("--version", "--help")}
    for what, s in figures.items():
        print(f"cadence {what}: {s * 1e3:.0f} ms, python -c pass: {base * 1e3:.0f} ms ({s / base:.1f}x)")
    cmd = [sys.executable, "-X", "importtime", "-m", "cadence", "--version"]
    said = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=120).stderr
    imported = {line.split("|")[-1].strip().split(".")[0] for line in said.splitlines() if "|" in line}
    assert not imported & {"scipy", "matplotlib"}  # once 2.1 s of its 2.8 (bench's noise variants)
