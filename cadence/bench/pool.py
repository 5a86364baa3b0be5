"""The benchmarks' worker processes."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor


def spawned_pool(jobs: int | None, tasks: int) -> ProcessPoolExecutor:
    """A pool of ``jobs`` worker processes (default: one per core, never more than ``tasks``), spawned,
    not forked: the caller may hold threads (a bus session) whose locks a fork would copy held."""
    import multiprocessing
    import os

    n = max(1, min(jobs or os.cpu_count() or 1, tasks or 1))
    return ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"))
