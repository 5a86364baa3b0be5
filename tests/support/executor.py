"""The executor in a test: the example task shortened, a store serving its sets planned once, the sim
backend's settings, and the next message of a kind."""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path

from common.runtime.bus import Bus, BusConfig
from common.trajectory.task import load_task
from schemas import (
    ParetoSet,
    RobotEvent,
    RobotState,
    ServiceStatus,
)
from schemas.topology import encode
from services.executor.__main__ import Settings
from services.executor.settings import SourceSettings
from services.pareto_store.__main__ import Settings as StoreSettings
from services.pareto_store.__main__ import main as store_main
from services.registry import BY_NAME
from tests.support.cell import CELL, Cell, InProcessService, free_port
from tests.support.paths import planned_once

TASK = """
[task]
name = "shuttle"
[planner]
population = 16
generations = 6
n_solutions = 5
[[paths]]
id = "there"
unit = "deg"
waypoints = [[0, -90, 90, -90, -90, 0], [30, -80, 100, -100, -90, 20], [45, -70, 95, -110, -90, 40]]
[[paths]]
id = "back"
unit = "deg"
waypoints = [[45, -70, 95, -110, -90, 40], [20, -85, 92, -95, -90, 10], [0, -90, 90, -90, -90, 0]]
[[cycle]]
gripper = "on"
[[cycle]]
move = "there"
[[cycle]]
wait_for = "part"
[[cycle]]
gripper = "off"
[[cycle]]
wait = 0.2
[[cycle]]
move = "back"
"""


SPEED = 8.0


# The UR controller's tests not about overruns: a controller paces the samples on the wall clock, and a
# loaded CI machine misses servo deadlines in runs (the sim arm's time is its samples: no run stops it)
CALM = 1000


def tracked(*names: str) -> list[str | SourceSettings]:
    """Declared sources that measure to the arm and see the body (C = 0.85 m by ISO 13855): a test's
    distances are the person's distance to the arm, S."""
    return [SourceSettings(n, detects="body", to_robot=True) for n in names]


def sim_settings(task_file: Path, **changes: object) -> Settings:
    """The executor as these tests run it: the sim arm, no FIFO, one cycle with no operator, starting at
    k = 3 with no decision maker; the real overrun rule (the sim arm's time is the samples it was sent, so
    a loaded machine's overruns are counted and never stop it); ``changes`` override."""
    base: dict[str, object] = {
        "task": str(task_file),
        "fifo_priority": 0,
        "cycles": 1,
        "wait_for_signals": False,
        "start_selection": "initial",
        "initial_k": 3,
    }
    return Settings(**{**base, **changes})


async def store_serving(
    bus: Bus, task: Path, data: Path, where: Cell | str, planned: Path | None = None
) -> InProcessService:
    """A store serving ``task`` in the cell ``where`` (or on the Zenoh endpoint ``where``), from
    ``planned`` (a store's SQLite file), by default the task's sets as planned once per test run: the
    store serves stored sets at once (tests of planning are elsewhere)."""
    data.mkdir(parents=True, exist_ok=True)
    shutil.copy(planned or planned_once(task), data / "pareto.sqlite")
    health = aiter(bus.subscribe(bus.key("health/pareto_store"), ServiceStatus, maxsize=1))
    settings = StoreSettings(task=str(task))
    if isinstance(where, Cell):
        store = where.service("pareto_store", store_main, settings, data)
    else:  # a Zenoh endpoint
        store = InProcessService("pareto_store", store_main, settings, data, where)
    async with asyncio.timeout(60):
        async for _, status in health:
            if status.state == "serving":
                return store
    raise AssertionError("unreachable")


async def cached_sets(bus: Bus, task_file: Path, data: Path) -> dict[str, ParetoSet]:
    """The task's sets from the store, put in the executor's cache under ``data`` as a run before this one
    leaves them: a start with the store down runs them, and a start on a full disk writes nothing before
    its first cycle's record."""
    cache = data / "executor"
    cache.mkdir(parents=True)
    sets = {}
    for pid in load_task(task_file).paths:
        sets[pid] = (await bus.get(bus.key(f"pareto/{pid}"), ParetoSet))[0].message
        (cache / f"{pid}.msgpack").write_bytes(encode(sets[pid]))
    return sets


async def operator_resumes(bus: Bus) -> None:
    """An operator who clears every latched stop as soon as it comes: for tests that are about a cycle,
    not about stops, on a loaded machine that misses deadlines (a watchdog trip is latched too)."""
    states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=1))
    async for _, s in states:
        if s.state == "stopped":
            await bus.get(f"{bus.key('robot/resume')}?by=the operator of the test", RobotEvent, timeout=10)


async def next_of(sub, pred=lambda m: True, timeout: float = 30.0):
    async with asyncio.timeout(timeout):
        async for _, msg in sub:
            if pred(msg):
                return msg
    raise AssertionError("unreachable")


async def next_while_busy(sub, busy, quiet_s: float = 60.0, limit_s: float = 900.0):
    """The next message of ``sub``, waiting as long as ``busy`` (another subscription: the executor's
    events) says something at least every ``quiet_s``: on the wall clock a cycle takes what the host
    gives it (a loaded host's stalls trip the controller's watchdog, and each costs a resume), and a
    test fails when nothing moves, not when the host is slow. ``limit_s`` bounds it all the same."""
    got = asyncio.ensure_future(anext(sub))
    try:
        async with asyncio.timeout(limit_s):
            while not got.done():
                said = asyncio.ensure_future(anext(busy))
                done, _ = await asyncio.wait(
                    {got, said}, timeout=quiet_s, return_when=asyncio.FIRST_COMPLETED
                )
                if not done:
                    said.cancel()
                    raise AssertionError(f"no message, and nothing from the executor for {quiet_s:g} s")
                if said not in done:
                    said.cancel()
        return got.result()[1]
    finally:
        got.cancel()


@dataclass(frozen=True)
class Processes:
    """The store and the executor as processes of their own, and the router this test holds."""

    bus: Bus
    endpoint: str
    procs: tuple[subprocess.Popen[bytes], ...]  # the store, the executor

    @property
    def executor(self) -> subprocess.Popen[bytes]:
        return self.procs[1]


SERVICES = ("pareto_store", "executor")


@asynccontextmanager
async def executor_processes(
    tmp_path: Path, sets: Path, executor_env: dict[str, str]
) -> AsyncIterator[Processes]:
    """The example task's store (from its planned ``sets``) and executor, each a process on the wall clock
    connected to a Zenoh router this test opens (nothing in lockstep: what a timing rests on is the host's),
    the executor starting at k = 15 with no operator, at FIFO where the host grants it, with
    ``executor_env`` added. At the end each gets SIGCONT (one a test left stopped takes its signal) and
    SIGTERM; one still running 30 s later is aborted, its threads' stacks written to its log, and the test
    fails; at a failure, the tail of each log is printed beside it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    data = tmp_path / "data"
    data.mkdir()
    shutil.copy(sets, data / "pareto.sqlite")
    env = {**os.environ, "CADENCE_BUS_CONNECT": f"['{endpoint}']", "CADENCE_DATA_DIR": str(data),
           "CADENCE_CADENCE_CELL": CELL}  # fmt: skip
    executor = {
        **env,
        "CADENCE_EXECUTOR_START_SELECTION": "initial",
        "CADENCE_EXECUTOR_INITIAL_K": "15",
        "CADENCE_EXECUTOR_WAIT_FOR_SIGNALS": "false",
        "CADENCE_EXECUTOR_FIFO_PRIORITY": "80" if os.geteuid() == 0 else "0",  # as its unit grants
        # the host's core locks (no lock dir of its own): an executor of another test, or of a suite
        # beside this one, holds its core, and this one's FIFO thread takes another (loaded run 3, issue 53)
        **executor_env,
    }
    procs: list[subprocess.Popen[bytes]] = []
    failed, hung = False, []
    try:
        async with await Bus.open(BusConfig(mode="router", listen=[endpoint]), CELL) as bus:
            for name, e in zip(SERVICES, (env, executor), strict=True):
                log = (tmp_path / f"{name}.log").open("wb")
                run = [sys.executable, "-X", "faulthandler", "-m", f"services.{name}"]  # stacks at SIGABRT
                unit = BY_NAME[name].start_as_unit  # the unit's priority (the executor's Nice=)
                procs.append(
                    subprocess.Popen(run, env=e, stdout=log, stderr=subprocess.STDOUT, preexec_fn=unit)
                )
            yield Processes(bus, endpoint, tuple(procs))
    except BaseException:
        failed = True
        raise
    finally:
        alive = [p.poll() is None for p in procs]  # before the stop: had a service died?
        for p in procs:
            p.send_signal(signal.SIGCONT)
            p.terminate()
        for name, p in zip(SERVICES, procs, strict=False):
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:  # its threads' stacks to its log (faulthandler), then gone
                hung.append(name)
                p.send_signal(signal.SIGABRT)
                p.wait(30)
        if failed or hung:  # what the services said, beside the failure
            print(f"still running at the failure (store, executor): {alive}")
            for name in SERVICES:
                said = (tmp_path / f"{name}.log").read_text()[-8000:]
                print(f"--- {name}.log (the last 8000 characters)\n{said}")
    assert not hung, f"{hung} did not exit within 30 s of SIGTERM (the stacks above)"
