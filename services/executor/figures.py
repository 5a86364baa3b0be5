"""The figures of a curve the arm may run (common/safety/separation.py ``Figures``: its top speed and longest
stop, S_p's v_r and T_s), which speed and separation monitoring scales it by (reaction.py): found in a
worker thread before a motion, some tenths of a second each, remembered per curve, and found ahead, while
the arm works, for every path at every k.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
from collections import OrderedDict
from collections.abc import Callable
from functools import partial

import numpy as np

from common.robot.ur16e import JointLimits
from common.runtime.service import first_of
from common.safety.geometry import Arm
from common.safety.separation import Figures
from common.trajectory.scaling import Curve
from common.trajectory.task import PathPlan
from services.executor.sets import SetCache

log = logging.getLogger("cadence.executor")

FIGURES_KEPT = 256  # curves whose figures are remembered (a path at a k: found once, some tenths of a s)


def _at_lowest_priority(work: Callable[[], object]) -> asyncio.Future[object]:
    """``work`` in a thread of its own at the least priority the scheduler gives (Linux: a thread's nice
    value is its own). A daemon: the process's exit never waits for it. A pool's worker is joined at exit,
    and one at nice 19 beside busy loops took tens of seconds to finish its figures, after SIGTERM."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[object] = loop.create_future()

    def settle(result: object, error: BaseException | None) -> None:
        if not done.done():
            done.set_exception(error) if error is not None else done.set_result(result)

    def run() -> None:
        with contextlib.suppress(OSError, AttributeError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        result, error = None, None
        try:
            result = work()
        except BaseException as exc:  # handed to the awaiting task, as a pool would
            error = exc
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile: nobody waits
            loop.call_soon_threadsafe(settle, result, error)

    threading.Thread(target=run, name="figures", daemon=True).start()
    return done


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
            with self._lock:
                self._kept[key] = found
                while len(self._kept) > FIGURES_KEPT:
                    self._kept.popitem(last=False)
        return found

    def known(self, path: PathPlan, h: np.ndarray) -> bool:
        with self._lock:
            return _figures_key(path, h) in self._kept

    async def prefetch(self, sets: SetCache, k_now: Callable[[], int], stop: asyncio.Event) -> None:
        """With separation monitoring: the figures of every path at every k, the k in force first, found
        in a thread of its own at the lowest priority while the arm works, so that a path at a new k does
        not wait for them (some tenths of a second each), and nothing that must be on time waits for
        this. Again whenever the sets change."""
        if not self.on:
            return
        while not stop.is_set():
            sets.arrived.clear()
            k = k_now()
            for pid, s in list(sets.sets.items()):
                path = sets.task.paths[pid]
                for i in sorted(range(len(s.solutions)), key=lambda i: abs(i + 1 - k)):
                    h = np.array(s.solutions[i].h)
                    if not self.known(path, h) and not stop.is_set():
                        try:
                            await _at_lowest_priority(partial(self.of, path, h, Curve.of(h, path)))
                        except Exception:  # found again before the path runs, which says why it cannot
                            log.exception("no figures ahead for '%s' at k = %d", pid, i + 1)
            await first_of(sets.arrived.wait(), stop.wait())
