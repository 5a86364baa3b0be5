"""pareto_store: plans the task program's paths (in a process pool, so queries stay answered), keeps
the sets in SQLite, and answers ``pareto/<path_id>`` and ``pareto/<path_id>/<k>`` (DESIGN §1, §3)."""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Annotated

import msgspec

from common.bus import QueryError, Request
from common.lifetime import die_with_parent
from common.planner import content_hash
from common.resources import EXAMPLE_TASK
from common.service import CommonSettings, ServiceContext, service_main
from common.task import Task, load_task
from schemas.pareto import ParetoSet, ParetoSolutionReply, PlanProgress
from schemas.topology import encode
from services.pareto_store.jobs import lower_priority, plan_job
from services.pareto_store.store import SetStore

log = logging.getLogger("cadence.pareto_store")
NAME = "pareto_store"
_SET_DECODER = msgspec.msgpack.Decoder(ParetoSet)


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    task: str = str(EXAMPLE_TASK)
    workers: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1


def answer(
    sets: dict[str, ParetoSet], task: Task, cell: str, req: Request, seq: int
) -> ParetoSet | ParetoSolutionReply:
    """The reply to a query on ``cadence/<cell>/pareto/…``: a set, one solution, or a QueryError."""
    rest = req.key.split(f"cadence/{cell}/pareto/", 1)[-1].split("/")
    path_id = rest[0]
    if path_id not in task.paths:
        raise QueryError(f"unknown path '{path_id}'; this task has {', '.join(task.paths)}")
    if path_id not in sets:
        raise QueryError(f"path '{path_id}' is being computed; subscribe to pareto/progress")
    s = sets[path_id]
    if len(rest) == 1:
        return s
    try:
        k = int(rest[1])
    except ValueError:
        raise QueryError(f"k must be an integer, got {rest[1]!r}") from None
    if not 1 <= k <= len(s.solutions) or len(rest) > 2:
        raise QueryError(
            f"path '{path_id}' has solutions k = 1 … {len(s.solutions)}, not {'/'.join(rest[1:])}"
        )
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
    seq = 0
    progress_key = ctx.bus.key("pareto/progress")

    def progress(pid: str, state: str, message: str = "") -> None:
        nonlocal seq
        done = sum(1 for p in task.paths if p in sets)
        ctx.bus.put(
            progress_key,
            PlanProgress(
                t_ns=time.time_ns(),
                seq=seq,
                path_id=pid,
                state=state,
                done_paths=done,
                total_paths=len(task.paths),
                message=message,
            ),
        )
        seq += 1

    async def handler(req: Request) -> ParetoSet | ParetoSolutionReply:
        nonlocal seq
        ctx.counters["queries"] += 1
        seq += 1
        return answer(sets, task, ctx.common.cell, req, seq)

    ctx.bus.serve(ctx.bus.key("pareto/**"), handler)
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
                msg = _SET_DECODER.decode(encode(msg))
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
