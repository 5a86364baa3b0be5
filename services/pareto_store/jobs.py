"""The work the store's process pool does. A module of its own, not __main__, so that spawned workers
can import it whether the service was started as `python -m services.pareto_store` or in-process."""

from __future__ import annotations

import contextlib
import multiprocessing
import os
from concurrent.futures import Executor, ProcessPoolExecutor

import numpy as np

from common.runtime.lifetime import die_with_parent
from common.trajectory.planner import plan_path
from common.trajectory.shipped import as_message
from common.trajectory.task import PathPlan, PlannerSettings, Task
from schemas.pareto import ParetoSet

_NICE = 10


def plan_job(
    path: PathPlan, task: Task, settings: PlannerSettings, digest: str, warm: list[list[float]] | None = None
) -> ParetoSet:
    """Runs in a worker process: plan one path (seeded by ``warm``, the interval vectors of its last set
    before an edit) and return it as the wire message."""
    return as_message(plan_path(path, task.limits, settings, warm=[np.array(h) for h in warm or []]), digest)


def lower_priority(pool: Executor) -> None:
    """Planning is background work: the service's loop and its queries come first. The parent renices
    the workers as soon as they exist, so even their start-up (the imports) runs at low priority."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, proc.pid, _NICE)


def worker_pool(workers: int) -> ProcessPoolExecutor:
    """Spawned (a fork would copy the service's threads), from the loop's thread; a worker outlives no
    store, however it ends."""
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=die_with_parent, initargs=(os.getpid(),))  # fmt: skip


def abandon(pool: Executor) -> None:
    """A plan still in flight is abandoned: its worker is ended, not waited for."""
    workers = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in workers:
        proc.terminate()
