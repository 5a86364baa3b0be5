"""The decision maker's windows in a test: data time near now (each ended before it is sent), the
selection that answers one, and the k Alg. 1 gives a sequence of them."""

from __future__ import annotations

import asyncio

import pytest

from common.decision import Params, State, step
from common.runtime.bus import Bus
from schemas import HrvWindow, Selection
from tests.support.cell import now_ns, put

# The test's windows are 14 s long (the decision maker does not read a window's length) and start 41 of
# them before now: near the decision maker's clock, as live ones are, and each ended before it is sent
# (nothing from the receiver's future is taken).
S = 1_000_000_000
SPAN = 14 * S


BASE = [now_ns() - 41 * SPAN]


@pytest.fixture(autouse=True)
def _base_now() -> None:
    BASE[0] = now_ns() - 41 * SPAN


def window(i: int, rr: float | None, quality: str = "good") -> HrvWindow:
    return HrvWindow(
        t_ns=BASE[0] + (i + 1) * SPAN,
        seq=i,
        start_ns=BASE[0] + i * SPAN,
        end_ns=BASE[0] + (i + 1) * SPAN,
        mean_rr_s=rr,
        n_beats=37,
        excluded_fraction=0.0,
        quality=quality,
    )


async def answer(bus: Bus, sub, w: HrvWindow) -> Selection:
    """Publish a window and wait for the selection that answers it (republishes are skipped)."""
    put(bus, bus.key("hrv/window"), w, block=True)
    async with asyncio.timeout(10):
        async for _, sel in sub:
            if sel.window_end_ns == w.end_ns:
                return sel
    raise AssertionError("unreachable")


def expected(windows: list[HrvWindow], rr_r: float) -> list[int]:
    p, s, out = Params.of(rr_r), None, []
    s = State.initial(p)
    for w in windows:
        s = step(p, s, w.mean_rr_s, w.quality == "good").state
        out.append(s.k)
    return out
