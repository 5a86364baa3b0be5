"""A study session's file (paper §III-C): one MCAP per subject and condition, its bus traffic plus two
metadata records, ``cadence.session`` at the start and ``cadence.session.end`` at the end. Not a bus
message: what `cadence session` and the simulated study write, and all `cadence study analyse` reads."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.base import Name, Seconds, Text, TimeNs
from schemas.operator import Calibration

SESSION_RECORD = "cadence.session"
SESSION_END_RECORD = "cadence.session.end"

# the paper's conditions: (a) minimum time, (b) minimum jerk, (c) tuned online; and (y), yoked: k fixed
# at the subject's own mean k of (c), the same average pace without adapting, which tells "adapting"
# from "slower" when (c) looks better
Condition = Literal["a", "b", "c", "y"]
CONDITION_NAMES: dict[str, str] = {
    "a": "minimum time",
    "b": "minimum jerk",
    "c": "tuned online",
    "y": "yoked to (c)'s mean k",
}
TlxScore = Annotated[int, msgspec.Meta(ge=0, le=100)]


class Tlx(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """NASA-TLX, raw (unweighted, Hart 2006): six items 0–100, asked at the end of a session; for
    performance 0 is perfect and 100 failure, as on the paper form."""

    mental: TlxScore
    physical: TlxScore
    temporal: TlxScore
    performance: TlxScore
    effort: TlxScore
    frustration: TlxScore

    @property
    def raw(self) -> float:
        return (self.mental + self.physical + self.temporal + self.performance + self.effort
                + self.frustration) / 6  # fmt: skip


class SessionInfo(msgspec.Struct, frozen=True, kw_only=True):
    """Written when the condition is in force: everything the analysis needs besides the traffic."""

    subject: Name
    condition: Condition
    cell: Name
    calibration: Calibration | None  # None: the analysis refuses the file (no RR_r to normalise by)
    start_ns: TimeNs  # the cell's data time when the condition took effect
    minutes: Annotated[float, msgspec.Meta(gt=0, le=24 * 60)]  # as planned
    task: Name  # the task file's name
    task_sha256: Annotated[str, msgspec.Meta(pattern="^[0-9a-f]{64}$")]
    software: Name  # "cadence <version>"
    simulated: bool = False  # an operator twin, not a person
    notes: Text = ""
    # with a study plan (`cadence study plan`): the plan's file name, the session's place in the subject's
    # schedule (1 = first), the rest since their last session ended, and the training that ran before
    # the condition (recorded in the file, outside the analysed span)
    study: Name = ""
    period: Annotated[int, msgspec.Meta(ge=1, le=20)] | None = None
    break_s: Seconds | None = None
    training_start_ns: TimeNs | None = None
    yoked_k: Annotated[int, msgspec.Meta(ge=1, le=100)] | None = None  # condition y: the k it held
    # the planned sets the robot ran on (common/trajectory/shipped.py: sets_digest; "" where not known)
    # and what numpy computed with in the process that wrote the file (common/runtime/numeric.py): the
    # first things to compare when two runs
    # that should agree do not
    sets_sha256: Annotated[str, msgspec.Meta(pattern="^([0-9a-f]{64})?$")] = ""
    build: Text = ""


class SessionEnd(msgspec.Struct, frozen=True, kw_only=True):
    """Written last: a file without it was not closed (the recorder died) and is not analysed."""

    end_ns: TimeNs  # the cell's data time at the end
    complete: bool  # ran its planned minutes; False: cut short (Ctrl-C, a fault), ``reason`` says why
    reason: Text = ""
    wall_s: Seconds = 0.0
    tlx: Tlx | None = None  # the subject's NASA-TLX for this session, when asked
