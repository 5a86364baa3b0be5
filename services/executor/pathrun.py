"""The path in progress, and its one owner (STYLE 15): the playback the servo loop plays
(services/executor/playback.py), the ramps of the time scale and the switch of solution offered to it, and
the path's SSM figures (common/safety/separation.py ``Figures``: top link speed and longest stop of the curve
being
played, and of a switched one while it is pending).

Everything that changes what the loop plays goes through here, one change planned at a time (``lock``),
each planned from one consistent picture of what is in force (``Playback.now``) and checked against what
else is pending: a ramp on the current curve and on a pending switched one, a switch under the ramps in
force and pending. An offer goes into the loop's one mailbox, and the planner waits, without the lock,
for the loop's word on it (``changed``: the loop's notification, one per change, never a poll).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

import numpy as np

from common.robot.ur16e import JointLimits
from common.runtime.clock import monotonic
from common.runtime.service import first_of
from common.safety.geometry import Arm
from common.safety.separation import BARE, Figures
from common.trajectory.scaling import LIMIT_RTOL, Curve, Ramp, plan_ramp, ramp_ratio, switch_curve
from common.trajectory.task import PathPlan
from services.executor.playback import SIGMA_EPS, InForce, Offer, Playback, Switch
from services.executor.servo import MotionResult, Servo
from services.executor.settings import RAMP_LEAD_S

Scale = Callable[[Figures], float]  # the σ the person's distance allows now, for a curve of these figures


class PathRun:
    def __init__(
        self,
        path: PathPlan,
        curve: Curve,
        figures: Figures,
        k: int,
        start: Ramp,
        convert: Callable[[np.ndarray], object],
        limits: JointLimits,
        speed: float = 1.0,
        arm: Arm = BARE,
    ) -> None:
        """``speed``: playback seconds per wall second (the clock's speed), for leads given in wall time;
        ``arm``: the robot and its tool, whose fastest point a switched curve's figures take."""
        self.path, self.k, self.figures, self.limits, self.speed = path, k, figures, limits, speed
        self.arm = arm
        self.pending_figures: Figures | None = None  # of a switched curve not yet taken
        self.changed = asyncio.Event()
        self.ended = asyncio.Event()
        loop = asyncio.get_running_loop()

        def notify() -> None:  # from the servo thread, once per change
            with contextlib.suppress(RuntimeError):  # a loop already closed: nobody waits
                loop.call_soon_threadsafe(self.changed.set)

        self.playback = Playback(curve, start, convert, notify, loop.time)
        self.lock = asyncio.Lock()
        self.ramps = self.ramps_refused = 0
        self.switched_at = 0.0  # the path time of the last switch taken
        self.plan_s = 0.2  # how long planning a switch takes (wall s, smoothed): the switch point's lead

    @property
    def guard(self) -> Figures:
        """The figures σ is chosen for: the curve played, and a switched one while it may still be taken."""
        pending = self.pending_figures
        return self.figures if pending is None else self.figures.worst(pending)

    async def play(self, loop: Servo, settle_ticks: int) -> MotionResult:
        try:
            return await asyncio.wrap_future(loop.run(self.playback, settle_ticks))
        finally:
            self.ended.set()

    async def until(self, done: Callable[[], bool]) -> bool:
        """Wait for the loop to make ``done`` true, woken by each change it makes; False when the motion
        ended first."""
        while not done():
            if self.ended.is_set() or self.playback.finished:
                return done()
            self.changed.clear()
            await first_of(self.changed.wait(), self.ended.wait())
        return True

    async def post(self, base: InForce, ramp: Ramp | None = None, switch: Switch | None = None) -> bool:
        """Offer changes planned from ``base`` and wait for the loop's word: True when it adopted them."""
        pb = self.playback
        if not pb.offer(ramp, switch, base):
            return False
        offer = pb.mailbox
        await self.until(lambda: pb.settled(offer))
        now = pb.now
        return (ramp is None or ramp is now.ramp or ramp is now.pending_ramp) and (
            switch is None or switch is now.pending_switch or now.curve is switch.curve
        )

    # --- the scale ------------------------------------------------------------------------------------

    async def ramp_to(self, sigma: float, lead_s: float) -> Ramp | None:
        """Plan and offer a ramp to ``sigma`` from ``lead_s`` (wall) ahead of the loop, inside the limits
        on the curve in force and on a pending switched one: the ramp the loop adopted, or None."""
        async with self.lock:
            pb = self.playback
            now = pb.now
            also = [now.pending_switch.curve] if now.pending_switch is not None else []
            args = (now.curve, now.ramp, pb.t + lead_s * self.speed, sigma, self.limits, also)
            ramp = await asyncio.to_thread(plan_ramp, *args)
            if ramp is None:
                self.ramps_refused += 1
                return None
            took = await self.post(now, ramp=ramp)
            self.ramps += took
            return ramp if took else None

    async def keep_fallback(self, lead_s: float, keep_s: float) -> None:
        """A stop planned ``lead_s`` (wall) ahead for the loop to take should the lease run out, planned
        again once the state changed or its start is under ``keep_s`` ahead (Playback, the lease)."""
        pb = self.playback
        now, fb = pb.now, pb.fallback
        if now.pending_ramp is not None or now.ramp.target <= 0.0:  # a change in flight, or held already
            return
        if (
            fb is not None
            and fb.base is now
            and fb.ramp is not None
            and fb.ramp.t0 >= pb.t + keep_s * self.speed
        ):
            return
        also = [now.pending_switch.curve] if now.pending_switch is not None else []
        args = (now.curve, now.ramp, pb.t + lead_s * self.speed, 0.0, self.limits, also)
        stop = await asyncio.to_thread(plan_ramp, *args)
        if stop is not None and pb.now is now:
            pb.fallback = Offer(now, ramp=stop)

    # --- a new k within the path ----------------------------------------------------------------------

    def plan_switch(self, now: InForce, h_new: np.ndarray, s_switch: float) -> tuple[Curve, Figures] | None:
        """In a worker thread: the joined curve, checked as a trajectory and under every ramp in force and
        pending, and its figures from the switch on."""
        sw = switch_curve(now.curve, self.path, h_new, s_switch, self.limits)
        ramps = [r for r in (now.ramp, now.pending_ramp) if r is not None]
        if sw is None or any(ramp_ratio(sw.curve, r, self.limits) > 1 + LIMIT_RTOL for r in ramps):
            return None
        return sw.curve, Figures.of(sw.curve, self.limits, s_switch, arm=self.arm)

    async def switch(
        self, k: int, h_new: np.ndarray, wanted: Callable[[], int], lead_s: float, allowed: Scale
    ) -> tuple[bool, str]:
        """Re-time the rest of the path with solution ``k`` (intervals ``h_new``) from ``lead_s`` (wall, at
        σ = 1) ahead, or from where a pending ramp ends, whichever is later; ``wanted()`` is the k
        wanted now (a newer selection wins). The switched curve is taken only at a σ its own figures allow
        for the distance then (``allowed``): when the arm is faster, a ramp down comes first. (taken, why
        not)."""
        why = "no longer wanted"
        try:
            for _ in range(4):  # the loop may pass the switch point, or run faster than allowed there
                async with self.lock:
                    pb = self.playback
                    now = pb.now
                    if wanted() != k or k == self.k or pb.finished:
                        return False, "no longer wanted"
                    ahead = (lead_s + self.plan_s) * self.speed * max(pb.sigma, 0.05)
                    ramp = now.pending_ramp or now.ramp
                    ends = float(ramp.state(np.array([max(ramp.end, pb.t)]))[0][0])
                    s_switch = max(pb.s + ahead, ends + 1e-6)
                    started = monotonic()
                    planned = await asyncio.to_thread(self.plan_switch, now, h_new, s_switch)
                    self.plan_s = 0.7 * self.plan_s + 0.3 * (monotonic() - started)
                    if planned is None:
                        return False, f"k = {k} cannot take over within '{self.path.id}' inside the limits"
                    joined, figures = planned
                    self.pending_figures = figures
                    top = allowed(figures)
                    if now.target > top + SIGMA_EPS:  # slower first, on both curves; the switch after it
                        t_min = pb.t + RAMP_LEAD_S * self.speed
                        args = (now.curve, now.ramp, t_min, top, self.limits, [joined])
                        slow = await asyncio.to_thread(plan_ramp, *args)
                        if slow is not None:
                            self.ramps += await self.post(now, ramp=slow)
                        why = f"the arm was faster than k = {k} allows near the person"
                        continue
                    offer = Switch(s_switch, joined, top)
                    if not await self.post(now, switch=offer):
                        why = "the loop passed the switch point first"
                        continue
                # a held arm reaches the switch point only once the scale frees it
                await self.until(lambda: self.playback.now.pending_switch is not offer)  # noqa: B023
                if self.playback.curve is joined:
                    self.figures, self.k, self.switched_at = figures, k, s_switch
                    return True, ""
                why = "the scale rose past what k allows before the switch point"
            return False, why
        finally:
            self.pending_figures = None
