"""A cell's separation readings judged as they arrive and kept, the nearest fresh one, and the scale it allows
(DESIGN §8; common/safety/separation.py): one set of rules for the two places that read people, the
executor's looks (services/executor/reaction.py) and the separation guard beside the servo
(services/executor/guard_process.py), so that the guard can never free what the executor would hold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.runtime.errors import Rejected
from common.safety.geometry import Arm, Body, Pose, Sensor, intrusion_iso13855, separation
from common.safety.separation import Figures, Nearest, Sources, Spell, Ssm
from schemas.operator import Separation

UNDECLARED_C = intrusion_iso13855("legs")  # 1.2 m: the largest C of ISO 13855, for a source nobody placed


@dataclass(frozen=True, slots=True)
class Rules:
    """What the cell's settings say of its readings (services/executor/settings.py ``Settings.rules``)."""

    arm: Arm
    sensors: dict[str, Sensor]
    ssm: Ssm  # C = 0: each reading is kept as its room, S − C
    max_age_s: float
    skew_s: float
    max_rate_hz: float
    refuse_undeclared: bool
    adoption_s: float = 0.1  # T_r's part for the arm's answer: a ramp's lead (separation.Spell)


class Watch:
    """The readings of every source, each judged on arrival (rate before age, the stamp against this
    host's clock, the source's own key) and kept as its room S − C, S measured to the arm and tool at the
    joints then; the nearest fresh room, and σ for it on a curve's figures."""

    def __init__(self, rules: Rules) -> None:
        self.rules = rules
        self.sources = Sources(
            rules.max_age_s, rules.skew_s, tuple(rules.sensors), max_rate_hz=rules.max_rate_hz
        )
        self._body: tuple[bytes, Body] | None = None  # the arm's body at the joints it was last found for
        self.spell = Spell(rules.adoption_s)

    def receive(self, sep: Separation, own_key: bool, stamp_age_s: float, now: float, q: np.ndarray) -> None:
        """Take one reading, or refuse it (``Rejected``, with the reason a counter keeps): ``own_key``, it
        came on its source's own key (``operator/separation/<source>``), which on an installed cell only
        that source's account may put; ``stamp_age_s`` this host's clock less its stamp (loop seconds);
        ``q`` the arm's joints now."""
        r = self.rules
        if r.refuse_undeclared and sep.source not in r.sensors:
            raise Rejected("undeclared", f"'{sep.source}' is no source of this cell (separation_sources), "
                           'and separation_undeclared = "refuse"')  # fmt: skip
        if r.refuse_undeclared and not own_key:
            raise Rejected("shared_key", f"'{sep.source}' on operator/separation: an installed cell takes "
                           "a source's readings on its own key only")  # fmt: skip
        why = self.sources.judge(sep.source, stamp_age_s, sep.age_s, now)
        if why == "ahead":
            raise Rejected("ahead", f"'{sep.source}' stamped {-stamp_age_s:.3f} s ahead of the executor's "
                           f"clock (the cell's skew bound is {self.sources.skew_s:g} s)")  # fmt: skip
        if why == "stale":
            old = max(stamp_age_s, 0.0) + sep.age_s
            raise Rejected("stale", f"'{sep.source}' {old:.3f} s old on arrival (at most "
                           f"{self.sources.max_age_s:g} s is used)")  # fmt: skip
        if why == "flood":
            raise Rejected("flood", f"'{sep.source}' sends over {self.sources.max_rate_hz:g} readings a "
                           "second: the arm holds until it sends at its rate again")  # fmt: skip
        sensor = self.sensor(sep.source)
        points = np.asarray(sep.points, dtype=float) if sep.points else None
        s = separation(self.body(q), sensor, sep.distance_m, points, sep.to_robot, sep.placed)
        self.sources.take(sep.source, s - sensor.intrusion_m, stamp_age_s, sep.age_s, now)

    def sensor(self, name: str) -> Sensor:
        """A declared source, or one nobody declared: in the cell frame, with the largest C a scanner can
        have (legs at the floor), its plain distances ranges from the cell's origin."""
        return self.rules.sensors.get(name) or Sensor(name, Pose(), UNDECLARED_C)

    def body(self, q: np.ndarray) -> Body:
        """The arm and tool at joints ``q``, found again only when the joints moved."""
        q = np.asarray(q, dtype=float)
        key = q.tobytes()
        if self._body is None or self._body[0] != key:
            self._body = (key, self.rules.arm.body(q))
        return self._body[1]

    def nearest(self, now: float) -> Nearest:
        return self.sources.nearest(now)

    def allowed(self, figures: Figures, nearest: Nearest, in_force: float, now: float) -> float:
        """σ, stepped, for that distance on a curve of these figures (None: a hold), played at σ =
        ``in_force`` now (the arm keeps it through T_r: S_r is its); 0 once a spell of S < S_p can no
        longer end in time by slowing (``Spell``)."""
        wanted = figures.scale(self.rules.ssm, nearest.distance_m, in_force)
        return self.spell.sigma(
            wanted, figures.ssm(self.rules.ssm), figures.speed_m_s, nearest, in_force, now
        )
