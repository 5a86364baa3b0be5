"""A flood of separation readings at the highest rate one process here can put (tests/support/flood.py:
about 600k a second), on the wall clock, with the store and the executor as processes behind a Zenoh
router (issue 74). Before, such a flood saturated the executor's loop, its readings reached it more than
0.3 s old, and were counted ``stale`` rather than as a flood: the arm ran on the honest far reading (113
moving samples in 6 s), and a person at 1.5 m seen by a source nobody declared was forgotten once their
readings stopped arriving in time (the arm at scale ≥ 0.5 in 73 of 97 moving samples beside them).

Now a source's rate is judged before its readings' age, and a source that falls silent keeps its person
where last seen (common/safety/separation.py, ``Sources``). Two phases, the cell's declared tracker saying
6 m at 20 Hz throughout:

- the flood alone: the arm slows within T_r of its start and is at rest within T_r + T_s of the path it
  runs (its S_p's own budget: the executor's figures), and does not move until it ends; after it, the
  arm runs again (the hold was the flood's, not for good);
- a person at 1.5 m on an undeclared source at 20 Hz, the arm held for them, then the flood: the arm does
  not move from the person's hold until the person, after the flood, walks off (their own source says
  6 m), and then it runs again.

The controller's watchdog stops the arm when a starved servo falls silent (issue 73: the servo still
shares the executor's interpreter); a stopped arm is a held one, and the test resumes it, as a person at
the cell would, only where the arm may run again."""

from __future__ import annotations

import asyncio
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest

from schemas import RobotEvent, RobotState, Separation, ServiceStatus
from schemas.topology import encode
from services.executor.settings import Settings as ExecutorSettings
from tests.support.arm import figures_at_top_k, speed
from tests.support.executor import Processes, executor_processes

SOURCES = '[{ name = "tracker", detects = "body" }]'
WATCHED = {"CADENCE_EXECUTOR_SEPARATION": "true", "CADENCE_EXECUTOR_SEPARATION_SOURCES": SOURCES}
FAR, NEAR, HEIGHT, PERIOD_S = 6.0, 1.5, 1.0, 0.05
FLOOD_S = 2.5
SKEW_S = 0.05  # the clock skew the cell's settings allow (common/runtime/config.py): a part of T_r
FLOOD_AGE_S = 0.5  # stale on arrival on any host, as a flood that saturates the executor arrives
REFUSED = "rejected/operator/separation/"
FLOODS = REFUSED + "flood"
MOVING = 1e-3  # m/s: the arm's fastest point


class Watcher:
    """The test's side of the cell: the tracker and the camera, the arm's states as they come (with the
    wall time each came at), and a resume after each of the watchdog's stops while the arm may run."""

    def __init__(self, cell: Processes) -> None:
        self.cell, self.bus = cell, cell.bus
        self.arm = ExecutorSettings().arm()
        self.states: list[tuple[float, RobotState]] = []
        self.camera: float | None = None  # where the undeclared camera sees its person (None: silent)
        self.may_run = True
        self.key = self.bus.key("operator/separation")
        self.sub = self.bus.subscribe(self.bus.key("robot/state"), RobotState, maxsize=100_000)
        self.health = self.bus.subscribe(self.bus.key("health/executor"), ServiceStatus, maxsize=1)
        self.resuming: asyncio.Task[object] | None = None

    def tell(self, source: str, x: float) -> None:
        sep = Separation(t_ns=time.time_ns(), seq=0, distance_m=math.hypot(x, HEIGHT), source=source,
                         points=((x, 0.0, HEIGHT),), placed=True)  # fmt: skip
        self.bus.put_raw(self.key, encode(sep))

    async def track(self) -> None:
        while True:
            self.tell("tracker", FAR)
            if self.camera is not None:
                self.tell("camera:side", self.camera)
            await asyncio.sleep(PERIOD_S)

    async def next(self) -> RobotState:
        s = (await self.sub.receive(60))[1]
        self.states.append((time.time(), s))
        if (
            self.may_run
            and s.state == "stopped"
            and "watchdog" in s.reason
            and (self.resuming is None or self.resuming.done())
        ):
            by = f"{self.bus.key('robot/resume')}?by=flood-test"
            self.resuming = asyncio.create_task(self.bus.get(by, RobotEvent, timeout=20))
        return s

    async def until(self, what: str, pred, timeout: float = 120.0) -> float:
        """Until a state for which ``pred`` holds: the wall time it came."""
        async with asyncio.timeout(timeout):
            while not pred(await self.next()):
                pass
        print(f"  {what}: {self.states[-1][1].scale:.2f} scale, {self.states[-1][1].reason!r}")
        return self.states[-1][0]

    def held_for_the_person(self, s: RobotState) -> bool:
        """Held at scale 0 for the camera's person, the nearest (the tracker says 6 m)."""
        return (
            s.scale == 0.0 and not self.running(s) and s.separation_m is not None and s.separation_m < FAR / 2
        )

    def running(self, s: RobotState) -> bool:
        return s.state == "moving" and speed(self.arm, s) > MOVING

    async def flood(self, seconds: float) -> tuple[float, float]:
        """A flood of far readings on a second source for ``seconds``, each stale on arrival, taking the
        arm's states meanwhile: its first and last put on the wall clock."""
        flooder = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "tests.support.flood", self.cell.endpoint, self.key, "scanner:rogue",
            str(seconds), str(FLOOD_AGE_S), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        )  # fmt: skip
        said = asyncio.ensure_future(flooder.communicate())
        while not said.done():
            got = asyncio.ensure_future(self.next())
            await asyncio.wait({got, said}, return_when=asyncio.FIRST_COMPLETED)
            if not got.done():
                got.cancel()
        out = said.result()[0].decode().strip()
        assert flooder.returncode == 0, out
        print(f"  the flood: {out.splitlines()[-1]}")
        flood = json.loads(out.splitlines()[-1])
        return flood["start"], flood["end"]

    async def counted(self, name: str, timeout: float = 10.0) -> int:
        """The executor's counter ``name`` once its status (every second) has it, 0 if not within
        ``timeout``."""
        try:
            async with asyncio.timeout(timeout):
                while not (n := (await self.health.receive(timeout))[1].counters.get(name, 0)):
                    pass
        except TimeoutError:
            return 0
        return n

    def moving_between(self, start: float, end: float) -> list[tuple[float, RobotState]]:
        return [(t, s) for t, s in self.states if start <= t <= end and self.running(s)]


@pytest.mark.asyncio
async def test_a_flood_holds_the_arm_while_it_lasts_and_a_near_person_stays_held_through_a_far_one(
    tmp_path: Path, example_sets: Path
) -> None:
    _, each = figures_at_top_k(example_sets)  # the executor starts at k = 15, and no selection comes
    async with executor_processes(tmp_path, example_sets, WATCHED) as processes:
        cell = Watcher(processes)
        await cell.bus.until_subscribed(cell.key, 120)
        tracker = asyncio.create_task(cell.track())
        try:
            await cell.until("the arm runs, the tracker at 6 m", lambda s: cell.running(s) and s.scale == 1.0)

            # the flood alone
            start, end = await cell.flood(FLOOD_S)
            seen = next((t for t, s in cell.states if t >= start and s.scale < 1.0), math.inf)
            held = next((t for t, s in cell.states if t >= start and not cell.running(s)), math.inf)
            moved = cell.moving_between(held, end)
            after = await cell.until("after the flood, the arm runs again", cell.running, 60)
            print(f"  slowing {seen - start:.3f} s and held {held - start:.3f} s after the flood began; "
                  f"{len(moved)} moving states until it ended {end - start:.3f} s after; running again "
                  f"{after - end:.3f} s after")  # fmt: skip
            path = next(s.path_id for t, s in reversed(cell.states) if t < start and s.path_id)
            tr = sum(ExecutorSettings().reaction_parts(SKEW_S).values())
            bound = tr + each[path].stop_time_s
            assert seen - start <= tr, f"the flood not answered within T_r = {tr:.2f} s"
            assert held - start <= bound, f"the arm not at rest within T_r + T_s = {bound:.2f} s on '{path}'"
            assert not moved, moved[:3]
            assert await cell.counted(FLOODS), "the flood was taken for stale readings"

            # a person at 1.5 m seen by an undeclared camera, then the flood on another source
            cell.camera = NEAR
            cell.may_run = False
            seen = time.time()
            held = await cell.until("the person at 1.5 m holds the arm", cell.held_for_the_person, 60)
            start, end = await cell.flood(FLOOD_S)
            stay = time.time() + 1.0  # the person stays a second past the flood
            while time.time() < stay:
                await cell.next()
            cell.camera, cell.may_run, left = FAR, True, time.time()
            moved = cell.moving_between(held, left)
            after = await cell.until("the person walked off: the arm runs again", cell.running, 60)
            print(f"  held {held - seen:.3f} s after the person was seen; {len(moved)} moving states until "
                  f"they walked off, {left - start:.3f} s after the flood began; running {after - left:.3f} "
                  "s after")  # fmt: skip
            assert not moved, moved[:3]
        finally:
            tracker.cancel()
        counters = (await cell.health.receive(30))[1].counters
        print(f"  the executor's refusals: { {k: v for k, v in counters.items() if k.startswith(REFUSED)} }")
