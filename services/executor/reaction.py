"""Reacting within a path (issue 31): the time scale follows the nearest person's distance, and a new
selection takes effect from a little ahead on the path instead of at the next path start.

Both change what the servo loop is playing (services/executor/playback.py) while it plays, so both are
planned here, one at a time (a lock), each checked against the other's change still pending: a ramp of
the scale is checked on the current curve and on a pending switched one; a switch is checked with the
ramps in force and pending. What reaches the loop was checked at every controller step it covers.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import Callable

import numpy as np

from common.runtime.node import Node
from common.separation import Ssm, path_speed, stepped
from common.trajectory.limits import JointLimits
from common.trajectory.scaling import (
    DT,
    LIMIT_RTOL,
    Curve,
    Ramp,
    plan_ramp,
    ramp_ratio,
    stop_time,
    switch_curve,
)
from common.trajectory.task import PathPlan
from schemas.operator import Separation
from services.executor.playback import Playback
from services.executor.settings import Settings
from services.executor.supervisor import Supervisor

log = logging.getLogger("cadence.executor")
RAISE_BY = 0.1  # a higher σ is taken only when it is this much higher (or 1): no ramp per centimetre
LEAD_S = 0.02  # a ramp starts at least this far ahead of the loop (wall s): time to plan and hand it over


@dataclasses.dataclass(slots=True)
class Running:
    """The path being played: its own copy, its safety figures, the loop's source."""

    path: PathPlan
    playback: Playback
    ssm: Ssm
    speed_m_s: float  # the fastest point of the arm at σ = 1 on this path
    k: int


def path_figures(curve: Curve, limits: JointLimits, ssm: Ssm) -> tuple[Ssm, float]:
    """The path's SSM (T_s: its longest stop) and its top link speed at σ = 1; before the motion, in a
    worker thread."""
    t = np.arange(0.0, curve.t_f + 0.02, 0.02)
    top = path_speed(curve.at(t, order=0)[0], 0.02)
    return dataclasses.replace(ssm, stop_time_s=max(ssm.stop_time_s, stop_time(curve, limits))), top


class Reactions:
    def __init__(self, node: Node, safety: Supervisor, limits: JointLimits) -> None:
        self.node, self.safety, self.limits = node, safety, limits
        s: Settings = node.ctx.settings
        self.settings, self.clock = s, node.ctx.common.clock
        self.ssm = Ssm(s.human_speed_m_s, s.reaction_s, s.stop_time_s, s.intrusion_m, s.uncertainty_m,
                       s.separation_max_age_s)  # fmt: skip
        self.separation: Separation | None = None
        self.running: Running | None = None
        self.lock = asyncio.Lock()
        self.zone = ""  # the last zone said in an event: full, reduced, hold, unknown
        self.idle_scale = 1.0 if not s.separation else 0.0
        self.last_speed_m_s = 1.0  # the top speed of the last path run: the scale shown between paths

    # --- the scale ------------------------------------------------------------------------------

    def admit(self, sep: Separation) -> None:
        self.separation = sep

    def age_s(self) -> float | None:
        """How old the last separation is, in wall seconds (the sensor's own latency included)."""
        if self.separation is None:
            return None
        data_s = (self.clock.now_ns() - self.separation.t_ns) / 1e9
        return self.clock.wall_s(max(0.0, data_s)) + self.separation.age_s

    def wanted(self, ssm: Ssm, speed_m_s: float) -> float:
        if not self.settings.separation:
            return 1.0
        age = self.age_s()
        distance = None if self.separation is None or age is None else self.separation.distance_m
        sigma = ssm.scale(distance, age if age is not None else np.inf, speed_m_s)
        return stepped(sigma)

    def scale_now(self) -> float:
        r = self.running
        return r.playback.sigma if r is not None else self.idle_scale

    def start_ramp(self, path: PathPlan, carried: Ramp, ssm: Ssm, speed_m_s: float) -> Ramp:
        """The σ-state a path starts with: at rest at its start, any σ (the wanted one); otherwise the one
        the last path ended with, carried over."""
        b = path.boundary
        if not any(np.any(x) for x in (b.v0, b.a0, b.j0)):
            return Ramp.hold(0.0, 0.0, self.wanted(ssm, speed_m_s))
        return carried

    async def keep_scale(self) -> None:
        """Every ``scale_period_s``: the σ wanted for the distance now, planned as a ramp when it differs.
        A look that fails is said and tried again at the next: this task dying would leave the arm at
        whatever scale it had, near a person or not."""
        period = self.settings.scale_period_s
        while not self.node.ctx.stop.is_set():
            await asyncio.sleep(period)
            try:
                await self.look()
            except Exception as e:  # any failure of one look: the next one runs
                self.node.ctx.counters["scale_errors"] += 1
                if self.node.ctx.counters["scale_errors"] == 1:  # the traceback once, not 50 times a second
                    log.exception("the scale's look failed")
                r = self.running
                self.safety.event("info", f"the time scale could not be planned ({e!r}): trying again",
                                  r.path.id if r else None)  # fmt: skip

    async def look(self) -> None:
        r = self.running
        if r is None:
            self.idle_scale = self.wanted(self.ssm, self.last_speed_m_s)
            self.say_zone(self.idle_scale)
            return
        self.last_speed_m_s = r.speed_m_s
        wanted = self.wanted(r.ssm, r.speed_m_s)
        self.say_zone(wanted)
        pb = r.playback
        pending = pb.pending_ramp
        current = (pending[0] if pending is not None else pb.ramp).target
        if abs(wanted - current) < 1e-9 or (current < wanted < min(1.0, current + RAISE_BY)):
            return
        async with self.lock:
            await self.offer_ramp(r, wanted)

    async def offer_ramp(self, r: Running, sigma: float) -> None:
        pb = r.playback
        base = pb.ramp
        t_min = pb.t + LEAD_S * self.node.ctx.common.speed  # playback time runs at the clock's speed
        joined = pb.pending_curve  # one read: the loop may take it meanwhile
        also = [joined[1]] if joined is not None else []
        ramp = await asyncio.to_thread(plan_ramp, pb.curve, base, t_min, sigma, self.limits, also)
        if ramp is None:
            self.node.ctx.counters["ramps_refused"] += 1
            return
        if pb.offer_ramp(ramp, base):
            self.node.ctx.counters["ramps"] += 1

    def say_zone(self, sigma: float) -> None:
        age = self.age_s()
        sep = self.separation
        if sep is None or age is None or age > self.ssm.max_age_s:
            zone = "unknown"
            why = "no separation yet" if sep is None else f"the last separation is {age:.2f} s old"
            text = f"{why}: holding on the path"
        else:
            zone = "full" if sigma >= 1.0 else "hold" if sigma <= 0.0 else "reduced"
            text = f"a person at {sep.distance_m:.2f} m ({sep.source}): scale {sigma:.2f}"
        if zone != self.zone:
            self.zone = zone
            r = self.running
            self.safety.event("scale", text, r.path.id if r else None)

    # --- a new k within the path ------------------------------------------------------------------

    def plan_switch(
        self, r: Running, h_new: np.ndarray, s_switch: float, base: Curve, ramps: list[Ramp]
    ) -> Curve | None:
        """In a worker thread: the joined curve, checked as a trajectory and under every ramp in force."""
        sw = switch_curve(base, r.path, h_new, s_switch, self.limits)
        if sw is None or any(ramp_ratio(sw.curve, x, self.limits) > 1 + LIMIT_RTOL for x in ramps):
            return None
        return sw.curve

    async def switch(self, k: int, h_new: np.ndarray, wanted: Callable[[], int]) -> bool:
        """Re-time the rest of the running path with solution ``k`` (its intervals ``h_new``), from
        ``switch_lead_s`` ahead. ``wanted()`` says the k wanted now: a newer selection wins. True when
        the loop took it.

        The lock covers the planning and the offer only: a held arm (σ = 0) reaches the switch point only
        when the scale rises again, and that ramp needs the lock."""
        for _ in range(3):  # the loop may pass the switch point while it is planned: try again
            async with self.lock:
                r = self.running
                if r is None or wanted() != k or k == r.k:
                    return False
                pb = r.playback
                ahead = self.settings.switch_lead_s * self.node.ctx.common.speed * max(pb.sigma, 0.05)
                s_switch, base, offer = pb.s + ahead, pb.curve, pb.pending_ramp
                ramps = [pb.ramp] + ([offer[0]] if offer is not None else [])
                joined = await asyncio.to_thread(self.plan_switch, r, h_new, s_switch, base, ramps)
                if joined is None:
                    why = (
                        f"k = {k} cannot take over within '{r.path.id}' inside the limits: from the next path"
                    )
                    self.safety.event("info", why, r.path.id)
                    return False
                if not pb.offer_curve(s_switch, joined, base):
                    continue
            while pb.pending_curve is not None and not pb.finished and self.running is r:
                await asyncio.sleep(DT)  # the loop takes it at s_switch
            if pb.curve is joined:
                text = (f"k {r.k} → {k} within '{r.path.id}' at s = {s_switch:.3f} s of "
                        f"{base.t_f:.3f} s; it now ends at {joined.t_f:.3f} s")  # fmt: skip
                self.safety.event("switch", text, r.path.id)
                r.k = k
                return True
        return False
