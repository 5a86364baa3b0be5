"""The executor's work: the task's cycles through the safety states of ``common/motion.py``, wired to the
servo loop, the backend and the bus (DESIGN §8, §9).

Every state change is published (``robot/event`` kind "state", and ``robot/state`` carries the state and
its reason), so an operator sees why the robot moves or does not. A motion starts only from ``ready``;
after a stop (limits, overruns, a lost controller) the robot stays still until the stop is cleared: by
``cadence robot resume`` (the queryable ``robot/resume``), or, for the sim backend only, by an automatic
policy with a back-off and a cap per hour.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import Counter, deque
from typing import Literal

import numpy as np

from common.decision import k_for_path
from common.motion import Event, IllegalTransition, Motion, State, mode_of, transition
from common.runtime.bus import Bus, QueryError, Request
from common.runtime.clock import Clock
from common.runtime.errors import TrajectoryRejected
from common.runtime.service import ServiceContext, first_of
from common.trajectory.task import PathPlan, Step, Task
from common.trajectory.validate import validated_samples
from schemas.decision import Selection
from schemas.operator import OperatorError, OperatorSignal
from schemas.robot import CycleReport, EventKind, RobotEvent, RobotState
from schemas.topology import (
    OPERATOR_ERROR,
    OPERATOR_SIGNAL,
    ROBOT_CYCLE,
    ROBOT_EVENT,
    ROBOT_STATE,
    SELECTION,
)
from services.executor.backends import Backend, RobotUnavailable
from services.executor.persist import ExecutorStore
from services.executor.servo import MotionResult, ServoLoop
from services.executor.sets import SetCache
from services.executor.settings import Settings

log = logging.getLogger("cadence.executor")
RATE_HZ = 500.0
STOPPED_STATES = (State.STOPPED, State.RECOVERING)


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

    async def wait(
        self, name: str, stop: asyncio.Event, timeout_s: float | None = None
    ) -> Literal["arrived", "stopped", "late"]:
        """``timeout_s``: wall seconds to wait at most (a step's deadline at the clock's speed)."""
        end = None if timeout_s is None else time.monotonic() + timeout_s
        while self.received[name] <= self.consumed[name]:
            if stop.is_set():
                return "stopped"
            left = None if end is None else end - time.monotonic()
            if left is not None and left <= 0:
                return "late"
            self.arrived.clear()
            timer = [asyncio.sleep(left)] if left is not None else []
            await first_of(self.arrived.wait(), stop.wait(), *timer)
        self.consumed[name] += 1
        return "arrived"


class AutoResume:
    """The sim backend's automatic resume: after ``first_s``, doubling with each resume in the last hour,
    at most ``per_hour`` of them; then a person must resume."""

    def __init__(self, first_s: float, per_hour: int) -> None:
        self.first_s, self.per_hour = first_s, per_hour
        self.times: deque[float] = deque()

    def delay_s(self, now: float) -> float | None:
        while self.times and now - self.times[0] > 3600.0:
            self.times.popleft()
        if len(self.times) >= self.per_hour:
            return None
        return min(self.first_s * 2 ** len(self.times), 60.0)

    def used(self, now: float) -> None:
        self.times.append(now)


class Executor:
    def __init__(self, ctx: ServiceContext, task: Task, backend: Backend, loop: ServoLoop) -> None:
        self.ctx, self.task, self.backend, self.loop = ctx, task, backend, loop
        self.settings: Settings = ctx.settings
        self.notes: list[str] = []  # what was wrong with the files on disk, for the status
        self.clock: Clock = ctx.common.clock
        self.bus = ctx.bus
        folder = ctx.common.data_path / "executor"
        self.sets = SetCache(ctx.bus, folder, task)
        self.store = ExecutorStore(folder)
        self.signals = Signals(ctx.bus, {s.wait_for for s in task.cycle if s.wait_for is not None})
        self.selection: Selection | None = None
        self.selection_changed = asyncio.Event()
        self.motion = Motion()
        self.state_changed = asyncio.Event()
        self.auto = (
            AutoResume(self.settings.auto_resume_s, self.settings.auto_resume_per_hour)
            if self.settings.resume_policy == "auto"
            else None
        )
        self.path_id: str | None = None
        self.k: int | None = None
        self.waiting_for: str | None = None
        self.events_out = ctx.bus.publisher(ROBOT_EVENT)
        self.states_out = ctx.bus.publisher(ROBOT_STATE)
        self.cycles_out = ctx.bus.publisher(ROBOT_CYCLE)
        self.errors_out = ctx.bus.publisher(OPERATOR_ERROR)  # a part not there by its step's deadline
        # a button on a digital input of the controller: its rising edge is that step's signal, published
        # as any signal is (the executor counts it when it comes back, as it would one from elsewhere)
        self.signals_out = ctx.bus.publisher(OPERATOR_SIGNAL)
        self.buttons = {s.input: s.wait_for for s in task.cycle if s.input is not None and s.wait_for}
        self._inputs = 0
        self._last_event: tuple[str, str] | None = None

    # --- the safety states --------------------------------------------------------------------------

    def fire(self, event: Event, reason: str = "") -> Motion:
        """Move the state machine; a change is an event on the bus and the service's state. MOVE from a
        state that may not move raises IllegalTransition: the motion must not start."""
        old = self.motion
        new = self.motion = transition(old, event, reason)
        if (new.state, new.reason) != (old.state, old.reason):
            why = f": {new.reason}" if new.reason else ""
            self.ctx.state = f"{new.state}{why}"
            change = (old.state.value, new.state.value)
            self.event("state", f"{old.state} → {new.state}{why}", self.path_id, repeat=True, change=change)
            self.state_changed.set()
        return new

    def _ready(self) -> None:
        """Leave the waiting states that the next step has resolved (a set, a refusal re-checked)."""
        if self.motion.state is State.WAITING_FOR_SET:
            self.fire(Event.SET_READY)
        if self.motion.state is State.REFUSED:
            self.fire(Event.CHANGED)

    # --- bus ----------------------------------------------------------------------------------------

    def event(
        self,
        kind: EventKind,
        message: str,
        path_id: str | None = None,
        repeat: bool = False,
        change: tuple[str, str] | None = None,
    ) -> RobotEvent:
        """Publish a RobotEvent (and log it); the same event twice in a row only once, unless asked.
        ``change``: a state change's (from, to)."""
        msg = RobotEvent(
            t_ns=self.clock.now_ns(),
            seq=self.events_out.next_seq(),
            kind=kind,
            message=message,
            path_id=path_id,
            from_state=change[0] if change else None,
            to_state=change[1] if change else None,
        )
        if not repeat and self._last_event == (kind, message):
            return msg
        self._last_event = (kind, message)
        level = logging.INFO if kind in ("started", "connected", "info", "state") else logging.WARNING
        log.log(level, "%s: %s", kind, message)
        self.ctx.counters[f"event_{kind}"] += 1
        self.events_out.put(msg)
        return msg

    async def on_selection(self, _: str, sel: Selection) -> None:
        if self.selection is None or (sel.t_ns, sel.seq) != (self.selection.t_ns, self.selection.seq):
            self.selection = sel
            self.selection_changed.set()
            self.fire(Event.SELECTION)

    async def ask_selection(self) -> bool:
        """Selections are state: ask for the current one at start (DESIGN §11). True when one came."""
        for r in await self.bus.get(SELECTION, timeout=self.settings.query_timeout_s):
            if r.message is not None:
                await self.on_selection(r.key, r.message)
                return True
        return False

    async def start_selection(self) -> None:
        """No motion without a current selection: the decision maker's, or, when it cannot be reached, what
        ``start_selection`` allows. What was chosen, and why, is an event."""
        if await self.ask_selection():
            assert self.selection is not None
            self.event("info", f"selection from the decision maker: k = {self.selection.k}")
            return
        policy = self.settings.start_selection or ("wait" if self.settings.backend == "ur_rtde" else "last")
        last = self.store.record.selection
        max_age = self.settings.last_selection_max_age_s
        unreachable = "the decision maker does not answer"
        if policy == "last" and last is not None and last.age_s() <= max_age:
            await self.on_selection("", last.selection())
            self.event(
                "info",
                f"{unreachable}: going on at the last selection applied, k = {last.k} (n = {last.n}), "
                f'{last.age_s():.0f} s ago (start_selection = "last")',
            )
        elif policy == "initial":
            k = self.settings.initial_k
            await self.on_selection(
                "", Selection(t_ns=self.clock.now_ns(), seq=0, k=k, n=k, delta=0, reason="initial")
            )
            self.event(
                "info",
                f'{unreachable}: starting at initial_k = {k}, as configured (start_selection = "initial")',
            )
        else:
            why = (
                'start_selection = "wait"'
                if policy == "wait"
                else "no selection on file"
                if last is None
                else f"the last one on file is {last.age_s():.0f} s old, over {max_age:.0f} s"
            )
            self.event("info", f"{unreachable}: waiting for a selection ({why})")

    async def on_resume(self, req: Request) -> RobotEvent:
        """``robot/resume``: a person clears a latched stop. The reply is the state change it made."""
        by = req.params.get("by", "")
        if self.motion.state is not State.STOPPED:
            raise QueryError(f"nothing to resume: the robot is {self.motion.state}")
        return await self.resume(f"resumed by {by or 'cadence robot resume'}")

    async def resume(self, who: str) -> RobotEvent:
        self.fire(Event.RESUME, who)
        try:
            await asyncio.to_thread(self.backend.reset_fault)
            fault = self.backend.fault()
        except RobotUnavailable as exc:
            fault = str(exc)
        if fault:
            self.fire(Event.RECOVERY_FAILED, f"{fault} (resume failed)")
        else:
            self.fire(Event.RECOVERED, who)
        return self.event("state", f"{self.motion.state}: {self.motion.reason}", self.path_id, repeat=True)

    async def while_stopped(self) -> bool:
        """Latched: the robot stays still until a resume clears the stop. Meanwhile a lost controller is
        reconnected with back-off (the robot still stays stopped), and the sim's automatic policy, if
        configured, resumes after its back-off. False when the service stops."""
        delay = 1.0
        while self.motion.state in STOPPED_STATES and not self.ctx.stop.is_set():
            wait_s = 5.0
            if self.motion.state is State.STOPPED and self.backend.link_lost():
                try:
                    await asyncio.to_thread(self.backend.reconnect)
                    self.event(
                        "connected",
                        f"reconnected to {self.settings.host}; "
                        "the robot stays stopped until `cadence robot resume`",
                    )
                except RobotUnavailable as exc:
                    self.event("disconnected", str(exc))
                    wait_s, delay = delay, min(delay * 2, 10.0)
            elif self.motion.state is State.STOPPED and self.auto is not None:
                auto_s = self.auto.delay_s(time.monotonic())
                if auto_s is None:
                    self.event(
                        "info",
                        f"{self.auto.per_hour} automatic resumes in the last hour: the robot stays stopped "
                        "until `cadence robot resume`",
                    )
                else:
                    await first_of(asyncio.sleep(auto_s), self.ctx.stop.wait())  # wall time: a person's
                    if self.ctx.stop.is_set() or self.motion.state is not State.STOPPED:
                        continue
                    self.auto.used(time.monotonic())
                    await self.resume(f'resumed automatically after {auto_s:.0f} s (resume_policy = "auto")')
                    continue
            self.state_changed.clear()
            await first_of(self.state_changed.wait(), self.ctx.stop.wait(), asyncio.sleep(wait_s))
        return not self.ctx.stop.is_set()

    # --- telemetry ----------------------------------------------------------------------------------

    async def publish_state(self) -> None:
        period = 1.0 / self.settings.state_rate_hz
        while not self.ctx.stop.is_set():
            try:
                self._put_state()
            except Exception as exc:  # telemetry must outlive a backend's bad moment
                self.bus.handler_failed(self.states_out.key, exc)
            await asyncio.sleep(period)

    def _read_buttons(self) -> None:
        if not self.buttons:
            return
        now = self.backend.digital_inputs()
        rising, self._inputs = now & ~self._inputs, now
        for n, name in self.buttons.items():
            if rising >> n & 1:
                self.ctx.counters["buttons"] += 1
                seq = self.signals_out.next_seq()
                pressed = OperatorSignal(t_ns=self.clock.now_ns(), seq=seq, name=name, source=f"ur DI{n}")
                self.signals_out.put(pressed)

    def _put_state(self) -> None:
        self._read_buttons()  # at the state rate: a press lasts far longer than a state period
        q, qd = self.backend.actual_q(), self.backend.actual_qd()
        self.states_out.put(
            RobotState(
                t_ns=self.clock.now_ns(),
                seq=self.states_out.next_seq(),
                q=q.tolist(),
                qd=qd.tolist(),
                tcp=self.backend.tcp_pose().tolist(),
                path_id=self.path_id,
                k=self.k,
                mode=mode_of(self.motion.state),
                waiting_for=self.waiting_for,
                state=self.motion.state,
                reason=self.motion.reason[:4000],
            ),
        )

    async def keep_sets(self) -> None:
        """Fetch what is missing (the store may still be planning; a refused set was dropped), and wait
        while nothing is."""
        while not self.ctx.stop.is_set():
            if not self.sets.missing():
                self.sets.wanted.clear()
                await first_of(self.sets.wanted.wait(), self.ctx.stop.wait())
                continue
            why = await self.sets.fetch_missing(self.settings.query_timeout_s)
            waiting = [f"waiting for Pareto sets: {', '.join(why)}"] if why else []
            self.ctx.detail = "; ".join([*self.notes, *waiting])
            if why:
                await first_of(asyncio.sleep(2.0), self.ctx.stop.wait())

    # --- motion -------------------------------------------------------------------------------------

    async def until_changed(self, at_most_s: float = 5.0) -> None:
        """Wait for something that could resolve a refusal (a new selection, a new set), a stop, or a
        while (a person may have moved the arm)."""
        self.selection_changed.clear()
        self.sets.changed.clear()
        self.state_changed.clear()
        await first_of(
            self.selection_changed.wait(),
            self.sets.changed.wait(),
            self.state_changed.wait(),
            self.ctx.stop.wait(),
            asyncio.sleep(at_most_s),
        )

    async def reach(self, q_start: np.ndarray, path_id: str) -> bool:
        """Start-up safety: the arm must be at the path's first waypoint before the path runs."""
        off = float(np.max(np.abs(self.backend.actual_q() - q_start)))
        if off <= self.settings.start_tolerance_rad:
            return True
        if self.settings.start_policy == "refuse":
            why = f"the arm is {off:.4f} rad from the start of '{path_id}'; not moving"
            self.event("refused", why, path_id)
            self.fire(Event.REFUSE, why)
            return False
        self.event(
            "info", f"the arm is {off:.4f} rad from the start of '{path_id}': moving there slowly", path_id
        )
        self.fire(Event.MOVE, f"moving slowly to the start of '{path_id}'")
        ok = await asyncio.to_thread(
            self.backend.move_j, q_start, self.settings.start_speed, self.settings.start_acceleration
        )
        arrived = (
            float(np.max(np.abs(self.backend.actual_q() - q_start))) <= self.settings.start_tolerance_rad
        )
        if ok and arrived:
            self.fire(Event.DONE)
            return True
        if self.ctx.stop.is_set():
            self.fire(Event.SHUTDOWN)
        else:
            self.fire(
                Event.FAULT, f"the move to the start of '{path_id}' did not arrive: {self.backend.fault()}"
            )
        return False

    async def run_path(self, pid: str) -> int | None:
        """Run one path with the selection current at its start; its k, or None when stopped."""
        own: PathPlan = self.task.paths[pid]
        while not self.ctx.stop.is_set():
            if self.motion.state in STOPPED_STATES:
                if not await self.while_stopped():
                    return None
                continue
            if self.selection is None:
                await first_of(self.selection_changed.wait(), self.ctx.stop.wait())
                continue
            if fault := self.backend.fault():  # a stop at rest (the controller's, a lost link)
                self.event("protective_stop", f"before '{pid}': {fault}", pid)
                self.fire(Event.FAULT, fault)
                continue
            s = self.sets.sets.get(pid)
            if s is None:
                self.event("refused", f"no Pareto set for '{pid}' yet; waiting for the store", pid)
                self.fire(Event.SET_MISSING, f"no Pareto set for '{pid}'")
                await self.until_changed()
                continue
            self._ready()
            k = k_for_path(self.selection.k, len(s.solutions))
            try:
                q = await asyncio.to_thread(
                    validated_samples,
                    np.array(s.solutions[k - 1].h),
                    own,
                    self.task.limits,
                    np.array(s.waypoints),
                )
            except TrajectoryRejected as exc:
                self.event("refused", f"k = {k}: {exc}", pid)
                self.fire(Event.REFUSE, f"k = {k} of '{pid}' refused")
                self.sets.discard(pid, str(exc))  # never cached for good: the store is asked again
                await self.until_changed()
                continue
            if not await self.reach(q[0], pid):
                if self.motion.state is State.REFUSED:
                    await self.until_changed()
                continue
            try:
                self.fire(Event.MOVE, f"'{pid}' at k = {k}")
            except IllegalTransition as exc:  # a stop came in between: no motion
                log.warning("%s", exc)
                continue
            await asyncio.to_thread(self.store.applied, self.selection)
            self.path_id, self.k = pid, k
            targets = self.backend.prepare(q)
            settle = round(self.settings.settle_s * RATE_HZ)
            result: MotionResult = await asyncio.wrap_future(self.loop.run(targets, settle))
            await asyncio.to_thread(self.backend.motion_ended)
            self.ctx.counters["paths"] += 1
            self.ctx.counters["overruns"] = self.loop.overruns
            if result.overruns:
                self.event("overrun", f"{result.overruns} servo overruns during '{pid}'", pid, repeat=True)
            if result.outcome == "done":
                self.fire(Event.DONE)
                return k
            if result.outcome == "stopped":
                self.event("info", f"stopped during '{pid}' (decelerating stop)", pid)
                self.fire(Event.SHUTDOWN)
                return None
            if result.outcome == "overruns":
                why = f"{self.settings.overrun_limit} servo overruns in a row during '{pid}'"
            else:
                why = f"during '{pid}': {self.backend.fault() or 'refused by the arm'}"
            self.event("protective_stop", why, pid)
            self.fire(Event.FAULT, why)
            self.ctx.counters["protective_stops"] += 1
        return None

    async def wait_for(self, step: Step, cycle: int) -> Literal["arrived", "stopped", "late"]:
        """A ``wait_for`` step; past its deadline the part is late: an operator error (kind ``late``),
        then the robot keeps waiting or goes on without it, as the task program says."""
        assert step.wait_for is not None
        timeout = None if step.deadline is None else self.clock.wall_s(step.deadline)
        got = await self.signals.wait(step.wait_for, self.ctx.stop, timeout)
        if got != "late":
            return got
        assert step.deadline is not None
        then = "kept waiting" if step.on_late == "wait" else "went on without it"
        self.ctx.counters["late"] += 1
        self.errors_out.put(
            OperatorError(
                t_ns=self.clock.now_ns(),
                seq=self.errors_out.next_seq(),
                cycle=cycle,
                kind="late",
                description=f"'{step.wait_for}' not there {step.deadline:g} s after the robot came: {then}",
                source="executor",
            )
        )
        if step.on_late == "wait":
            return await self.signals.wait(step.wait_for, self.ctx.stop)
        return "late"

    async def run(self) -> None:
        cycle = 0
        while not self.ctx.stop.is_set() and (self.settings.cycles == 0 or cycle < self.settings.cycles):
            started, ks = self.clock.now_ns(), {}
            await asyncio.to_thread(self.store.cycle, cycle)
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
                    self.fire(Event.WAIT_OPERATOR, f"waiting for '{step.wait_for}'")
                    self.waiting_for = step.wait_for
                    got = await self.wait_for(step, cycle)
                    self.waiting_for = None
                    if got == "stopped":
                        return
                    self.fire(Event.OPERATOR)
            end = self.clock.now_ns()
            await asyncio.to_thread(self.store.cycle, None)
            self.cycles_out.put(
                CycleReport(
                    t_ns=end,
                    seq=self.cycles_out.next_seq(),
                    cycle=cycle,
                    cycle_time_s=(end - started) / 1e9,
                    k_per_path=ks,
                )
            )
            self.ctx.counters["cycles"] = cycle = cycle + 1
