"""What the servo loop sends, one controller step at a time (services/executor/servo.py).

``Samples``: targets computed before the motion (the tests' and the benchmarks' fixed motions).
``Playback``: a path's curve at path time s(t), under a time scale that another thread may change while
it runs (common/trajectory/scaling.py).

The other thread (the path's owner, services/executor/pathrun.py) talks to the loop through one
latest-wins mailbox, as the UR driver's scaled trajectory controller takes a new goal from one realtime
buffer: an ``Offer`` says what is to follow the state in force, a new ``Ramp`` of the scale from a
controller step still ahead and a new curve (a switch of solution) from a path time still ahead, and it
names the ``InForce`` state it was planned from. The loop reads the mailbox once a step. An offer planned
from the state still in force is adopted, whole; one planned from another (the loop took a change
meanwhile) or too late for its step is dropped and counted (``missed``), never applied late: the owner
plans again. A newer offer replaces an older one, so an offer carries what is still pending that it keeps.

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

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from common.runtime.clock import wall_monotonic
from common.trajectory.scaling import DT, Curve, Ramp

Array = NDArray[np.float64]
SIGMA_EPS = 1e-9


class Samples:
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


class Playback:
    """One path at a time scale. ``tick`` counts the samples sent; playback time is ``tick · DT``."""

    def __init__(
        self,
        curve: Curve,
        ramp: Ramp,
        convert: Callable[[Array], object],
        notify: Callable[[], None] = _nothing,
        clock: Callable[[], float] = wall_monotonic,
    ) -> None:
        """``clock``: the owner's loop's (``loop.time``: the wall's monotonic clock, or a lockstep cell's
        data time), read from the loop's thread once a step while a lease is held."""
        self.now = InForce(ramp, curve)
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
        fb, t = self.fallback, self.tick * DT
        if fb is not None and fb.ramp is not None and fb.base is now and self._in_time(fb.ramp, None):
            stop = fb.ramp
        else:
            self.unchecked += 1
            t0 = t + DT
            s0, sig, sd, sdd = (float(x[0]) for x in now.ramp.state(np.array([t0])))
            stop = Ramp.between(t0, s0, (sig, sd, sdd), 0.0, max(self.stop_s, DT))
        self.now = replace(now, pending_ramp=stop, pending_switch=None)
        self.notify()

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
