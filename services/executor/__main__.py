"""executor: the only service that moves the robot (paper §II-D; DESIGN §8, §9).

It runs the task program cycle after cycle (services/executor/executor.py), through the safety states of
common/motion.py. At the start of every path it takes the current selection k, turns that path's solution
into 500 Hz samples, checks them against its own limits and its own copy of the waypoints, and hands them
to the servo loop (services/executor/servo.py) on a core of its own (services/executor/cores.py). A
selection arriving during a motion takes effect at the next path start. Whatever fails (no set, a refused
trajectory, a protective stop, a lost controller) is published, and the robot does not move until it is
resolved; a stop is latched until `cadence robot resume`. The decision maker or the store being down only
means the last selection and the cached sets are used.
"""

from __future__ import annotations

import asyncio
import logging
import os
import sys
from pathlib import Path

import numpy as np

from common.motion import Event
from common.runtime.config import CommonSettings
from common.runtime.errors import ConfigError
from common.runtime.service import ServiceContext, first_of, service_main
from common.trajectory.task import Task, load_task
from schemas.topology import OPERATOR_SIGNAL, ROBOT_RESUME, SELECTION
from services.executor.backends import Backend, RobotUnavailable, SimBackend, UrRtdeBackend
from services.executor.cores import claim_core, default_lock_dir
from services.executor.executor import Executor
from services.executor.servo import ServoLoop
from services.executor.settings import Settings

log = logging.getLogger("cadence.executor")
NAME = "executor"


def first_waypoint(task: Task) -> np.ndarray:
    first = next(s.move for s in task.cycle if s.move is not None)
    return task.paths[first].waypoints[0]


def make_backend(settings: Settings, task: Task, speed: float) -> Backend:
    if settings.backend == "ur_rtde":
        if speed != 1.0:
            raise ConfigError(f"[{NAME}] backend: a real controller runs at speed 1, not {speed}")
        try:
            return UrRtdeBackend(
                settings.host,
                lookahead=settings.lookahead_s,
                gain=settings.gain,
                stop_deceleration=settings.stop_deceleration,
                watchdog_hz=settings.watchdog_hz,
                gripper_output=settings.gripper_output,
            )
        except ValueError as exc:
            raise ConfigError(f"[{NAME}] {exc}") from None
    q0 = np.radians(settings.sim_start_deg) if settings.sim_start_deg is not None else first_waypoint(task)
    if len(q0) != 6:
        raise ConfigError(f"[{NAME}] sim_start_deg: 6 joint angles, got {len(q0)}")
    return SimBackend(
        q0,
        lookahead=settings.lookahead_s,
        gain=settings.gain,
        stop_deceleration=settings.stop_deceleration,
        speed=speed,
        limits=task.limits,
        gripper_output=settings.gripper_output,
    )


async def main(ctx: ServiceContext) -> None:
    settings: Settings = ctx.settings
    task = load_task(settings.task)
    backend = make_backend(settings, task, ctx.common.speed)
    lock_dir = Path(settings.lock_dir) if settings.lock_dir else default_lock_dir()
    claim = claim_core(os.sched_getaffinity(0), lock_dir, settings.servo_core)
    loop = ServoLoop(
        backend,
        core=claim.core,
        fifo_priority=settings.fifo_priority if claim.core is not None else 0,
        lock_memory=settings.lock_memory,
        speed=ctx.common.speed,
        spin_us=settings.spin_us,
        overrun_limit=settings.overrun_limit,
        realtime=backend.realtime,
    )
    ex = Executor(ctx, task, backend, loop)
    ex.sets.load()
    loaded = ex.store.load()
    ex.notes = [p for p in (*ex.sets.problems, loaded.problem) if p]
    ctx.detail = "; ".join(ex.notes)
    if claim.note:
        log.warning("%s", claim.note)
    if claim.core is not None:
        ctx.counters["servo_core"] = claim.core
    bus = ctx.bus
    bus.handle(SELECTION, ex.on_selection, maxsize=1)
    bus.handle(OPERATOR_SIGNAL, ex.signals.on_signal)
    bus.serve(ROBOT_RESUME, ex.on_resume)
    if loaded.value is not None and loaded.value.cycle_in_progress is not None:
        ex.event(
            "info",
            f"cycle {loaded.value.cycle_in_progress} of the last run was cut short by a restart; "
            "it has no report, and cycles count again from 0",
        )
    delay = 1.0
    while True:
        try:
            await asyncio.to_thread(backend.connect)
            break
        except RobotUnavailable as exc:
            ex.event("disconnected", f"{exc}; retrying in {delay:.0f} s")
            ex.fire(Event.DISCONNECTED, str(exc))
            await first_of(asyncio.sleep(delay), ctx.stop.wait())
            if ctx.stop.is_set():
                claim.release()
                return
            delay = min(delay * 2, 30.0)
    ex.event("connected", f"{backend.name} backend ready")
    ex.fire(Event.CONNECTED)
    loop.start()
    for w in loop.warnings:
        log.warning("%s", w)
    helpers = [asyncio.create_task(ex.publish_state()), asyncio.create_task(ex.keep_sets())]
    stopper = asyncio.create_task(_stop_motion_on(ctx.stop, loop, backend))
    try:
        await ex.start_selection()
        await ex.sets.fetch_missing(settings.query_timeout_s)
        k = ex.selection.k if ex.selection is not None else None
        ex.event("started", f"task '{task.name}', {len(task.paths)} paths, k = {k if k else 'none yet'}")
        await ex.run()
        if not ctx.stop.is_set():
            ex.fire(Event.SHUTDOWN, "cycles done")
    finally:
        loop.request_stop()
        for t in (*helpers, stopper):
            t.cancel()
        await asyncio.gather(*helpers, stopper, return_exceptions=True)
        await asyncio.to_thread(loop.close)
        await asyncio.to_thread(backend.close)
        claim.release()
        summary = loop.summary()
        log.info(
            "servo timing: %d ticks, p99.9 error %.1f µs, max %.1f µs, %d overruns",
            summary.ticks,
            summary.p999_err_us,
            summary.max_err_us,
            summary.overruns,
        )


async def _stop_motion_on(stop: asyncio.Event, loop: ServoLoop, backend: Backend) -> None:
    """SIGTERM during a motion: a decelerating stop, then the service ends its cycle loop."""
    await stop.wait()
    loop.request_stop()
    backend.stop_move()


def prepare(settings: Settings, common: CommonSettings) -> None:
    task = load_task(settings.task)  # a bad task file stops the service at start: one line, exit 2
    make_backend(settings, task, common.speed)
    if settings.resume_policy == "auto" and settings.backend != "sim":
        raise ConfigError(
            f'[{NAME}] resume_policy: "auto" is for the sim backend only; a real robot\'s stop needs a person'
        )


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv, prepare)


if __name__ == "__main__":
    sys.exit(run())
