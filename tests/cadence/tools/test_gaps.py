"""What a watcher of the bus did not see, from the senders' numbers (cadence/tools/gaps.py): the demo's
summary counts what the cell sent, and says what its observer missed (issue 39: stopped for 10 s, it
counted 8 cycles where a monitor saw 12, and said nothing)."""

from __future__ import annotations

import asyncio

from cadence.demo.observe import Observed
from cadence.tools.gaps import Gaps
from schemas import CycleReport
from tests.support.cell import CELL

CYCLES = f"cadence/{CELL}/robot/cycle"


def test_a_jump_in_a_senders_numbers_is_what_was_missed_and_a_repeat_or_a_restart_is_not() -> None:
    g = Gaps()
    assert g.note(CYCLES, 5) == 0  # the first seen: what came before the watcher is not counted
    assert g.note(CYCLES, 6) == 0
    assert g.note(CYCLES, 6) == 0  # a republication
    assert g.note(CYCLES, 10) == 3  # 7, 8 and 9 were sent and not seen
    assert g.note(CYCLES, 0) == 0  # the executor restarted: it numbers from 0 again
    assert g.note(CYCLES, 3) == 2
    assert g.missed[CYCLES] == 5
    assert g.restarts[CYCLES] == 1
    assert "robot/cycle 5" in g.said()
    assert Gaps().said() == ""


def test_the_demos_observer_counts_the_cycles_it_missed_and_says_so() -> None:
    obs = Observed(epoch_ns=0)
    handle = obs.watch(CYCLES, obs.cycles.append)

    def cycle(i: int) -> CycleReport:
        return CycleReport(t_ns=(i + 1) * 60_000_000_000, seq=i, cycle=i, cycle_time_s=60.0, k_per_path={})

    async def feed() -> None:
        for i in (0, 1, 2, 3, 8, 9, 10, 11):  # stopped while 4 … 7 were sent
            await handle(CYCLES, cycle(i))

    asyncio.run(feed())
    assert len(obs.cycles) == 8
    assert obs.n_cycles == 12  # what a monitor saw
    assert "robot/cycle 4" in obs.gaps.said()
