"""Data time for sources (DESIGN §4): services reason on data time only; the few that look at the wall
clock (ECG sources, the executor's servo clock, the operator twin) read it through a ``Clock``, so that a
simulation can run every service ``speed`` times faster than real time on one shared time base.

All processes of one run share ``epoch_ns`` (a wall-clock instant) and ``speed``: data time is
``epoch + (wall − epoch) · speed``, whoever computes it. Without an epoch data time is wall time.

A driven clock (``driven``: a lockstep cell, common/runtime/lockstep.py) is the event loop's own: data
time is ``epoch + loop.time()``, and the loop takes its next instant only when every task of the cell
waits for one. A busy host then slows the run and never changes it.

This module is the one door to time in ``services/`` and ``common/`` (ruff's banned-api rule in
pyproject.toml holds every other module to it; the servo thread, the backends' controllers and the
lockstep loop keep their own): data time (``Clock``), the loop's seconds (``monotonic``, ``pause``), and the
wall's, for what a person reads or what the host took (``wall_ns``, ``wall_monotonic``). A name says which.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Clock:
    speed: float = 1.0
    epoch_ns: int | None = None
    driven: bool = False  # the event loop's time is data time (a lockstep cell); ``speed`` is not used

    def __post_init__(self) -> None:
        if not self.speed > 0:
            raise ValueError(f"speed must be positive, got {self.speed}")

    def data_ns(self, wall_ns: int) -> int:
        if self.epoch_ns is None:
            return wall_ns
        return self.epoch_ns + round((wall_ns - self.epoch_ns) * self.speed)

    def now_ns(self) -> int:
        if self.driven:
            return (self.epoch_ns or 0) + round(asyncio.get_running_loop().time() * 1e9)
        return self.data_ns(time.time_ns())

    def loop_s(self, data_s: float) -> float:
        """How long a stretch of data time takes on the event loop's clock: the wall's divided by the
        speed, or data time itself where the loop is driven (a lockstep cell's)."""
        return data_s if self.driven else data_s / self.speed

    async def sleep(self, data_s: float) -> None:
        await asyncio.sleep(max(0.0, self.loop_s(data_s)))


def monotonic() -> float:
    """Seconds on the clock a node's waits run on, for ages and timeouts: the running event loop's, which
    is the wall's monotonic clock, or a lockstep cell's data time (off the loop: the wall's)."""
    try:
        return asyncio.get_running_loop().time()
    except RuntimeError:
        return time.monotonic()


async def pause(loop_s: float) -> None:
    """Wait ``loop_s`` seconds of the running event loop's clock (the wall's, or a lockstep cell's data
    time): a back-off, a retry, a wait with a timeout. A stretch of data time is ``Clock.sleep``."""
    await asyncio.sleep(loop_s)


def wall_ns() -> int:
    """The wall's time of day: what a person reads (a file's stamp, how old a record is), never data time."""
    return time.time_ns()


def wall_monotonic() -> float:
    """The wall's monotonic seconds: how long the host took (a computation, a rate limit on logs, a
    service's uptime), whatever clock the data runs on."""
    return time.monotonic()


async def first_of(*aws: Awaitable[object]) -> None:
    """Wait for the first of ``aws`` to finish (an event, a sleep, a stop); the others are cancelled.
    The first one's exception, if it raised, is raised."""
    tasks = [asyncio.ensure_future(a) for a in aws]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
    for t in done:
        t.result()
