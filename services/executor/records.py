"""What the executor keeps on disk before what depends on it (DESIGN §9): the selection applied, the cycle
in progress, the path the arm moves on, a stop latched (services/executor/persist.py). A disk that cannot
take a record is a state, not a crash: said once, and where the arm would move on an unwritten record,
the arm is held still until the disk takes it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from functools import partial

from common.runtime.clock import first_of, pause
from common.safety.states import Event, State
from schemas.decision import Selection
from services.executor.kit import Kit, Safety
from services.executor.persist import ExecutorStore

log = logging.getLogger("cadence.executor")

RETRY_S = 2.0  # a refused write is tried again this often (loop seconds) while it holds the arm


class Records:
    """Owns the executor's record on disk and every write of it: the writes in the background, the hold of
    the arm while the disk refuses, and the status's word on it."""

    def __init__(self, kit: Kit, store: ExecutorStore, safety: Safety) -> None:
        self.kit, self.store, self.safety = kit, store, safety
        self.say = kit.note("disk")
        self.unwritten: str | None = None  # what could not be written (a full disk), while it cannot
        self.held_unwritten = False  # the arm held for it: said once, apart from the first refusal

    def received(self, sel: Selection) -> None:
        """A selection decided, kept in the background (a restart goes on at the newest k decided)."""
        self.in_background(partial(self.store.received, sel))

    def latch(self, why: str | None) -> None:
        """A stop latched (or cleared by a resume), kept on disk as a selection is."""
        self.in_background(partial(self.store.latch, why))

    def in_background(self, write: Callable[[], None]) -> None:
        """In the node's task group; where the node no longer runs (a stop latched as it ends), now."""
        if self.kit.start_soon(self.keep(write, hold=False), "a record") is None:
            try:
                write()
            except OSError as exc:
                log.error("cannot write %s: %s", self.store.path, exc.strerror or exc)

    async def applied(self, sel: Selection, hold: bool = True) -> bool:
        """The selection a path runs at, before it runs (``hold``; a switch within a moving path does not)."""
        return await self.keep(partial(self.store.applied, sel), hold)

    async def cycle(self, cycle: int | None) -> bool:
        """The cycle begun (None: ended), before its first step."""
        return await self.keep(partial(self.store.cycle, cycle))

    async def keep(self, write: Callable[[], None], hold: bool = True) -> bool:
        """Write the executor's record before what depends on it (a cycle, a path at a selection). A disk
        that cannot take it (full, read-only) is a state, not a crash (DESIGN §9): said once (an event, the
        status, one log line naming the file), and with ``hold`` the arm stays still, the write tried again
        every 2 s until it goes through, then the cycles go on by themselves. False when stopped first."""
        while True:
            try:
                await asyncio.to_thread(write)
            except OSError as exc:
                if self.unwritten is None:
                    self.unwritten = f"cannot write {self.store.path}: {exc.strerror or exc}"
                    self.say(self.unwritten)
                    self.kit.counters["write_errors"] += 1
                    if not hold:
                        self.safety.event("info", f"{self.unwritten}; going on without it")
                if not hold:
                    return True
                # a disk that first refused a write the arm did not wait for (a selection received while
                # it moved) was said as going on: the hold that follows is news, said once too
                if not self.held_unwritten:
                    self.held_unwritten = True
                    self.safety.event("refused", f"{self.unwritten}; holding the arm still until it can")
                if self.safety.motion.state is State.READY:
                    self.safety.fire(Event.REFUSE, self.unwritten)
                await first_of(pause(RETRY_S), self.kit.stop.wait())
                if self.kit.stop.is_set():
                    return False
                continue
            if self.unwritten is not None:
                self.safety.event("info", f"{self.store.path} written again: going on")
                self.unwritten, self.held_unwritten = None, False
                self.say("")
                self.safety.ready()
            return True

    @contextlib.asynccontextmanager
    async def in_motion(self, pid: str) -> AsyncIterator[bool]:
        """The arm may move inside: so it says on disk before the first step (the arm held until the disk
        takes it; False: the service stopped first, and nothing may move), and only a body that ends in
        order (a return, a fault handled) says it no longer does. A run that dies inside (a crash, a kill,
        a power cut) leaves it said, and the restart comes up stopped until a person resumes."""
        said = await self.keep(partial(self.store.moving, pid))
        yield said
        if said:
            await self.keep(partial(self.store.moving, None), hold=False)
