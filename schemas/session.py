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

# the paper's conditions: (a) minimum time, (b) minimum jerk, (c) tuned online
Condition = Literal["a", "b", "c"]
CONDITION_NAMES: dict[str, str] = {"a": "minimum time", "b": "minimum jerk", "c": "tuned online"}


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


class SessionEnd(msgspec.Struct, frozen=True, kw_only=True):
    """Written last: a file without it was not closed (the recorder died) and is not analysed."""

    end_ns: TimeNs  # the cell's data time at the end
    complete: bool  # ran its planned minutes; False: cut short (Ctrl-C, a fault), ``reason`` says why
    reason: Text = ""
    wall_s: Seconds = 0.0
