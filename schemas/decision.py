"""The decision maker's output: ``decision/selection`` (paper Alg. 1; DESIGN §7)."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.base import RR_MAX_S, Message, TimeNs

# "fixed": a condition that holds one k (the study's a and b: decision_maker mode = "fixed")
# "movement": held, the wearer moved well above their level at work (RR then says nothing of mental load)
Reason = Literal["initial", "stress", "rest", "cumulative", "hold", "low-quality", "fixed", "movement"]
MAX_N = 1000  # solutions per Pareto set; the paper's N is 15

SolutionIndex = Annotated[int, msgspec.Meta(ge=1, le=MAX_N)]
Threshold = Annotated[float, msgspec.Meta(gt=0.0, le=RR_MAX_S)]


class Selection(Message, frozen=True, tag="decision.selection.v1"):
    """The solution index k (1 = smoothest … n = fastest) and why it moved. State, not an event: it is
    republished periodically and answered on query."""

    k: SolutionIndex
    n: SolutionIndex
    delta: Annotated[int, msgspec.Meta(ge=-MAX_N, le=MAX_N)]
    reason: Reason
    window_end_ns: TimeNs | None = None
    # the thresholds Alg. 1 decides against, from the calibration in force (new fields: old decoders skip
    # them; None for a fixed condition): RR_r, RR_s = RR_r - offset, RR_s^max = RR_s - sigma_s
    rr_rest_s: Threshold | None = None
    rr_stress_s: Threshold | None = None
    rr_stress_max_s: Threshold | None = None

    def __post_init__(self) -> None:
        if self.k > self.n:
            raise ValueError(f"k = {self.k} is above n = {self.n}")
