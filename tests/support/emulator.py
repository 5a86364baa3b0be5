"""The UR controller emulator as its own process, for the tests of the real backend at its protocol
boundary, and what `cadence bench executor` must print."""

from __future__ import annotations

import json
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

# The controller stops the program when kicks stop for 1/WATCHDOG_HZ s. On a loaded 2-core CI machine the
# emulator's own threads can fall 100 ms behind (the 10 Hz default), and with a third load (a venv being
# built beside two busy loops) over 0.5 s: the tests give it 1 s, the least the executor's settings allow.
WATCHDOG_HZ = 1.0


def free_loopback() -> str:
    """A 127.x address on which the emulator's three ports are free (parallel runs, leftovers)."""
    for _ in range(50):
        host = f"127.0.{random.randint(1, 254)}.{random.randint(2, 254)}"
        try:
            for port in (30004, 29999, 30003):
                with socket.socket() as s:
                    s.bind((host, port))
            return host
        except OSError:
            continue
    raise RuntimeError("no free loopback address for the emulator")


class EmulatorProcess:
    def __init__(
        self, host: str, recipes: Path | None = None, q0_deg: list[float] | None = None, *extra: str
    ) -> None:
        self.host = host
        cmd = [sys.executable, "-m", "services.ur_emulator", "--host", host, *extra]
        if recipes is not None:
            cmd += ["--recipes-out", str(recipes)]
        if q0_deg is not None:
            cmd += ["--q0-deg", *map(str, q0_deg)]
        self.proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        self.lines: list[str] = []
        ready = threading.Event()

        def read() -> None:
            for line in self.proc.stdout:
                self.lines.append(line.rstrip())
                if line.startswith("ready"):
                    ready.set()

        threading.Thread(target=read, daemon=True).start()
        if not ready.wait(20):
            self.proc.kill()
            raise RuntimeError(f"the emulator did not start: {self.lines}")

    def wait_for_line(self, text: str, timeout: float = 10.0) -> str:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for line in self.lines:
                if text in line:
                    return line
            time.sleep(0.02)  # polling the reader thread's list; bounded by the timeout
        raise AssertionError(f"no line with {text!r} in {self.lines}")

    def say(self, line: str) -> None:
        """A line on the emulator's standard input (``estop``, ``di N 1``)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def press(self, n: int, on: bool = True) -> None:
        """A button on standard digital input ``n`` (the emulator's stdin command)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(f"di {n} {int(on)}\n")
        self.proc.stdin.flush()

    def stop(self, sig: int = signal.SIGTERM) -> int:
        self.proc.send_signal(sig)
        return self.proc.wait(10)


def check_bench_executor_output(r: subprocess.CompletedProcess[str]) -> dict[str, int | float]:
    """The bench's contract, whichever way the run ended: the figures as the last JSON line, and exit 0
    after the whole run, or exit 1 with the reason when the loop stopped the robot early (a shared
    machine's stall of 10 ms is 5 overruns in a row, the executor's stop; the figures say so)."""
    print("\n" + r.stdout)
    figures = json.loads(r.stdout.strip().splitlines()[-1])
    assert set(figures) == EXPECTED
    assert figures["period_us"] == 2000
    assert figures["prepare_ms"] > 0
    assert figures["p50_err_us"] <= figures["p99_err_us"] <= figures["p999_err_us"] <= figures["max_err_us"]
    if r.returncode == 0:
        assert figures["ticks"] >= 1500, figures
    else:
        assert r.returncode == 1, r.stderr
        assert "ended a motion early" in r.stderr, r.stderr
        assert figures["overruns"] > 0 or "control script" in r.stderr, (figures, r.stderr)
    return figures


EXPECTED = {
    "period_us",
    "ticks",
    "p50_err_us",
    "p99_err_us",
    "p999_err_us",
    "max_err_us",
    "longest_overrun_run",
    "overruns",
    "prepare_ms",
}
