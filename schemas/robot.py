"""The executor's output: ``robot/state``, ``robot/cycle``, ``robot/event`` (DESIGN §8, §9)."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.base import Message, Name, NonNegInt, Seconds, Text
from schemas.decision import SolutionIndex

# What a UR16e can report: joints within ±2π (and a little), speeds far below 10 rad/s, the tool
# within a few metres of the base and its rotation vector within ±2π.
Joints = Annotated[
    list[Annotated[float, msgspec.Meta(ge=-7.0, le=7.0)]], msgspec.Meta(min_length=6, max_length=6)
]
JointSpeeds = Annotated[
    list[Annotated[float, msgspec.Meta(ge=-10.0, le=10.0)]], msgspec.Meta(min_length=6, max_length=6)
]
Pose = Annotated[
    list[Annotated[float, msgspec.Meta(ge=-10.0, le=10.0)]], msgspec.Meta(min_length=6, max_length=6)
]


class RobotState(Message, frozen=True, tag="robot.state.v1"):
    q: Joints
    qd: JointSpeeds
    tcp: Pose
    path_id: Name | None = None
    k: SolutionIndex | None = None
    mode: Name = (
        "idle"  # coarse, derived from ``state`` (common/safety/states.py mode_of): moving, waiting, …
    )
    waiting_for: Name | None = None  # the operator signal a ``wait_for`` step waits for
    # the executor's safety state (common/safety/states.py) and why it is in it: why the robot does not move
    state: Name = "starting"
    reason: Text = ""
    # the time scale σ the current path runs at (1: as planned; 0: holding on the path for a person) and
    # the separation it was chosen for (speed and separation monitoring; None when it is off)
    scale: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)] = 1.0
    separation_m: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] | None = None
    # the seq of the selection in force at the executor: a decision maker numbers its next one after it, so
    # that one restarted without its state, or one whose seq a rogue took, is never locked out
    selection_seq: NonNegInt | None = None


class CycleReport(Message, frozen=True, tag="robot.cycle.v1"):
    cycle: NonNegInt
    cycle_time_s: Seconds
    k_per_path: Annotated[dict[Name, SolutionIndex], msgspec.Meta(max_length=1000)]


# "state": a change of the executor's safety state (common/safety/states.py), "from → to: why" for a person,
# and from_state/to_state for a program
# "scale": the time scale changed for a person's distance; "switch": a new k took effect within a path
EventKind = Literal[
    "refused",
    "overrun",
    "protective_stop",
    "connected",
    "disconnected",
    "started",
    "info",
    "state",
    "scale",
    "switch",
]


class RobotEvent(Message, frozen=True, tag="robot.event.v1"):
    kind: EventKind
    message: Text
    path_id: Name | None = None
    from_state: Name | None = None  # kind "state": the safety state left (common/safety/states.py State)
    to_state: Name | None = None  # kind "state": the safety state entered
