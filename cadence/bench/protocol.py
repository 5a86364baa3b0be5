"""One timing protocol for a benchmark that compares with a baseline (issue 77): equal tries, interleaved
(A B A B …), CPU time of the process tree beside wall time, the median and the spread, the host's load.

Why: the planner's ratio read 11.1× one week and 28.3× the next for the same code, because Cadence had
the best of 3 tries and the baseline the best of 1, timed one after the other in wall time on a shared
host: more tries are more chances at a quiet moment, and a burst of load hits one side only. Interleaved
equal tries meet the same host; CPU time leaves out the time a process waits for a core.
"""

from __future__ import annotations

import os
import resource
import statistics
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

T = TypeVar("T")


def tree_cpu_s() -> float:
    """CPU seconds of this process and of its children that have ended (a pool joined within a try), to
    the microsecond (``os.times`` counts in ticks of 10 ms: a 2 ms evaluation would read 0 or 10)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


@dataclass(frozen=True, slots=True)
class Side:
    """One side's tries: CPU and wall seconds, in the order they ran."""

    cpu_s: tuple[float, ...]
    wall_s: tuple[float, ...]

    @property
    def cpu(self) -> float:
        return statistics.median(self.cpu_s)

    @property
    def wall(self) -> float:
        return statistics.median(self.wall_s)

    @property
    def cpu_spread(self) -> float:
        """(max − min) / median of the CPU tries: how far one try may stray."""
        return (max(self.cpu_s) - min(self.cpu_s)) / self.cpu if self.cpu > 0 else 0.0

    def to_json(self) -> dict[str, Any]:
        return {"cpu_s": self.cpu, "wall_s": self.wall, "cpu_spread": self.cpu_spread,
                "cpu_tries_s": list(self.cpu_s), "wall_tries_s": list(self.wall_s)}  # fmt: skip


def sides_json(sides: Mapping[str, Side]) -> dict[str, dict[str, Any]]:
    return {name: side.to_json() for name, side in sides.items()}


def interleaved(sides: Mapping[str, Callable[[], T]], tries: int) -> tuple[dict[str, Side], dict[str, T]]:
    """Each side ``tries`` times, one try of each in turn; the last result of each."""
    if tries < 1:
        raise ValueError(f"tries must be at least 1, got {tries}")
    cpu: dict[str, list[float]] = {name: [] for name in sides}
    wall: dict[str, list[float]] = {name: [] for name in sides}
    last: dict[str, T] = {}
    for _ in range(tries):
        for name, run in sides.items():
            c0, w0 = tree_cpu_s(), time.perf_counter()
            last[name] = run()
            wall[name].append(time.perf_counter() - w0)
            cpu[name].append(tree_cpu_s() - c0)
    return {name: Side(tuple(cpu[name]), tuple(wall[name])) for name in sides}, last


def protocol(tries: int, workers: int) -> dict[str, Any]:
    """What a benchmark's JSON says of how it was timed (docs/development.md, "Benchmarks")."""
    return {"tries": tries, "interleaved": True, "workers": workers, "load": round(os.getloadavg()[0], 2)}
