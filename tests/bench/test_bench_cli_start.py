"""How fast the command line starts (issue 56): `cadence --version` and `--help` beside `python -c pass`
in the same run, the median of several starts each, CPU and wall. Prints the figures; asserts what does
not depend on the host's speed: a start that parses nothing imports neither scipy nor matplotlib."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from cadence.bench.protocol import interleaved, protocol

pytestmark = pytest.mark.bench

TRIES = 5


def started(args: list[str]) -> object:
    return subprocess.run([sys.executable, *args], capture_output=True, check=True, timeout=120)


def test_bench_the_command_line_starts_without_importing_the_world() -> None:
    """Under the benchmarks' protocol (cadence/bench/protocol.py): equal tries, interleaved, each start's
    CPU (the child's, once it ended) beside its wall time; the baseline is Python starting alone."""
    argv = {
        "": ["-c", "pass"],
        "--version": ["-m", "cadence", "--version"],
        "--help": ["-m", "cadence", "--help"],
    }
    sides, _ = interleaved({what: (lambda a=a: started(a)) for what, a in argv.items()}, TRIES)
    base = sides[""]
    for what in ("--version", "--help"):
        s = sides[what]
        print(f"cadence {what}: {s.cpu * 1e3:.0f} ms CPU ({s.wall * 1e3:.0f} ms wall), python -c pass: "
              f"{base.cpu * 1e3:.0f} ms CPU ({base.wall * 1e3:.0f}), "
              f"{s.cpu - base.cpu:.3f} s above it")  # fmt: skip
    print(json.dumps({"start": {w or "python -c pass": sides[w].to_json() for w in sides},
                      "protocol": protocol(TRIES, 1)}))  # fmt: skip
    cmd = [sys.executable, "-X", "importtime", "-m", "cadence", "--version"]
    said = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=120).stderr
    imported = {line.split("|")[-1].strip().split(".")[0] for line in said.splitlines() if "|" in line}
    assert not imported & {"scipy", "matplotlib"}  # once 2.1 s of its 2.8 (bench's noise variants)
