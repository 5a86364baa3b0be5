"""Benchmark of the Pareto store on loopback: a stored set's query latency, and the latency of queries
while the store is planning (its planning runs in a worker process, so the event loop stays free)."""

from __future__ import annotations

import asyncio

import pytest

from cadence.bench.store import StoreBench, bench_store
from tests.support.paths import BENCH_QUICK, EXAMPLE_TASK

pytestmark = pytest.mark.bench
QUERIES = 50 if BENCH_QUICK else 200


def test_bench_store_query_latency() -> None:
    r = asyncio.run(bench_store(str(EXAMPLE_TASK), queries=QUERIES))
    p = StoreBench.pct
    stored, during = r.stored_ms, r.during_planning_ms
    print(
        f"\nstored set ({len(stored)} queries): p50 {p(stored, 50):.2f} ms, p99 {p(stored, 99):.2f} ms\n"
        f"while planning ({len(during)} queries): p50 {p(during, 50):.2f} ms, "
        f"p99.9 {p(during, 99.9):.2f} ms, "
        f"max {max(during, default=float('nan')):.2f} ms"
    )
    assert len(r.stored_ms) == QUERIES
    assert len(r.during_planning_ms) > 10
