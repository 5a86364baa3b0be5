"""The path in progress: what the servo loop sends, one controller step at a time
(services/executor/servo.py), in the servo's own process (services/executor/servo_process.py) or thread,
and the one owner of what it plays (``PathRun``) on the event loop.

``Samples``: targets computed before the motion (the tests' and the benchmarks' fixed motions).
``Playback``: a path's curve at path time s(t), under a time scale that another thread may change while
it runs (common/trajectory/scaling.py).

The owner (``PathRun`` below, in another thread or, through a mirror, in another process) talks to the
loop through one latest-wins mailbox, as the UR driver's scaled trajectory controller takes a new goal
from one realtime buffer: an ``Offer`` says what is to follow the state in force, a new ``Ramp`` of the
scale from a controller step still ahead and a new curve (a switch of solution) from a path time still
ahead, and it names the ``InForce`` state it was planned from. The loop reads the mailbox once a step. An
offer planned from the state still in force is adopted, whole; one planned from another (the loop took a
change meanwhile) or too late for its step is dropped and counted (``missed``), never applied late: the
owner plans again. A newer offer replaces an older one, so an offer carries what is still pending that it
keeps.

The loop says what it did with each offer, and when a pending change took effect or was dropped, through
``notify`` (the owner's wake-up, once per change: not per step). A switch carries the highest scale it may
be taken at (``max_sigma``: the scale the person's distance allows on the switched curve); at a higher one
it is dropped, so the arm never runs a faster curve at a scale chosen for a slower one.

The scale in force is leased (DESIGN §8, T_r): the owner renews ``lease`` (a deadline on the loop's
clock) at every look at the person's distance, and keeps a stop planned ahead (``fallback``, a ramp to
σ = 0 checked like any other, from the state in force). Should the looks stop coming (the owner's thread
starved, a stall of the host), the loop itself takes that stop when the lease runs out, from its own
thread: the arm never runs on a scale nobody has confirmed for longer than the adoption budget. With no
valid stop planned (the state changed since), it ramps σ down over ``stop_s`` unchecked: a stop that
skipped the check, said and counted (``lapses``), not an arm that ran on.

Inside ``next`` there is no lock, no logging and no container that grows: a few floats, one Horner
evaluation of the current span, and a new ``InForce`` only when something changes.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from common.robot.ur16e import JointLimits
from common.runtime.clock import first_of, monotonic, wall_monotonic
from common.safety.geometry import Arm
from common.safety.separation import BARE, Figures
from common.trajectory.scaling import DT, LIMIT_RTOL, Curve, Ramp, plan_ramp, ramp_ratio, switch_curve
from common.trajectory.task import PathPlan

Array = NDArray[np.float64]
SIGMA_EPS = 1e-9
RAMP_LEAD_S = 0.022  # a ramp of the scale starts this far ahead of the loop (planning, a step; wall s)


class Samples:
    """Targets computed before the motion (the tests' and the benchmarks' fixed motions), sent in order."""

    def __init__(self, targets: Sequence[object]) -> None:
        self.targets, self.sent = targets, 0
        self.last = targets[-1]

    @property
    def done(self) -> bool:
        return self.sent >= len(self.targets)

    def next(self) -> object | None:
        if self.sent >= len(self.targets):
            return None
        self.sent += 1
        return self.targets[self.sent - 1]


@dataclass(frozen=True, slots=True)
class Switch:
    """From path time ``s`` on, ``curve`` (the path in force up to there, then the rest at a new k); taken
    only at a scale of at most ``max_sigma``."""

    s: float
    curve: Curve
    max_sigma: float = 1.0


@dataclass(frozen=True, slots=True)
class InForce:
    """What the loop plays and what it holds pending: replaced whole at every change, so one read of it
    is a consistent picture, and an offer names the one it was planned from."""

    ramp: Ramp
    curve: Curve
    pending_ramp: Ramp | None = None
    pending_switch: Switch | None = None

    @property
    def target(self) -> float:
        """The scale the arm is heading for: the pending ramp's end, else the ramp's."""
        return (self.pending_ramp or self.ramp).target


@dataclass(frozen=True, slots=True)
class Offer:
    """The changes to follow ``base``: what is pending in it, with ``ramp`` and ``switch`` replacing
    their kind (None keeps base's)."""

    base: InForce
    ramp: Ramp | None = None
    switch: Switch | None = None

    @property
    def pending(self) -> tuple[Ramp | None, Switch | None]:
        return (self.ramp or self.base.pending_ramp, self.switch or self.base.pending_switch)


def _nothing() -> None:
    pass


class Owned(Protocol):
    """A playback as its owner (``PathRun``) sees it: a ``Playback`` in the servo's thread, or its mirror
    beside a servo process (services/executor/remote.py). Read on the owner's loop; ``now`` changes only
    when the loop says so (``notify``)."""

    now: InForce
    mailbox: Offer | None
    fallback: Offer | None
    stop_s: float
    figures: Figures | None  # what σ is chosen for: a separation guard beside the servo reads them
    began: tuple[Ramp, float] | None
    lapses: int
    unchecked: int

    @property
    def t(self) -> float: ...
    @property
    def s(self) -> float: ...
    @property
    def sigma(self) -> float: ...
    @property
    def finished(self) -> bool: ...
    @property
    def curve(self) -> Curve: ...
    def offer(
        self, ramp: Ramp | None = None, switch: Switch | None = None, base: InForce | None = None
    ) -> bool: ...
    def renew(self, until: float) -> None: ...
    def settled(self, offer: Offer | None = None) -> bool: ...
    def state(self) -> Ramp: ...


# the servo's playback of a curve: (curve, start, notify, the owner's clock, the joints to hold at first)
MakePlayback = Callable[[Curve, Ramp, Callable[[], None], Callable[[], float], object | None], Owned]


class Playback:
    """One path at a time scale. ``tick`` counts the samples sent; playback time is ``tick · DT``."""

    def __init__(
        self,
        curve: Curve,
        ramp: Ramp,
        convert: Callable[[Array], object],
        notify: Callable[[], None] = _nothing,
        clock: Callable[[], float] = wall_monotonic,
        hold: object | None = None,
    ) -> None:
        """``clock``: the owner's loop's (``loop.time``: the wall's monotonic clock, or a lockstep cell's
        data time), read from the loop's thread once a step while a lease is held. ``hold``: where the arm
        stands as the motion begins (in the form servo takes), sent instead of the curve's first point
        while the path has not advanced at σ = 0: a settled arm is off that point by up to the settle
        tolerance, and pulling it there crept it at some mm/s beside a person who held it (loaded run 11
        of 55add05, issue 53)."""
        self.now = InForce(ramp, curve)
        self._hold, self._s0 = hold, float(ramp.at(0.0)[0])
        self.convert, self.notify, self.clock = convert, notify, clock
        self.tick = 0
        self.s = 0.0
        self.sigma = float(ramp.c[0])
        self.last = convert(curve.at(np.array([curve.t_f]), order=0)[0, 0])
        self.finished = False
        self.mailbox: Offer | None = None  # written by the owner only
        self._seen: Offer | None = None  # read and written by the loop only
        # the last ramp that began to play and when (the loop's clock: the wall's, or a lockstep cell's data
        # time), one tuple written whole: the owner measures how soon a reading's scale was in force by it
        self.began: tuple[Ramp, float] | None = None
        # the lease on the scale in force (the owner's, renewed at each look; None: none, the scale holds)
        self.lease: float | None = None
        self.fallback: Offer | None = None  # the stop to take when the lease runs out (the owner's)
        self.stop_s = 1.0  # an unchecked stop's length, when no fallback fits the state (the path's T_s)
        self.figures: Figures | None = None  # its owner's: a guard's (servo_process.py), unused in a thread
        self.lapsed = False  # the lease ran out and the loop took its stop; a renewal clears it
        self.lapses = 0  # how often
        self.unchecked = 0  # of which with no fallback that fitted
        self.adopted = 0  # offers taken into the state
        self.missed = 0  # offers or pending changes dropped: too late, or planned from another state
        self.span = 0

    @property
    def done(self) -> bool:
        return self.finished

    @property
    def seen(self) -> Offer | None:
        """The last offer the loop read from the mailbox (adopted or dropped)."""
        return self._seen

    @property
    def t(self) -> float:
        return self.tick * DT

    @property
    def ramp(self) -> Ramp:
        return self.now.ramp

    @property
    def curve(self) -> Curve:
        return self.now.curve

    # --- the owner's side ---------------------------------------------------------------------------

    def offer(
        self, ramp: Ramp | None = None, switch: Switch | None = None, base: InForce | None = None
    ) -> bool:
        """Post the changes planned from ``base`` (default: the state now). False when it is already too
        late for them (a ramp starting at a step already sent, a switch at a path time already passed) or
        the state is no longer ``base``; the loop may still drop it later, and says so (``notify``)."""
        base = base or self.now
        if base is not self.now or self.finished or not self._in_time(ramp, switch):
            return False
        self.mailbox = Offer(base, ramp, switch)
        return True

    def renew(self, until: float) -> None:
        """The owner has looked: the scale in force holds until ``until`` (the loop's clock)."""
        self.lease, self.lapsed = until, False

    def settled(self, offer: Offer | None = None) -> bool:
        """Whether the loop has seen the last offer posted (adopted or dropped it), or has ended."""
        return self.finished or self._seen is (offer or self.mailbox)

    # --- the loop's side ----------------------------------------------------------------------------

    def _in_time(self, ramp: Ramp | None, switch: Switch | None) -> bool:
        return (ramp is None or ramp.t0 >= self.t + DT / 2) and (switch is None or switch.s > self.s)

    def _read_mailbox(self) -> None:
        offer = self.mailbox
        if offer is None or offer is self._seen:
            return
        self._seen = offer
        if offer.base is self.now and self._in_time(offer.ramp, offer.switch):
            ramp, switch = offer.pending
            self.now = replace(self.now, pending_ramp=ramp, pending_switch=switch)
            self.adopted += 1
        else:
            self.missed += 1
        self.notify()

    def _lapse(self) -> None:
        """The lease ran out: the planned stop, or one over ``stop_s`` from the σ-state now."""
        self.lapsed = True
        now = self.now
        if now.target <= 0.0 and (now.pending_ramp is None or now.pending_ramp.target <= 0.0):
            return  # stopping or stopped already
        self.lapses += 1
        fb = self.fallback
        if fb is not None and fb.ramp is not None and fb.base is now and self._in_time(fb.ramp, None):
            stop = fb.ramp
        else:
            self.unchecked += 1
            stop = self._unchecked_to(0.0)
        self.now = replace(now, pending_ramp=stop, pending_switch=None)
        self.notify()

    def _unchecked_to(self, sigma: float) -> Ramp:
        """σ from its state at the next step to ``sigma`` over ``stop_s``: a ramp no planner checked, that
        never leaves the span between the two. A quintic joined to the state's σ̈ is not: cut at the end of
        a ramp down (σ̈ of 15-25 /s²) it rose from 0.51 to past 1 before it fell (a walk-in, issue 74). So
        it keeps σ's rate only where that heads for ``sigma``, drops σ̈ (a jerk: the stop is unchecked
        anyway), and where even that leaves the span, starts from rest (a smoothstep, monotone)."""
        t0 = self.tick * DT + DT
        s0, sig, sd, _ = (float(x[0]) for x in self.now.ramp.state(np.array([t0])))
        duration = max(self.stop_s, DT)
        toward = sd if (sigma - sig) * sd > 0.0 else 0.0
        ramp = Ramp.between(t0, s0, (sig, toward, 0.0), sigma, duration)
        lo, hi = min(sig, sigma) - 1e-9, max(sig, sigma) + 1e-9
        sigmas = ramp.state(t0 + np.linspace(0.0, duration, 33))[1]
        if toward and not (lo <= sigmas.min() and sigmas.max() <= hi):
            ramp = Ramp.between(t0, s0, (sig, 0.0, 0.0), sigma, duration)
        return ramp

    def cut(self, sigma: float) -> bool:
        """The separation guard's word (services/executor/guard_process.py): σ down to ``sigma`` from the
        next step, over ``stop_s``, unchecked like the lease's own stop, when its owner's ramp did not come
        within the guard's grace. False when the scale in force is that low already, or a ramp to it
        begins at the next step."""
        now, t = self.now, self.tick * DT
        pending = now.pending_ramp
        if now.ramp.target <= sigma + SIGMA_EPS or (
            pending is not None and pending.target <= sigma + SIGMA_EPS and pending.t0 <= t + 1.5 * DT
        ):
            return False
        # counted by the guard's figures (guard_cuts), not as a stop
        self.now = replace(now, pending_ramp=self._unchecked_to(sigma))
        self.notify()
        return True

    def next(self) -> object | None:
        self._read_mailbox()
        lease = self.lease
        if lease is not None and not self.lapsed and self.clock() > lease:
            self._lapse()
        t = self.tick * DT
        now = self.now
        pending = now.pending_ramp
        if pending is not None and t >= pending.t0 - DT / 2:
            now = self.now = replace(now, ramp=pending, pending_ramp=None)
            self.began = (pending, self.clock())
            self.notify()
        s, sigma = now.ramp.at(t)
        switch = now.pending_switch
        if switch is not None and s >= switch.s:
            slow = sigma <= switch.max_sigma + SIGMA_EPS and now.target <= switch.max_sigma + SIGMA_EPS
            if self.s < switch.s and slow:  # nothing past the switch was sent from the old curve
                now = self.now = replace(now, curve=switch.curve, pending_switch=None)
                self.span = 0
            else:
                now = self.now = replace(now, pending_switch=None)
                self.missed += 1
            self.notify()
        if s >= now.curve.t_f:
            self.finished = True
            self.notify()
            return None
        self.tick += 1
        self.s, self.sigma = s, sigma
        if self._hold is not None:
            if sigma <= SIGMA_EPS and s <= self._s0:  # held before the path's first step: still
                return self._hold
            self._hold = None
        return self.convert(self._point(s))

    def _point(self, s: float) -> Array:
        curve = self.now.curve
        starts, spans = curve.starts, len(curve.starts)
        i = self.span
        while i + 1 < spans and starts[i + 1] <= s:  # s never goes back: walk forward from the last span
            i += 1
        self.span = i
        tau = s - starts[i]
        coeffs = curve.taylor[i]
        q = coeffs[5] * tau
        for k in (4, 3, 2, 1):
            q = (q + coeffs[k]) * tau
        q += coeffs[0]
        return q

    def state(self) -> Ramp:
        """The σ-state now, for the next path's playback (the scale carries over)."""
        return self.now.ramp.rebased(self.t)


Scale = Callable[[Figures], float]  # the σ the person's distance allows now, for a curve of these figures


class PathRun:
    """The path in progress's one owner (STYLE 15): the playback the servo loop plays, the ramps
    of the time scale and the switch of solution offered to it, and the path's SSM figures
    (common/safety/separation.py ``Figures``: top link speed and longest stop of the curve being played,
    and of a switched one while it is pending).

    Everything that changes what the loop plays goes through here, one change planned at a time (``lock``),
    each planned from one consistent picture of what is in force (``Playback.now``) and checked against
    what else is pending: a ramp on the current curve and on a pending switched one, a switch under the
    ramps in force and pending. An offer goes into the loop's one mailbox, and the planner waits, without
    the lock, for the loop's word on it (``changed``: the loop's notification, one per change, never a
    poll). The motion itself is played by its caller (services/executor/motions.py), which sets ``ended``.
    """

    def __init__(
        self,
        path: PathPlan,
        curve: Curve,
        figures: Figures,
        k: int,
        start: Ramp,
        make: MakePlayback,
        limits: JointLimits,
        speed: float = 1.0,
        arm: Arm = BARE,
        hold: object | None = None,
    ) -> None:
        """``speed``: playback seconds per wall second (the clock's speed), for leads given in wall time;
        ``arm``: the robot and its tool, whose fastest point a switched curve's figures take; ``hold``:
        where the arm stands (joints), held there until the path advances (``Playback``); ``make``: the
        servo's playback of it (``Servo.playback``: in its thread, or a mirror of one in its process)."""
        self.path, self.k, self.limits, self.speed = path, k, limits, speed
        self.arm = arm
        self._figures = figures
        self._pending_figures: Figures | None = None  # of a switched curve not yet taken
        self.changed = asyncio.Event()
        self.ended = asyncio.Event()
        loop = asyncio.get_running_loop()

        def notify() -> None:  # from the servo's thread (or the loop's own, a process's), once per change
            with contextlib.suppress(RuntimeError):  # a loop already closed: nobody waits
                loop.call_soon_threadsafe(self.changed.set)

        self.playback: Owned = make(curve, start, notify, loop.time, hold)
        self.playback.figures = self.guard
        self.lock = asyncio.Lock()
        self.ramps = self.ramps_refused = 0
        self.lapses_counted = 0  # of the playback's lapses, those in the executor's counters already
        self.switched_at = 0.0  # the path time of the last switch taken
        self.plan_s = 0.2  # how long planning a switch takes (wall s, smoothed): the switch point's lead

    @property
    def figures(self) -> Figures:
        return self._figures

    @figures.setter
    def figures(self, figures: Figures) -> None:
        self._figures = figures
        self.playback.figures = self.guard

    @property
    def pending_figures(self) -> Figures | None:
        return self._pending_figures

    @pending_figures.setter
    def pending_figures(self, figures: Figures | None) -> None:
        self._pending_figures = figures
        self.playback.figures = self.guard

    @property
    def guard(self) -> Figures:
        """The figures σ is chosen for: the curve played, and a switched one while it may still be taken."""
        pending = self.pending_figures
        return self.figures if pending is None else self.figures.worst(pending)

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
