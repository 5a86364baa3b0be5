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
from typing import Annotated, Literal

import msgspec
import numpy as np

from common.motion import Event
from common.runtime.config import CommonSettings
from common.runtime.errors import ConfigError
from common.runtime.resources import EXAMPLE_TASK
from common.runtime.service import ServiceContext, first_of, service_main
from common.trajectory.task import Task, load_task
from schemas.decision import MAX_N
from schemas.topology import OPERATOR_SIGNAL, ROBOT_RESUME, SELECTION
from services.executor.backends import Backend, RobotUnavailable, SimBackend, UrRtdeBackend
from services.executor.cores import claim_core, default_lock_dir
from services.executor.executor import Executor
from services.executor.servo import ServoLoop

log = logging.getLogger("cadence.executor")
NAME = "executor"


def _range(lo: float, hi: float) -> msgspec.Meta:
    return msgspec.Meta(ge=lo, le=hi)


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    task: str = str(EXAMPLE_TASK)
    backend: Literal["sim", "ur_rtde"] = "sim"
    host: str = "127.0.0.1"  # ur_rtde: the controller
    lookahead_s: Annotated[float, _range(0.03, 0.2)] = 0.1  # servoJ (UR's range)
    gain: Annotated[float, _range(100.0, 2000.0)] = 300.0  # servoJ (UR's range)
    gripper_output: Annotated[int, _range(0, 7)] = 0  # standard digital output driving the gripper
    watchdog_hz: Annotated[float, _range(1.0, 500.0)] = 10.0  # ur_rtde: the arm stops below this rate
    servo_core: Annotated[int, _range(0, 4095)] | None = None  # default: the last free core
    lock_dir: str | None = None  # where executors claim cores (default /run/cadence)
    fifo_priority: Annotated[int, _range(0, 99)] = 80  # 0: no SCHED_FIFO
    lock_memory: bool = True
    spin_us: Annotated[int, _range(0, 1900)] = 400
    overrun_limit: Annotated[int, _range(1, 1000)] = 5  # this many overruns in a row stop the robot
    stop_deceleration: Annotated[float, _range(0.5, 40.0)] = 4.0  # rad/s², SIGTERM and overrun stops
    settle_s: Annotated[float, _range(0.0, 10.0)] = 0.5  # after the last sample, wait this long at most
    start_policy: Literal["move", "refuse"] = "move"  # the arm is not at the path's start
    start_speed: Annotated[float, _range(0.01, 1.0)] = 0.3  # rad/s, the slow move there
    start_acceleration: Annotated[float, _range(0.01, 2.0)] = 0.6  # rad/s²
    start_tolerance_rad: Annotated[float, _range(1e-5, 0.05)] = 2e-3
    # With the decision maker unreachable at start: "wait" for it, go on at the "last" selection applied
    # (if younger than last_selection_max_age_s), or start at "initial" initial_k. Default: "wait" for
    # ur_rtde, "last" for sim.
    start_selection: Literal["wait", "last", "initial"] | None = None
    last_selection_max_age_s: Annotated[float, _range(0.0, 86400.0)] = 300.0
    initial_k: Annotated[int, _range(1, MAX_N)] = 8  # start_selection = "initial" (Alg. 1's k0 for N = 15)
    # A stop is latched until `cadence robot resume`; "auto" (sim only) resumes after auto_resume_s,
    # doubling, at most auto_resume_per_hour times an hour.
    resume_policy: Literal["manual", "auto"] = "manual"
    auto_resume_s: Annotated[float, _range(0.1, 600.0)] = 2.0
    auto_resume_per_hour: Annotated[int, _range(1, 10_000)] = 10
    state_rate_hz: Annotated[float, _range(1.0, 500.0)] = 50.0  # robot/state, wall clock
    query_timeout_s: Annotated[float, _range(0.1, 60.0)] = 2.0
    wait_for_signals: bool = True  # false: `wait_for` steps pass at once (no operator on the bus)
    cycles: Annotated[int, _range(0, 10**9)] = 0  # stop after this many cycles; 0: run until stopped
    sim_start_deg: list[Annotated[float, _range(-360.0, 360.0)]] | None = None  # sim: pose at start


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
