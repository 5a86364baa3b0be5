"""The executor's output: ``robot/state``, ``robot/cycle``, ``robot/event`` (DESIGN §8, §9)."""

from __future__ import annotations

from typing import Literal

from schemas.base import Message, NonNegInt, Seconds
from schemas.pareto import Vector6


class RobotState(Message, frozen=True, tag="robot.state.v1"):
    q: Vector6
    qd: Vector6
    tcp: Vector6
    path_id: str | None = None
    k: int | None = None
    mode: str = "idle"
    waiting_for: str | None = None  # the operator signal a ``wait_for`` step waits for


class CycleReport(Message, frozen=True, tag="robot.cycle.v1"):
    cycle: NonNegInt
    cycle_time_s: Seconds
    k_per_path: dict[str, int]


class RobotEvent(Message, frozen=True, tag="robot.event.v1"):
    kind: Literal["refused", "overrun", "protective_stop", "connected", "disconnected", "started", "info"]
    message: str
    path_id: str | None = None
