"""Sets by hash across the cells of a plant (issue 58): a store asks ``cadence/plant/sets/<hash>`` before
it plans a path and answers for every set it has; a set that comes back is served only once every
trajectory in it passes the executor's own check on this cell's path and limits. Across real routers:
only a cell's store may ask and answer there, and the question and its answer cross a line and the plant."""

from __future__ import annotations

import asyncio
from pathlib import Path

import msgspec
import numpy as np
import pytest

from common.runtime.bus import Bus, BusConfig
from common.trajectory.shipped import shipped_or_planned
from common.trajectory.task import load_task
from common.trajectory.validate import set_problems
from schemas import ParetoSet, ServiceStatus
from schemas.topology import PLANT_SETS, key_for
from tests.services.pareto_store.test_pareto_store import serving, start_store
from tests.support.cell import Cell
from tests.support.paths import EXAMPLE_TASK


async def status_of(cell: Cell, task: Path, data: Path) -> tuple[ServiceStatus, ParetoSet]:
    """A store's status once it serves, and its set of path a."""
    async with cell.session() as client:
        sub = client.subscribe(client.key("health/pareto_store"), ServiceStatus, maxsize=1)
        s = start_store(task, data, cell)
        try:
            status = await serving(aiter(sub))
            (reply,) = await client.get(client.key("pareto/a"), ParetoSet)
            assert reply.message is not None, reply.error
            return status, reply.message
        finally:
            await s.close()


def faster(s: ParetoSet, by: float) -> ParetoSet:
    """The set with every trajectory ``by`` times as fast: the same path, over the arm's limits."""
    sols = [msgspec.structs.replace(x, h=[h / by for h in x.h], t_f=x.t_f / by) for x in s.solutions]
    return msgspec.structs.replace(s, solutions=sols)


@pytest.mark.asyncio
async def test_a_cell_takes_a_set_another_cell_planned_and_refuses_one_that_fails_the_check(
    task_file: Path, tmp_path: Path, cell: Cell
) -> None:
    """Cell one plans; cell two, on the same plant with the same task program, takes both sets by their
    hash and plans nothing. A third cell asked by someone answering a set whose trajectories break the
    limits (a compromised or broken peer) refuses it and plans its own."""
    one = Cell(name="one", network=cell.network)
    two = Cell(name="two", network=cell.network)
    three = Cell(name="three", network=cell.network)
    planned, set_a = await status_of(one, task_file, tmp_path / "one")
    assert planned.counters.get("computed") == 2
    async with one.session() as watch:  # cell one's store runs again (from its SQLite), answering the plant
        sub = watch.subscribe(watch.key("health/pareto_store"), ServiceStatus, maxsize=1)
        s1 = start_store(task_file, tmp_path / "one", one)
        try:
            await serving(aiter(sub))
            taken, got = await status_of(two, task_file, tmp_path / "two")
        finally:
            await s1.close()
    assert taken.counters.get("computed", 0) == 0
    assert taken.counters.get("plant_sets_taken") == 2
    assert got.solutions == set_a.solutions and got.content_hash == set_a.content_hash

    # someone answers every hash with cell one's set, its trajectories twice as fast: over the limits
    fast = faster(set_a, 2.0)
    async with three.session() as liar:

        async def answer(req: object) -> ParetoSet:
            return fast

        liar.serve(key_for(PLANT_SETS, "three"), answer)
        refused, own = await status_of(three, task_file, tmp_path / "three")
    assert refused.counters.get("plant_sets_refused") == 2  # a's over the limits, b's of other inputs
    assert refused.counters.get("computed") == 2  # both planned here instead
    assert own.solutions != fast.solutions


def test_the_check_refuses_another_hash_other_waypoints_and_fast_trajectories(
    task_file: Path,
) -> None:
    from common.trajectory.planner import content_hash
    from services.pareto_store.jobs import plan_job

    task = load_task(str(task_file))
    path = task.paths["b"]
    digest = content_hash(path, task.limits, task.planner)
    good = plan_job(path, task, task.planner, digest)
    assert set_problems(good, path, task.limits, digest) == []
    assert "other inputs" in set_problems(good, path, task.limits, "0" * 64)[0]
    moved = msgspec.structs.replace(good, waypoints=(np.asarray(good.waypoints) + 0.01).tolist())
    assert any("waypoint" in p for p in set_problems(moved, path, task.limits, digest))
    fast = faster(good, 3.0)
    assert any("over its limit" in p for p in set_problems(fast, path, task.limits, digest))


@pytest.mark.asyncio
async def test_only_a_cells_store_asks_and_answers_a_set_across_a_line_and_the_plant(tmp_path: Path) -> None:
    """Two cells on two lines behind the plant's router, over mTLS with each cell's generated rules: cell
    two's store asks for a set by its hash and gets cell one's answer, four routers away. Cell two's
    executor asking the same gets nothing (only stores ask), nor does the plant's monitor; and an
    executor that declares an answerer there answers no one (only stores answer)."""
    from cadence.bench.plant import layout

    lay = layout(tmp_path, 2, per_line=1)
    (c1, c2) = lay.cells
    cfg = lambda path: BusConfig(config_file=str(path))  # noqa: E731
    routers = [*lay.cell_routers, *lay.line_routers, lay.plant_router]
    task = load_task(str(EXAMPLE_TASK))
    the_set = shipped_or_planned(next(iter(task.paths.values())), task)
    selector = f"cadence/plant/sets/{the_set.content_hash}"
    opened = [await Bus.open(cfg(r.config), r.name) for r in routers]
    try:
        async with (
            await Bus.open(cfg(c1.accounts["pareto_store"]), c1.name) as store1,
            await Bus.open(cfg(c2.accounts["pareto_store"]), c2.name) as store2,
            await Bus.open(cfg(c2.accounts["executor"]), c2.name) as exec2,
            await Bus.open(cfg(c1.accounts["executor"]), c1.name) as exec1,
            await Bus.open(cfg(lay.monitor), "plant") as monitor,
        ):

            async def give(req: object) -> ParetoSet:
                return the_set

            store1.serve("cadence/plant/sets/*", give)
            got: list = []
            async with asyncio.timeout(60):  # until the answerer's declaration has crossed four routers
                while not got:
                    got = [r for r in await store2.get(selector, ParetoSet, timeout=1.0) if r.message]
            assert got[0].message == the_set
            for asker in (exec2, monitor):
                assert not [r for r in await asker.get(selector, ParetoSet, timeout=1.0) if r.message]
            await store1.close()

            async def lie(req: object) -> ParetoSet:
                return msgspec.structs.replace(the_set, path_id="from_an_executor")

            exec1.serve("cadence/plant/sets/*", lie)
            # then a store of cell one answers again, declared after the executor's answerer: once its
            # answer crosses, the executor's would have too, had its router let it in
            async with await Bus.open(cfg(c1.accounts["pareto_store"]), c1.name) as again:
                again.serve("cadence/plant/sets/*", give)
                got = []
                async with asyncio.timeout(60):
                    while not got:
                        got = [r for r in await store2.get(selector, ParetoSet, timeout=1.0) if r.message]
                assert [r.message.path_id for r in got] == [the_set.path_id]
    finally:
        for bus in reversed(opened):
            await bus.close()
