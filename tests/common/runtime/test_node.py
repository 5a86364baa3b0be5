"""A node's logic without Zenoh (common/runtime/node.py, common/runtime/memory.py): the decision maker's
handlers called as methods, the node served on the in-memory bus with the real bus's typing, graph checks
and decoding, and a node class held to its role's declaration in the graph."""

from __future__ import annotations

import asyncio
from pathlib import Path

import msgspec
import pytest

from common.decision import Params, State, step
from common.hrv.live import Taken
from common.runtime.bus import Bus, QueryError
from common.runtime.config import CommonSettings
from common.runtime.errors import BusError
from common.runtime.memory import MemoryNetwork, run_node, serving
from common.runtime.node import Node, Rejected, check, every, node_main, on
from common.runtime.service import ServiceContext, serve
from schemas import Calibration, HrvWindow, Selection
from schemas.topology import CALIBRATION, HRV_WINDOW, ROBOT_STATE, SELECTION, decode_any
from services.decision_maker.__main__ import DecisionMaker, Settings
from services.hrv_analyser.__main__ import HrvAnalyser
from services.hrv_analyser.__main__ import Settings as AnalyserSettings
from tests.support.cell import CELL, now_ns, put
from tests.support.data import ECG, needs_data

S = 1_000_000_000


def window(base: int, i: int, rr: float | None, quality: str = "good") -> HrvWindow:
    return HrvWindow(t_ns=base + (i + 1) * 30 * S, seq=i, start_ns=base + i * 30 * S,
                     end_ns=base + (i + 1) * 30 * S, mean_rr_s=rr, n_beats=37, excluded_fraction=0.0,
                     quality=quality)  # fmt: skip


async def decision_maker(tmp_path: Path, settings: Settings) -> DecisionMaker:
    bus = MemoryNetwork().bus(role="decision_maker")
    ctx = ServiceContext(
        "decision_maker", bus, CommonSettings(data_dir=str(tmp_path)), settings, asyncio.Event()
    )
    node = DecisionMaker(ctx)
    await node.setup()
    return node


@pytest.mark.asyncio
async def test_the_decision_makers_handlers_are_alg_1_called_as_methods(tmp_path: Path) -> None:
    node = await decision_maker(tmp_path, Settings(rr_rest_s=0.85))
    (first,) = await node.current()
    assert isinstance(first, Selection)
    assert (first.k, first.reason) == (8, "initial")
    base, p = now_ns() - 8 * 30 * S, Params.of(0.85)  # windows that have ended
    state = State.initial(p)
    for i, rr in enumerate([0.80, 0.78, 0.70, 0.69, 0.90, 0.95]):
        (sel,) = await node.on_window(window(base, i, rr))
        state = step(p, state, rr, True).state
        assert isinstance(sel, Selection)
        assert sel.k == state.k
        assert sel.window_end_ns == base + (i + 1) * 30 * S
    with pytest.raises(Rejected) as r:  # answered already: a replay is dropped and counted, not stepped
        await node.on_window(window(base, 2, 0.5))
    assert r.value.code == "duplicate"
    assert node.ctx.counters["windows"] == 7
    # a session fixes k: windows are counted and not answered; the reply is the selection it starts with
    answer = await node.set_condition(_request("mode=fixed;k=b;by=test"))
    assert isinstance(answer.reply, Selection)
    assert (answer.reply.k, answer.reply.reason) == (1, "fixed")
    assert list(answer.publish) == [answer.reply]
    assert await node.on_window(window(base, 6, 0.5)) == []
    with pytest.raises(QueryError, match="mode='sometimes'"):
        await node.set_condition(_request("mode=sometimes"))


@pytest.mark.asyncio
async def test_without_calibration_the_node_publishes_nothing_and_a_calibration_starts_it(
    tmp_path: Path,
) -> None:
    node = await decision_maker(tmp_path, Settings())
    assert await node.current() == []
    assert node.ctx.state == "waiting for calibration"
    assert await node.on_window(window(now_ns() - 30 * S, 0, 0.8)) == []
    assert node.ctx.counters["windows_without_calibration"] == 1
    with pytest.raises(QueryError, match="no calibration yet"):
        await node.query(_request(""))
    (sel,) = await node.on_calibration(Calibration(t_ns=5, seq=0, subject="s1", rr_rest_s=0.9))
    assert isinstance(sel, Selection)
    assert sel.reason == "initial"
    assert node.ctx.state == "running"
    assert await node.on_calibration(Calibration(t_ns=6, seq=1, subject="s1", rr_rest_s=0.9)) == []  # in use


@pytest.mark.asyncio
async def test_the_node_served_on_the_bus_in_memory_answers_windows_queries_and_drops_bad_input(
    tmp_path: Path,
) -> None:
    network = MemoryNetwork()
    stop = asyncio.Event()
    service = network.bus(role="decision_maker")
    common = CommonSettings(data_dir=str(tmp_path), status_period_s=0.1)
    settings = Settings(rr_rest_s=0.85, republish_s=60.0)
    task = asyncio.ensure_future(
        serve("decision_maker", node_main(DecisionMaker), common, None, settings, stop,  # type: ignore[arg-type]
              install_signals=False, bus=service)
    )  # fmt: skip
    async with network.bus() as test:
        sub = test.subscribe(test.key("decision/selection"), Selection)
        await test.until_subscribed(test.key("hrv/window"), timeout=10)
        assert (await sub.receive(10))[1].reason == "initial"
        base = now_ns() - 60 * S  # a window that has ended
        put(test, test.key("hrv/window"), window(base, 0, 0.80))
        assert (await sub.receive(10))[1].window_end_ns == base + 30 * S
        test.put_raw(test.key("hrv/window"), b"\x93not a window")  # bounds and types: the real decoder
        put(test, test.key("hrv/window"), window(base, 0, 0.80))  # a duplicate: the real admission
        (reply,) = await test.get(test.key("decision/selection"), Selection, 5.0)
        assert reply.error is None
        assert reply.message is not None
        assert reply.message.window_end_ns == base + 30 * S
        (reply,) = await test.get(test.key("decision/condition") + "?mode=never", Selection, 5.0)
        assert reply.error is not None
        assert "mode='never'" in reply.error
        async with asyncio.timeout(10):
            while service.rejected[(test.key("hrv/window"), "duplicate")] != 1:
                await asyncio.sleep(0)  # handled by the node's own task on this loop
        assert service.decode_errors[test.key("hrv/window")] == 1
    stop.set()
    await task
    # the ports it opened are exactly its role's in the graph
    assert {(k, t.suffix) for k, _, t in service.ports} == {
        ("publish", "decision/selection"),
        ("publish", "decision/condition"),
        ("subscribe", "hrv/window"),
        ("subscribe", "operator/calibration"),
        ("subscribe", "robot/state"),  # the seq of the selection in force, to number after it
        ("publish", "health/*"),
        ("ask", "hrv/window"),  # the windows it missed, from the analyser (at start and after a gap)
    }


@pytest.mark.asyncio
async def test_the_bus_in_memory_refuses_what_the_graph_refuses() -> None:
    async with MemoryNetwork().bus(role="hrv_analyser") as bus:
        with pytest.raises(BusError, match="does not let hrv_analyser publish decision/selection"):
            bus.publisher(SELECTION)
        with pytest.raises(BusError, match="subscribe robot/state"):
            bus.subscribe(ROBOT_STATE)
        out = bus.publisher(HRV_WINDOW)
        with pytest.raises(TypeError, match="hrv/window carries HrvWindow, not Selection"):
            out.put(Selection(t_ns=1, seq=0, k=1, n=1, delta=0, reason="initial"))  # type: ignore[arg-type]  # the mistake under test
    assert type(bus) is Bus  # the product's own, on another transport


@needs_data
@pytest.mark.asyncio
async def test_the_analysers_handlers_window_a_record_and_drop_a_chunk_out_of_line(tmp_path: Path) -> None:
    """Record 100 at 130 Hz in the H10's chunks of 73 samples, on the analyser node's handler: its windows
    are the offline pipeline's, in ns from the first chunk; a chunk an hour ahead is dropped, not windowed."""
    from common.hrv.records import read_record
    from common.hrv.rpeaks import detect_peaks
    from common.hrv.stream import peak_intervals, windows
    from schemas.ecg import EcgChunk

    bus = MemoryNetwork().bus(role="hrv_analyser")
    ctx = ServiceContext("hrv_analyser", bus, CommonSettings(data_dir=str(tmp_path)), AnalyserSettings(),
                         asyncio.Event())  # fmt: skip
    node = HrvAnalyser(ctx)
    await node.setup()
    x = read_record(str(ECG / "100"), fs=130.0).uv[: 130 * 95]
    t0, out = now_ns() - 100 * S, []  # 95 s that have happened
    for i in range(0, len(x), 73):
        chunk = EcgChunk(
            t_ns=t0 + round(i * 1e9 / 130), seq=i, fs_hz=130.0, samples_uv=x[i : i + 73].tolist()
        )
        out += await node.on_chunk(chunk)
        if i == 73 * 300:
            with pytest.raises(Rejected) as r:
                await node.on_chunk(msgspec.structs.replace(chunk, t_ns=chunk.t_ns + 3600 * S))
            assert r.value.code == "ahead"
    got = [m for m in out if isinstance(m, HrvWindow)]
    want = windows(peak_intervals(detect_peaks(x, 130.0), 130.0), 30.0)[: len(got)]
    assert len(got) == 3
    assert [m.seq for m in got] == [0, 1, 2]
    for m, w in zip(got, want, strict=True):
        assert m.start_ns == t0 + round(w.start_s * 1e9)
        assert m.mean_rr_s == w.mean_rr_s
        assert m.quality == w.quality
    assert ctx.counters["windows"] == 3
    assert ctx.counters["beats"] > 100


@pytest.mark.asyncio
async def test_a_replay_waits_for_its_reader_sends_every_chunk_and_then_stops_its_service(
    tmp_path: Path,
) -> None:
    """The gateway as a node on the bus in memory: nothing before a reader of ecg/samples is there (a
    recording is worth nothing to nobody), then every 73-sample chunk in order, then the service ends by
    itself."""
    import numpy as np

    from schemas.ecg import EcgChunk
    from services.ecg_gateway.__main__ import EcgGateway
    from services.ecg_gateway.__main__ import Settings as GatewaySettings

    csv = tmp_path / "ecg.csv"
    t = np.arange(0, 20, 1 / 130)
    np.savetxt(csv, np.c_[t, 1000 * np.exp(-(((t % 0.8) - 0.4) ** 2) / 2e-4)], delimiter=",")
    network, stop = MemoryNetwork(history=1000), asyncio.Event()
    service = network.bus(role="ecg_gateway")
    common = CommonSettings(data_dir=str(tmp_path), status_period_s=0.1)
    task = asyncio.ensure_future(
        serve("ecg_gateway", node_main(EcgGateway), common, None, GatewaySettings(record=str(csv), speed=0.0),  # type: ignore[arg-type]
              stop, install_signals=False, bus=service)
    )  # fmt: skip
    async with network.bus() as test:
        # its first status: it runs, and has sent no ECG
        await network.until(lambda: any(k.endswith("/health/ecg_gateway") for k, _ in network.sent), 10)
        assert not any(k.endswith("/ecg/samples") for k, _ in network.sent)
        sub = test.subscribe(test.key("ecg/samples"), EcgChunk, maxsize=10_000)
        got = [(await sub.receive(10))[1] for _ in range(-(-len(t) // 73))]
        async with asyncio.timeout(10):
            await task  # the replay ended: so did the service
    assert [c.seq for c in got] == list(range(len(got)))
    assert sum(len(c.samples_uv) for c in got) == len(t)
    assert [c.t_ns - got[0].t_ns for c in got] == [round(i * 73 * 1e9 / 130) for i in range(len(got))]


def test_a_node_is_held_to_its_roles_declaration() -> None:
    class Foreign(Node):  # the analyser does not read the calibration in the graph
        role = "hrv_analyser"

        @on(CALIBRATION)
        async def on_calibration(self, cal: Calibration) -> list[msgspec.Struct]:
            return []

    with pytest.raises(BusError, match="does not let hrv_analyser read operator/calibration"):
        check(Foreign)

    class Deaf(Node):  # the decision maker must read its windows
        role = "decision_maker"

    with pytest.raises(BusError, match=r"no handler for .*hrv/window"):
        check(Deaf)
    check(DecisionMaker)


def _request(parameters: str):
    from common.runtime.bus import Request

    return Request(f"cadence/{CELL}/decision/condition", parameters)


@pytest.mark.asyncio
async def test_the_executors_one_safety_state_latches_a_stop_and_only_a_resume_clears_it(
    tmp_path: Path,
) -> None:
    """The executor's handlers as methods, no bus: every change of its one state is an event with its from
    and to, a resume with nothing stopped is refused with the state, a stop ignores a new selection, and
    robot/state carries the same state once the arm is connected."""
    from common.runtime.bus import Request
    from common.safety.states import Event
    from schemas import OperatorSignal, RobotEvent, RobotState
    from services.executor.__main__ import Executor
    from services.executor.settings import Settings as ExecutorSettings

    settings = ExecutorSettings(lock_dir=str(tmp_path / "locks"), fifo_priority=0, lock_memory=False)
    bus = MemoryNetwork().bus(role="executor")
    ctx = ServiceContext("executor", bus, CommonSettings(data_dir=str(tmp_path)),
                         settings, asyncio.Event())  # fmt: skip
    node = Executor(ctx)
    await node.setup()
    try:
        assert await node.state() == []  # nothing said about an arm not yet connected
        with pytest.raises(QueryError, match="nothing to resume: the robot is starting"):
            await node.resume(Request(f"cadence/{CELL}/robot/resume", "by=test"))
        assert await node.safety.connect()
        node.connected = True
        assert node.safety.motion.state == "waiting_for_selection"
        node.on_selection(Selection(t_ns=now_ns(), seq=0, k=3, n=15, delta=0, reason="initial"))
        node.safety.fire(Event.FAULT, "a bump")
        node.on_selection(Selection(t_ns=now_ns(), seq=1, k=4, n=15, delta=1, reason="window"))
        assert (node.safety.motion.state, node.safety.motion.reason) == ("stopped", "a bump")
        (*_, state) = await node.state()
        assert isinstance(state, RobotState)
        assert (state.state, state.mode, state.reason) == (
            "stopped", "fault", "a bump",
        )  # fmt: skip
        reply = await node.resume(Request(f"cadence/{CELL}/robot/resume", "by=test"))
        assert reply.message == "ready: resumed by test"
        changes = [(e.from_state, e.to_state) for e in node.published if isinstance(e, RobotEvent)
                   and e.kind == "state" and e.from_state is not None]  # fmt: skip
        assert changes == [
            ("starting", "waiting_for_selection"),
            ("waiting_for_selection", "ready"),
            ("ready", "stopped"),
            ("stopped", "recovering"),
            ("recovering", "ready"),
        ]
        with pytest.raises(Rejected) as r:  # no step of the example task waits for it
            await node.on_signal(OperatorSignal(t_ns=now_ns(), seq=0, name="coffee", source="test"))
        assert r.value.code == "unknown_signal"
    finally:
        await node.close()


@needs_data
@pytest.mark.asyncio
@pytest.mark.parametrize("with_acc", [True, False], ids=["with its accelerometer", "ECG only"])
async def test_the_gateway_replays_the_polar_export_with_its_accelerometer_or_says_it_has_none(
    tmp_path: Path, with_acc: bool
) -> None:
    from schemas import AccChunk, EcgChunk, ServiceStatus
    from services.ecg_gateway.__main__ import EcgGateway
    from services.ecg_gateway.__main__ import Settings as GatewaySettings

    polar = ECG / "polar_h10"
    settings = GatewaySettings(
        record=str(polar / "Polar_H10_55354125_20210516_080846_ECG.txt"),
        acc_record=str(polar / "Polar_H10_55354125_20210516_080900_ACC.txt") if with_acc else None,
        speed=50.0,  # 3 s: its status comes while it runs
    )
    network, stop = MemoryNetwork(history=1000), asyncio.Event()
    service = network.bus(role="ecg_gateway")
    common = CommonSettings(data_dir=str(tmp_path), status_period_s=0.1)
    task = asyncio.ensure_future(
        serve("ecg_gateway", node_main(EcgGateway), common, None, settings, stop,  # type: ignore[arg-type]
              install_signals=False, bus=service)
    )  # fmt: skip
    async with network.bus() as test:
        acc = test.subscribe(test.key("ecg/acc"), AccChunk, maxsize=10_000)
        ecg = test.subscribe(test.key("ecg/samples"), EcgChunk, maxsize=10_000)
        status = test.subscribe(test.key("health/ecg_gateway"), ServiceStatus, maxsize=10_000)
        first = (await ecg.receive(10))[1]
        said = (await status.receive(10))[1]
        while said.counters.get("chunks", 0) < 50:  # its status once the replay is under way
            said = (await status.receive(10))[1]
        if with_acc:
            got = [(await acc.receive(10))[1] for _ in range(100)]  # 100 s, one chunk a second
            assert (got[0].t_ns - first.t_ns) / 1e9 == pytest.approx(11.03, abs=0.01)
            assert [len(c.x_mg) for c in got] == [25] * 100
            assert got[0].x_mg[:2] == [-993, -993]
            assert "accelerometer" not in said.detail
        else:
            assert said.detail.startswith("no accelerometer: windows are read without movement")
        async with asyncio.timeout(30):
            await task  # the replay ended


@pytest.mark.asyncio
async def test_a_strap_whose_accelerometer_stops_mid_session_is_said_on_the_gateways_status(
    tmp_path: Path,
) -> None:
    from types import SimpleNamespace

    from services.ecg_gateway.__main__ import EcgGateway
    from services.ecg_gateway.__main__ import Settings as GatewaySettings

    bus = MemoryNetwork().bus(role="ecg_gateway")
    ctx = ServiceContext("ecg_gateway", bus, CommonSettings(data_dir=str(tmp_path)),
                         GatewaySettings(source="polar"), asyncio.Event())  # fmt: skip
    node = EcgGateway(ctx)
    node.source, node.acc_until_ns = SimpleNamespace(accelerometer=True), 100 * S  # type: ignore[assignment]
    node.say_accelerometer(102 * S)  # the last accelerometer frame 2 s before this ECG: on time
    assert ctx.detail == ""
    node.say_accelerometer(112 * S)
    assert ctx.detail.startswith("no accelerometer for 12 s: windows are read without movement")
    node.acc_until_ns = 111 * S  # it came back
    node.say_accelerometer(112 * S)
    assert ctx.detail == ""


@pytest.mark.asyncio
async def test_a_part_put_down_is_said_again_while_the_robot_waits_and_counted_once(tmp_path: Path) -> None:
    """A signal sent while the executor was stopped for 2 s was lost, and the cell waited 1,100 s for a
    part already there (issue 40). Signals are state: the twin says a placed part again every second
    while the robot waits for it, and the executor counts a copy once."""
    from common.sim.twin import TwinParams
    from schemas import RobotState
    from services.executor.cycles import Signals
    from services.operator_twin.__main__ import OperatorTwin
    from services.operator_twin.__main__ import Settings as TwinSettings

    common = CommonSettings(data_dir=str(tmp_path))
    bus = MemoryNetwork().bus(role="operator_twin")
    ctx = ServiceContext("operator_twin", bus, common, TwinSettings(TwinParams(seed=3)), asyncio.Event())
    twin = OperatorTwin(ctx)
    await twin.setup()
    twin.origin_ns -= 30 * S  # its states have happened: nothing from its future is taken
    t0 = twin.origin_ns
    twin.line.anchor(t0 - S)  # the robot's stream, as it was 30 s ago

    def state(t_s: float, waiting: str | None) -> RobotState:
        return RobotState(t_ns=t0 + round(t_s * S), seq=0, q=[0.0] * 6, qd=[0.0] * 6, tcp=[0.0] * 6,
                          path_id=None, k=8, mode="waiting", waiting_for=waiting,
                          state="waiting_for_operator")  # fmt: skip

    assert await twin.on_state(state(0.0, "part_a2")) == []  # it goes to fetch the part
    when = twin.pending[0][0]
    twin.placed["part_a2"] = (when, when)  # put down (the stream says it then, once)
    twin.pending.clear()
    again = [
        m
        for t in (when + 0.5, when + 1.2, when + 1.9, when + 2.3)
        for m in await twin.on_state(state(t, "part_a2"))
    ]
    assert [(m.name, m.t_ns) for m in again] == [("part_a2", t0 + round(when * S))] * 2  # once a second
    assert await twin.on_state(state(when + 5.0, None)) == []  # taken: not said again
    assert await twin.on_state(state(when + 9.0, None)) == []

    signals, stop = Signals({"part_a2"}), asyncio.Event()
    waiting = asyncio.create_task(signals.wait("part_a2", stop))
    await asyncio.sleep(0)  # the robot waits now
    for m in again * 3:
        signals.receive(m)
    assert await waiting == "arrived"
    assert signals.received["part_a2"] == 1


@pytest.mark.asyncio
async def test_a_twin_away_until_calibrated_fetches_no_part_until_a_calibration_at_rest(
    tmp_path: Path,
) -> None:
    """The demo cell's at-rest calibration (issue 56): the robot waits for a part the twin, away, does not
    fetch; a calibration at work does not bring it; one at rest does, and it fetches the part the robot
    waits for from then."""
    from common.sim.twin import TwinParams
    from schemas import RobotState
    from schemas.operator import Calibration
    from services.operator_twin.__main__ import OperatorTwin
    from services.operator_twin.__main__ import Settings as TwinSettings

    settings = TwinSettings(TwinParams(seed=3, away_until_calibrated=True))
    common = CommonSettings(data_dir=str(tmp_path))
    bus = MemoryNetwork().bus(role="operator_twin")
    ctx = ServiceContext("operator_twin", bus, common, settings, asyncio.Event())
    twin = OperatorTwin(ctx)
    await twin.setup()
    twin.origin_ns -= 60 * S
    t0 = twin.origin_ns
    twin.line.anchor(t0 - S)
    waiting = RobotState(t_ns=t0 + 5 * S, seq=0, q=[0.0] * 6, qd=[0.0] * 6, tcp=[0.0] * 6, path_id=None, k=8,
                         mode="waiting", waiting_for="part_a2", state="waiting_for_operator")  # fmt: skip
    assert await twin.on_state(waiting) == []
    assert twin.pending == [] and twin.operator.away
    at_work = Calibration(t_ns=t0 + 20 * S, seq=0, subject="twin-1", rr_rest_s=0.76, posture="working")
    assert await twin.on_calibration(at_work) == []
    assert twin.pending == [] and twin.operator.away
    at_rest = Calibration(t_ns=t0 + 30 * S, seq=0, subject="twin-1", rr_rest_s=0.85)
    assert await twin.on_calibration(at_rest) == []
    assert twin.operator.arrived_s == pytest.approx(30.0)
    assert [part for _, part in twin.pending] == ["part_a2"]
    assert twin.pending[0][0] > 30.0  # put down after its handling time, from the arrival


@pytest.mark.asyncio
async def test_the_analyser_answers_for_its_last_windows_one_at_a_time(tmp_path: Path) -> None:
    from common.runtime.bus import Request
    from services.hrv_analyser.__main__ import KEPT_WINDOWS

    bus = MemoryNetwork().bus(role="hrv_analyser")
    ctx = ServiceContext("hrv_analyser", bus, CommonSettings(data_dir=str(tmp_path)),
                         AnalyserSettings(), asyncio.Event())  # fmt: skip
    node = HrvAnalyser(ctx)
    await node.setup()
    base = now_ns() - 100 * 30 * S
    for i in range(KEPT_WINDOWS + 10):  # what it made; it keeps the last KEPT_WINDOWS
        node.sent(Taken(None, [window(base, i, 0.8)]))

    def ask(after: int | str) -> Request:
        return Request(f"cadence/{CELL}/hrv/window", f"after={after}")

    first_kept = base + 11 * 30 * S
    assert (await node.window_after(ask(0))).end_ns == first_kept
    assert (await node.window_after(ask(first_kept))).end_ns == first_kept + 30 * S
    with pytest.raises(QueryError, match="no window after it"):
        await node.window_after(ask(base + (KEPT_WINDOWS + 10) * 30 * S))
    with pytest.raises(QueryError, match="expected after=<end_ns>"):
        await node.window_after(ask("soon"))


@pytest.mark.asyncio
async def test_run_node_feeds_the_inputs_in_order_and_gives_back_what_the_node_published(
    tmp_path: Path,
) -> None:
    base, rrs = now_ns() - 8 * 30 * S, [0.80, 0.78, 0.70, 0.69, 0.90, 0.95]
    inputs = [(HRV_WINDOW, window(base, i, rr)) for i, rr in enumerate(rrs)]
    out = await run_node(DecisionMaker, Settings(rr_rest_s=0.85, republish_s=600), inputs, tmp_path)
    answers = [m for m in out if isinstance(m, Selection) and m.reason != "initial"]
    p = Params.of(0.85)
    state, want = State.initial(p), []
    for rr in rrs:
        state = step(p, state, rr, True).state
        want.append(state.k)
    assert [a.k for a in answers] == want  # each window handled before the next was sent
    assert [a.window_end_ns for a in answers] == [w.end_ns for _, w in inputs]


@pytest.mark.asyncio
async def test_the_output_port_numbers_what_a_node_sends_and_a_selection_keeps_its_own(
    tmp_path: Path,
) -> None:
    from schemas.ecg import EcgChunk
    from schemas.topology import ECG_SAMPLES

    class Counting(Node):  # builds every chunk with seq 0: numbering is the port's
        role = "ecg_gateway"

        async def stream(self):  # type: ignore[override]
            for i in range(3):
                yield [EcgChunk(t_ns=now_ns() + i, seq=0, fs_hz=130.0, samples_uv=[0] * 73, source="test")]

    async with serving(Counting, None, tmp_path) as run:
        await run.network.until(lambda: len(run.published(ECG_SAMPLES)) == 3, 10)
        assert [c.seq for c in run.published(ECG_SAMPLES)] == [0, 1, 2]

    async with serving(DecisionMaker, Settings(rr_rest_s=0.85, republish_s=0.01), tmp_path) as run:
        await run.network.until(lambda: len(run.published(SELECTION)) >= 3, 10)
        seqs = {s.seq for s in run.published(SELECTION)}
        assert len(seqs) == 1  # republished as it was: a selection's seq is its identity, not a count


def test_a_timer_is_declared_in_the_graph_beside_the_ports() -> None:
    class Ticking(Node):  # the gateway has no timer in the graph
        role = "ecg_gateway"

        @every
        async def tick(self) -> list[msgspec.Struct]:
            return []

    with pytest.raises(BusError, match="does not let ecg_gateway time tick"):
        check(Ticking)

    class Idle(Node):  # the decision maker republishes its selection on a timer the graph declares
        role = "decision_maker"

        @on(HRV_WINDOW)
        async def on_window(self, w: HrvWindow) -> list[msgspec.Struct]:
            return []

        @on(CALIBRATION)
        async def on_calibration(self, c: Calibration) -> list[msgspec.Struct]:
            return []

    with pytest.raises(BusError, match=r"no handler for .*current"):
        check(Idle)


@pytest.mark.asyncio
async def test_each_part_has_its_own_word_in_the_status_and_none_overwrites_anothers(tmp_path: Path) -> None:
    """The executor's parts say what holds them in the status's detail: the disk's refusal, the sets it
    waits for, the damaged files it moved aside. Once they shared one field, and the sets' wait wiped the
    disk's refusal from the status while the arm was still held for it."""
    bus = MemoryNetwork().bus(role="executor")
    ctx = ServiceContext("executor", bus, CommonSettings(data_dir=str(tmp_path)), None, asyncio.Event())
    disk, sets = ctx.note("disk"), ctx.note("sets")
    disk("cannot write executor.json: No space left on device")
    sets("waiting for Pareto sets: b1_to_b2")
    ctx.detail = "a service's own word"
    assert ctx.status(0).detail == (
        "a service's own word; cannot write executor.json: No space left on device; "
        "waiting for Pareto sets: b1_to_b2"
    )
    sets("")  # the sets came: the disk's refusal stands
    assert ctx.status(1).detail == "a service's own word; cannot write executor.json: No space left on device"
    await bus.close()


@pytest.mark.asyncio
async def test_work_started_beside_a_nodes_own_is_in_its_task_group_ends_with_it_and_fails_it(
    tmp_path: Path,
) -> None:
    """``Node.start_soon``: a helper runs in the node's task group, is cancelled when the service stops,
    and its failure is the service's (no task left running, none failing unseen); before the node runs
    and after it ended there is no group, and the work is dropped (closed, never a warning)."""
    began, ended = asyncio.Event(), asyncio.Event()

    async def helper(fail: bool = False) -> None:
        began.set()
        try:
            if fail:
                raise ValueError("the helper's own")
            await asyncio.Event().wait()
        finally:
            ended.set()

    class Helped(DecisionMaker):
        fail = False

        async def work(self) -> None:
            assert self.start_soon(helper(self.fail), "helper") is not None
            await super().work()

    settings = Settings(rr_rest_s=0.85, republish_s=600)
    async with serving(Helped, settings, tmp_path) as run:
        await asyncio.wait_for(began.wait(), 10)
        assert not ended.is_set()
        node = run.node
    assert ended.is_set()  # cancelled with the group
    late = helper()
    assert node.start_soon(late, "too late") is None
    assert late.cr_frame is None  # closed
    early = helper()
    assert Helped(node.ctx).start_soon(early, "too early") is None
    assert early.cr_frame is None

    Helped.fail = True
    began.clear()
    with pytest.raises(ValueError, match="the helper's own"):
        async with serving(Helped, settings, tmp_path / "failing"):
            await asyncio.wait_for(began.wait(), 10)


@pytest.mark.asyncio
async def test_the_in_memory_network_keeps_no_history_unless_a_test_asks_and_then_a_bounded_one() -> None:
    """The lockstep demo runs on this network for hours: it once kept every message it carried (126 MB
    per data hour of a 6-hour demo). By default nothing is kept; a test that reads what was put asks for
    the latest N."""
    for history, kept in ((0, 0), (10, 10)):
        network = MemoryNetwork(history=history)
        async with network.bus(role="decision_maker") as bus:
            out = bus.publisher(SELECTION)
            for i in range(1000):
                out.put(Selection(t_ns=i + 1, seq=i + 1, k=8, n=15, delta=0, reason="hold"))
            await network.settle()
        assert len(network.sent) == len(network.senders) == kept
        if kept:
            assert [decode_any(p).seq for _, p in network.sent] == list(range(991, 1001))  # the latest
