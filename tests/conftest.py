"""Fixtures and the scheduling of test files; the helpers the tests share are in tests/support."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from common.runtime.lockstep import LockstepLoop
from common.runtime.memory import MemoryNetwork
from tests.support.cell import Cell, free_port, now_ns
from tests.support.decisions import _base_now  # noqa: F401 (autouse: each test's windows end near its now)
from tests.support.paths import (
    EXAMPLE_TASK,
    planned_once,
)

# Each test file goes to one of the xdist workers, whole (``--dist loadfile``, pyproject); the files
# that run a demo cell at 16x (the demo, the lab, the wheel's demo) share one worker, one at a time: two
# such cells on a 2-core machine, with other work running, starved each other's simulated operator. (The
# systemd cells run at real time, beside them.)
CELL_FILES = frozenset({"test_demo.py", "test_lab.py", "test_packaging.py", "test_walk_in.py"})
# then the files that take a minute or more, longest first (a full run's --durations=0): xdist's own
# order, by the number of tests in a file (pyproject: --no-loadscope-reorder turns it off), left these
# one- and two-test files to the end, and the run waited 80 s on its last worker
SLOW_FILES = ("test_systemd.py", "test_lockstep_stories.py", "test_other_machines.py", "test_ur_emulator.py",
              "test_study.py", "test_executor_safety.py")  # fmt: skip
BENCH_TIMEOUT_S = 3600  # s: the pyproject's 1,200 s is for a test


def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    if config.getvalue("dist") != "loadfile":
        return None  # another distribution asked for on the command line: xdist's own
    from xdist.scheduler import LoadFileScheduling

    class CellsTogether(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            file = super()._split_scope(nodeid)
            return "cells" if Path(file).name in CELL_FILES else file

    return CellsTogether(config, log)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The cell files first: the worker that takes them is busy with them alone for minutes, while the
    others work through the rest, the slow files first. A benchmark may take longer than a test's
    ``timeout`` (pyproject): the whole HRV cross-validation takes minutes on its own, so a benchmark's
    limit is an hour."""
    order = {name: i for i, name in enumerate(SLOW_FILES, start=1)} | dict.fromkeys(CELL_FILES, 0)
    items.sort(key=lambda item: order.get(item.path.name, len(order)))
    for item in items:
        if item.get_closest_marker("bench") is not None and item.get_closest_marker("timeout") is None:
            item.add_marker(pytest.mark.timeout(BENCH_TIMEOUT_S))


def pytest_asyncio_loop_factories(config: pytest.Config, item: pytest.Item) -> dict[str, object]:
    """A test marked ``lockstep`` runs on a lockstep loop: its cell's clock is driven, so what it checks
    cannot depend on how fast the host is (a servo loop's deadlines, a sender's rate, a switch planned in
    time); every other test on asyncio's own loop."""
    if item.get_closest_marker("lockstep") is not None:
        return {"lockstep": LockstepLoop}
    return {"asyncio": asyncio.new_event_loop}


@pytest.fixture
def example_task_path() -> Path:
    return EXAMPLE_TASK


@pytest.fixture(scope="session")
def example_sets(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The example task's sets, planned once per test run into a store's SQLite file: tests that need
    them served copy it into their store's data folder (a store serves stored sets without planning)."""
    return planned_once(EXAMPLE_TASK, tmp_path_factory)


@pytest.fixture
def endpoint() -> str:
    """A loopback endpoint for one test's sessions (multicast scouting stays off)."""
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def cell(request: pytest.FixtureRequest) -> Cell:
    """A cell on the in-memory bus: a node's logic with its real ports, decoding and graph checks. In a
    test marked ``lockstep`` its services read the lockstep loop's data time, from now to the second, and
    the test stamps its own messages with ``Cell.now_ns``."""
    if request.node.get_closest_marker("lockstep") is not None:
        return Cell(network=MemoryNetwork(), epoch_ns=now_ns())
    return Cell(network=MemoryNetwork())


@pytest.fixture
def zenoh_cell(endpoint: str) -> Cell:
    """A cell on real Zenoh (loopback, scouting off): the bus itself and the cell end to end."""
    return Cell(endpoint=endpoint)
