"""The Pareto store, started in-process on the in-memory bus and as a process on its own."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from common.runtime.bus import Bus, BusConfig
from common.trajectory.task import load_task
from schemas import ParetoSet, ParetoSolutionReply, ServiceStatus
from schemas.topology import TOPICS, AnyMessage
from services.pareto_store.__main__ import ParetoStore, Settings, main
from services.pareto_store.jobs import plan_job
from services.pareto_store.store import SetStore
from tests.support.cell import CELL, Cell, InProcessService
from tests.support.tasks import TINY as TASK

pytestmark = pytest.mark.asyncio


def start_store(task: Path, data: Path, cell: Cell) -> InProcessService:
    return cell.service("pareto_store", main, Settings(task=str(task)), data)


async def serving(sub) -> ServiceStatus:
    """The store's periodic status once it has planned everything it lacked (no race: it repeats)."""
    async with asyncio.timeout(60):
        async for _, status in sub:
            if status.state == "serving":
                return status
    raise AssertionError("unreachable")


async def test_the_store_plans_answers_restarts_from_sqlite_and_never_serves_stale_sets(
    task_file: Path, tmp_path: Path, cell: Cell
) -> None:
    async with cell.session() as client:
        health = client.key("health/pareto_store")
        store = start_store(task_file, tmp_path / "data", cell)
        status = await serving(aiter(client.subscribe(health, ServiceStatus, maxsize=1)))
        assert status.counters.get("computed") == 2

        set_a = (await client.get(client.key("pareto/a"), ParetoSet))[0].message
        assert set_a.path_id == "a"
        assert len(set_a.solutions) == 5
        assert set_a.constraints == "exact"
        one = (await client.get(client.key("pareto/a/5"), ParetoSolutionReply))[0].message
        assert one.solution == set_a.solutions[4]
        assert one.n == 5
        unknown = (await client.get(client.key("pareto/zzz"), AnyMessage))[0]
        assert unknown.message is None
        assert "unknown path 'zzz'" in unknown.error
        bad_k = (await client.get(client.key("pareto/a/6"), AnyMessage))[0]
        assert "k = 1 … 5" in bad_k.error

        # random bytes on every key of the topology while the store runs: counted, and it still answers
        keys = [client.key(t.suffix.replace("*", "a")) for t in TOPICS]
        for k, t in zip(keys, TOPICS, strict=True):
            client.subscribe(k, t.message)
        async with asyncio.timeout(10):
            while not all(client.decode_errors[k] for k in keys):
                for k in keys:
                    client.put_raw(k, os.urandom(41))
                await asyncio.sleep(0.02)
        assert (await client.get(client.key("pareto/a"), ParetoSet))[0].message == set_a
        await store.close()

        # restart: the same sets, from SQLite, nothing recomputed
        store = start_store(task_file, tmp_path / "data", cell)
        status = await serving(aiter(client.subscribe(health, ServiceStatus, maxsize=1)))
        assert status.counters.get("computed", 0) == 0
        again = (await client.get(client.key("pareto/a"), ParetoSet))[0].message
        assert again.solutions == set_a.solutions
        assert again.content_hash == set_a.content_hash
        await store.close()

        # a changed task program: path a is planned again, b is still valid
        task_file.write_text(TASK.replace("[30, -80, 100, -100, -90, 20]", "[25, -80, 100, -100, -90, 20]"))
        store = start_store(task_file, tmp_path / "data", cell)
        status = await serving(aiter(client.subscribe(health, ServiceStatus, maxsize=1)))
        assert status.counters.get("computed") == 1
        new_a = (await client.get(client.key("pareto/a"), ParetoSet))[0].message
        assert new_a.content_hash != set_a.content_hash
        assert new_a.waypoints[1][0] == pytest.approx(25 * 3.141592653589793 / 180)
        await store.close()


def run_store(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "services.pareto_store", *args], capture_output=True, text=True, timeout=60
    )


async def test_a_malformed_config_stops_the_store_at_start_naming_file_and_field(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("[pareto_store]\nworkers = 'many'\n")
    proc = run_store("--config", str(cfg))
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0
    assert str(cfg) in proc.stderr
    assert "workers" in proc.stderr


async def test_a_bad_task_file_stops_the_store_at_start(tmp_path: Path) -> None:
    task = tmp_path / "t.toml"
    task.write_text(TASK.replace('unit = "deg"', 'unit = "grad"', 1))
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[pareto_store]\ntask = '{task}'\n")
    proc = run_store("--config", str(cfg))
    assert proc.returncode == 2
    assert str(task) in proc.stderr
    assert "path 'a'" in proc.stderr
    assert "unit" in proc.stderr


async def test_sigterm_stops_the_store_process_with_exit_0(
    task_file: Path, tmp_path: Path, endpoint: str
) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f"[cadence]\ndata_dir = '{tmp_path / 'd'}'\nstatus_period_s = 0.1\n"
        f"[bus]\nconnect = ['{endpoint}']\n[pareto_store]\ntask = '{task_file}'\n"
    )
    client = await Bus.open(BusConfig(listen=[endpoint]), CELL)
    async with client:
        sub = aiter(client.subscribe(client.key("health/pareto_store"), ServiceStatus, maxsize=1))
        proc = subprocess.Popen([sys.executable, "-m", "services.pareto_store", "--config", str(cfg)])
        try:
            # as a process, its workers plan both paths (they import the job from its own module)
            status = await serving(sub)
            assert status.counters.get("computed") == 2
            proc.send_signal(signal.SIGTERM)
            assert await asyncio.to_thread(proc.wait, 20) == 0
        finally:
            proc.kill()


async def test_an_edited_path_is_seeded_by_its_last_set_and_a_new_count_of_waypoints_is_not(
    task_file: Path, tmp_path: Path
) -> None:
    task = load_task(task_file)
    store = SetStore(tmp_path / "pareto.sqlite")
    digests, _ = store.current(task)
    for pid in ("a", "b"):
        store.save(plan_job(task.paths[pid], task, task.planner, digests[pid]))
    edited = tmp_path / "edited.toml"
    edited.write_text(
        TASK.replace("[30, -80, 100, -100, -90, 20]", "[25, -80, 100, -100, -90, 20]").replace(
            "waypoints = [[45, -70, 95, -110, -90, 40], [0",
            "waypoints = [[45, -70, 95, -110, -90, 40], [9, 9, 9, 9, 9, 9], [0",
        )
    )
    task2 = load_task(edited)
    digests2, stored = store.current(task2)
    assert stored == {}  # both changed
    node = ParetoStore.__new__(ParetoStore)
    node.store, node.task, node.digests = store, task2, digests2
    warm = node.warm_starts(["a", "b"])
    assert list(warm) == ["a"]  # b has a waypoint more: no interval maps onto another
    assert warm["a"] == [s.h for s in store.load("a", digests["a"]).solutions]
    seeded = plan_job(task2.paths["a"], task2, task2.planner, digests2["a"], warm["a"])
    assert seeded.content_hash == digests2["a"]
    assert len(seeded.solutions) == 5
    store.close()
