"""The executor's Pareto sets (DESIGN §9): fetched from the store, kept in memory and on disk, so the
robot keeps working while the store is down. A set is taken only if its content hash is the one the
executor computes from its own copy of the task and it has that task's waypoints: a set planned for other
waypoints, limits or settings is never used. A cached file that fails validation is moved aside; a set
whose trajectory the executor refuses is dropped from the cache and fetched again (``discard``)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from pathlib import Path

import msgspec
import numpy as np

from common.runtime.bus import Bus
from common.runtime.clock import first_of, pause
from common.runtime.storage import atomic_write, load_checked
from common.trajectory.planner import content_hash
from common.trajectory.task import Task
from schemas.pareto import ParetoSet
from schemas.topology import PARETO_SET, encode

log = logging.getLogger("cadence.executor")


class SetCache:
    """Owns the Pareto sets the executor runs on: fetched from the store, checked against its own task,
    cached on disk, and kept fetched while a path has none."""

    def __init__(self, bus: Bus, folder: Path, task: Task) -> None:
        self.bus, self.folder, self.task = bus, folder, task
        self.digests = {pid: content_hash(p, task.limits, task.planner) for pid, p in task.paths.items()}
        self.sets: dict[str, ParetoSet] = {}
        self.changed = asyncio.Event()  # set whenever a set arrives; the executor waits on it
        self.arrived = asyncio.Event()  # the same, for the figures' prefetch (each waiter clears its own)
        self.wanted = asyncio.Event()  # set whenever a set goes missing; the fetcher waits on it
        self.problems: list[str] = []  # cached files moved aside, for the status
        self._decoder = msgspec.msgpack.Decoder(ParetoSet)

    def file(self, pid: str) -> Path:
        return self.folder / f"{pid}.msgpack"

    def mismatch(self, pid: str, s: ParetoSet) -> str | None:
        """Why a set that decoded is not this task's set for ``pid``; None when it is."""
        own = self.task.paths[pid]
        if s.path_id != pid or s.content_hash != self.digests[pid]:
            return (
                f"the set for '{pid}' was planned from other inputs (hash {s.content_hash[:12]}, "
                f"the executor's task gives {self.digests[pid][:12]})"
            )
        if np.shape(s.waypoints) != own.waypoints.shape:
            return f"the set for '{pid}' has {len(s.waypoints)} waypoints, the task {len(own.waypoints)}"
        return None

    def load(self) -> None:
        """Sets cached by an earlier run (a restart while the store is down must not stop the robot)."""
        for pid in self.digests:
            loaded = load_checked(self.file(pid), self._decoder.decode)
            if loaded.problem:
                log.error("%s", loaded.problem)
                self.problems.append(loaded.problem)
            s = loaded.value
            if s is not None and self.mismatch(pid, s) is None:
                self.sets[pid] = s
        if self.missing():
            self.wanted.set()

    def missing(self) -> list[str]:
        return [pid for pid in self.digests if pid not in self.sets]

    def discard(self, pid: str, why: str) -> None:
        """A set the executor refused is not kept, on disk or in memory; the store is asked again."""
        if self.sets.pop(pid, None) is not None:
            log.warning("dropping the cached set for '%s': %s", pid, why)
            self.file(pid).unlink(missing_ok=True)
            self.wanted.set()

    async def fetch(self, pid: str, timeout: float) -> str | None:
        """Ask the store for one path's set; None when it was taken, else why not."""
        replies = await self.bus.get(PARETO_SET.at(pid), timeout=timeout)
        if not replies:
            return "the Pareto store did not answer"
        r = replies[0]
        if r.message is None:
            return r.error or "an empty reply"
        s: ParetoSet = r.message
        if (why := self.mismatch(pid, s)) is not None:
            return why
        if self.sets.get(pid) != s:
            try:
                await asyncio.to_thread(atomic_write, self.file(pid), encode(s))
            except OSError as exc:  # a full disk: not cached, asked again later (the arm waits for it)
                return f"cannot cache it in {self.file(pid)}: {exc.strerror or exc}"
            self.sets[pid] = s  # cached only once it passed every check and is on disk
            self.changed.set()
            self.arrived.set()
        return None

    async def fetch_missing(self, timeout: float) -> dict[str, str]:
        """Every path still without a set: {path: why not}."""
        why = {}
        for pid in self.missing():
            reason = await self.fetch(pid, timeout)
            if reason is not None:
                why[pid] = reason
        return why

    async def keep(self, timeout: float, stop: asyncio.Event, say: Callable[[str], None]) -> None:
        """Fetch what is missing (the store may still be planning; a refused set was dropped), said in the
        status (``say``), and wait while nothing is."""
        while not stop.is_set():
            if not self.missing():
                self.wanted.clear()
                await first_of(self.wanted.wait(), stop.wait())
                continue
            try:
                why = await self.fetch_missing(timeout)
            except Exception as exc:  # the store's reply or the bus: said, and asked again
                log.exception("fetching the Pareto sets failed")
                why = {"all": f"fetching failed ({exc!r})"}
            say(f"waiting for Pareto sets: {', '.join(why)}" if why else "")
            if why:
                await first_of(pause(2.0), stop.wait())
