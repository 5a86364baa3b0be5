"""A motion on the servo loop (DESIGN §8, §9): a task's path at a k, or the slow move to a path's start,
each checked, scaled by the person's distance under the lease on it and the controller's watchdog, and
ended by a fault as a protective stop. What it ends at is carried into the next.
"""

from __future__ import annotations

import asyncio

import numpy as np

from common.robot.ur16e import JointLimits
from common.safety.separation import Figures
from common.safety.states import Event
from common.trajectory.approach import approach
from common.trajectory.scaling import Curve, Ramp, resume_ramp
from common.trajectory.task import PathPlan
from common.trajectory.validate import check_trajectory
from services.executor.backends import Backend
from services.executor.figures import CurveFigures
from services.executor.kit import Kit, Safety
from services.executor.playback import PathRun
from services.executor.reaction import Reactions
from services.executor.servo import MotionResult, Servo
from services.executor.settings import Settings

RATE_HZ = 500.0


class Motions:
    """Owns the arm's motions on the servo loop, one at a time, and the σ-state the last one ended with."""

    def __init__(
        self,
        kit: Kit,
        settings: Settings,
        safety: Safety,
        backend: Backend,
        servo: Servo,
        reactions: Reactions,
        figures: CurveFigures,
        limits: JointLimits,
    ) -> None:
        self.kit, self.settings, self.safety, self.backend, self.servo = kit, settings, safety, backend, servo
        self.reactions, self.figures, self.limits = reactions, figures, limits
        self.carried = Ramp.hold(0.0, 0.0, 1.0)  # the σ-state the last motion ended with

    def prepare(self, h: np.ndarray, own: PathPlan, claimed: np.ndarray) -> tuple[Curve, Figures]:
        """In a worker thread, before the motion: the trajectory checked against the executor's own
        limits and waypoints (raises TrajectoryRejected), its curve, and with separation monitoring on,
        its top speed and longest stop (S_p's v_r and T_s)."""
        check_trajectory(h, own, self.limits, claimed)
        curve = Curve.of(h, own)
        return curve, self.figures.of(own, h, curve)

    async def reach(self, q_start: np.ndarray, path_id: str, where: str = "the start of") -> bool:
        """Start-up safety: the arm must be where the path starts (its first waypoint, or the point it goes
        on from after a stop: ``where``) before the path runs."""
        q = self.backend.actual_q()
        off = float(np.max(np.abs(q - q_start)))
        s = self.settings
        if off <= s.start_tolerance_rad:
            return True
        if s.start_policy == "refuse":
            why = f"the arm is {off:.4f} rad from {where} '{path_id}'; not moving"
            self.safety.event("refused", why, path_id)
            self.safety.fire(Event.REFUSE, why)
            return False
        self.safety.event(
            "info", f"the arm is {off:.4f} rad from {where} '{path_id}': moving there slowly", path_id
        )
        self.safety.fire(Event.MOVE, f"moving slowly to {where} '{path_id}'")
        own, h = approach(q, q_start, s.start_speed, s.start_acceleration, self.limits,
                          f"approach to {path_id}")  # fmt: skip
        curve = Curve.of(h, own)
        figures = await asyncio.to_thread(self.figures.of, own, h, curve, False)  # made once
        result, _ = await self.play(own, curve, figures, 0)  # no solution of a set: no k
        arrived = float(np.max(np.abs(self.backend.actual_q() - q_start))) <= s.start_tolerance_rad
        if result.outcome == "done" and arrived:
            self.safety.fire(Event.DONE)
            return True
        if result.outcome == "stopped" or self.kit.stop.is_set():
            self.safety.fire(Event.SHUTDOWN)
            return False
        self.protective_stop(
            f"the move to {where} '{path_id}' did not arrive: {self.backend.fault() or result.outcome}",
            path_id,
        )
        return False

    async def resume_ramp(self, curve: Curve, figures: Figures, at: float) -> Ramp | None:
        """The scale of a path going on from rest at path time ``at``: up to what the distance allows now."""
        sigma = self.reactions.allowed_now(figures)
        return await asyncio.to_thread(resume_ramp, curve, at, sigma, self.limits)

    def protective_stop(self, why: str, pid: str) -> None:
        """A motion ended by a fault (the arm's, the controller's, a run of overruns): latched, and said."""
        self.safety.event("protective_stop", why, pid)
        self.safety.fire(Event.FAULT, why)
        self.kit.counters["protective_stops"] += 1

    async def play(
        self, own: PathPlan, curve: Curve, figures: Figures, k: int, start: Ramp | None = None
    ) -> tuple[MotionResult, PathRun]:
        """One motion on the servo loop, a task's path or the slow move to its start: at the scale the
        person's distance allows, under the lease on it and the controller's watchdog. ``start``: the
        scale of a path going on from within (``resumed``)."""
        # prepare() arms a controller's watchdog, here, outside the loop (a servo process: there, before the
        # motion); each step's target is then only converted to the form servo takes, touching nothing
        self.backend.prepare(own.waypoints[:1])
        start = start or self.reactions.start_ramp(own, self.carried, figures)
        here = self.backend.actual_q()  # held there until the path advances
        run = PathRun(own, curve, figures, k, start, self.servo.playback, self.limits, self.kit.speed,
                      self.reactions.arm, here)  # fmt: skip
        self.reactions.running(run)
        settle = round(self.settings.settle_s * RATE_HZ)
        counters = self.kit.counters
        try:
            result: MotionResult = await asyncio.wrap_future(self.servo.run(run.playback, settle))
        finally:
            run.ended.set()
            self.reactions.ended(run)
            counters["ramps"] += run.ramps
            counters["ramps_refused"] += run.ramps_refused
            counters["lease_lapses"] += run.playback.lapses - run.lapses_counted
            counters["unchecked_stops"] += run.playback.unchecked
            self.carried = run.playback.state()
        await asyncio.to_thread(self.backend.motion_ended)
        counters["overruns"] = self.servo.overruns
        pid = own.id
        if result.overruns:
            self.safety.event("overrun", f"{result.overruns} servo overruns during '{pid}'", pid, repeat=True)
        if lapses := run.playback.lapses:  # the looks at the distance stopped coming: the loop stopped
            unchecked = run.playback.unchecked
            why = f" ({unchecked} unchecked: no planned stop fitted)" if unchecked else ""
            said = f"the scale's lease ran out {lapses} times during '{pid}': the servo took its stop{why}"
            self.safety.event("scale", said, pid, repeat=True)
        return result, run
