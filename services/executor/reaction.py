"""Speed and separation monitoring in the executor (DESIGN §8; common/safety/separation.py): every source's
distance on ``operator/separation``, the nearest fresh one winning, and the time scale σ it allows for the
path in progress, looked at every ``scale_period_s`` (the node's timer) and handed to the path's owner
(``PathRun``, services/executor/playback.py) as a ramp. Between paths the scale a path would start at is
kept, and the zone the arm is in (full speed, reduced, held, unknown) is said when it changes, at most once
a second per zone, with the changes folded in between counted.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from common.robot.ur16e import JointLimits
from common.runtime.clock import monotonic
from common.safety.geometry import Sensor
from common.safety.separation import Adoption, Figures, Nearest
from common.safety.watch import Watch
from common.trajectory.scaling import Ramp
from common.trajectory.task import PathPlan
from schemas.operator import Separation
from services.executor.kit import Kit, Safety
from services.executor.playback import RAMP_LEAD_S, SIGMA_EPS, PathRun
from services.executor.settings import Settings

log = logging.getLogger("cadence.executor")
RAISE_BY = 0.1  # a higher σ is taken only when it is this much higher (or 1): no ramp per centimetre
SAY_EVERY_S = 1.0  # a zone is said at most this often (two sources flapping made 20–40 events a second)


class Zones:
    """When to say the zone the arm is in: at a change, at most once every ``every_s`` per zone; what
    changed meanwhile is counted and said with the next."""

    def __init__(self, every_s: float = SAY_EVERY_S) -> None:
        self.every_s = every_s
        self.current = self.said = ""
        self.said_at: dict[str, float] = {}
        self.changes = 0

    def update(self, zone: str, now: float) -> int | None:
        """None: nothing to say now; else say ``zone``, this many changes folded before it."""
        if zone != self.current:
            self.current, self.changes = zone, self.changes + 1
        if zone == self.said or now - self.said_at.get(zone, -np.inf) < self.every_s:
            return None
        folded, self.changes = self.changes - 1, 0
        self.said, self.said_at[zone] = zone, now
        return folded


class Reactions:
    """Owns what the executor knows of the people near the arm: the readings kept per source, the nearest,
    the scale it allows on the path running (the look, the lease, the adoption's lateness), and the zone
    said. The figures of the curves it scales are figures.py's."""

    def __init__(
        self,
        kit: Kit,
        s: Settings,
        safety: Safety,
        limits: JointLimits,
        joints: Callable[[], np.ndarray],
        guard: Callable[[], Nearest | None] = lambda: None,
    ) -> None:
        """``joints``: the arm's joints now (the backend's), where a reading's points are measured to;
        ``guard``: the nearest as the separation guard beside the servo judged it, while it runs
        (guard_process.py): the same readings by the same rules, read as they came, whatever this loop has
        still to decode; its word is in force within its grace, so these looks being late holds nothing."""
        self.kit, self.safety, self.limits, self.joints, self.guard = kit, safety, limits, joints, guard
        self.guarded = False  # the last look took the guard's nearest
        self.clock, self.on = kit.clock, s.separation
        self.watch = Watch(s.rules(kit.clock_skew_s))
        # C is each source's own: a reading is kept as S − C, the room a person has before S_p's other terms
        self.ssm, self.arm, self.sources = self.watch.rules.ssm, self.watch.rules.arm, self.watch.sources
        self.adoption = Adoption(s.adoption_budget_s)
        self.offered_on: PathRun | None = None  # the path the ramp the adoption waits for was offered on
        self._counted_at = -math.inf
        self.nearest = Nearest(None, "", "no separation yet")
        self.run: PathRun | None = None
        self.idle_scale = 0.0 if self.on else 1.0
        self.last_figures = Figures(1.0, 0.0)  # of the last path run: the scale shown between paths
        self.zones = Zones()

    # --- the distance -------------------------------------------------------------------------------

    def receive(self, sep: Separation, own_key: bool = True) -> None:
        """A reading as it arrives, judged on this executor's clock before its content is looked at
        (common/safety/watch.py: refused, ``Rejected`` and counted, or kept as the person's room at the
        joints now), and its arrival noted for the adoption's measure."""
        stamp_age = self.clock.loop_s((self.clock.now_ns() - sep.t_ns) / 1e9)
        now = monotonic()
        self.watch.receive(sep, own_key, stamp_age, now, self.joints())
        self.adoption.arrived(now)

    def sensor(self, name: str) -> Sensor:
        return self.watch.sensor(name)

    def shown_m(self) -> float | None:
        """S of the nearest reading, as a person reads it (the distance, not the room past C)."""
        n = self.nearest
        return None if n.distance_m is None else n.distance_m + self.sensor(n.source).intrusion_m

    def look_distance(self) -> Nearest:
        """The nearest now: this loop's own, or, while a guard runs, the nearer of the two (a distance this
        loop has and the guard has not yet seen counts); a flood this loop saw holds the arm whatever the
        guard says. Only where this loop has no fresh distance at all does the guard's alone count: this
        loop being late (a flood on another key it must decode) is not a silent sensor, and the guard, which
        reads the separation keys alone, sees a sensor that is."""
        own, guard = self.sources.nearest(monotonic()), self.guard()
        self.guarded = guard is not None
        if guard is None or self.sources.flooding:
            self.nearest = own
        elif own.distance_m is None or guard.distance_m is None:  # the guard's hold, or its distance alone
            self.nearest = guard
        else:
            self.nearest = own if own.distance_m < guard.distance_m else guard
        return self.nearest

    def allowed(self, figures: Figures) -> float:
        """σ, stepped, for the nearest fresh distance now, on a curve of these figures (1 when off); 0 while
        the executor answers readings later than T_r allows it (``Adoption``). The arm runs on at the
        scale in force (or the one it heads for, if higher) through T_r: S_r counts that one."""
        if not self.on:
            return 1.0
        late = self.adoption.late and not self.guarded
        r = self.run
        in_force = max(r.playback.sigma, r.playback.now.target) if r is not None else 0.0
        return 0.0 if late else self.watch.allowed(figures, self.nearest, in_force, monotonic())

    # --- the scale ----------------------------------------------------------------------------------

    def scale_now(self) -> float:
        r = self.run
        return r.playback.sigma if r is not None else self.idle_scale

    def start_ramp(self, path: PathPlan, carried: Ramp, figures: Figures) -> Ramp:
        """The σ-state a path starts with: at rest at its start, the σ allowed now on it; otherwise the one
        the last path ended with, carried over."""
        b = path.boundary
        if not any(np.any(x) for x in (b.v0, b.a0, b.j0)):
            return Ramp.hold(0.0, 0.0, self.allowed_now(figures))
        return carried

    def allowed_now(self, figures: Figures) -> float:
        """σ for the nearest distance now (looked at afresh), before a motion starts."""
        if self.on:
            self.look_distance()
        return self.allowed(figures)

    def running(self, run: PathRun) -> None:
        """A motion begins on the servo loop: the looks scale it, and its starting scale is leased (the
        first look may be late)."""
        self.run = run
        self.lease(run)

    def ended(self, run: PathRun) -> None:
        """The motion is over: the scale shown is what the arm ended at, until the next look."""
        if self.run is run:
            self.run = None
        self.idle_scale = run.playback.sigma

    async def look(self) -> None:
        """Every ``scale_period_s``: the σ the distance allows now, planned as a ramp when it differs. A look
        that fails is said and tried again at the next: the arm must not keep whatever scale it had."""
        if not self.on:
            return
        try:
            await self._look()
        except Exception as e:  # any failure of one look: the next one runs
            self.kit.counters["scale_errors"] += 1
            if self.kit.counters["scale_errors"] == 1:  # the traceback once, not 50 times a second
                log.exception("the scale's look failed")
            r = self.run
            self.safety.event("info", f"the time scale could not be planned ({e!r}): trying again",
                              r.path.id if r else None)  # fmt: skip

    async def _look(self) -> None:
        r, a = self.run, self.adoption
        if r is not None and (lapsed := r.playback.lapses - r.lapses_counted):  # counted as soon as seen
            self.kit.counters["lease_lapses"] += lapsed
            r.lapses_counted += lapsed
        if r is None or r is not self.offered_on:  # a ramp offered on a path that ended never plays
            a.dropped()
        ramp, at = (r.playback.began if r is not None else None) or (None, None)
        a.began(ramp, at, monotonic(), r.playback.now.pending_ramp if r is not None else None)
        arrival = a.take()  # the readings this look answers
        nearest = self.look_distance()
        wanted = self.allowed(r.guard if r is not None else self.last_figures)
        self.say_zone(wanted, nearest)
        self.count_adoption()
        if r is None:
            self.idle_scale = wanted  # the next path starts at it
            a.answered(arrival, monotonic())
            return
        self.last_figures = r.figures
        budget = self.adoption.budget_s
        current = r.playback.now.target
        if current <= wanted + SIGMA_EPS:  # the scale the arm heads for is one this look allows
            self.lease(r)
        if abs(wanted - current) < 1e-9 or (current < wanted < min(1.0, current + RAISE_BY)):
            # the scale in force answers them, found so now: not once the fallback below is planned (a
            # loaded host's planning counted as lateness, and held the arm for it)
            a.answered(arrival, monotonic())
            await r.keep_fallback(0.75 * budget, 0.5 * budget)
            return
        await r.keep_fallback(0.75 * budget, 0.5 * budget)
        current = r.playback.now.target
        ramp = await r.ramp_to(wanted, RAMP_LEAD_S)
        if ramp is None:  # the next look plans again, for these readings too
            a.dropped_arrival(arrival)
        elif wanted < current:  # answered when the servo plays its first step
            a.offered(ramp, arrival)
            self.offered_on = r
            self.lease(r)  # the ramp down is the loop's: the scale it heads for is confirmed
        else:  # a rise may come late: nothing waits for it
            a.answered(arrival, monotonic())

    def lease(self, run: PathRun) -> None:
        """The scale the arm heads for holds until the next look is due, with room for one late; past it
        the loop takes the stop kept ready for it (services/executor/playback.py). Given at a path's start
        and by a look that finds that scale no higher than the distance allows, or has the ramp down
        adopted: a look that wants a lower scale and cannot have it (a refused ramp, a planner starved)
        lets the lease run out, so no arm runs on a scale the last reading did not allow."""
        if self.on:
            run.playback.stop_s = max(run.guard.stop_time_s, self.ssm.stop_time_s)
            run.playback.renew(monotonic() + self.adoption.budget_s / 2)

    def count_adoption(self) -> None:
        """The adoption's figures in the status (ms), at most every 5 s: a quantile of 10⁵ delays is not
        free."""
        c, a, now = self.kit.counters, self.adoption, monotonic()
        c["adoption_late"], c["adoption_n"] = a.times_late, len(a.delays)
        if now - self._counted_at < 5.0:
            return
        self._counted_at = now
        for name, value in a.quantiles().items():
            c[f"adoption_{name}_ms"] = round(value * 1000)

    def say_zone(self, sigma: float, nearest: Nearest) -> None:
        if self.on and self.adoption.late and not self.guarded:
            budget = self.adoption.budget_s * 1000
            zone, text = (
                "late",
                f"a reading's scale was not in force within {budget:.0f} ms: holding on the path",
            )
        elif nearest.distance_m is None:
            zone, text = "unknown", f"{nearest.why}: holding on the path"
        else:
            zone = "full" if sigma >= 1.0 else "hold" if sigma <= 0.0 else "reduced"
            text = f"a person at {self.shown_m():.2f} m ({nearest.source}): scale {sigma:.2f}"
            if nearest.why:  # a silent source's person, where last seen
                text += f" ({nearest.why})"
        folded = self.zones.update(zone, monotonic())
        if folded is None:
            return
        if folded:
            text += f" ({folded} changes in the last {SAY_EVERY_S:g} s not said)"
        r = self.run
        self.safety.event("scale", text, r.path.id if r else None)
