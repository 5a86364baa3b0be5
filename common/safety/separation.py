"""Speed and separation monitoring (ISO/TS 15066 §5.5.4): how fast the robot may move with a person at a
given distance, as a time scale σ of the current trajectory (common/trajectory/scaling.py).

The protective separation distance (ISO/TS 15066 eq. 1, constant speeds):

    S_p = v_h (T_r + T_s) + v_r T_r + B + C + Z_d + Z_r,     B = v_r T_s / 2

v_h the person's speed toward the robot (1.6 m/s, ISO 13855's walking speed), T_r the time from the
person's move to the robot's reaction (sensor, adapter, bus, the executor's next ramp), T_s the time the
robot takes to stop (the scale's ramp from 1 to 0: the arm decelerates along its path, so the stopping
distance B at a linear ramp is v_r T_s / 2), C the intrusion distance (how far a body part reaches past
the point the sensor sees), Z_d and Z_r the uncertainties of the person's and the robot's position.
Solved for the largest v_r whose S_p fits the measured separation S:

    v_r ≤ (S − v_h (T_r + T_s) − C − Z_d − Z_r) / (T_r + T_s / 2)

v_r is the speed of the fastest point of the arm; the path's own top speed at σ = 1 (``Figures``) turns
it into σ. Unknown separation (none yet, or older than ``max_age_s``) is read as a person at the robot:
σ = 0, the arm holds its place on the path until a fresh distance frees it.

Which distance (``Sources``): every fresh reading of every source counts, and the nearest wins. A far
reading, from a second sensor, a rogue publisher or one under a real sensor's own name, can never hide a
near one while that is fresh; a wrong near one can only slow the arm. Fresh is judged on the receiver's
clock twice over: by the sender's stamp (``now − t_ns + age_s``) and by arrival (a reading lives at most
``max_age_s`` from the moment it came, less the age it came with), so neither a sender's clock that runs
ahead nor a late relay makes a reading live longer. A stamp ahead of the receiver's clock by more than the
cell's skew bound is refused, not clamped. A source declared in the settings that has no fresh reading
holds the arm even while others speak: a scanner that died is not a scanner that sees nobody. Any other
source falling silent is not forgotten either: its person stays where last seen (``Sources``) until a
fresh reading of it says otherwise. A source's rate is judged before its readings'
age, so a flood that saturates the receiver is seen as a flood (a hold), not as stale readings.

S, C and the arm's speed are the cell's (common/safety/geometry.py): S the person's distance to the arm
and its tool, C the source's own by ISO 13855, v_r the fastest point of arm and tool. ``Sources`` keeps
each reading as its room, S − C, so that a source that sees legs (C 1.2 m) and one that sees hands are
weighed alike; ``Ssm`` then takes C = 0.

T_r, the reaction time, is the sum of what lies between a person's move and the arm's answer to it (the
executor's settings, docs/robot.md): the sensor's own latency where its messages do not carry it
(``age_s``), the oldest reading accepted (``max_age_s``: the adapter and the bus are inside it, for a
reading older than that is not used), the clock skew between hosts (a stamp may say a reading is younger
than it is by that much), the executor's adoption (from a reading's arrival to the step that plays the
scale it led to, measured on the wall clock by ``Adoption``, with a budget past which the arm holds), and
the robot's own command delay (servoJ's lookahead: the arm follows its target that much later).
T_s is the longest stop of the path actually played (``common/trajectory/scaling.stop_time``, from every
controller step), and v_r its top speed; a switch to another solution within a path is taken only at
the σ the distance allows on the joined curve, with the joined curve's T_s and v_r.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from common.robot.ur16e import JointLimits
from common.safety.geometry import Arm
from common.trajectory.scaling import Curve, stop_time

Array = NDArray[np.float64]
BARE = Arm()  # the arm alone, at the cell's origin: a tool's points are the cell's to declare
QUANTUM = 0.05  # σ is chosen in steps of this (rounded down: the safe side), so a walk is a few ramps


@dataclass(frozen=True, slots=True)
class Ssm:
    human_speed_m_s: float = 1.6  # v_h
    reaction_s: float = 0.2  # T_r
    stop_time_s: float = 0.5  # T_s: per path, its longest stop (scaling.stop_time)
    intrusion_m: float = 0.2  # C
    uncertainty_m: float = 0.1  # Z_d + Z_r
    max_age_s: float = 0.3
    # the stopping distance over the speed (B / v_r): T_s / 2 for a stop that starts at once and
    # decelerates linearly, as ISO/TS 15066 writes B; a path's own is measured (scaling.Stop.travel_s)
    stop_travel_s: float | None = None

    @property
    def travel_s(self) -> float:
        return self.stop_time_s / 2 if self.stop_travel_s is None else self.stop_travel_s

    def protective_distance(self, robot_speed_m_s: float) -> float:
        """S_p for a robot moving at ``robot_speed_m_s``."""
        tr, ts = self.reaction_s, self.stop_time_s
        return (self.human_speed_m_s * (tr + ts) + robot_speed_m_s * (tr + self.travel_s)
                + self.intrusion_m + self.uncertainty_m)  # fmt: skip

    def allowed_speed(self, separation_m: float, in_force_m_s: float = 0.0) -> float:
        """The largest robot speed whose S_p fits ``separation_m`` (0: too close even for a robot at rest),
        for an arm running at ``in_force_m_s`` now. The arm keeps that speed through T_r before any new
        one acts, so S_r is v_in_force T_r (ISO/TS 15066: the speed in force over T_r), not the new
        speed's: a slower speed is the one whose own stop still fits after a reaction at the old one."""
        room = separation_m - self.protective_distance(0.0)
        per = self.reaction_s + self.travel_s
        if per <= 0.0:  # no reaction time and no stop: any speed, or none
            return math.inf if room >= 0.0 else 0.0
        same = room / per  # a speed kept through T_r and the stop
        if in_force_m_s <= same:
            return max(0.0, same)
        if self.travel_s <= 0.0:
            return 0.0
        return max(0.0, (room - in_force_m_s * self.reaction_s) / self.travel_s)

    def scale(
        self, separation_m: float | None, age_s: float, path_speed_m_s: float, in_force: float = 0.0
    ) -> float:
        """σ in [0, 1] for the path whose top speed at σ = 1 is ``path_speed_m_s``, played at σ =
        ``in_force`` now."""
        if separation_m is None or not math.isfinite(separation_m) or age_s > self.max_age_s:
            return 0.0
        if path_speed_m_s <= 0.0:
            return 1.0
        v = self.allowed_speed(separation_m, in_force * path_speed_m_s)
        return min(1.0, v / path_speed_m_s)


def stepped(sigma: float) -> float:
    """σ as the executor asks for it: 1, or rounded down to a step of ``QUANTUM``."""
    return 1.0 if sigma >= 1.0 else math.floor(sigma / QUANTUM + 1e-9) * QUANTUM


@dataclass(frozen=True, slots=True)
class Figures:
    """What S_p needs of the curve being played, from path time ``s_from`` on: its top link speed at σ = 1
    (v_r / σ), its longest stop (T_s) and the path time that stop covers (B / v_r): the longer of the
    executor's own ramp and the robot's own stops (common/robot/stopping.py), ``stop_by`` saying which."""

    speed_m_s: float
    stop_time_s: float
    stop_travel_s: float = 0.0
    stop_by: str = ""

    @classmethod
    def of(
        cls, curve: Curve, limits: JointLimits, s_from: float = 0.0, dt: float = 0.002, arm: Arm = BARE
    ) -> Figures:
        """Before the curve is played (a path's, or a joined one before a switch is accepted): in a worker
        thread, some tenths of a second for a long path. ``arm``: its tool's points and its stops count
        too."""
        s = np.append(np.arange(s_from, curve.t_f, dt), curve.t_f)
        own = stop_time(curve, limits, s_from)
        q, qd = curve.at(s, order=1)
        robot = arm.stops.worst(np.abs(qd).max(axis=0), limits.velocity)
        time_s, travel_s = max(own.time_s, robot.time_s), max(own.travel_s, robot.time_s)
        by = "the executor's ramp" if own.time_s >= robot.time_s else robot.by
        return cls(float(arm.speeds(q, qd).max()), time_s, travel_s, by)

    def worst(self, other: Figures) -> Figures:
        """The conservative reading of two (a switch pending: either curve may be played)."""
        by = self.stop_by if self.stop_time_s >= other.stop_time_s else other.stop_by
        return Figures(max(self.speed_m_s, other.speed_m_s), max(self.stop_time_s, other.stop_time_s),
                       max(self.stop_travel_s, other.stop_travel_s), by)  # fmt: skip

    def ssm(self, base: Ssm) -> Ssm:
        """``base`` with this curve's stop (never below base's own T_s, a floor from the settings)."""
        time_s, travel_s = max(self.stop_time_s, base.stop_time_s), max(self.stop_travel_s, base.travel_s)
        return replace(base, stop_time_s=time_s, stop_travel_s=travel_s)

    def scale(self, base: Ssm, distance_m: float | None, in_force: float = 0.0) -> float:
        """σ, stepped, for a person at ``distance_m`` (None: unknown, a hold), the curve played at σ =
        ``in_force`` now."""
        return stepped(self.ssm(base).scale(distance_m, 0.0, self.speed_m_s, in_force))


OTHERS = "(others)"  # where readings of sources past ``max_sources`` are kept, together


@dataclass(slots=True)
class _Readings:
    """One source's fresh readings that can still be the nearest: (fresh until, distance), fresh until
    rising, distance rising (a reading farther than a later-expiring one can never be the nearest); and
    the last one seen once none is fresh (``last``), which no silence ever forgets."""

    kept: deque[tuple[float, float]] = field(default_factory=deque)
    last: tuple[float, float] | None = None  # the latest-expiring reading gone stale: where last seen

    def add(self, until: float, distance: float, keep: int) -> None:
        self.last = None  # a fresh reading of the source says where its person is now
        if any(u >= until and d <= distance for u, d in self.kept):
            return  # one as near that lives as long: this one never wins
        kept = deque((u, d) for u, d in self.kept if not (u <= until and d >= distance))
        i = next((n for n, (u, _) in enumerate(kept) if u > until), len(kept))
        kept.insert(i, (until, distance))
        while len(kept) > keep:  # a flood: the two latest become one, nearer and longer-lived (safe side)
            u2, d2 = kept.pop()
            u1, d1 = kept.pop()
            kept.append((max(u1, u2), min(d1, d2)))
        self.kept = kept

    def nearest(self, now: float) -> float | None:
        """The nearest fresh distance, None when none is fresh (``last`` then says where last seen)."""
        while self.kept and self.kept[0][0] < now:
            self.last = self.kept.popleft()
        return self.kept[0][1] if self.kept else None


@dataclass(frozen=True, slots=True)
class Nearest:
    distance_m: float | None  # None: hold the arm
    source: str  # whose reading it is, or what holds the arm
    why: str = ""  # when None: why, in words; with a distance: why it is one assumed, not read
    taken_s: float = -math.inf  # when the reading was taken, on the receiver's clock (its age counted)


@dataclass(slots=True)
class Spell:
    """ISO/TS 15066's bound on a spell of S < S_p(v), v the speed in force (issue 74): it must end, the
    arm at rest or S ≥ S_p(v) again, within T_r + T_s of its start. Slowing down ends one only where the
    person stops coming (S_p shrinks with v); one who walks on keeps it open while the arm follows them
    down, which took up to 0.25 s past the bound. So a spell starts when the reading that shows it was
    taken, slowing may end it for T_r less ``lead_s`` (the adoption of a ramp), and past that the arm
    stops, whatever a lower speed would allow, until the spell ends: a stop begun then ends within T_s,
    the stop S_p budgets, so within the bound."""

    lead_s: float
    began_s: float | None = None
    stopping: bool = False

    def sigma(
        self, wanted: float, ssm: Ssm, speed_m_s: float, nearest: Nearest, in_force: float, now: float
    ) -> float:
        """``wanted``, or 0 where this spell can no longer end in time by slowing; ``ssm`` with the curve's
        stop, ``speed_m_s`` its top speed at σ = 1, played at σ = ``in_force``."""
        v, d = in_force * speed_m_s, nearest.distance_m
        if d is None or v <= 0.0 or d >= ssm.protective_distance(v):  # no spell: a hold, at rest, or room
            self.began_s, self.stopping = None, False
            return wanted
        if self.began_s is None:
            self.began_s = min(now, nearest.taken_s) if math.isfinite(nearest.taken_s) else now
        self.stopping = self.stopping or now - self.began_s >= ssm.reaction_s - self.lead_s
        return 0.0 if self.stopping else wanted


class Sources:
    """The distances of every source, the nearest fresh one winning (module docstring). Times are the
    receiver's clock in seconds (``now``); a reading's age comes with it.

    ``declared``: sources that must each have a fresh reading, or the arm holds. ``keep`` bounds what one
    source keeps and ``max_sources`` how many names are told apart; past either, readings are merged on the
    safe side (the nearer distance, the longer life), never dropped.

    Rate before age: a source that sends more than ``max_rate_hz`` readings in a second is flooding,
    whatever the age or the stamp of what it sends (a flood that saturates the receiver arrives stale, and
    counted as stale it once went unseen while the arm ran): what it sends past that is not looked at (a
    flood must not cost the others their turn), and it holds the arm until a second after its last reading
    past the rate, for a reading it sent and was not looked at may have been the near one.

    Silence never frees the arm: a source whose readings all went stale is not forgotten. Its person stays
    where last seen until a fresh reading of the same source says otherwise; so a near person whose
    sensor's readings stop arriving in time (a flood on another source, a saturated host) keeps the arm
    held while a far source speaks on. (Not walked in from there at v_h: a source the cell relies on is
    declared, and a declared source's silence holds the arm at once; one nobody declared only ever adds a
    nearer person, and walking its last one in would hold the arm for good once it is gone.) With no fresh
    reading at all the arm holds, whatever was last seen."""

    def __init__(
        self,
        max_age_s: float,
        skew_s: float,
        declared: tuple[str, ...] = (),
        keep: int = 32,
        max_sources: int = 32,
        max_rate_hz: float = math.inf,
    ) -> None:
        self.max_age_s, self.skew_s, self.declared = max_age_s, skew_s, tuple(declared)
        self.keep, self.max_sources, self.max_rate_hz = keep, max_sources, max_rate_hz
        self.readings: dict[str, _Readings] = {name: _Readings() for name in self.declared}
        self.rates: dict[str, tuple[float, int]] = {}  # source: (start of its second, readings in it)
        self.flooding: dict[str, float] = {}  # source: until when it holds the arm
        self.heard = False

    def name(self, source: str) -> str:
        """The name a source's readings are kept under: past ``max_sources`` names, all others are one."""
        return source if source in self.readings or len(self.readings) < self.max_sources else OTHERS

    def judge(self, source: str, stamp_age_s: float, sensor_age_s: float, now: float) -> str:
        """What a reading's envelope says before its content is looked at: "" to look at it, else why not:
        "flood" (its source is past its rate this second: judged first, every reading counts toward it),
        "ahead" (stamped ahead of the receiver's clock by more than the skew), "stale" (too old already)."""
        name = self.name(source)
        if len(self.rates) > 4 * self.max_sources:  # names judged and never kept (a flood of names)
            self.rates = {k: v for k, v in self.rates.items() if k in self.readings}
        start, n = self.rates.get(name, (now, 0))
        if now - start >= 1.0:
            start, n = now, 0
        self.rates[name] = (start, n + 1)
        if n + 1 > self.max_rate_hz:
            self.flooding[name] = now + 1.0
            return "flood"
        if stamp_age_s < -self.skew_s:
            return "ahead"
        if max(stamp_age_s, 0.0) + sensor_age_s >= self.max_age_s:
            return "stale"
        return ""

    def take(
        self, source: str, distance_m: float, stamp_age_s: float, sensor_age_s: float, now: float
    ) -> str:
        """Keep a reading ``judge`` let through: "" when kept, "far" when its distance is not a number."""
        if not math.isfinite(distance_m):
            return "far"
        age = max(stamp_age_s, 0.0) + sensor_age_s
        self.readings.setdefault(self.name(source), _Readings()).add(
            now + self.max_age_s - age, distance_m, self.keep
        )
        self.heard = True
        return ""

    def receive(
        self, source: str, distance_m: float, stamp_age_s: float, sensor_age_s: float, now: float
    ) -> str:
        """Take one reading: ``stamp_age_s`` is the receiver's clock minus the sender's stamp (negative: the
        stamp is ahead), ``sensor_age_s`` the age it says it had when stamped. Returns "" when taken, else
        why not (``judge``, ``take``)."""
        return self.judge(source, stamp_age_s, sensor_age_s, now) or self.take(
            source, distance_m, stamp_age_s, sensor_age_s, now
        )

    def nearest(self, now: float) -> Nearest:
        for name, until in list(self.flooding.items()):
            if until < now:
                del self.flooding[name]
        if self.flooding:
            name = next(iter(self.flooding))
            return Nearest(None, name, f"'{name}' sends over {self.max_rate_hz:g} readings a second")
        fresh: list[Nearest] = []
        last_seen: list[Nearest] = []  # silent sources' people, where last seen
        silent = []
        for name, readings in self.readings.items():
            d = readings.nearest(now)
            if d is not None:
                fresh.append(Nearest(d, name, taken_s=readings.kept[0][0] - self.max_age_s))
            elif name in self.declared:
                silent.append(name)
            elif readings.last is not None:
                why = f"where last seen: no fresh reading from '{name}' for {now - readings.last[0]:.1f} s"
                # taken when last seen: a spell it shows began then (Spell), not at this look
                last_seen.append(Nearest(readings.last[1], name, why, readings.last[0] - self.max_age_s))
        if silent:
            return Nearest(None, silent[0], f"no fresh distance from {', '.join(silent)} (declared)")
        if not fresh:  # a person last seen far, alone, frees nothing: nothing fresh is a hold
            old = f"the last separation is over {self.max_age_s:.2f} s old"
            return Nearest(None, "", old if self.heard else "no separation yet")
        return min(fresh + last_seen, key=lambda n: n.distance_m or 0.0)


class Adoption:
    """How long the executor takes to act on a reading (a part of T_r, DESIGN §8): from its arrival to the
    controller step in which the servo plays the scale it led to (a ramp's first step), or, when the
    scale in force already answers it, to the look that found so. Times are the loop's clock in seconds.

    ``budget_s`` is the term T_r holds for it. A reading not answered within it (one measured over it, or
    one still waiting past it) makes the arm hold (``late``) until a reading is answered within it again:
    S_p was computed for the budget, not for what the host gave."""

    KEPT = 100_000  # the latest delays kept for the distribution

    def __init__(self, budget_s: float) -> None:
        self.budget_s = budget_s
        self.oldest: float | None = None  # the arrival of the oldest reading no look has taken yet
        self.waiting: tuple[object, float] | None = None  # a ramp offered, and the oldest arrival it answers
        self.delays: deque[float] = deque(maxlen=self.KEPT)
        self.late = False
        self.times_late = 0  # how often the arm was held for it

    def arrived(self, now: float) -> None:
        if self.oldest is None:
            self.oldest = now

    def take(self) -> float | None:
        """At a look: the oldest arrival it answers (the readings since the last look)."""
        oldest, self.oldest = self.oldest, None
        return oldest

    def answered(self, arrival: float | None, at: float) -> None:
        if arrival is not None:
            self._record(at - arrival)

    def offered(self, ramp: object, arrival: float | None) -> None:
        """A ramp that answers readings from ``arrival`` on; answered once the servo plays it (``began``)."""
        if arrival is None:
            return
        if self.waiting is not None:
            arrival = min(arrival, self.waiting[1])
        self.waiting = (ramp, arrival)

    def began(self, ramp: object | None, at: float | None, now: float, pending: object | None) -> None:
        """At each look: what the servo has begun playing (``ramp`` from ``at``) and what it holds pending.
        The ramp waited for, when begun, is measured; a wait past the budget makes the arm hold before the
        ramp comes. One neither begun nor pending any more was replaced before it played (the lease's stop,
        a newer ramp): it will never play, and its readings go to this look. Waiting on for it held the arm
        for good: a hold wants no ramp, so no newer one ever came to end the wait."""
        if self.waiting is None:
            return
        wanted, arrival = self.waiting
        if ramp is wanted and at is not None:
            self.waiting = None
            self._record(at - arrival)
        elif wanted is not pending:
            self.dropped()
        elif now - arrival > self.budget_s:
            self._over()

    def dropped_arrival(self, arrival: float | None) -> None:
        """Readings a look could not answer (its ramp was refused): the next look answers them."""
        if arrival is not None:
            self.oldest = arrival if self.oldest is None else min(arrival, self.oldest)

    def dropped(self) -> None:
        """The ramp waited for will never play (the path ended, the loop dropped it): its readings are
        answered by the next look."""
        if self.waiting is not None:
            _, arrival = self.waiting
            self.waiting = None
            self.dropped_arrival(arrival)

    def _record(self, delay_s: float) -> None:
        self.delays.append(delay_s)
        if delay_s > self.budget_s:
            self._over()
        elif self.waiting is None:
            self.late = False

    def _over(self) -> None:
        if not self.late:
            self.times_late += 1
        self.late = True

    def quantiles(self) -> dict[str, float]:
        """p50, p99.9 and the max of the delays kept, in seconds (empty when none)."""
        if not self.delays:
            return {}
        d = np.fromiter(self.delays, dtype=float)
        return {
            "p50": float(np.quantile(d, 0.5)),
            "p99.9": float(np.quantile(d, 0.999)),
            "max": float(d.max()),
        }
