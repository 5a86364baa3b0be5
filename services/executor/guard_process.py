"""The separation guard (DESIGN §8, issue 73): people's readings → the scale the arm may run at, in a small
process of its own beside the servo, at a real-time priority below the servo's.

Why: the executor's event loop also decodes everything else it is sent. A flood on another key (5,000
messages every 50 ms) kept its readings waiting up to 350 ms (p99.9), a third of them arriving stale,
against the 0.1 s that T_r budgets for the executor's adoption. Here nothing else is read: a session of
its own subscribes to the separation keys only, judges each reading by the executor's own rules
(common/safety/watch.py) against the joints the servo last wrote, and writes σ for the nearest fresh one,
with the moment it last fell, into the servo's shared memory (``Channel.guard``), as each reading comes
and every ``JUDGE_S`` (a reading going stale, the arm moving). The servo compares it with the scale in
force each step; when the executor's own ramp down has not begun within the guard's grace, the playback
ramps down to it itself (servo_process.py ``Server.guarded``).

The guard only ever lowers the scale: the executor still plans every ramp, renews the lease, and holds the
arm on its own judgement; a guard that dies or falls silent leaves the executor's reaction as it was, and
is started again. Started by the executor (services/executor/guard.py) as ``python -m
services.executor.guard_process FD`` with its configuration pickled on stdin; it ends when its executor
does.
"""

from __future__ import annotations

import asyncio
import mmap
import os
import pickle
import signal
import sys
from dataclasses import dataclass

import numpy as np

from common.runtime.bus import Bus, BusConfig
from common.runtime.clock import Clock, pause, wall_monotonic
from common.runtime.errors import Rejected
from common.safety.separation import Figures
from common.safety.watch import Watch
from schemas.operator import Separation
from schemas.topology import OPERATOR_SEPARATION, OPERATOR_SEPARATION_OF, source_chunk
from services.executor.channel import Channel
from services.executor.settings import Settings
from services.registry import EXECUTOR

JUDGE_S = 0.005  # σ is judged again this often between readings (s)


@dataclass(frozen=True, slots=True)
class GuardConfig:
    """What the guard is started with (pickled on its stdin)."""

    settings: Settings
    bus: BusConfig
    cell: str
    clock: Clock
    skew_s: float
    fifo_priority: int  # 0: normal priority


class Guard:
    """The judgement: readings kept as the executor keeps them, σ written with the moment it last fell."""

    def __init__(self, ch: Channel, watch: Watch, clock: Clock) -> None:
        self.ch, self.watch, self.clock = ch, watch, clock
        self.run, self.sigma, self.since = -1, np.inf, 0.0
        self.q = np.zeros(6)
        self.said: tuple[str, str] = ("", "")

    def reading(self, sep: Separation, own_key: bool) -> None:
        now = wall_monotonic()
        stamp_age = self.clock.loop_s((self.clock.now_ns() - sep.t_ns) / 1e9)
        try:
            self.watch.receive(sep, own_key, stamp_age, now, self.q)
        except Rejected:  # the executor refuses it too, and counts and says why
            return
        self.judge()

    def judge(self) -> None:
        """σ for the nearest fresh room now, on the figures of the curve the servo plays; NaN while it plays
        none (nothing to judge)."""
        now, at, g = wall_monotonic(), Channel.AT, self.ch.guard
        got = self.ch.state.read()
        if got is None:
            return
        v = got[0]
        self.q = v[at["q"] : at["q"] + 6].copy()
        run, figures = int(v[at["run"]]), v[at["v_r"] : at["v_r"] + 3]
        nearest = self.watch.nearest(now)
        sigma = np.nan
        if v[at["moving"]] and np.all(np.isfinite(figures)):
            speed, stop, travel = map(float, figures)
            sigma = self.watch.allowed(Figures(speed, stop, travel), nearest, float(v[at["sigma"]]), now)
            if run != self.run or sigma < self.sigma:
                self.since = now
            self.run, self.sigma = run, sigma
        ga = Channel.GUARD_AT
        g.view[ga["run"]], g.view[ga["sigma"]], g.view[ga["since"]] = run, sigma, self.since
        g.view[ga["beat"]] = now
        g.view[ga["distance"]] = np.nan if nearest.distance_m is None else nearest.distance_m
        said = (nearest.source, nearest.why)
        g.write(None if said == self.said else "\n".join(said).encode())
        self.said = said


async def guard(ch: Channel, cfg: GuardConfig) -> None:
    watch = Watch(cfg.settings.rules(cfg.skew_s))
    g = Guard(ch, watch, cfg.clock)
    parent = os.getppid()
    async with await Bus.open(cfg.bus, cfg.cell, role=EXECUTOR.name) as bus:
        bus.take(OPERATOR_SEPARATION, lambda key, sep: g.reading(sep, own_key=False))

        def of(key: str, sep: Separation) -> None:
            if key.rsplit("/", 1)[-1] == source_chunk(sep.source):  # else another's key: refused there
                g.reading(sep, own_key=True)

        bus.take(OPERATOR_SEPARATION_OF, of)
        while os.getppid() == parent:
            g.judge()
            await pause(JUDGE_S)


def main(argv: list[str]) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the executor's to answer; this one ends with it
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    cfg: GuardConfig = pickle.loads(sys.stdin.buffer.read())
    if cfg.fifo_priority > 0:
        try:  # its session's threads, started below, inherit it
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(cfg.fifo_priority))
        except OSError as exc:
            print(
                f"the separation guard runs at normal priority: SCHED_FIFO refused ({exc})", file=sys.stderr
            )
    ch = Channel(memoryview(mmap.mmap(int(argv[1]), Channel.SIZE)))
    asyncio.run(guard(ch, cfg))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
