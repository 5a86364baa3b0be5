"""Pareto sets (queryable ``pareto/<path_id>``, ``pareto/<path_id>/<k>``) and ``pareto/progress``."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.base import Finite, Message, Name, NonNegInt, Seconds, Text
from schemas.decision import MAX_N, SolutionIndex

Vector6 = Annotated[list[Finite], msgspec.Meta(min_length=6, max_length=6)]
MAX_PATH_S = 300.0  # one path of a cell's cycle never takes five minutes; the validator samples it whole
MAX_WAYPOINTS = 1000
Interval = Annotated[float, msgspec.Meta(gt=0.0, le=MAX_PATH_S)]


class ParetoSolution(msgspec.Struct, frozen=True, kw_only=True):
    k: SolutionIndex
    h: Annotated[list[Interval], msgspec.Meta(min_length=2, max_length=MAX_WAYPOINTS + 1)]
    t_f: Interval
    f_time: Seconds
    f_jerk: Seconds

    def __post_init__(self) -> None:
        if abs(sum(self.h) - self.t_f) > 1e-6 * self.t_f:
            raise ValueError(f"solution k = {self.k}: t_f = {self.t_f} is not the sum of its h")


class PathEnd(msgspec.Struct, frozen=True, kw_only=True):
    """One end of a path on the wire; ``Boundary`` (common/trajectory/bspline.py) holds both ends."""

    velocity: Vector6
    acceleration: Vector6
    jerk: Vector6


class Limits(msgspec.Struct, frozen=True, kw_only=True):
    velocity: Vector6
    acceleration: Vector6
    jerk: Vector6


class ParetoSet(Message, frozen=True, tag="pareto.set.v1"):
    """A path's set as planned; ``content_hash`` names the inputs it was planned from. Solutions are
    k = 1 … n in order, each with one interval more than there are waypoints."""

    path_id: Name
    content_hash: Name
    constraints: Literal["exact", "hull"]
    waypoints: Annotated[list[Vector6], msgspec.Meta(min_length=2, max_length=MAX_WAYPOINTS)]
    limits: Limits
    start: PathEnd
    end: PathEnd
    front: Annotated[
        list[Annotated[list[Finite], msgspec.Meta(min_length=2, max_length=2)]],
        msgspec.Meta(max_length=100_000),
    ]
    solutions: Annotated[list[ParetoSolution], msgspec.Meta(min_length=1, max_length=MAX_N)]

    def __post_init__(self) -> None:
        for i, s in enumerate(self.solutions):
            if s.k != i + 1:
                raise ValueError(f"solutions[{i}] has k = {s.k}; solutions are k = 1 … n in order")
            if len(s.h) != len(self.waypoints) + 1:
                raise ValueError(
                    f"solution k = {s.k} has {len(s.h)} intervals for {len(self.waypoints)} waypoints"
                )


class ParetoSolutionReply(Message, frozen=True, tag="pareto.solution.v1"):
    """One solution of a path's set: the reply to ``pareto/<path_id>/<k>``."""

    path_id: Name
    content_hash: Name
    n: Annotated[int, msgspec.Meta(ge=1, le=MAX_N)]
    solution: ParetoSolution

    def __post_init__(self) -> None:
        if self.solution.k > self.n:
            raise ValueError(f"solution k = {self.solution.k} is above n = {self.n}")


PlanState = Literal["queued", "running", "done", "failed", "stored"]


class PlanProgress(Message, frozen=True, tag="pareto.progress.v1"):
    path_id: Name
    state: PlanState
    done_paths: NonNegInt
    total_paths: NonNegInt
    message: Text = ""
