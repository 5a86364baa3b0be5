"""executor: the only service that moves the robot (paper §II-D; DESIGN §8, §9).

It runs the task program cycle after cycle (services/executor/cycles.py), through the one safety state of
common/safety/states.py, which only the supervisor changes (services/executor/supervisor.py).
At the start of every
path it takes the current selection k, turns that path's solution into 500 Hz samples, checks them against its
own limits and its own copy of the waypoints, and hands them to the servo loop (services/executor/servo.py) on
a core of its own (services/executor/cores.py). A selection arriving during a motion takes effect at the next
path start, or, with ``switch_within_path``, from a tenth of a second ahead within the path; with
``separation`` the path's time scale follows the nearest person's distance (services/executor/reaction.py).
Whatever fails (no set, a refused trajectory, a protective stop, a lost controller) is published,
and the robot does not move until it is resolved; a stop is latched until `cadence robot resume`. The decision
maker or the store being down only means the last selection and the cached sets are used.
"""

from __future__ import annotations

import asyncio
import logging
import math
import sys
from typing import Any

from common.runtime.bus import Request
from common.runtime.clock import monotonic
from common.runtime.config import CommonSettings
from common.runtime.errors import ConfigError
from common.runtime.lifetime import name_this_thread
from common.runtime.node import Node, Out, Rejected, answers, every, node_main, on
from common.runtime.service import service_main
from common.runtime.transport import ZenohTransport
from common.safety.states import Event
from common.trajectory.task import load_task
from schemas.decision import Selection
from schemas.operator import OperatorSignal, Separation
from schemas.robot import RobotEvent
from schemas.topology import (
    OPERATOR_SEPARATION,
    OPERATOR_SEPARATION_OF,
    OPERATOR_SIGNAL,
    ROBOT_RESUME,
    SELECTION,
    Topic,
    source_chunk,
)
from services.executor.backends import Backend, backend_for
from services.executor.cycles import Cycles
from services.executor.figures import CurveFigures
from services.executor.guard import GuardProcess
from services.executor.kit import Kit
from services.executor.motions import Motions
from services.executor.persist import ExecutorStore
from services.executor.reaction import Reactions
from services.executor.records import Records
from services.executor.remote import RemoteBackend, ServoProcess
from services.executor.selection import SelectionInForce
from services.executor.servo import Servo, claim_for, servo_for
from services.executor.sets import SetCache
from services.executor.settings import Settings
from services.executor.supervisor import Supervisor
from services.executor.telemetry import Snapshot, Telemetry
from services.registry import EXECUTOR

log = logging.getLogger("cadence.executor")
NAME = EXECUTOR.name
__all__ = ["Settings", "main", "run"]


class Executor(Node):
    """The node: builds the parts (each handed its kit, its settings and the parts it calls), routes
    the bus to them, and owns only the servo loop, its core and the backend it drives."""

    role = NAME
    ends_with_work = True  # the task's last cycle (``cycles``) ends the service
    stop_grace_s = 30.0  # at a stop, a moving arm decelerates to rest and the cycles say so

    async def setup(self) -> None:
        ctx = self.ctx
        s, common, driven = ctx.settings, ctx.common, ctx.common.clock.driven
        speed = 1.0 if driven else common.speed  # a driven clock's time is data time

        def set_state(state: str) -> None:
            ctx.state = state

        self.guard: GuardProcess | None = None  # the separation guard beside a servo process
        kit = Kit(common.clock, speed, common.clock_skew_s, ctx.counters, ctx.stop, self.publish, ctx.note,
                  set_state, self.start_soon)  # fmt: skip
        task = load_task(s.task)
        self.backend: Backend
        self.loop: Servo
        if s.servo == "process" and not driven:  # the loop, its path and the robot: a process of their own
            self.claim, fifo, warnings = claim_for(s)
            try:
                proc = ServoProcess(s, speed, self.claim.core, fifo, self.servo_died)
                proc.start()
            except OSError as exc:  # no memfd, no pidfd: a kernel before 5.3, a seccomp filter
                self.claim.release()
                why = f"[executor] the servo process cannot be started ({exc}); "
                raise ConfigError(why + 'servo = "thread" runs the loop in the executor\'s process') from None
            except Exception:
                self.claim.release()
                raise
            proc.warnings = warnings + proc.warnings
            self.loop, self.backend = proc, RemoteBackend(proc)  # its name and clock as it found them
            zenoh = isinstance(ctx.bus.transport, ZenohTransport)
            if s.separation and s.separation_guard and zenoh:  # readings no flood on another key delays
                self.guard = GuardProcess.beside(proc.fd, proc.ch, s, ctx.bus.cfg, common.cell, common.clock,
                                                 common.clock_skew_s, fifo)  # fmt: skip
                if self.guard is not None:
                    self.guard.start()
        else:  # the sim arm's slow moves wait on the wall between steps, except in a lockstep cell
            self.backend = backend_for(s, task, math.inf if driven else speed)
            self.loop, self.claim = servo_for(self.backend, s, speed, self.backend.realtime, lockstep=driven)
            self.loop.start()  # its set-up now: what it could not get is known before the arm is reached
        if self.claim.core is not None:
            ctx.counters["servo_core"] = self.claim.core
        if missing := "; ".join(self.loop.warnings):
            if (s.realtime or ("required" if s.backend == "ur_rtde" else "optional")) == "required":
                self.claim.release()
                self.loop.close()
                robot = " with a real robot" if s.backend == "ur_rtde" else ""
                raise ConfigError(f"[executor] the servo loop cannot run in real time{robot}: {missing} "
                                  '(realtime = "required")')  # fmt: skip
            log.warning("the servo loop is not real-time: %s", missing)
            ctx.detail = f"servo not real-time: {missing}"
        folder = common.data_path / NAME
        # each part gets the kit and the parts it calls, never this node (services/executor/kit.py)
        self.safety = Supervisor(kit, s, self.backend)
        guard = self.guard
        nearest = guard.nearest if guard is not None else lambda: None
        self.reactions = Reactions(kit, s, self.safety, task.limits, self.backend.actual_q, nearest)
        self.sets = SetCache(ctx.bus, folder, task)
        self.figures = CurveFigures(task.limits, s.arm(), s.separation)
        records = Records(kit, ExecutorStore(folder), self.safety)
        self.safety.latched_to(records.latch)
        self.chosen = SelectionInForce(kit, s, ctx.bus, self.safety, records, self.sets, self.reactions)
        motions = Motions(
            kit, s, self.safety, self.backend, self.loop, self.reactions, self.figures, task.limits
        )
        self.cycles = Cycles(
            kit, s, task, self.safety, self.backend, self.sets, records, self.chosen, motions
        )
        self.say_sets = kit.note("sets")  # the sets' fetching (SetCache.keep), after the cycles' files
        self.telemetry = Telemetry(kit, self.backend, task, self.snapshot)
        self.cycles.load()
        self.connected = False
        self.timed_at = monotonic()

    def servo_died(self, why: str) -> None:
        """The servo process died between motions: a protective stop, latched (one in motion ends the
        motion as a fault, which the cycles latch)."""
        self.ctx.counters["servo_deaths"] += 1
        self.safety.event("protective_stop", why, self.safety.path_id)
        self.safety.fire(Event.FAULT, why)

    @on(SELECTION, arrival=True)  # judged as it comes: a replayed flood cannot push a new one out of a queue
    def on_selection(self, sel: Selection) -> None:
        ahead_s = (sel.t_ns - self.ctx.common.clock.now_ns()) / 1e9
        if ahead_s > self.ctx.common.clock_skew_s:  # it would stand until a later stamp: never
            raise Rejected("ahead", f"a selection stamped {ahead_s:.3f} s ahead of the executor's clock")
        self.chosen.select(sel)

    def about_now(self, sig: OperatorSignal) -> None:
        """On arrival, before the queue: a signal stamped outside its admission window is refused."""
        self.cycles.signals.admit(sig, self.ctx.common.clock.now_ns())

    @on(OPERATOR_SIGNAL, screen="about_now")
    async def on_signal(self, sig: OperatorSignal) -> Out:
        self.cycles.signals.receive(sig)
        return []

    @on(OPERATOR_SEPARATION, arrival=True)  # every reading counts, kept per source as it comes
    def on_separation(self, sep: Separation) -> None:
        self.reactions.receive(sep, own_key=False)

    @on(OPERATOR_SEPARATION_OF, arrival=True, keyed=True)  # a source's own key: its account's alone
    def on_separation_of(self, key: str, sep: Separation) -> None:
        chunk = key.rsplit("/", 1)[-1]
        if chunk != source_chunk(sep.source):
            raise Rejected("impostor", f"a reading under '{sep.source}' on {key}: the key of another source")
        self.reactions.receive(sep, own_key=True)

    def reads(self, topic: Topic[Any]) -> bool:
        watched = topic.family in (OPERATOR_SEPARATION.family, OPERATOR_SEPARATION_OF.family)
        return not watched or self.ctx.settings.separation

    @every
    async def scale(self) -> Out:
        await self.reactions.look()
        return []

    @answers(ROBOT_RESUME)
    async def resume(self, req: Request) -> RobotEvent:
        return await self.safety.resume_by(req.params.get("by", ""))

    def snapshot(self) -> Snapshot:
        """What the parts say of the arm now, for robot/state."""
        r, sel = self.reactions, self.chosen.selection
        return Snapshot(self.safety.motion, self.safety.path_id, self.chosen.k, self.cycles.waiting_for,
                        r.scale_now(), r.shown_m() if r.on else None,
                        sel.seq if sel is not None else None)  # fmt: skip

    @every
    async def state(self) -> Out:
        common = self.ctx.common  # the servo's timing (percentiles of its ring) once a status period
        if not common.clock.driven and monotonic() - self.timed_at >= common.status_period_s:
            await self.time_servo()
        return self.telemetry.sample() if self.connected else []

    async def time_servo(self) -> None:
        """The servo's tick timing in the status (`cadence top`, `cadence bench executor --load`)."""
        self.timed_at = monotonic()
        t = await asyncio.to_thread(self.loop.summary)
        c = self.ctx.counters
        c["servo_ticks"], c["overruns"] = t.ticks, t.overruns
        c["servo_longest_overrun_run"] = t.longest_overrun_run
        c["servo_p50_us"], c["servo_p99_us"] = round(t.p50_err_us), round(t.p99_err_us)
        c["servo_p99.9_us"], c["servo_max_us"] = round(t.p999_err_us), round(t.max_err_us)
        if self.guard is not None:
            if (why := self.guard.check()) is not None:
                c["guard_deaths"] += 1
                self.safety.event("info", why, self.safety.path_id)
            for name, value in self.guard.figures().items():  # figures, not counts: Counter.update adds
                c[name] = value

    async def work(self) -> None:
        if not await self.safety.connect():
            return
        self.connected = True
        k_now = lambda: self.chosen.selection.k if self.chosen.selection is not None else 1  # noqa: E731
        stop = self.ctx.stop
        # beside the cycles, in the node's task group: each says its own errors; they end with the service
        self.start_soon(self.sets.keep(self.ctx.settings.query_timeout_s, stop, self.say_sets), "the sets")
        self.start_soon(self.brake_on_stop(), "the brake at a stop")
        self.start_soon(self.figures.prefetch(self.sets, k_now, stop), "the curves' figures")
        if not self.ctx.settings.separation:
            self.safety.event("info", "separation monitoring is off ([executor] separation = false): the arm "
                              "runs at the planned speed whoever is near")  # fmt: skip
        else:
            self.safety.event("info", "S_p budgets the robot's own stops beside the executor's ramp: "
                              f"{self.ctx.settings.stops().source}")  # fmt: skip
            if self.ctx.settings.backend == "ur_rtde":  # a software ramp is not safety-rated (ISO 13849)
                self.safety.event("info", "separation monitoring slows the arm as a second layer, not a "
                                  "safety function: the scanners' safety outputs must be wired to the "
                                  "controller's safeguard or reduced-speed inputs")  # fmt: skip
        try:
            await self.cycles.start()
            await self.cycles.run()
            if not self.ctx.stop.is_set():
                self.safety.fire(Event.SHUTDOWN, "cycles done")
        finally:
            self.loop.request_stop()

    async def brake_on_stop(self) -> None:
        """SIGTERM during a motion: a decelerating stop, then the cycles end."""
        await self.ctx.stop.wait()
        self.loop.request_stop()

    async def close(self) -> None:
        if self.guard is not None:
            self.guard.close()
        self.loop.request_stop()
        await asyncio.to_thread(self.loop.close)
        await asyncio.to_thread(self.backend.close)
        self.claim.release()
        log.info("servo timing: %s", self.loop.summary())


main = node_main(Executor)


def prepare(settings: Settings, common: CommonSettings) -> None:
    backend_for(settings, load_task(settings.task), common.speed)  # a bad task file: one line, exit 2
    settings.sensors()  # monitoring with no source, or a C below ISO 13855's: one line, exit 2
    settings.arm()  # a stopping table that does not reach full speed: one line, exit 2
    if settings.resume_policy == "auto" and settings.backend != "sim":
        raise ConfigError(
            f'[{NAME}] resume_policy: "auto" is for the sim backend only; a real robot\'s stop needs a person'
        )


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv, prepare)


if __name__ == "__main__":
    name_this_thread(NAME)  # the event loop's thread, beside the servo's (`top -H`): its own process
    sys.exit(run())
