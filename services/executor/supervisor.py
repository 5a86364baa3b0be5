"""The executor's one safety state (common/safety/states.py) and its one owner (DESIGN §9).

Every change of the state goes through ``Supervisor.fire``, so every change is published the same way: an
event (``robot/event`` kind "state", with its from and to) and the service's state, which ``robot/state``
carries with its reason. Clearing a stop lives here too, so the latch has one keeper: a person's resume
(``robot/resume``), or, for the sim backend only, the automatic policy with its back-off and hourly cap.
Meanwhile a lost controller is reconnected with back-off, and the robot stays stopped.
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Callable

from common.runtime.bus import QueryError
from common.runtime.clock import first_of, monotonic, pause
from common.safety.states import Event, Motion, State, transition
from schemas.robot import EventKind, RobotEvent
from services.executor.backends import Backend, RobotUnavailable
from services.executor.kit import Kit
from services.executor.settings import Settings

log = logging.getLogger("cadence.executor")
STOPPED_STATES = (State.STOPPED, State.RECOVERING)


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


class Supervisor:
    """Owns the safety state: every change, its event and the status's state; a stop's clearing; the
    link to the controller."""

    def __init__(self, kit: Kit, settings: Settings, backend: Backend) -> None:
        self.kit, self.backend, self.host = kit, backend, settings.host
        self.motion = Motion()
        self.changed = asyncio.Event()  # set at every change of state
        self.path_id: str | None = None  # the path the arm is on, or ran last: events name it
        self.auto = (
            AutoResume(settings.auto_resume_s, settings.auto_resume_per_hour)
            if settings.resume_policy == "auto"
            else None
        )
        self._last_event: tuple[str, str] | None = None
        self.on_latch: Callable[[str | None], None] = lambda why: None  # ``latched_to``

    def latched_to(self, keep: Callable[[str | None], None]) -> None:
        """Tell ``keep`` of every stop latched (its reason) and every one cleared (None): the records keep
        it on disk, so a restart comes up stopped."""
        self.on_latch = keep

    @property
    def stopped(self) -> bool:
        return self.motion.state in STOPPED_STATES

    def fire(self, event: Event, reason: str = "") -> Motion:
        """Move the state machine. MOVE from a state that may not move raises IllegalTransition: the
        motion must not start."""
        old = self.motion
        new = self.motion = transition(old, event, reason)
        if (new.state, new.reason) != (old.state, old.reason):
            why = f": {new.reason}" if new.reason else ""
            self.kit.set_state(f"{new.state}{why}")
            change = (old.state.value, new.state.value)
            self.event("state", f"{old.state} → {new.state}{why}", self.path_id, repeat=True, change=change)
            self.changed.set()
            if new.state is State.STOPPED and old.state is not State.RECOVERING:
                self.on_latch(new.reason)
            elif old.state in STOPPED_STATES and new.state not in STOPPED_STATES:
                self.on_latch(None)
        return new

    def ready(self) -> None:
        """Leave the waiting states that the next step has resolved (a set, a refusal re-checked)."""
        if self.motion.state is State.WAITING_FOR_SET:
            self.fire(Event.SET_READY)
        if self.motion.state is State.REFUSED:
            self.fire(Event.CHANGED)

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
            t_ns=self.kit.clock.now_ns(),
            seq=0,
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
        self.kit.counters[f"event_{kind}"] += 1
        self.kit.publish(msg)
        return msg

    async def resume_by(self, by: str) -> RobotEvent:
        """A person clears a latched stop; what it changed, as the event that says so."""
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
        """Latched: the robot stays still until a resume clears the stop. False when the service stops."""
        stop, delay = self.kit.stop, 1.0
        while self.stopped and not stop.is_set():
            wait_s = 5.0
            if self.motion.state is State.STOPPED and self.backend.link_lost():
                try:
                    await asyncio.to_thread(self.backend.reconnect)
                    self.event(
                        "connected",
                        f"reconnected to {self.host}; the robot stays stopped until `cadence robot resume`",
                    )
                except RobotUnavailable as exc:  # right after an e-stop the controller refuses a while
                    wait_s, delay = delay, min(delay * 2, 10.0)
                    self.event("disconnected", f"{exc}; trying again in {wait_s:.0f} s")
            elif self.motion.state is State.STOPPED and self.auto is not None:
                auto_s = self.auto.delay_s(monotonic())
                if auto_s is None:
                    self.event(
                        "info",
                        f"{self.auto.per_hour} automatic resumes in the last hour: the robot stays stopped "
                        "until `cadence robot resume`",
                    )
                else:
                    await first_of(pause(auto_s), stop.wait())  # the loop's: data time in lockstep
                    if stop.is_set() or self.motion.state is not State.STOPPED:
                        continue
                    self.auto.used(monotonic())
                    await self.resume(f'resumed automatically after {auto_s:.0f} s (resume_policy = "auto")')
                    continue
            self.changed.clear()
            await first_of(self.changed.wait(), stop.wait(), pause(wait_s))
        return not stop.is_set()

    async def connect(self) -> bool:
        """Reach the controller, retrying with back-off while it cannot be reached; False when the
        service stops first."""
        delay = 1.0
        while True:
            try:
                await asyncio.to_thread(self.backend.connect)
                break
            except RobotUnavailable as exc:
                self.event("disconnected", f"{exc}; retrying in {delay:.0f} s")
                self.fire(Event.DISCONNECTED, str(exc))
                await first_of(pause(delay), self.kit.stop.wait())
                if self.kit.stop.is_set():
                    return False
                delay = min(delay * 2, 30.0)
        self.event("connected", f"{self.backend.name} backend ready")
        self.fire(Event.CONNECTED)
        return True
