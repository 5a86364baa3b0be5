"""The executor's side of its separation guard (services/executor/guard_process.py): started beside the
servo process on the same shared memory, watched, started again should it die, and its figures read for
the status: how often the servo took the guard's σ itself (``guard_cuts``), and how soon the scale a
reading allowed was in force by any hand (``guard_p50_ms`` … ``guard_max_ms``: the guard's fall → the step
that plays it).
"""

from __future__ import annotations

import logging
import os
import pickle
import subprocess
import sys

import msgspec
import numpy as np

from common.runtime.bus import BusConfig
from common.runtime.clock import Clock, wall_monotonic
from common.safety.separation import Nearest
from services.executor.channel import QUIET, Channel, said
from services.executor.guard_process import GuardConfig
from services.executor.settings import Settings

log = logging.getLogger("cadence.executor")
BELOW_SERVO = 10  # the guard's FIFO priority, this far under the servo's
LIVE_S = 0.1  # a guard that wrote nothing for this long is not counted on


def guard_bus(cfg: BusConfig) -> BusConfig | None:
    """The guard's way onto the executor's bus: a client of the routers the executor reaches (it listens
    on nothing, and takes no port of the executor's); None where the executor names none (a lone peer)."""
    if not cfg.connect and not cfg.config_file:
        return None
    return msgspec.structs.replace(cfg, mode="client", listen=[])


class GuardProcess:
    """The guard, one at a time; ``fd``: the servo's shared memory (``Channel``)."""

    def __init__(self, fd: int, ch: Channel, config: GuardConfig) -> None:
        self.fd, self.ch, self.config = fd, ch, config
        self.proc: subprocess.Popen[bytes] | None = None

    @classmethod
    def beside(
        cls,
        fd: int,
        ch: Channel,
        s: Settings,
        bus: BusConfig,
        cell: str,
        clock: Clock,
        skew_s: float,
        fifo: int,
    ) -> GuardProcess | None:
        """The guard of a cell whose bus it can reach, else None (said)."""
        way = guard_bus(bus)
        if way is None:
            log.warning("no separation guard: the executor's bus names no router to reach it by")
            return None
        return cls(fd, ch, GuardConfig(s, way, cell, clock, skew_s, max(fifo - BELOW_SERVO, 0)))

    def start(self) -> None:
        cmd = [sys.executable, "-m", "services.executor.guard_process", str(self.fd)]
        env = {**os.environ, **QUIET}
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, pass_fds=(self.fd,), env=env,
                                     start_new_session=True)  # fmt: skip
        assert self.proc.stdin is not None
        self.proc.stdin.write(pickle.dumps(self.config))
        self.proc.stdin.close()

    def check(self) -> str | None:
        """Once a status period: None while it runs; else how it ended, and it is started again."""
        proc = self.proc
        if proc is None or proc.poll() is None:
            return None
        why = f"the separation guard ended ({said(proc.returncode)}): started again"
        log.error("%s; meanwhile the executor's looks alone scale the arm", why)
        self.start()
        return why

    def nearest(self) -> Nearest | None:
        """Its nearest room while it runs and wrote lately, else None: read, not sent, so the executor's
        looks take it as it is, whatever their loop has still to decode (services/executor/reaction.py)."""
        got = self.ch.guard.read()
        if self.proc is None or self.proc.poll() is not None or got is None:
            return None
        v, at = got[0], Channel.GUARD_AT
        if not wall_monotonic() - float(v[at["beat"]]) < LIVE_S:
            return None
        source, _, why = got[1].partition("\n")
        distance = float(v[at["distance"]])
        return Nearest(None if distance != distance else distance, source, why)

    def figures(self) -> dict[str, int]:
        """The status's guard figures: cuts, and the adoptions' quantiles (ms) over the ring it keeps."""
        v = self.ch.state.read()
        if v is None:
            return {}
        at = Channel.AT
        adopted = int(v[0][at["adopted"]])
        out = {
            "guard_cuts": int(v[0][at["cuts"]]),
            "guard_n": adopted,
            "guard_unheard": int(v[0][at["unheard"]]),
        }
        held = self.ch.adoptions[: min(adopted, Channel.ADOPTIONS)].copy() * 1000
        if held.size:
            p50, p999 = np.percentile(held, [50.0, 99.9])
            out |= {
                "guard_p50_ms": round(p50),
                "guard_p99.9_ms": round(p999),
                "guard_max_ms": round(held.max()),
            }
        return out

    def close(self) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is None:
            proc.kill()  # it holds nothing: its σ stops counting within GUARD_SILENT_S
            proc.wait()
