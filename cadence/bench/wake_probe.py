"""The host's own delay in `cadence bench plant`: a thread at a cell's priority asks to wake every 5 ms
and notes how late it woke (`python -m cadence.bench.wake_probe UNTIL_NS OUT.json`; the bench starts
it). A message through a cell's router waits for a core at least twice (the router, the reader) and
often more; on a host whose threads wait milliseconds for one, that is the tail of the in-cell latency
whatever the mesh does. So the bench prints this beside it, phase by phase: on a shared host, the
latencies are judged against this host's own delay in the same run, not against a fixed number.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import msgspec

PERIOD_NS = 5_000_000


def probe(until_ns: int) -> list[tuple[int, int]]:
    """(when it was due, monotonic ns; how late it woke, µs), until ``until_ns``. A wake later than a
    period starts the count again from it: no burst of wakes to catch up, each one a fresh sleep."""
    late: list[tuple[int, int]] = []
    due = time.monotonic_ns() + PERIOD_NS
    while due < until_ns:
        wait = due - time.monotonic_ns()
        if wait > 0:
            time.sleep(wait / 1e9)
        now = time.monotonic_ns()
        late.append((due, (now - due) // 1000))
        due = max(due, now - PERIOD_NS) + PERIOD_NS
    return late


if __name__ == "__main__":
    until, out = int(sys.argv[1]), sys.argv[2]
    Path(out).write_bytes(msgspec.json.encode(probe(until)))
