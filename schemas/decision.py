"""The decision maker's output: ``decision/selection`` (paper Alg. 1; DESIGN §7)."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.base import Message, TimeNs

# "fixed": a condition that holds one k (the study's a and b: decision_maker mode = "fixed")
Reason = Literal["initial", "stress", "rest", "cumulative", "hold", "low-quality", "fixed"]
MAX_N = 1000  # solutions per Pareto set; the paper's N is 15

SolutionIndex = Annotated[int, msgspec.Meta(ge=1, le=MAX_N)]


class Selection(Message, frozen=True, tag="decision.selection.v1"):
    """The solution index k (1 = smoothest … n = fastest) and why it moved. State, not an event: it is
    republished periodically and answered on query."""

    k: SolutionIndex
    n: SolutionIndex
    delta: Annotated[int, msgspec.Meta(ge=-MAX_N, le=MAX_N)]
    reason: Reason
    window_end_ns: TimeNs | None = None

    def __post_init__(self) -> None:
        if self.k > self.n:
            raise ValueError(f"k = {self.k} is above n = {self.n}")
