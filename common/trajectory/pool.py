"""Planning every path of a task at once, one process per core (`cadence plan`, `cadence bench plan`).

Why forked processes: a path is planned in a few tenths of a second, so a spawned worker's start-up (the
imports, about a second) would cost more than the planning. A fork starts with everything the parent
imported. Only for a process without threads of its own that matter: the Pareto store runs a Zenoh
session, so it spawns its workers once at start (services/pareto_store/jobs.py) and keeps them.
"""

from __future__ import annotations

import multiprocessing
import threading
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing.queues import SimpleQueue

import numpy as np
from numpy.typing import NDArray

from common.robot.ur16e import JointLimits
from common.trajectory.planner import ParetoResult, plan_path
from common.trajectory.task import PathPlan, PlannerSettings

PathProgress = Callable[[str, int, int], None]  # (path id, generation, of)
_queue: SimpleQueue[tuple[str, int, int] | None] | None = None


def _init(queue: SimpleQueue[tuple[str, int, int] | None] | None) -> None:
    global _queue
    _queue = queue


def _plan(
    path: PathPlan,
    limits: JointLimits,
    settings: PlannerSettings,
    warm: Sequence[NDArray[np.float64]],
    progress: PathProgress | None = None,
) -> ParetoResult:
    """In a worker, progress goes through the queue ``_init`` left; in this process, to ``progress``."""
    q = _queue

    def report(gen: int, total: int) -> None:
        if q is not None:
            q.put((path.id, gen, total))
        elif progress is not None:
            progress(path.id, gen, total)

    return plan_path(path, limits, settings, progress=report, warm=warm)


def plan_paths(
    paths: Sequence[PathPlan],
    limits: JointLimits,
    settings: PlannerSettings,
    workers: int,
    warm: Mapping[str, Sequence[NDArray[np.float64]]] | None = None,
    progress: PathProgress | None = None,
) -> dict[str, ParetoResult]:
    """Each path's result by id; ``workers`` ≤ 1 plans in this process. A path that fails raises its
    error here, after the others have finished (none is left running)."""
    warm = warm or {}
    if workers <= 1 or len(paths) <= 1:
        _init(None)
        return {p.id: _plan(p, limits, settings, warm.get(p.id, ()), progress) for p in paths}
    ctx = multiprocessing.get_context("fork")
    queue: SimpleQueue[tuple[str, int, int] | None] | None = ctx.SimpleQueue() if progress else None
    reader = None
    if queue is not None and progress is not None:
        reader = threading.Thread(target=_relay, args=(queue, progress), daemon=True)
        reader.start()
    try:
        with ProcessPoolExecutor(min(workers, len(paths)), mp_context=ctx, initializer=_init,
                                 initargs=(queue,)) as pool:  # fmt: skip
            futures = [pool.submit(_plan, p, limits, settings, warm.get(p.id, ())) for p in paths]
        return {p.id: f.result() for p, f in zip(paths, futures, strict=True)}
    finally:
        if queue is not None and reader is not None:
            queue.put(None)
            reader.join()


def _relay(queue: SimpleQueue[tuple[str, int, int] | None], progress: PathProgress) -> None:
    while (item := queue.get()) is not None:
        progress(*item)
