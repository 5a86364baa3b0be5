"""pareto_store: plans the task program's paths (in a process pool, so queries stay answered), keeps
the sets in SQLite, and answers ``pareto/<path_id>`` and ``pareto/<path_id>/<k>`` (DESIGN §1, §3)."""

from __future__ import annotations

import asyncio
import itertools
import logging
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Annotated

import msgspec

from common.runtime.bus import QueryError, Request
from common.runtime.config import CommonSettings
from common.runtime.lifetime import die_with_parent
from common.runtime.resources import EXAMPLE_TASK
from common.runtime.service import ServiceContext, service_main
from common.trajectory.planner import content_hash
from common.trajectory.task import Task, load_task
from schemas.pareto import ParetoSet, ParetoSolutionReply, PlanProgress, PlanState
from schemas.topology import PARETO_SET, PARETO_SOLUTION, PLAN_PROGRESS, key, validated
from services.pareto_store.jobs import lower_priority, plan_job
from services.pareto_store.store import SetStore

log = logging.getLogger("cadence.pareto_store")
NAME = "pareto_store"


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    task: str = str(EXAMPLE_TASK)
    workers: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1


def _chunks(cell: str, req: Request) -> list[str]:
    return req.key.removeprefix(key(cell, "pareto/")).split("/")


def answer_set(sets: dict[str, ParetoSet], task: Task, path_id: str) -> ParetoSet:
    """The reply to ``pareto/<path_id>``: the set, or a QueryError that says why not."""
    if path_id not in task.paths:
        raise QueryError(f"unknown path '{path_id}'; this task has {', '.join(task.paths)}")
    if path_id not in sets:
        raise QueryError(f"path '{path_id}' is being computed; subscribe to pareto/progress")
    return sets[path_id]


def answer_solution(
    sets: dict[str, ParetoSet], task: Task, path_id: str, k_text: str, seq: int
) -> ParetoSolutionReply:
    """The reply to ``pareto/<path_id>/<k>``: one solution, numbered from 1 as the selection's k."""
    s = answer_set(sets, task, path_id)
    try:
        k = int(k_text)
    except ValueError:
        raise QueryError(f"k must be an integer, got {k_text!r}") from None
    if not 1 <= k <= len(s.solutions):
        raise QueryError(f"path '{path_id}' has solutions k = 1 … {len(s.solutions)}, not {k_text}")
    return ParetoSolutionReply(
        t_ns=s.t_ns,
        seq=seq,
        path_id=path_id,
        content_hash=s.content_hash,
        n=len(s.solutions),
        solution=s.solutions[k - 1],
    )


async def main(ctx: ServiceContext) -> None:
    settings: Settings = ctx.settings
    task = load_task(settings.task)
    store, problem = await asyncio.to_thread(SetStore.open, ctx.common.data_path / "pareto.sqlite")
    if problem:
        log.error("%s", problem)
        ctx.detail = problem
    sets: dict[str, ParetoSet] = {}
    digests = {pid: content_hash(p, task.limits, task.planner) for pid, p in task.paths.items()}
    for pid, digest in digests.items():
        stored = await asyncio.to_thread(store.load, pid, digest)
        if stored is not None:
            sets[pid] = stored
    progress_out = ctx.bus.publisher(PLAN_PROGRESS)
    reply_seq = itertools.count()  # the replies' own sequence, apart from the progress messages'

    def progress(pid: str, state: PlanState, message: str = "") -> None:
        done = sum(1 for p in task.paths if p in sets)
        progress_out.put(
            PlanProgress(
                t_ns=time.time_ns(),
                seq=progress_out.next_seq(),
                path_id=pid,
                state=state,
                done_paths=done,
                total_paths=len(task.paths),
                message=message,
            ),
        )

    async def on_set(req: Request) -> ParetoSet:
        ctx.counters["queries"] += 1
        return answer_set(sets, task, _chunks(ctx.common.cell, req)[0])

    async def on_solution(req: Request) -> ParetoSolutionReply:
        ctx.counters["queries"] += 1
        path_id, k = _chunks(ctx.common.cell, req)
        return answer_solution(sets, task, path_id, k, next(reply_seq))

    ctx.bus.serve(PARETO_SET, on_set)
    ctx.bus.serve(PARETO_SOLUTION, on_solution)
    for pid in sets:
        progress(pid, "stored")
    missing = [pid for pid in task.paths if pid not in sets]
    # started from this (the loop's) thread by submit(); a worker outlives no store, however it ends
    pool = ProcessPoolExecutor(
        max_workers=settings.workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=die_with_parent,
        initargs=(os.getpid(),),
    )
    try:
        for pid in missing:
            progress(pid, "running")
            ctx.state = f"planning {pid}"
            try:
                future = pool.submit(plan_job, task.paths[pid], task, task.planner, digests[pid])
                lower_priority(pool)
                msg = await asyncio.wrap_future(future)
                # what is stored and served passes the schema's checks, as any receiver will apply them
                msg = validated(msg)
            except Exception as exc:  # a path that cannot be planned must not stop the others
                log.exception("planning %s failed", pid)
                ctx.counters["plan_failures"] += 1
                progress(pid, "failed", str(exc))
                continue
            await asyncio.to_thread(store.save, msg)
            sets[pid] = msg
            ctx.counters["computed"] += 1
            progress(pid, "done")
            if ctx.stop.is_set():
                break
        ctx.state = "serving"
        await ctx.stop.wait()
    finally:
        # A plan still in flight is abandoned: its worker is ended, not waited for.
        workers = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in workers:
            proc.terminate()
        store.close()


def prepare(settings: Settings, common: CommonSettings) -> None:
    load_task(settings.task)  # a bad task file stops the service at start: one line, exit 2


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv, prepare)


if __name__ == "__main__":
    sys.exit(run())
