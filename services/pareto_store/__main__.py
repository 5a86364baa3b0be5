"""pareto_store: plans the task program's paths (in a process pool, so queries stay answered), keeps
the sets in SQLite, and answers ``pareto/<path_id>`` and ``pareto/<path_id>/<k>`` (DESIGN §1, §3).

On a plant (issue 58) it first asks the other cells for a set planned from the same inputs, by its content
hash (``cadence/plant/sets/<hash>``), and answers theirs: cells running the same task program on the same
robot with the same limits plan it once. A set another cell answers is served only once every one of its
trajectories passes the executor's own check on this cell's path and limits."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import sqlite3
import sys
from collections.abc import AsyncIterator
from typing import Annotated

import msgspec

from common.runtime.bus import QueryError, Request
from common.runtime.clock import wall_ns
from common.runtime.config import CommonSettings
from common.runtime.errors import BusError
from common.runtime.lockstep import Inline
from common.runtime.node import Node, Out, answers, node_main
from common.runtime.resources import EXAMPLE_TASK
from common.runtime.service import service_main
from common.trajectory.shipped import shipped
from common.trajectory.task import Task, load_task
from common.trajectory.validate import set_problems
from schemas.pareto import ParetoSet, ParetoSolutionReply, PlanProgress, PlanState
from schemas.topology import PARETO_SET, PARETO_SOLUTION, PLANT_SETS, key, validated
from services.pareto_store.jobs import abandon, lower_priority, plan_job, worker_pool
from services.pareto_store.store import SetStore
from services.registry import STORE

log = logging.getLogger("cadence.pareto_store")
NAME = STORE.name


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    task: str = str(EXAMPLE_TASK)
    workers: Annotated[int, msgspec.Meta(ge=1, le=64)] = 2
    # serve the sets that ship with Cadence for a path planned from the same inputs (deploy/sets/): the
    # same trajectories on every machine; false: plan every path here
    shipped_sets: bool = True
    # ask the plant's other cells for a set planned from the same inputs before planning it (seconds to
    # wait for their answers; 0: never ask). A cell alone gets no answer but its own, at once.
    plant_sets_s: Annotated[float, msgspec.Meta(ge=0.0, le=60.0)] = 3.0


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


class ParetoStore(Node):
    role = NAME

    async def setup(self) -> None:
        self.task = load_task(self.ctx.settings.task)
        self.store, problem = await asyncio.to_thread(
            SetStore.open, self.ctx.common.data_path / "pareto.sqlite"
        )
        if problem:
            log.error("%s", problem)
            self.ctx.detail = problem
        self.digests, self.sets = await asyncio.to_thread(self.store.current, self.task)
        self.shipped = await asyncio.to_thread(self.take_shipped) if self.ctx.settings.shipped_sets else []
        self.reply_seq = itertools.count()  # the replies' own sequence, apart from the progress messages'
        if self.ctx.settings.plant_sets_s > 0:
            self.ctx.bus.asks(PLANT_SETS)  # a port opened now, asked only for a path not stored
        # a lockstep cell's planning is done in its loop's thread: its time waits for it (lockstep.py)
        self.pool = Inline() if self.ctx.common.clock.driven else worker_pool(self.ctx.settings.workers)

    def take_shipped(self) -> list[str]:
        """The paths whose sets ship with Cadence for exactly these inputs: served as shipped, the same
        bytes on every machine (common/trajectory/shipped.py), and kept in SQLite for a later warm start."""
        taken = []
        for pid, digest in self.digests.items():
            if pid not in self.sets and (s := shipped(pid, digest)) is not None:
                self.sets[pid] = s
                taken.append(pid)
                with contextlib.suppress(sqlite3.OperationalError):  # a full disk: served all the same
                    self.store.save(s)
        return taken

    def progress(self, pid: str, state: PlanState, message: str = "") -> PlanProgress:
        done = sum(1 for p in self.task.paths if p in self.sets)
        return PlanProgress(t_ns=wall_ns(), seq=0, path_id=pid, state=state,
                            done_paths=done, total_paths=len(self.task.paths), message=message)  # fmt: skip

    @answers(PARETO_SET)
    async def on_set(self, req: Request) -> ParetoSet:
        self.ctx.counters["queries"] += 1
        return answer_set(self.sets, self.task, _chunks(self.ctx.common.cell, req)[0])

    @answers(PARETO_SOLUTION)
    async def on_solution(self, req: Request) -> ParetoSolutionReply:
        self.ctx.counters["queries"] += 1
        path_id, k = _chunks(self.ctx.common.cell, req)
        return answer_solution(self.sets, self.task, path_id, k, next(self.reply_seq))

    @answers(PLANT_SETS)
    async def on_plant_set(self, req: Request) -> ParetoSet:
        """Another cell's store asks for a set by its content hash: one of this cell's, if it has it."""
        digest = req.key.rsplit("/", 1)[-1]
        found = next((s for s in self.sets.values() if s.content_hash == digest), None)
        found = found or await asyncio.to_thread(self.store.by_hash, digest)
        if found is None:
            raise QueryError(f"no set planned from {digest} in this cell")
        self.ctx.counters["sets_given"] += 1
        return found

    async def fetch(self, pid: str) -> ParetoSet | None:
        """A set for ``pid`` from another cell of the plant, checked; None when none came or none passed."""
        digest = self.digests[pid]
        try:
            replies = await self.ctx.bus.get(PLANT_SETS.at(digest), timeout=self.ctx.settings.plant_sets_s)
        except BusError as exc:
            log.warning("asking the plant for '%s': %s", pid, exc)
            return None
        for r in replies:
            if r.message is None:
                continue  # "not in this cell" (this store's own answer, and any cell's without it)
            s = msgspec.structs.replace(r.message, path_id=pid)
            problems = await asyncio.to_thread(
                set_problems, s, self.task.paths[pid], self.task.limits, digest
            )
            if problems:
                self.ctx.counters["plant_sets_refused"] += 1
                log.warning("a set for '%s' from %s refused: %s", pid, r.key, "; ".join(problems[:3]))
                continue
            return validated(s)
        return None

    async def stream(self) -> AsyncIterator[Out]:
        """Plans what SQLite does not hold, every path at once in the pool, saying how far it got. A
        path whose waypoints were edited starts from its last set (a warm start)."""
        yield [self.progress(pid, "stored") for pid in self.sets]
        missing = [pid for pid in self.task.paths if pid not in self.sets]
        for pid in missing if self.ctx.settings.plant_sets_s > 0 else []:
            if (s := await self.fetch(pid)) is None:
                continue
            with contextlib.suppress(sqlite3.OperationalError):  # a full disk: served all the same
                await asyncio.to_thread(self.store.save, s)
            self.sets[pid] = s
            self.ctx.counters["plant_sets_taken"] += 1
            log.info("'%s': planned elsewhere on the plant, taken by its hash", pid)
            yield [self.progress(pid, "stored", "taken from another cell of the plant")]
        missing = [pid for pid in missing if pid not in self.sets]
        log.info("task '%s': %d sets stored%s%s", self.task.name, len(self.sets),
                 f" ({len(self.shipped)} shipped with Cadence)" if self.shipped else "",
                 f", planning {', '.join(missing)}" if missing else "")  # fmt: skip
        if not missing:
            self.ctx.state = "serving"
            return
        self.ctx.state = f"planning {', '.join(missing)}"
        warm = await asyncio.to_thread(self.warm_starts, missing)
        futures = {}
        for pid in missing:
            futures[asyncio.wrap_future(self.pool.submit(plan_job, self.task.paths[pid], self.task,
                                                         self.task.planner, self.digests[pid],
                                                         warm.get(pid, [])))] = pid  # fmt: skip
            yield [self.progress(pid, "running", "warm start from its last set" if pid in warm else "")]
        lower_priority(self.pool)
        pending = set(futures)
        while pending:
            done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
            for fut in done:
                pid = futures[fut]
                try:
                    # what is stored and served passes the schema's checks, as any receiver will apply them
                    msg = validated(fut.result())
                except Exception as exc:  # a path that cannot be planned must not stop the others
                    log.error("planning %s failed: %s", pid, exc, exc_info=exc)
                    self.ctx.counters["plan_failures"] += 1
                    yield [self.progress(pid, "failed", str(exc))]
                    continue
                try:
                    await asyncio.to_thread(self.store.save, msg)
                except sqlite3.OperationalError as exc:  # a full disk: served from memory, planned again
                    self.ctx.detail = f"'{pid}' is not stored ({exc}): served from memory until a restart"
                    log.warning("%s", self.ctx.detail)
                self.sets[pid] = msg
                self.ctx.counters["computed"] += 1
                log.info("planned '%s': %d solutions", pid, len(msg.solutions))
                yield [self.progress(pid, "done")]
        self.ctx.state = "serving"

    def warm_starts(self, missing: list[str]) -> dict[str, list[list[float]]]:
        out = {}
        for pid in missing:
            prev = self.store.previous(pid, self.digests[pid])
            if prev is not None and len(prev.waypoints) == len(self.task.paths[pid].waypoints):
                out[pid] = [s.h for s in prev.solutions]
        return out

    async def close(self) -> None:
        abandon(self.pool)
        self.store.close()


main = node_main(ParetoStore)


def prepare(settings: Settings, common: CommonSettings) -> None:
    load_task(settings.task)  # a bad task file stops the service at start: one line, exit 2


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv, prepare)


if __name__ == "__main__":
    sys.exit(run())
