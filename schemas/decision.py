"""The decision maker's output: ``decision/selection`` (paper Alg. 1; DESIGN §7)."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.base import Message, NonNegInt

Reason = Literal["initial", "stress", "rest", "cumulative", "hold", "low-quality"]


class Selection(Message, frozen=True, tag="decision.selection.v1"):
    """The solution index k (1 = smoothest … n = fastest) and why it moved. State, not an event: it is
    republished periodically and answered on query."""

    k: Annotated[int, msgspec.Meta(ge=1)]
    n: Annotated[int, msgspec.Meta(ge=1)]
    delta: int
    reason: Reason
    window_end_ns: NonNegInt | None = None
