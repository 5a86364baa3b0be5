"""The lockstep loop (common/runtime/lockstep.py): a cell's clock that is driven, not read. Its time moves
on only when every task waits for a later instant; work handed to a thread is done at once, in order."""

from __future__ import annotations

import asyncio
import threading
import time

import pytest

from common.runtime import lockstep
from common.runtime.clock import Clock, monotonic
from tests.support.cell import Cell


def test_time_moves_only_when_every_task_waits_and_then_straight_to_the_next_instant() -> None:
    seen: list[tuple[str, float]] = []

    async def busy() -> None:
        loop = asyncio.get_running_loop()
        before = loop.time()
        sum(i * i for i in range(200_000))  # computing takes no data time
        seen.append(("busy", loop.time() - before))
        await asyncio.sleep(0.5)
        seen.append(("busy woke", loop.time()))

    async def sleeper() -> None:
        await asyncio.sleep(3600.0)  # an hour of data time, not waited for
        seen.append(("hour", asyncio.get_running_loop().time()))

    async def main() -> None:
        await asyncio.gather(sleeper(), busy())

    lockstep.run(main())
    assert seen == [("busy", 0.0), ("busy woke", 0.5), ("hour", 3600.0)]


def test_work_handed_to_a_thread_is_done_at_once_in_the_loops_own_thread_and_in_order() -> None:
    order: list[tuple[str, float, bool]] = []

    def work(name: str) -> str:
        order.append(
            (name, asyncio.get_event_loop().time(), threading.current_thread() is threading.main_thread())
        )
        return name

    async def task(name: str, after_s: float) -> str:
        await asyncio.sleep(after_s)
        return await asyncio.to_thread(work, name)

    async def main() -> list[str]:
        return list(await asyncio.gather(task("late", 2.0), task("early", 1.0)))

    assert lockstep.run(main()) == ["late", "early"]
    assert order == [("early", 1.0, True), ("late", 2.0, True)]


def test_a_driven_clock_is_the_loops_time_from_its_epoch() -> None:
    clock = Clock(speed=16.0, epoch_ns=1_000_000_000_000, driven=True)

    async def main() -> tuple[int, int, float]:
        start = clock.now_ns()
        await clock.sleep(30.0)  # data time, whatever the speed
        return start, clock.now_ns(), monotonic()

    start, after, mono = lockstep.run(main())
    assert start == 1_000_000_000_000
    assert after - start == 30_000_000_000
    assert mono == 30.0
    assert clock.loop_s(30.0) == 30.0


def test_under_a_ceiling_data_time_never_runs_ahead_of_the_wall_and_the_run_is_the_same() -> None:
    """``--speed 20``: the loop waits for the wall where it is ahead of it, and where it fell behind (here
    a stall of 0.2 s, 4 s of data time at 20×) it goes on from there, with no burst to catch up. A slow
    host can only put it further behind, so the bounds below hold on any host, and what happens is the
    run without a ceiling."""

    Record = list[tuple[float, float]]

    async def ticking(record: Record, start: float, stall: dict[str, float]) -> list[float]:
        loop, seen = asyncio.get_running_loop(), []
        for i in range(30):
            await asyncio.sleep(0.05 * (1 + i % 3))
            record.append((loop.time(), time.monotonic() - start))
            seen.append(loop.time())
            if i == 9:
                time.sleep(0.2)  # the host stalls
                stall["data_s"], stall["wall_s"] = loop.time(), time.monotonic() - start
        return seen

    free = lockstep.run(ticking([], time.monotonic(), {}))
    record: list[tuple[float, float]] = []
    stall: dict[str, float] = {}
    start = time.monotonic()
    capped = lockstep.run(ticking(record, start, stall), ceiling=20.0)
    assert capped == free
    for data_s, wall_s in record:
        assert data_s <= 20.0 * wall_s + 1e-9, (data_s, wall_s)
    # after the stall: one step at once (the loop was behind), then at the ceiling from there
    last_data_s, last_wall_s = record[-1]
    assert last_data_s - stall["data_s"] - 0.15 <= 20.0 * (last_wall_s - stall["wall_s"]) + 1e-9
    assert time.monotonic() - start >= free[-1] / 20.0


@pytest.mark.lockstep
@pytest.mark.asyncio
async def test_a_test_marked_lockstep_runs_on_a_lockstep_loop_and_its_cell_stamps_data_time(
    cell: Cell,
) -> None:
    """The harness of the executor's separation tests (tests/conftest.py): an hour of the cell's data time
    passes in no wall time, and the test's own stamps follow it, from now to the second."""
    assert isinstance(asyncio.get_running_loop(), lockstep.LockstepLoop)
    assert abs(cell.now_ns() - time.time_ns()) < 2e9
    before, wall = cell.now_ns(), time.monotonic()
    await asyncio.sleep(3600.0)
    assert cell.now_ns() - before == 3600 * 10**9
    assert time.monotonic() - wall < 60
