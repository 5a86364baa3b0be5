"""The executor's Pareto sets (DESIGN §9): fetched from the store, kept in memory and on disk, so the
robot keeps working while the store is down. A set is taken only if its content hash is the one the
executor computes from its own copy of the task: a set planned for other waypoints, limits or settings
is never used."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import msgspec

from common.bus import Bus
from common.planner import content_hash
from common.storage import atomic_write
from common.task import Task
from schemas.pareto import ParetoSet
from schemas.topology import encode

log = logging.getLogger("cadence.executor")


class SetCache:
    def __init__(self, bus: Bus, folder: Path, task: Task) -> None:
        self.bus, self.folder = bus, folder
        self.digests = {pid: content_hash(p, task.limits, task.planner) for pid, p in task.paths.items()}
        self.sets: dict[str, ParetoSet] = {}
        self.changed = asyncio.Event()  # set whenever a set arrives; the executor waits on it
        self._decoder = msgspec.msgpack.Decoder(ParetoSet)

    def file(self, pid: str) -> Path:
        return self.folder / f"{pid}.msgpack"

    def load(self) -> None:
        """Sets cached by an earlier run (a restart while the store is down must not stop the robot)."""
        for pid, digest in self.digests.items():
            try:
                s = self._decoder.decode(self.file(pid).read_bytes())
            except FileNotFoundError:
                continue
            except (OSError, msgspec.DecodeError) as exc:
                log.warning("ignoring the cached set %s: %s", self.file(pid), exc)
                continue
            if s.content_hash == digest and s.path_id == pid:
                self.sets[pid] = s

    def missing(self) -> list[str]:
        return [pid for pid in self.digests if pid not in self.sets]

    async def fetch(self, pid: str, timeout: float) -> str | None:
        """Ask the store for one path's set; None when it was taken, else why not."""
        replies = await self.bus.get(self.bus.key(f"pareto/{pid}"), ParetoSet, timeout)
        if not replies:
            return "the Pareto store did not answer"
        r = replies[0]
        if r.message is None:
            return r.error or "an empty reply"
        s: ParetoSet = r.message
        if s.path_id != pid or s.content_hash != self.digests[pid]:
            return (
                f"the store's set for '{pid}' was planned from other inputs (hash {s.content_hash[:12]}, "
                f"the executor's task gives {self.digests[pid][:12]})"
            )
        if self.sets.get(pid) != s:
            self.sets[pid] = s
            await asyncio.to_thread(atomic_write, self.file(pid), encode(s))
            self.changed.set()
        return None

    async def fetch_missing(self, timeout: float) -> dict[str, str]:
        """Every path still without a set: {path: why not}."""
        why = {}
        for pid in self.missing():
            reason = await self.fetch(pid, timeout)
            if reason is not None:
                why[pid] = reason
        return why
