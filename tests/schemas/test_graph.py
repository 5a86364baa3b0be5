"""The bus's graph (schemas/topology.py) is the one source: every service opens exactly the ports the
graph gives its role, a port it does not give is refused at start, a message of another type than its key's
is refused at the put, and what is derived from the graph (launch order, decoder) follows it."""

from __future__ import annotations

import ast
import asyncio
import shutil
from pathlib import Path

import msgspec
import numpy as np
import pytest

from cadence.tools.zenoh_codec import decode
from common.runtime.bus import Bus, BusConfig
from common.runtime.config import CONFIG_SECTIONS
from common.runtime.errors import BusError
from schemas import HrvWindow, Selection
from schemas.topology import (
    HEALTH,
    HRV_WINDOW,
    OPERATOR_SIGNAL,
    ROBOT_STATE,
    ROLE,
    ROLES,
    SELECTION,
    SERVICES,
    TOPICS,
    encode,
    launch_order,
)
from services.decision_maker.__main__ import Settings as DecisionSettings
from services.decision_maker.__main__ import main as decision_main
from services.ecg_gateway.__main__ import Settings as GatewaySettings
from services.ecg_gateway.__main__ import main as gateway_main
from services.executor.__main__ import Settings as ExecutorSettings
from services.executor.__main__ import main as executor_main
from services.hrv_analyser.__main__ import Settings as AnalyserSettings
from services.hrv_analyser.__main__ import main as analyser_main
from services.operator_twin.__main__ import Settings as TwinSettings
from services.operator_twin.__main__ import main as twin_main
from services.pareto_store.__main__ import Settings as StoreSettings
from services.pareto_store.__main__ import main as store_main
from tests.support.cell import CELL, InProcessService, put
from tests.support.paths import EXAMPLE_TASK, REPO

Port = tuple[str, str, str]


def synthetic_ecg(folder: Path) -> Path:
    """A small recording to replay (time s, µV): a beat every 0.8 s."""
    csv = folder / "ecg.csv"
    t = np.arange(0, 60, 1 / 130)
    np.savetxt(csv, np.c_[t, 1000 * np.exp(-(((t % 0.8) - 0.4) ** 2) / 2e-4)], delimiter=",")
    return csv  # (kind, role, the topic's key expression under the cell)


def graph_ports(role: str) -> set[Port]:
    """What the graph gives a role: publish (and answer), subscribe, ask."""
    out: set[Port] = set()
    for t in TOPICS:
        out |= {("publish", role, t.suffix)} if role in t.publishers else set()
        out |= {("subscribe", role, t.suffix)} if role in t.subscribers else set()
        out |= {("ask", role, t.suffix)} if role in t.askers else set()
    return out


def test_the_graph_names_only_roles_it_declares_and_every_key_has_a_publisher() -> None:
    for t in TOPICS:
        assert t.publishers, t.suffix
        for r in (*t.publishers, *t.subscribers, *t.askers):
            assert r in ROLE, f"{t.suffix}: unknown role {r}"
        assert t.pattern == "topic" or not t.subscribers, f"{t.suffix}: a query has askers, not subscribers"
    for r in ROLES:  # the per-topic view is the roles' declarations, read the other way
        for ports, view in (("outputs", "publishers"), ("answers", "publishers"), ("inputs", "subscribers"),
                            ("asks", "askers")):  # fmt: skip
            assert all(r.name in getattr(t, view) for t in getattr(r, ports)), (r.name, ports)
    assert {(r, t.suffix) for t in TOPICS for r in t.subscribers} == {
        (r.name, t.suffix) for r in ROLES for t in r.inputs
    }
    assert len({t.suffix for t in TOPICS}) == len(TOPICS)
    assert set(SERVICES) <= CONFIG_SECTIONS  # a service's settings table is a known section


def test_the_registry_has_one_node_for_each_service_of_the_graph_and_every_list_derives_from_it() -> None:
    from cadence.cli import SERVICES as RUNNABLE
    from cadence.cli import build_parser
    from services.registry import IN_GRAPH
    from services.registry import SERVICES as REGISTRY

    assert sorted(s.name for s in IN_GRAPH) == sorted(SERVICES)  # one node a role, and nothing more
    for s in IN_GRAPH:
        node = s.node_class()
        assert node.role == s.name
        assert s.settings() is s.module().Settings
        assert s.name in CONFIG_SECTIONS
    assert set(RUNNABLE) == {s.name for s in REGISTRY}
    run = next(
        a for a in build_parser()._subparsers._group_actions[0].choices["run"]._actions if a.dest == "service"
    )
    assert set(run.choices) == {s.name for s in REGISTRY}


def test_the_launch_order_starts_answerers_before_askers_and_readers_before_writers() -> None:
    order = launch_order()
    assert sorted(order) == sorted(SERVICES)
    at = {name: i for i, name in enumerate(order)}
    for t in TOPICS:
        for p in t.publishers:
            for a in t.askers:
                if ROLE[a].kind == "service" and ROLE[p].kind == "service" and a != p:  # a store asks others
                    assert at[p] < at[a], f"{a} asks {t.suffix} of {p}"
    # the data flow, from its end back to its source (Zenoh drops a put nobody subscribes to yet), but the
    # decision maker asks the analyser for windows it missed, so it comes after it (and what it missed
    # meanwhile it asks for); the executor and the twin read each other: the first declared goes first
    assert at["hrv_analyser"] < at["decision_maker"] < at["ecg_gateway"]
    assert at["hrv_analyser"] < at["executor"] < at["operator_twin"]


@pytest.mark.asyncio
async def test_a_role_opens_only_the_ports_the_graph_gives_it(endpoint: str) -> None:
    async with await Bus.open(BusConfig(listen=[endpoint]), CELL, role="hrv_analyser") as bus:
        out = bus.publisher(HRV_WINDOW)
        assert out.key == f"cadence/{CELL}/hrv/window"
        with pytest.raises(BusError, match="does not let hrv_analyser publish decision/selection"):
            bus.publisher(SELECTION)
        with pytest.raises(BusError, match="subscribe robot/state"):
            bus.subscribe(ROBOT_STATE)
        with pytest.raises(BusError, match=r"through Bus\.publisher"):
            put(bus, bus.key("hrv/window"), Selection(t_ns=1, seq=0, k=1, n=1, delta=0, reason="initial"))
        with pytest.raises(BusError, match="not a key of the graph"):
            bus.subscribe(f"cadence/{CELL}/elsewhere", HrvWindow)
        with pytest.raises(TypeError, match="hrv/window carries HrvWindow, not Selection"):
            out.put(Selection(t_ns=1, seq=0, k=1, n=1, delta=0, reason="initial"))  # type: ignore[arg-type]  # the mistake under test
        with pytest.raises(ValueError, match="needs one key"):
            bus.publisher(HEALTH)
        assert [(k, r, t.suffix) for k, r, t in bus.ports] == [("publish", "hrv_analyser", "hrv/window")]
    async with await Bus.open(BusConfig(listen=[endpoint]), CELL, role="operator_twin") as twin:
        twin.publisher(OPERATOR_SIGNAL)  # the twin is a node of its own
        with pytest.raises(BusError, match="does not let operator_twin publish hrv/window"):
            twin.publisher(HRV_WINDOW)
    with pytest.raises(BusError, match="unknown role"):
        await Bus.open(BusConfig(listen=[endpoint]), CELL, role="hrv-analyser")


@pytest.mark.asyncio
async def test_every_service_opens_exactly_the_ports_of_its_roles(
    tmp_path: Path, endpoint: str, example_sets: Path
) -> None:
    """Each service is started as it runs (its real ``main``) and watched until it has opened every
    port the graph gives it; one it does not get would have stopped it at start with a BusError."""
    (tmp_path / "store").mkdir()
    shutil.copy(example_sets, tmp_path / "store" / "pareto.sqlite")
    task = str(EXAMPLE_TASK)
    runs = [
        ("pareto_store", store_main, StoreSettings(task=task)),
        ("decision_maker", decision_main, DecisionSettings(rr_rest_s=0.8)),
        ("hrv_analyser", analyser_main, AnalyserSettings()),
        ("hrv_analyser", analyser_main, AnalyserSettings(input="rr")),  # ecg/rr is read only then
        ("ecg_gateway", gateway_main, GatewaySettings(record=str(synthetic_ecg(tmp_path)))),
        ("operator_twin", twin_main, TwinSettings()),
        # with separation monitoring: without it the executor leaves operator/separation unread
        (
            "executor",
            executor_main,
            ExecutorSettings(
                task=task,
                backend="sim",
                start_selection="wait",
                separation=True,
                separation_sources=["scanner:front"],
            ),
        ),
    ]
    async with await Bus.open(BusConfig(listen=[endpoint]), CELL):
        services = [
            InProcessService(
                name, main, settings, tmp_path / ("store" if name == "pareto_store" else f"d{i}"), endpoint
            )
            for i, (name, main, settings) in enumerate(runs)
        ]
        expected = {name: graph_ports(name) for name in SERVICES}

        def opened(name: str) -> set[Port]:
            return {
                (k, r, t.suffix)
                for s, (n, _, _) in zip(services, runs, strict=True)
                if n == name and s.ctx is not None
                for k, r, t in s.ctx.bus.ports
            }

        try:
            async with asyncio.timeout(90):
                while any(opened(n) != expected[n] for n in SERVICES):
                    for s in services:
                        if s.task.done():
                            s.task.result()  # a service the graph refused: its BusError, here
                    assert all(opened(n) <= expected[n] for n in SERVICES)
                    await asyncio.sleep(0.05)  # polls what the services opened; bounded by the timeout
        except TimeoutError:
            missing = {n: expected[n] - opened(n) for n in SERVICES if expected[n] - opened(n)}
            raise AssertionError(f"ports the graph gives and no service opened: {missing}") from None
        finally:
            await asyncio.gather(*(s.close() for s in services), return_exceptions=True)
    for t in TOPICS:  # by construction: what a subscriber decodes is what the publisher's port takes
        assert all(
            port[2].message is t.message
            for s in services
            if s.ctx
            for port in s.ctx.bus.ports
            if port[2].suffix == t.suffix
        )


def test_the_zenoh_cli_decoder_decodes_each_key_as_the_graph_types_it() -> None:
    w = HrvWindow(
        t_ns=2, seq=0, start_ns=0, end_ns=2, mean_rr_s=0.8, n_beats=3, excluded_fraction=0.0, quality="good"
    )
    assert msgspec.json.decode(decode(f"cadence/{CELL}/hrv/window", encode(w)))["mean_rr_s"] == 0.8
    wrong = msgspec.json.decode(decode(f"cadence/{CELL}/decision/selection", encode(w)))
    assert "error" in wrong
    assert wrong["key"] == f"cadence/{CELL}/decision/selection"
    assert msgspec.json.decode(decode("other/key", encode(w)))["quality"] == "good"  # by its tag alone


def test_a_services_name_is_spelled_in_the_graph_and_the_registry_only() -> None:
    """Everything else takes it from them (``registry.EXECUTOR.name``, ``registry.cell``,
    ``topology.cell_roster``): a renamed or added service is one entry, not a hunt through the CLI."""
    from services.registry import SERVICES

    names = {s.name for s in SERVICES}
    root = REPO
    spelled = []
    for folder in ("cadence", "common", "schemas", "services"):
        for f in sorted((root / folder).rglob("*.py")):
            if f.relative_to(root).as_posix() in ("schemas/topology.py", "services/registry.py"):
                continue
            for node in ast.walk(ast.parse(f.read_text())):
                if isinstance(node, ast.Constant) and node.value in names:
                    spelled.append(f"{f.relative_to(root)}:{node.lineno} {node.value}")
    assert spelled == []
