"""Pareto sets (queryable ``pareto/<path_id>``, ``pareto/<path_id>/<k>``) and ``pareto/progress``."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.base import Message, NonNegInt, PositiveFloat

Vector6 = Annotated[list[float], msgspec.Meta(min_length=6, max_length=6)]


class ParetoSolution(msgspec.Struct, frozen=True, kw_only=True):
    k: Annotated[int, msgspec.Meta(ge=1)]
    h: list[PositiveFloat]
    t_f: PositiveFloat
    f_time: float
    f_jerk: float


class Boundary(msgspec.Struct, frozen=True, kw_only=True):
    velocity: Vector6
    acceleration: Vector6
    jerk: Vector6


class Limits(msgspec.Struct, frozen=True, kw_only=True):
    velocity: Vector6
    acceleration: Vector6
    jerk: Vector6


class ParetoSet(Message, frozen=True, tag="pareto.set.v1"):
    """A path's set as planned; ``content_hash`` names the inputs it was planned from."""

    path_id: str
    content_hash: str
    constraints: Literal["exact", "hull"]
    waypoints: list[Vector6]
    limits: Limits
    start: Boundary
    end: Boundary
    front: list[Annotated[list[float], msgspec.Meta(min_length=2, max_length=2)]]
    solutions: list[ParetoSolution]


class ParetoSolutionReply(Message, frozen=True, tag="pareto.solution.v1"):
    """One solution of a path's set: the reply to ``pareto/<path_id>/<k>``."""

    path_id: str
    content_hash: str
    n: NonNegInt
    solution: ParetoSolution


class PlanProgress(Message, frozen=True, tag="pareto.progress.v1"):
    path_id: str
    state: Literal["queued", "running", "done", "failed", "stored"]
    done_paths: NonNegInt
    total_paths: NonNegInt
    message: str = ""
