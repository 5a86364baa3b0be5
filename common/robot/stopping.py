"""The robot's own stops, which S_p budgets beside the executor's ramp (ISO/TS 15066 §5.5.4: T_s and the
stopping distance are the robot system's; ISO 10218-1 Annex B: its maker states stopping time and distance
per joint by speed, payload and extension).

The executor's ramp (common/trajectory/scaling.py ``stop_time``) is the stop that acts while the executor
and its servo work. When they do not, other stops act, each its own time:
- **the brake**: every joint decelerating at ``stop_deceleration`` on its own, the servo's stop for SIGTERM
  and overruns, and the controller's when its watchdog finds the targets silent for ``watchdog_s`` (the
  arm runs on at the speed in force through that silence);
- **the controller's protective stop** (category 1: a scanner wired to the safeguard input, a stop from
  the dashboard) and **its emergency stop** (category 0), from the maker's figures or the installed
  robot's measured ones (``StopRow``, a table per joint by speed, payload and extension).

Each is budgeted as its time, and as the distance the arm's fastest point covers meanwhile with no credit
for deceleration (the travel at full speed equals the time): a stop only slows the arm, so its fastest
point covers at most v_r · T, whatever the path it brakes along. A row's figure counts for every speed up
to its own, every payload and every extension (the executor knows neither payload nor extension: the
worst row for a speed is its figure); a joint the table does not list takes the worst row of any joint.

**The UR16e** (``UR16E_STOPS``). Universal Robots publishes the e-Series' stopping times and distances as
graphs only (the hardware manual's "Stopping Time and Stopping Distance": joints 0–2 at 33, 66 and 100 %
of speed, payload and extension, categories 0–2), with no figures Cadence could read off them. The one
table of theirs in print is the CB3 UR5's, category 0 at 100 %: base 0.31 rad in 0.244 s, shoulder 0.70
rad in 0.530 s, elbow 0.22 rad in 0.164 s. Cadence's default for a UR16e is therefore a stated
conservative model, not the maker's figures: every stop of every joint at every speed within
``UR16E_STOP_S``, 0.75 s (1.4× the longest time in that table). A cell enters the figures measured on its
robot (ISO 10218-1 Annex B), or its safety configuration's Stopping Time limit, which the controller
itself enforces, as ``robot_stops`` (docs/robot.md). The sim's controller has no protective stop of its
own but the brake.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import msgspec
import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
Fraction = Annotated[float, msgspec.Meta(gt=0.0, le=1.0)]


class StopRow(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One figure of a stopping table: a stop of ``category`` of ``joint`` (0 base … 5 wrist 3) moving at
    ``speed`` of its top speed, carrying ``payload`` of the rated payload at ``extension`` of its reach,
    takes ``time_s`` from its cause to rest."""

    category: Literal[0, 1]
    joint: Annotated[int, msgspec.Meta(ge=0, le=5)]
    time_s: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)]
    speed: Fraction = 1.0
    payload: Fraction = 1.0
    extension: Fraction = 1.0


UR16E_STOP_S = 0.75
UR16E_STOPS = tuple(StopRow(c, j, UR16E_STOP_S) for c in (0, 1) for j in range(3))
UR16E_SOURCE = ("a stated conservative model (0.75 s, every stop, joint and speed): UR publishes the "
                "UR16e's as graphs only")  # fmt: skip


@dataclass(frozen=True, slots=True)
class Stop:
    """What S_p budgets for a robot's stop: its time, which is its travel too (B / v_r: no credit for
    deceleration, module docstring)."""

    time_s: float
    by: str  # which stop it is


@dataclass(frozen=True, slots=True)
class RobotStops:
    """The stops of one robot in one cell (module docstring)."""

    rows: tuple[StopRow, ...] = ()
    source: str = ""
    deceleration: float = math.inf  # rad/s², the brake's (inf: none to budget)
    watchdog_s: float = 0.0  # the controller's: the silence before it brakes (0: none)

    def __post_init__(self) -> None:
        for c in {r.category for r in self.rows}:
            for j in {r.joint for r in self.rows if r.category == c}:
                if not any(r.category == c and r.joint == j and r.speed == 1.0 for r in self.rows):
                    why = "a table must reach every speed the arm runs at"
                    raise ValueError(f"robot_stops: category {c}, joint {j} has no row at speed 1.0: {why}")

    def category(self, c: int, fraction: Array) -> float:
        """The longest stop of category ``c`` for joints moving at ``fraction`` of their top speeds (0 when
        the table has none of it)."""
        rows = [r for r in self.rows if r.category == c]
        listed = {r.joint for r in rows}

        def of(joint: int, f: float) -> float:  # the figure at the next speed measured up covers this one
            up = [r for r in rows if r.joint == joint and r.speed >= min(f, 1.0) - 1e-9]
            least = min(r.speed for r in up)
            return max(r.time_s for r in up if r.speed == least)

        worst = 0.0
        for j, f in enumerate(fraction):
            if f > 0.0 and rows:  # a joint not listed: the worst of the listed ones at its speed
                worst = max(worst, of(j, f) if j in listed else max(of(i, f) for i in listed))
        return worst

    def worst(self, peak_rad_s: Array, top_rad_s: Array) -> Stop:
        """The longest of the robot's stops for a curve whose joints peak at ``peak_rad_s`` (top speeds
        ``top_rad_s``)."""
        fraction = np.asarray(peak_rad_s, dtype=float) / np.asarray(top_rad_s, dtype=float)
        brake = float(np.max(peak_rad_s, initial=0.0)) / self.deceleration
        protective, emergency = self.category(1, fraction), self.category(0, fraction)
        stops = [Stop(brake, "the brake"), Stop(protective, "the protective stop"),
                 Stop(emergency, "the emergency stop")]  # fmt: skip
        if self.watchdog_s > 0.0:
            stops.append(Stop(self.watchdog_s + max(brake, protective), "the watchdog's stop"))
        return max(stops, key=lambda s: s.time_s)


NO_STOPS = RobotStops()  # the executor's ramp alone: a model's, a test's
