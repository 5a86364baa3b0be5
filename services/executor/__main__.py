"""executor: the only service that moves the robot (paper §II-D; DESIGN §8, §9).

It runs the task program cycle after cycle. At the start of every path it takes the current selection k,
turns that path's solution into 500 Hz samples, checks them against its own limits and its own copy of
the waypoints, and hands them to the servo loop (services/executor/servo.py). A selection arriving during
a motion takes effect at the next path start. Whatever fails (no set, a refused trajectory, a
protective stop, a lost controller) is published as a ``RobotEvent`` and the robot does not move until
it is resolved; the decision maker or the store being down only means the last selection and the cached
sets are used.
"""

from __future__ import annotations

import asyncio
import logging
import os
import sys
from collections import Counter
from pathlib import Path
from typing import Annotated, Literal

import msgspec
import numpy as np

from common.arm import DT
from common.bus import Bus
from common.clock import Clock
from common.decision import k_for_path
from common.errors import ConfigError, TrajectoryRejected
from common.service import CommonSettings, ServiceContext, first_of, service_main
from common.task import PathPlan, Task, load_task
from common.validate import validated_samples
from schemas.decision import MAX_N, Selection
from schemas.operator import OperatorSignal
from schemas.robot import CycleReport, RobotEvent, RobotState
from services.executor.backends import Backend, RobotUnavailable, SimBackend, UrRtdeBackend
from services.executor.servo import MotionResult, ServoLoop
from services.executor.sets import SetCache

log = logging.getLogger("cadence.executor")
NAME = "executor"
EXAMPLE_TASK = Path(__file__).resolve().parents[2] / "deploy" / "tasks" / "box_filling.toml"
RATE_HZ = 1.0 / DT


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
    servo_core: Annotated[int, _range(0, 4095)] | None = None  # default: the last core
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
    initial_k: Annotated[int, _range(1, MAX_N)] = 8  # until a selection is known (Alg. 1's k0 for N = 15)
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


class Signals:
    """Operator signals by name. A ``wait_for`` is met by a signal that arrived since the last wait for
    the same name, so a part put down before the robot got there is not missed. Only the names the task
    waits for are counted: any other is dropped, so a flood of names cannot grow the table."""

    def __init__(self, bus: Bus, names: set[str]) -> None:
        self.bus, self.names = bus, names
        self.received: Counter[str] = Counter()
        self.consumed: Counter[str] = Counter()
        self.arrived = asyncio.Event()

    async def on_signal(self, key: str, sig: OperatorSignal) -> None:
        if sig.name not in self.names:
            self.bus.reject(key, "unknown_signal", f"no step of the task waits for '{sig.name}'")
            return
        self.received[sig.name] += 1
        self.arrived.set()

    async def wait(self, name: str, stop: asyncio.Event) -> bool:
        while self.received[name] <= self.consumed[name]:
            if stop.is_set():
                return False
            self.arrived.clear()
            await first_of(self.arrived.wait(), stop.wait())
        self.consumed[name] += 1
        return True


class Executor:
    def __init__(self, ctx: ServiceContext, task: Task, backend: Backend, loop: ServoLoop) -> None:
        self.ctx, self.task, self.backend, self.loop = ctx, task, backend, loop
        self.settings: Settings = ctx.settings
        self.clock: Clock = ctx.common.clock
        self.bus = ctx.bus
        self.sets = SetCache(ctx.bus, ctx.common.data_path / "executor", task)
        self.signals = Signals(ctx.bus, {s.wait_for for s in task.cycle if s.wait_for is not None})
        self.selection: Selection | None = None
        self.selection_changed = asyncio.Event()
        self.path_id: str | None = None
        self.k: int | None = None
        self.mode = "idle"
        self.waiting_for: str | None = None
        self.seq = Counter[str]()
        self._last_event: tuple[str, str] | None = None

    # --- bus ----------------------------------------------------------------------------------------

    def event(self, kind: str, message: str, path_id: str | None = None, repeat: bool = False) -> None:
        """Publish a RobotEvent (and log it); the same event twice in a row only once, unless asked."""
        if not repeat and self._last_event == (kind, message):
            return
        self._last_event = (kind, message)
        level = logging.INFO if kind in ("started", "connected", "info") else logging.WARNING
        log.log(level, "%s: %s", kind, message)
        self.ctx.counters[f"event_{kind}"] += 1
        self.bus.put(
            self.bus.key("robot/event"),
            RobotEvent(
                t_ns=self.clock.now_ns(), seq=self._next("event"), kind=kind, message=message, path_id=path_id
            ),
            block=True,
        )

    def _next(self, name: str) -> int:
        self.seq[name] += 1
        return self.seq[name] - 1

    async def on_selection(self, _: str, sel: Selection) -> None:
        if self.selection is None or (sel.t_ns, sel.seq) != (self.selection.t_ns, self.selection.seq):
            self.selection = sel
            self.selection_changed.set()

    async def ask_selection(self) -> None:
        """Selections are state: ask for the current one at start (DESIGN §11)."""
        for r in await self.bus.get(
            self.bus.key("decision/selection"), Selection, self.settings.query_timeout_s
        ):
            if r.message is not None:
                await self.on_selection(r.key, r.message)

    async def publish_state(self) -> None:
        period = 1.0 / self.settings.state_rate_hz
        key = self.bus.key("robot/state")
        while not self.ctx.stop.is_set():
            q, qd = self.backend.actual_q(), self.backend.actual_qd()
            self.bus.put(
                key,
                RobotState(
                    t_ns=self.clock.now_ns(),
                    seq=self._next("state"),
                    q=q.tolist(),
                    qd=qd.tolist(),
                    tcp=self.backend.tcp_pose().tolist(),
                    path_id=self.path_id,
                    k=self.k,
                    mode=self.mode,
                    waiting_for=self.waiting_for,
                ),
            )
            await asyncio.sleep(period)

    async def keep_sets(self) -> None:
        """Fetch what is missing (the store may still be planning; a refused set was dropped), and wait
        while nothing is."""
        while not self.ctx.stop.is_set():
            if not self.sets.missing():
                self.sets.wanted.clear()
                await first_of(self.sets.wanted.wait(), self.ctx.stop.wait())
                continue
            why = await self.sets.fetch_missing(self.settings.query_timeout_s)
            if why:
                self.ctx.state = f"waiting for Pareto sets: {', '.join(why)}"
                await first_of(asyncio.sleep(2.0), self.ctx.stop.wait())

    # --- motion -------------------------------------------------------------------------------------

    def current_k(self) -> int:
        return self.selection.k if self.selection is not None else self.settings.initial_k

    async def until_changed(self, at_most_s: float = 5.0) -> None:
        """Wait for something that could resolve a refusal (a new selection, a new set), a stop, or a
        while (a person may have moved the arm)."""
        self.selection_changed.clear()
        self.sets.changed.clear()
        await first_of(
            self.selection_changed.wait(),
            self.sets.changed.wait(),
            self.ctx.stop.wait(),
            asyncio.sleep(at_most_s),
        )

    async def recover(self) -> bool:
        """Wait out a fault (protective stop, lost controller): reconnect with back-off; False on stop."""
        delay = 1.0
        while (fault := self.backend.fault()) and not self.ctx.stop.is_set():
            self.mode = "fault"
            self.ctx.state = f"fault: {fault}"
            if self.settings.backend == "ur_rtde":
                try:
                    await asyncio.to_thread(self.backend.reset_fault)
                    self.event("connected", f"reconnected to {self.settings.host}")
                    continue
                except RobotUnavailable as exc:
                    self.event("disconnected", str(exc))
            await first_of(asyncio.sleep(delay), self.ctx.stop.wait())
            delay = min(delay * 2, 10.0)
        return not self.ctx.stop.is_set()

    async def reach(self, q_start: np.ndarray, path_id: str) -> bool:
        """Start-up safety: the arm must be at the path's first waypoint before the path runs."""
        off = float(np.max(np.abs(self.backend.actual_q() - q_start)))
        if off <= self.settings.start_tolerance_rad:
            return True
        if self.settings.start_policy == "refuse":
            self.event(
                "refused", f"the arm is {off:.4f} rad from the start of '{path_id}'; not moving", path_id
            )
            return False
        self.event(
            "info", f"the arm is {off:.4f} rad from the start of '{path_id}': moving there slowly", path_id
        )
        self.mode = "moving_to_start"
        ok = await asyncio.to_thread(
            self.backend.move_j, q_start, self.settings.start_speed, self.settings.start_acceleration
        )
        return (
            ok
            and float(np.max(np.abs(self.backend.actual_q() - q_start))) <= self.settings.start_tolerance_rad
        )

    async def run_path(self, pid: str) -> int | None:
        """Run one path with the selection current at its start; its k, or None when stopped."""
        own: PathPlan = self.task.paths[pid]
        while not self.ctx.stop.is_set():
            if self.backend.fault() and not await self.recover():
                return None
            s = self.sets.sets.get(pid)
            if s is None:
                self.mode = "waiting"
                self.event("refused", f"no Pareto set for '{pid}' yet; waiting for the store", pid)
                await self.until_changed()
                continue
            k = k_for_path(self.current_k(), len(s.solutions))
            try:
                q = await asyncio.to_thread(
                    validated_samples,
                    np.array(s.solutions[k - 1].h),
                    own,
                    self.task.limits,
                    np.array(s.waypoints),
                )
            except TrajectoryRejected as exc:
                self.mode = "refused"
                self.event("refused", f"k = {k}: {exc}", pid)
                self.sets.discard(pid, str(exc))  # never cached for good: the store is asked again
                await self.until_changed()
                continue
            if not await self.reach(q[0], pid):
                if self.backend.fault():
                    continue
                await self.until_changed()
                continue
            self.path_id, self.k, self.mode = pid, k, "moving"
            self.ctx.state = f"running {pid} with k = {k}"
            targets = self.backend.prepare(q)
            settle = round(self.settings.settle_s * RATE_HZ)
            result: MotionResult = await asyncio.wrap_future(self.loop.run(targets, settle))
            await asyncio.to_thread(self.backend.motion_ended)
            self.mode = "idle"
            self.ctx.counters["paths"] += 1
            self.ctx.counters["overruns"] = self.loop.overruns
            if result.overruns:
                self.event("overrun", f"{result.overruns} servo overruns during '{pid}'", pid, repeat=True)
            if result.outcome == "done":
                return k
            if result.outcome == "stopped":
                self.event("info", f"stopped during '{pid}' (decelerating stop)", pid)
                return None
            if result.outcome == "overruns":
                self.event(
                    "protective_stop", f"{self.settings.overrun_limit} overruns in a row during '{pid}'", pid
                )
            else:
                self.event(
                    "protective_stop", f"during '{pid}': {self.backend.fault() or 'refused by the arm'}", pid
                )
            self.ctx.counters["protective_stops"] += 1
        return None

    async def run(self) -> None:
        cycle = 0
        while not self.ctx.stop.is_set() and (self.settings.cycles == 0 or cycle < self.settings.cycles):
            started, ks = self.clock.now_ns(), {}
            for step in self.task.cycle:
                if self.ctx.stop.is_set():
                    return
                if step.move is not None:
                    k = await self.run_path(step.move)
                    if k is None:
                        return
                    ks[step.move] = k
                elif step.gripper is not None:
                    await asyncio.to_thread(self.backend.set_gripper, step.gripper == "on")
                elif step.wait is not None:
                    await first_of(self.clock.sleep(step.wait), self.ctx.stop.wait())
                elif step.wait_for is not None and self.settings.wait_for_signals:
                    self.mode, self.ctx.state = "waiting", f"waiting for '{step.wait_for}'"
                    self.waiting_for = step.wait_for
                    ok = await self.signals.wait(step.wait_for, self.ctx.stop)
                    self.mode, self.waiting_for = "idle", None
                    if not ok:
                        return
            end = self.clock.now_ns()
            self.bus.put(
                self.bus.key("robot/cycle"),
                CycleReport(
                    t_ns=end,
                    seq=self._next("cycle"),
                    cycle=cycle,
                    cycle_time_s=(end - started) / 1e9,
                    k_per_path=ks,
                ),
                block=True,
            )
            self.ctx.counters["cycles"] = cycle = cycle + 1


async def main(ctx: ServiceContext) -> None:
    settings: Settings = ctx.settings
    task = load_task(settings.task)
    backend = make_backend(settings, task, ctx.common.speed)
    core = settings.servo_core if settings.servo_core is not None else max(os.sched_getaffinity(0))
    loop = ServoLoop(
        backend,
        core=core,
        fifo_priority=settings.fifo_priority,
        lock_memory=settings.lock_memory,
        speed=ctx.common.speed,
        spin_us=settings.spin_us,
        overrun_limit=settings.overrun_limit,
    )
    ex = Executor(ctx, task, backend, loop)
    ex.sets.load()
    if ex.sets.problems:
        ctx.detail = "; ".join(ex.sets.problems)
    bus = ctx.bus
    bus.handle(bus.key("decision/selection"), Selection, ex.on_selection, maxsize=1)
    bus.handle(bus.key("operator/signal"), OperatorSignal, ex.signals.on_signal)
    delay = 1.0
    while True:
        try:
            await asyncio.to_thread(backend.connect)
            break
        except RobotUnavailable as exc:
            ex.event("disconnected", f"{exc}; retrying in {delay:.0f} s")
            ctx.state = "waiting for the robot"
            await first_of(asyncio.sleep(delay), ctx.stop.wait())
            if ctx.stop.is_set():
                return
            delay = min(delay * 2, 30.0)
    ex.event("connected", f"{backend.name} backend ready")
    loop.start()
    for w in loop.warnings:
        log.warning("%s", w)
    helpers = [asyncio.create_task(ex.publish_state()), asyncio.create_task(ex.keep_sets())]
    stopper = asyncio.create_task(_stop_motion_on(ctx.stop, loop, backend))
    try:
        await ex.ask_selection()
        await ex.sets.fetch_missing(settings.query_timeout_s)
        ex.event("started", f"task '{task.name}', {len(task.paths)} paths, k = {ex.current_k()}")
        await ex.run()
        ctx.state = "cycles done" if not ctx.stop.is_set() else "stopped"
    finally:
        loop.request_stop()
        for t in (*helpers, stopper):
            t.cancel()
        await asyncio.gather(*helpers, stopper, return_exceptions=True)
        await asyncio.to_thread(loop.close)
        await asyncio.to_thread(backend.close)
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


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv, prepare)


if __name__ == "__main__":
    sys.exit(run())
