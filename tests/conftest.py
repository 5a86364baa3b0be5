"""Shared fixtures. Paths the project has never seen come from ``random_path`` with a printed seed."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from common.trajectory.bspline import Boundary
from common.trajectory.task import PathPlan

REPO = Path(__file__).resolve().parents[1]
EXAMPLE_TASK = REPO / "deploy" / "tasks" / "box_filling.toml"
SHARED_DATA = REPO.parent / "shared" / "data"
# the benchmarks (marker ``bench``, not in a plain ``uv run pytest``) in the shorter form .ci/run runs
BENCH_QUICK = os.environ.get("CADENCE_BENCH") == "quick"


# Each test file goes to one of the two xdist workers, whole (``--dist loadfile``, pyproject); the files
# that run a demo cell at 16x (the demo, the lab, the wheel's demo) share one worker, one at a time: two
# such cells on a 2-core machine, with other work running, starved each other's simulated operator. (The
# systemd cells run at real time, beside them.)
CELL_FILES = frozenset({"test_demo.py", "test_lab.py", "test_packaging.py"})


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
    other works through the rest."""
    items.sort(key=lambda item: item.path.name not in CELL_FILES)


def random_path(seed: int, n_waypoints: int = 6, boundary: bool = False) -> PathPlan:
    """A UR16e-like path: waypoints within ±π, consecutive steps of up to ~70° per joint."""
    rng = np.random.default_rng(seed)
    wp = [rng.uniform(-1.5, 1.5, 6)]
    for _ in range(n_waypoints - 1):
        wp.append(np.clip(wp[-1] + rng.uniform(-1.2, 1.2, 6), -np.pi, np.pi))
    wp = np.array(wp)
    if boundary:
        small = lambda s: rng.uniform(-s, s, 6)  # noqa: E731
        b = Boundary(small(0.2), small(0.5), small(2.0), small(0.2), small(0.5), small(2.0))
    else:
        b = Boundary.at_rest(6)
    print(f"random_path(seed={seed}, W={n_waypoints}, boundary={boundary})")
    return PathPlan(f"random{seed}", wp, b)


@pytest.fixture
def example_task_path() -> Path:
    return EXAMPLE_TASK


def plan_sets(task_file: Path, db: Path) -> Path:
    """Every path of ``task_file`` planned, in this process, into a store's SQLite file ``db``."""
    from common.trajectory.planner import content_hash
    from common.trajectory.task import load_task
    from services.pareto_store.jobs import plan_job
    from services.pareto_store.store import SetStore

    task = load_task(task_file)
    store, _ = SetStore.open(db)
    for path in task.paths.values():
        store.save(plan_job(path, task, task.planner, content_hash(path, task.limits, task.planner)))
    store.close()
    return db


_PLANNED: dict[str, Path] = {}  # a task program's text → its sets, planned once per test run


def planned_once(task_file: Path, tmp_path_factory: pytest.TempPathFactory | None = None) -> Path:
    """A store's SQLite file with ``task_file``'s sets, planned the first time a test asks for them.
    A store that plans in each test puts its low-priority worker behind any CPU load on the machine:
    under CI's load a store took over 60 s to serve a one-path task."""
    text = task_file.read_text()
    if text not in _PLANNED:
        folder = (
            tmp_path_factory.mktemp("sets") if tmp_path_factory else Path(tempfile.mkdtemp(prefix="sets-"))
        )
        if tmp_path_factory is None:
            atexit.register(shutil.rmtree, folder, True)
        _PLANNED[text] = plan_sets(task_file, folder / "pareto.sqlite")
    return _PLANNED[text]


@pytest.fixture(scope="session")
def example_sets(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The example task's sets, planned once per test run into a store's SQLite file: tests that need
    them served copy it into their store's data folder (a store serves stored sets without planning)."""
    return planned_once(EXAMPLE_TASK, tmp_path_factory)


def now_ns() -> int:
    """Data time for a test's messages: now, to the second. Receivers believe a stream's first message
    when it is near their data clock (common/runtime/admission.py), as a live source's is."""
    import time

    return time.time_ns() // 1_000_000_000 * 1_000_000_000


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def endpoint() -> str:
    """A loopback endpoint for one test's sessions (multicast scouting stays off)."""
    return f"tcp/127.0.0.1:{free_port()}"


class InProcessService:
    """A service running in this test's event loop exactly as `cadence run <name>` runs it (its real
    ``main``, real Zenoh, data on disk), connecting to the test's listening endpoint; dora's MockNode."""

    def __init__(
        self,
        name: str,
        main,
        settings: object,
        data: Path,
        endpoint: str,
        speed: float = 1.0,
        cell: str = "cell1",
        epoch_ns: int | None = None,
    ) -> None:
        import asyncio

        from common.runtime.bus import BusConfig
        from common.runtime.config import CommonSettings
        from common.runtime.service import serve

        self.stop = asyncio.Event()
        self.cell = cell
        self.ctx = None  # the service's context once it runs (its bus, its counters)

        async def wrapped(ctx) -> None:
            self.ctx = ctx
            await main(ctx)

        # a faster clock needs an epoch, or its data time would be the wall's while its sleeps are shorter;
        # services of one cell share it (``epoch_ns``), as a demo's do
        epoch = epoch_ns if epoch_ns is not None else time.time_ns() if speed != 1.0 else None
        common = CommonSettings(
            cell=cell, data_dir=str(data), status_period_s=0.1, speed=speed, epoch_ns=epoch
        )
        self.task = asyncio.ensure_future(
            serve(
                name,
                wrapped,
                common,
                BusConfig(connect=[endpoint]),
                settings,
                stop=self.stop,
                install_signals=False,
            )
        )

    async def listening(self, bus, *suffixes: str, timeout: float = 30.0) -> None:
        """Wait until this service's subscriptions to ``cadence/<its cell>/<suffix>`` are known to the test's
        session, so what the test publishes next reaches them: Zenoh drops a put that has no known
        subscriber, and a service's first status can come before its subscriptions. The right way to
        wait before publishing; never wait on a status for that. (Matching counts every subscriber,
        the test's own too: call it before the test subscribes to the same keys.)"""
        import asyncio

        async with asyncio.timeout(timeout):
            for suffix in suffixes:
                while True:
                    if self.task.done():
                        self.task.result()  # the service died: say why
                        raise AssertionError(f"the service ended before subscribing to {suffix}")
                    try:
                        await bus.until_subscribed(f"cadence/{self.cell}/{suffix}", 0.5)
                        break
                    except TimeoutError:
                        continue

    async def reaches(self, *suffixes: str, timeout: float = 30.0) -> None:
        """Wait until this service's own session knows a subscriber of each key, so what it publishes
        next arrives (a service that feeds another: the analyser's windows, the decision maker)."""
        import asyncio

        async with asyncio.timeout(timeout):
            while self.ctx is None:
                if self.task.done():
                    self.task.result()
                await asyncio.sleep(0.01)  # polls a flag the service's first step sets; bounded above
            for suffix in suffixes:
                await self.ctx.bus.until_subscribed(self.ctx.bus.key(suffix), timeout)

    async def close(self) -> None:
        import asyncio

        self.stop.set()
        await asyncio.wait_for(self.task, 15)


def put(bus, key: str, msg, block: bool = False) -> None:
    """A message on any key from a session that speaks for nobody (a test's): the typed ports are the
    services' only way to publish, so a test's raw put lives here, not on the Bus."""
    from schemas.topology import encode

    bus.put_raw(key, encode(msg), block)
