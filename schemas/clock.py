"""``clock``: the cell's data clock, for a tool that joins a simulated cell (DESIGN §4)."""

from __future__ import annotations

from typing import Annotated

import msgspec

from schemas.base import Message, TimeNs


class CellClock(Message, frozen=True, tag="clock.cell.v1"):
    """How to read the cell's data time: ``epoch + (wall − epoch) · speed``, the time base every process of
    a simulated cell shares (``t_ns``: that time when the answer was made). A tool that stamps what it
    says (a sensor's adapter, a mark) asks for it; a cell on its hosts' synchronised wall clock has nobody
    answering, and the wall clock is the cell's."""

    epoch_ns: TimeNs
    speed: Annotated[float, msgspec.Meta(gt=0.0, le=1000.0)]
