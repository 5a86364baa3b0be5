"""Planned sets shipped as data (common/trajectory/shipped.py, issue 53): the example task's file is the
task's as it is now, every trajectory in it may run, `cadence plan --ship` writes one that reads back, an
edited or broken file is refused or passed over, and the store serves shipped sets without planning."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest

from common.runtime.errors import InputError
from common.runtime.resources import EXAMPLE_TASK, SHIPPED_SETS
from common.trajectory.planner import content_hash
from common.trajectory.shipped import read_shipped, sets_digest, shipped
from common.trajectory.task import load_task
from common.trajectory.validate import trajectory_problems
from schemas import ParetoSet, ServiceStatus
from services.pareto_store.__main__ import Settings, main
from services.pareto_store.store import SetStore
from tests.support.cell import Cell

EXAMPLE_SETS = SHIPPED_SETS / "box_filling.json"
AGAIN = "plan it again: uv run cadence plan deploy/tasks/box_filling.toml --out /tmp/sets --ship " + str(
    EXAMPLE_SETS.relative_to(SHIPPED_SETS.parent.parent)
)


def test_the_example_tasks_shipped_sets_are_its_paths_as_they_are_now_and_may_all_run() -> None:
    """A change to the task program, its limits, its planner settings or PLANNER_VERSION changes a path's
    content hash: the shipped set would silently stop being served, and the story with it."""
    task = load_task(EXAMPLE_TASK)
    doc = read_shipped(EXAMPLE_SETS)
    assert doc.task == task.name
    by_path = {s.path_id: s for s in doc.sets}
    assert set(by_path) == set(task.paths)
    for pid, path in task.paths.items():
        s = by_path[pid]
        assert s.content_hash == content_hash(path, task.limits, task.planner), f"'{pid}' is stale: {AGAIN}"
        assert shipped(pid, s.content_hash) == s
        assert [x.k for x in s.solutions] == list(range(1, task.planner.n_solutions + 1))
        t_f = [x.t_f for x in s.solutions]
        assert t_f == sorted(t_f, reverse=True)  # k = 1 the slowest, k = N the fastest
        for x in s.solutions:
            assert trajectory_problems(np.array(x.h), path, task.limits) == [], (pid, x.k)


def test_plan_ship_writes_a_file_that_reads_back_and_an_edit_or_a_break_is_refused(tmp_path: Path) -> None:
    task = tmp_path / "tiny.toml"
    task.write_text(EXAMPLE_TASK.read_text().replace("population = 90", "population = 30\ngenerations = 4"))
    file = tmp_path / "sets" / "tiny.json"
    r = subprocess.run([sys.executable, "-m", "cadence", "plan", str(task), "--out", str(tmp_path / "out"),
                        "--no-plots", "--ship", str(file)],
                       capture_output=True, text=True, timeout=300)  # fmt: skip
    assert r.returncode == 0, r.stderr
    doc = read_shipped(file)
    assert f"shipped sets {doc.sets_sha256[:12]}" in " ".join(r.stdout.split())
    planned = {p.stem: json.loads(p.read_text()) for p in (tmp_path / "out").glob("*.json")}
    hs = {pid: [s["h"] for s in d["solutions"]] for pid, d in planned.items()}
    assert sets_digest(hs) == doc.sets_sha256
    assert all(s.t_ns == 0 for s in doc.sets)
    pid = doc.sets[0].path_id
    assert shipped(pid, doc.sets[0].content_hash, folder=file.parent) == doc.sets[0]

    text = file.read_text()
    h = doc.sets[0].solutions[0].h[0]
    file.write_text(text.replace(repr(h), repr(h + 1e-9), 1))  # a hand's edit: the digest no longer fits
    with pytest.raises(InputError, match="not those it names"):
        read_shipped(file)
    file.write_text(text[: len(text) // 2])  # cut: neither served nor fatal, the store plans
    with pytest.raises(InputError, match="not a file of shipped sets"):
        read_shipped(file)
    assert shipped(pid, doc.sets[0].content_hash, folder=tmp_path / "none") is None


async def serving(sub: AsyncIterator[tuple[str, ServiceStatus]]) -> ServiceStatus:
    async with asyncio.timeout(120):
        async for _, status in sub:
            if status.state == "serving":
                return status
    raise AssertionError("the store's status stream ended")


@pytest.mark.asyncio
async def test_the_store_serves_the_shipped_sets_without_planning_and_plans_a_path_edited_since(
    tmp_path: Path, cell: Cell
) -> None:
    task = load_task(EXAMPLE_TASK)
    doc = {s.path_id: s for s in read_shipped(EXAMPLE_SETS).sets}
    edited = tmp_path / "edited.toml"  # an intermediate waypoint of b1_to_b2 moved by a degree
    edited.write_text(EXAMPLE_TASK.read_text().replace("[-35.0, -104.0, 98.0,", "[-34.0, -104.0, 98.0,"))

    async with cell.session() as client:

        async def served(task_file: Path, data: str = "data", shipped: bool = True) -> ServiceStatus:
            sub = aiter(client.subscribe(client.key("health/pareto_store"), ServiceStatus, maxsize=1))
            settings = Settings(task=str(task_file), shipped_sets=shipped)
            svc = cell.service("pareto_store", main, settings, tmp_path / data)
            try:
                return await serving(sub)
            finally:
                await svc.close()

        async def ask(pid: str) -> ParetoSet:
            return (await client.get(client.key(f"pareto/{pid}"), ParetoSet))[0].message

        sub = aiter(client.subscribe(client.key("health/pareto_store"), ServiceStatus, maxsize=1))
        svc = cell.service("pareto_store", main, Settings(task=str(EXAMPLE_TASK)), tmp_path / "data")
        status = await serving(sub)
        assert status.counters.get("computed", 0) == 0  # nothing planned: every path shipped
        assert {pid: await ask(pid) for pid in task.paths} == doc
        await svc.close()
        store = SetStore(tmp_path / "data" / "pareto.sqlite")
        assert store.current(task)[1] == doc  # kept in SQLite too: an edit starts warm from them
        store.close()

        status = await served(edited)
        assert status.counters.get("computed") == 1  # the edited path alone is planned
        status = await served(EXAMPLE_TASK, "own", shipped=False)  # `shipped_sets = false`: all planned here
        assert status.counters.get("computed") == len(task.paths)
