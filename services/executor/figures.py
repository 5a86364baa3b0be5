"""The figures of a curve the arm may run (common/safety/separation.py ``Figures``: its top speed and longest
stop, S_p's v_r and T_s), which speed and separation monitoring scales it by (reaction.py): found in a
worker thread before a motion, some tenths of a second each, remembered per curve, and found ahead, while
the arm works, for every path at every k.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import os
import signal
import threading
from collections import OrderedDict
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import cast

import numpy as np

from common.robot.ur16e import JointLimits
from common.runtime.clock import first_of
from common.safety.geometry import Arm
from common.safety.separation import Figures
from common.trajectory.scaling import Curve
from common.trajectory.task import PathPlan
from services.executor.sets import SetCache

log = logging.getLogger("cadence.executor")

FIGURES_KEPT = 256  # curves whose figures are remembered (a path at a k: found once, some tenths of a s)


def _find(conn: Connection, limits: JointLimits, arm: Arm) -> None:
    """The finder's process: at the least priority, the figures of each curve it is sent, until the pipe
    closes (the executor ended, however it ended). A Ctrl-C at the terminal reaches the whole process
    group: the executor decides what it means, and the finder ends with it (no traceback of its own)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.nice(19)
    while True:
        try:
            curve = conn.recv()
        except (EOFError, OSError):
            return
        try:
            conn.send((Figures.of(curve, limits, arm=arm), None))
        except Exception as exc:  # said to the executor, which finds them again before the path runs
            conn.send((None, repr(exc)))


class Finder:
    """A process of its own that finds curves' figures ahead, at the least priority, one at a time.

    Not a thread: a thread of the executor's at nice 19 held the GIL while the scheduler gave it no CPU,
    and every other thread of the process waited for it, the FIFO servo thread first (beside busy loops:
    the servo's ticks up to 0.4-0.8 s late in a bench of the two, 2.3 s in a walk-in test, 36,000 missed
    deadlines). At nice 0 it took the GIL from the servo every switch interval instead (late ticks up to
    20 ms). A process shares no GIL. It is killed, never joined, when the executor ends."""

    def __init__(self, limits: JointLimits, arm: Arm) -> None:
        ctx = multiprocessing.get_context("spawn")  # no fork of a process with a FIFO thread and Zenoh's
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_find, args=(child, limits, arm), name="cadence-figures", daemon=True)
        self._proc.start()
        child.close()

    async def of(self, curve: Curve) -> Figures:
        """Its figures, once the finder answers: the pipe watched by the event loop, no thread (a
        lockstep loop runs a thread's work inline, and would wait for the finder at nice 19). EOFError:
        the finder ended."""
        self._conn.send(curve)
        loop = asyncio.get_running_loop()
        readable: asyncio.Future[None] = loop.create_future()
        fd = self._conn.fileno()

        def ready() -> None:
            if not readable.done():
                readable.set_result(None)

        loop.add_reader(fd, ready)
        try:
            await readable
        finally:
            loop.remove_reader(fd)
        found, error = self._conn.recv()  # all there: the finder sends each answer whole
        if error is not None:
            raise RuntimeError(error)
        return cast(Figures, found)

    def close(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self._proc.kill()
        self._conn.close()


def _figures_key(path: PathPlan, h: np.ndarray) -> tuple[str, bytes, bytes]:
    """A curve is its waypoints and its h: two motions of one id (moves to a path's start from two places)
    may share an h and not a geometry."""
    return path.id, np.asarray(path.waypoints, dtype=float).tobytes(), np.asarray(h, dtype=float).tobytes()


class CurveFigures:
    """Owns the figures found for the curves the arm may run (the last ``FIGURES_KEPT``), and their finding
    ahead of time. With separation monitoring off there is nothing to find: every curve's are zero."""

    def __init__(self, limits: JointLimits, arm: Arm, on: bool) -> None:
        self.limits, self.arm, self.on = limits, arm, on
        self._kept: OrderedDict[tuple[str, bytes, bytes], Figures] = OrderedDict()
        self._lock = threading.Lock()  # the paths' and the prefetch's worker threads

    def of(self, path: PathPlan, h: np.ndarray, curve: Curve, keep: bool = True) -> Figures:
        """In a worker thread, before a path: its top speed and longest stop, remembered per (path, its
        waypoints, h). ``keep=False`` for a motion made once (the move to a path's start, from wherever
        the arm is): it would push a path's figures out of the memory for nothing."""
        if not self.on:
            return Figures(0.0, 0.0)
        key = _figures_key(path, h)
        with self._lock:
            if (known := self._kept.get(key)) is not None:
                self._kept.move_to_end(key)
                return known
        found = Figures.of(curve, self.limits, arm=self.arm)
        if keep:
            self.keep(path, h, found)
        return found

    def keep(self, path: PathPlan, h: np.ndarray, found: Figures) -> None:
        with self._lock:
            self._kept[_figures_key(path, h)] = found
            while len(self._kept) > FIGURES_KEPT:
                self._kept.popitem(last=False)

    def known(self, path: PathPlan, h: np.ndarray) -> bool:
        with self._lock:
            return _figures_key(path, h) in self._kept

    async def prefetch(self, sets: SetCache, k_now: Callable[[], int], stop: asyncio.Event) -> None:
        """With separation monitoring: the figures of every path at every k, the k in force first, found
        in a process of its own at the lowest priority (``Finder``) while the arm works, so that a path at
        a new k does not wait for them (some tenths of a second each), and nothing that must be on time
        waits for this. Again whenever the sets change."""
        if not self.on:
            return
        finder = Finder(self.limits, self.arm)  # a process's start: a few ms, its imports are its own
        try:
            while not stop.is_set():
                sets.arrived.clear()
                k = k_now()
                for pid, s in list(sets.sets.items()):
                    path = sets.task.paths[pid]
                    for i in sorted(range(len(s.solutions)), key=lambda i: abs(i + 1 - k)):
                        h = np.array(s.solutions[i].h)
                        if not self.known(path, h) and not stop.is_set():
                            try:
                                self.keep(path, h, await finder.of(Curve.of(h, path)))
                            except (EOFError, OSError) as exc:  # the finder is gone: found in place
                                log.error("the figures' finder ended (%r): none found ahead", exc)
                                return
                            except Exception:  # found again before the path runs, which says why not
                                log.exception("no figures ahead for '%s' at k = %d", pid, i + 1)
                await first_of(sets.arrived.wait(), stop.wait())
        finally:
            finder.close()
