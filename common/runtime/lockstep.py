"""A cell whose time is driven, not read (DESIGN §4; ROS 2's ``/clock`` with ``use_sim_time``, trio's
``MockClock(autojump_threshold=0)``): its nodes run in one process, on one event loop whose clock is data
time. The loop takes its next instant only when every task of the cell is waiting for a later one: a
handler, a timer, a stream's next chunk all run to their next wait before time moves on. So a run is a
function of its inputs and seeds. A busy host makes it slower and never different, and nothing waits
on the wall: ten minutes of a cell take what its computing takes.

Work a node hands to a thread (``asyncio.to_thread``: SQLite, a file) runs at once, in the loop's own
thread, at the instant it was asked for. Time does not move while it runs, and no other task runs
beside it, so its result comes back in the same order on every host.

Only for simulation: a lockstep cell has no wall clock, no sockets and no threads of its own. Its nodes
meet on the in-memory bus (common/runtime/memory.py), and its services read ``Clock(driven=True)``
(``CommonSettings.lockstep``).
"""

from __future__ import annotations

import asyncio
import contextvars
import selectors
import time
from collections.abc import Callable, Coroutine
from concurrent.futures import Executor, Future
from typing import Any, TypeVar, TypeVarTuple, Unpack

T = TypeVar("T")
Ts = TypeVarTuple("Ts")


class _Jumping(selectors.DefaultSelector):
    """The loop's selector: when nothing is ready, the wait for the next timer is not waited, it is
    skipped: the loop's clock moves to that timer at once, or, under a ceiling, once the wall clock
    allows it."""

    def __init__(self, loop: LockstepLoop) -> None:
        super().__init__()
        self.loop = loop

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        ready: list[tuple[selectors.SelectorKey, int]] = super().select(0)
        if ready or timeout == 0:
            return ready
        if timeout is None:  # no timer at all: only the outside (a signal, a thread) can wake the loop
            return super().select(None)
        due = self.loop.now + timeout
        if (ceiling := self.loop.ceiling) is not None:
            wait = self.loop.wall0 + due / ceiling - time.monotonic()
            if wait > 0 and (ready := super().select(wait)):  # a signal: it is handled at this instant
                return ready
            # reached late (behind, or a wait that overslept): from here on at the ceiling, with no burst
            # to catch up
            self.loop.wall0 = max(self.loop.wall0, time.monotonic() - due / ceiling)
        self.loop.now = due
        return []


class LockstepLoop(asyncio.SelectorEventLoop):
    """An event loop whose ``time()`` is the cell's data time, from 0 (seconds).

    ``ceiling``: data time runs at most ``ceiling`` times as fast as the wall clock (``--speed``: a run
    at a pace a person can follow). Where it is ahead, the loop waits for the wall; where it fell behind
    (planning, a slow host, a stall), it goes on from there at the ceiling, with no burst to catch up.
    A ceiling changes when a run happens, never what it does.
    """

    def __init__(self, ceiling: float | None = None) -> None:
        self.now = 0.0
        self.ceiling = ceiling
        self.wall0 = time.monotonic()
        super().__init__(_Jumping(self))

    def time(self) -> float:
        return self.now

    def run_in_executor(
        self, executor: Executor | None, func: Callable[[Unpack[Ts]], T], *args: *Ts
    ) -> asyncio.Future[T]:
        """At once, here: a thread's result would come back after a wall-clock delay, between other
        tasks in an order the host's speed decides."""
        done: asyncio.Future[T] = self.create_future()
        try:
            done.set_result(contextvars.copy_context().run(func, *args))
        except BaseException as exc:  # the caller awaits it, as it would a thread's
            done.set_exception(exc)
        return done


class Inline(Executor):
    """An executor that does the work when it is handed over, in the caller's thread: a process pool's
    stand-in in a lockstep cell (the store's planning takes no data time, and comes back in order)."""

    def submit(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> Future[T]:
        done: Future[T] = Future()
        try:
            done.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # the caller gets it from the future, as from a pool
            done.set_exception(exc)
        return done


def run(main: Coroutine[Any, Any, T], ceiling: float | None = None) -> T:
    """``main`` on a fresh lockstep loop, as ``asyncio.run`` runs it on a wall-clock one: Ctrl-C cancels
    it, so that it can still say what ran (``LockstepLoop`` for ``ceiling``)."""
    with asyncio.Runner(loop_factory=lambda: LockstepLoop(ceiling)) as runner:
        return runner.run(main)
