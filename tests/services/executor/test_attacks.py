"""Issue 52's attacks on a cell, each at the executor's (or the bus's) own code: a flood on one source, a
replayed selection, a stack of operator signals, a payload nested to break the decoder. Each is refused,
counted, and never frees the arm or lets it through a wait."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import msgspec
import pytest

from common.runtime.bus import Bus
from common.runtime.memory import MemoryNetwork, serving
from common.runtime.node import Rejected
from common.safety.separation import Nearest, Sources
from schemas import OperatorSignal, Selection, Separation
from schemas.topology import (
    OPERATOR_SEPARATION,
    OPERATOR_SEPARATION_OF,
    OPERATOR_SIGNAL,
    encode,
    source_chunk,
)
from services.executor.__main__ import Executor
from services.executor.cycles import Signals
from tests.support.cell import now_ns
from tests.support.executor import TASK, sim_settings, tracked

pytestmark = pytest.mark.asyncio
S = 1_000_000_000


@pytest.fixture
def task_file(tmp_path: Path) -> Path:
    f = tmp_path / "shuttle.toml"
    f.write_text(TASK)
    return f


@pytest.mark.filterwarnings("ignore")
def test_a_source_over_its_rate_holds_the_arm_and_never_displaces_another() -> None:
    """A second source floods 100 m at 34,000 a second beside an honest 0.6 m at 20 Hz: the nearest is the
    honest reading or a hold, never the flood's; once the flood stops, a second later, the honest one."""
    table = Sources(0.3, 0.05, ("scanner:front",), max_rate_hz=1000)
    seen = set()
    for i in range(34_000):  # one second
        now = i / 34_000
        if i % 1700 == 0:
            assert table.receive("scanner:front", 0.6, 0.0, 0.0, now) == ""
        table.receive("scanner:back", 100.0, 0.0, 0.0, now)
        if i % 100 == 0:
            seen.add(table.nearest(now).distance_m)
    assert seen <= {0.6, None}
    assert None in seen  # the flood held the arm
    assert table.nearest(1.0).why.startswith("'scanner:back' sends over 1000 readings a second")
    table.receive("scanner:front", 0.6, 0.0, 0.0, 2.01)
    assert table.nearest(2.01).distance_m == 0.6  # a second after the flood: the honest reading


@pytest.mark.filterwarnings("ignore")
def test_a_flood_that_arrives_stale_is_still_a_flood_and_holds_the_arm() -> None:
    """Rate before age: a flood that saturates the receiver reaches it old (316k readings a second were
    0.3 s old on arrival, counted stale, and the arm ran on the honest far reading). Every reading counts
    toward its source's rate, whatever its age or stamp, and past the rate the arm holds."""
    table = Sources(0.3, 0.05, ("scanner:front",), max_rate_hz=1000)
    table.receive("scanner:front", 5.0, 0.0, 0.0, 0.0)
    ages = [0.5, -3600.0] * 2500  # one second of readings, stale and an hour ahead
    whys = {table.receive("scanner:back", 100.0, age, 0.0, i / 5000) for i, age in enumerate(ages)}
    assert whys == {"stale", "ahead", "flood"}
    table.receive("scanner:front", 5.0, 0.0, 0.0, 0.5)
    assert table.nearest(0.5).distance_m is None
    assert table.nearest(0.5).why.startswith("'scanner:back' sends over 1000 readings a second")


@pytest.mark.filterwarnings("ignore")
def test_silence_never_frees_the_arm_a_near_person_unheard_stays_where_last_seen() -> None:
    """A person seen at 1.5 m by a source nobody declared, whose readings then stop arriving in time (a
    flood on another source, a saturated host): once forgotten, as if they had left, while a far source
    spoke on. They stay where last seen until a fresh reading of the same source says otherwise; with no
    fresh reading at all the arm holds, whatever was last seen."""
    table = Sources(0.3, 0.05, ("twin",))
    table.receive("twin", 6.0, 0.0, 0.0, 0.0)
    table.receive("camera:side", 1.5, 0.0, 0.0, 0.0)
    for i in range(1, 100):  # the twin at 6 m every 50 ms; the camera's readings all come too old
        now = 0.05 * i
        table.receive("twin", 6.0, 0.0, 0.0, now)
        assert table.receive("camera:side", 1.0, 0.4, 0.0, now) == "stale"  # (nearer, but not looked at)
        assert table.nearest(now).distance_m == 1.5
        assert table.nearest(now).source == "camera:side"
    assert table.nearest(4.9).why == "where last seen: no fresh reading from 'camera:side' for 4.6 s"
    table.receive("camera:side", 4.0, 0.0, 0.0, 5.0)  # the same source, fresh: the person walked off
    assert table.nearest(5.0) == Nearest(4.0, "camera:side", taken_s=5.0)
    table.receive("twin", 6.0, 0.0, 0.0, 5.2)
    seen = table.nearest(5.4)  # where last seen, taken when last seen
    assert seen == Nearest(4.0, "camera:side", seen.why, taken_s=5.0)
    table.receive("twin", 6.0, 0.0, 0.0, 5.4)
    table.receive("camera:side", 3.0, 0.0, 0.0, 5.4)
    table.receive("scanner:rogue", 100.0, 0.0, 0.0, 5.4)  # a far one, of another name, frees nothing
    assert table.nearest(5.6).distance_m == 3.0
    assert table.nearest(6.0).distance_m is None  # nothing fresh: a hold, not the 3 m last seen


async def test_an_installed_cell_refuses_a_source_it_does_not_declare(
    tmp_path: Path, task_file: Path
) -> None:
    """``separation_undeclared = "refuse"`` (what `cadence install --scanner` writes): a reading under a
    name the cell does not declare is refused and counted, however near or far it says, and so is a
    declared one's on the shared key (where any sensor's account may put): a source's readings count on
    its own key only, which the router lets its account alone put. A simulated cell's default takes
    both. A reading on one source's key under another's name is never taken."""
    SOURCES = ("scanner:front", "camera:rogue")
    for policy, nearest in (("refuse", 2.0), ("use", 0.5)):
        # readings live 5 s: the point is whose they are, not how fast this host delivers them
        settings = sim_settings(task_file, separation=True, separation_sources=tracked("scanner:front"),
                                separation_undeclared=policy, separation_max_age_s=5.0)  # fmt: skip
        async with serving(Executor, settings, tmp_path / policy) as run:
            key = run.test.key(OPERATOR_SEPARATION.suffix)
            await run.test.until_subscribed(key, 10)
            own = {s: run.test.key(OPERATOR_SEPARATION_OF.at(source_chunk(s)).suffix) for s in SOURCES}
            for k in own.values():
                await run.test.until_subscribed(k, 10)
            for source, d in (("scanner:front", 2.0), ("camera:rogue", 0.5)):
                sep = Separation(t_ns=now_ns(), seq=0, distance_m=d, source=source, to_robot=True)
                run.test.put_raw(own[source], encode(sep))  # each on its own key
                run.test.put_raw(key, encode(sep))  # and on the shared one, which any sensor may put
            await run.network.settle()
            run.node.reactions.look_distance()
            assert run.node.reactions.shown_m() == pytest.approx(nearest)
            rejected = run.node.ctx.bus.rejected
            refused = policy == "refuse"
            assert rejected.get((own["camera:rogue"], "undeclared"), 0) == refused
            assert rejected.get((key, "undeclared"), 0) == refused
            assert rejected.get((key, "shared_key"), 0) == refused  # the declared one, on the shared key
            # one sensor's key with another's name: never taken, installed or not
            sep = Separation(t_ns=now_ns(), seq=0, distance_m=0.1, source="scanner:front", to_robot=True)
            run.test.put_raw(own["camera:rogue"], encode(sep))
            await run.network.settle()
            assert rejected[(own["camera:rogue"], "impostor")] == 1


async def test_a_flood_on_one_source_never_pushes_anothers_reading_out_of_the_executors_input(
    tmp_path: Path, task_file: Path
) -> None:
    """Through the executor's own input (decoded and taken on arrival): 3,000 far readings of one source
    between two near ones of another leave the near ones, where a queue of 256 once dropped them."""
    # readings live 5 s here: the point is the queue, not how fast this host delivers 3,000 messages
    settings = sim_settings(task_file, separation=True, separation_sources=tracked("scanner:front"),
                            separation_max_rate_hz=100_000, separation_max_age_s=5.0)  # fmt: skip
    async with serving(Executor, settings, tmp_path) as run:
        key = run.test.key(OPERATOR_SEPARATION.suffix)
        await run.test.until_subscribed(key, 10)

        def reading(source: str, d: float) -> bytes:
            return encode(Separation(t_ns=now_ns(), seq=0, distance_m=d, source=source, to_robot=True))

        run.test.put_raw(key, reading("scanner:front", 0.6))
        for _ in range(3000):
            run.test.put_raw(key, reading("scanner:back", 100.0))
        run.test.put_raw(key, reading("scanner:front", 0.7))
        await run.network.settle()
        near = run.node.reactions.look_distance()
        assert near.source == "scanner:front"
        assert run.node.reactions.shown_m() == pytest.approx(0.6)
        assert run.node.ctx.bus.rejected.get((key, "queue_full"), 0) == 0


async def test_a_replayed_selection_is_refused_and_counted_and_a_republished_one_is_no_new_decision(
    tmp_path: Path, task_file: Path
) -> None:
    settings = sim_settings(task_file)
    async with serving(Executor, settings, tmp_path) as run:
        ex = run.node
        t = now_ns()
        captured = Selection(t_ns=t - 600 * S, seq=40, k=15, n=15, delta=1, reason="rest")
        current = Selection(t_ns=t - 10 * S, seq=52, k=8, n=15, delta=-1, reason="stress")
        ex.on_selection(captured)
        ex.on_selection(current)
        for _ in range(80):  # 8 s of a replay at 10 Hz
            with pytest.raises(Rejected) as r:
                ex.on_selection(captured)
            assert r.value.code == "stale"
        ex.on_selection(current)  # the decision maker's republishing: nothing new, nothing refused
        with pytest.raises(Rejected):  # its seq and stamp with another k: not the decision maker's
            ex.on_selection(msgspec.structs.replace(current, k=15))
        assert ex.chosen.selection == current
        fixed = Selection(t_ns=t - 5 * S, seq=53, k=1, n=15, delta=0, reason="fixed")  # numbered after it
        ex.on_selection(fixed)
        assert ex.chosen.selection == fixed
        calibrated = Selection(
            t_ns=t - 6 * S, seq=54, k=8, n=15, delta=0, reason="initial"
        )  # a second before
        ex.on_selection(calibrated)
        assert ex.chosen.selection == calibrated


async def test_a_rogue_seq_or_stamp_never_locks_the_decision_maker_out(
    tmp_path: Path, task_file: Path
) -> None:
    """As the decision maker's account (issue 74): seq 2⁶³−1 at a current stamp once made every honest
    selection after it stale; a stamp 40 ms ahead refused the next honest decision ("27.4 s older"); one
    stamped an hour ago at 10 Hz held its k in 306 of 343 states, uncounted. Each is refused and counted,
    or passed by the honest decision maker's next selection, numbered after the seq in force."""
    async with serving(Executor, sim_settings(task_file), tmp_path) as run:
        ex = run.node
        t = now_ns()
        honest = Selection(t_ns=t - 30 * S, seq=52, k=8, n=15, delta=-1, reason="stress")
        ex.on_selection(honest)
        with pytest.raises(Rejected) as r:
            ex.on_selection(Selection(t_ns=t, seq=2**63 - 1, k=1, n=15, delta=0, reason="hold"))
        assert r.value.code == "jump"
        for i in range(36_000 // 100):  # an hour-old stamp, at 10 Hz, numbered on and on
            with pytest.raises(Rejected) as r:
                ex.on_selection(
                    Selection(t_ns=t - 3600 * S + i, seq=53 + i, k=1, n=15, delta=0, reason="hold")
                )
            assert r.value.code == "stale"
        assert ex.chosen.selection == honest
        ahead = Selection(t_ns=t + 40_000_000, seq=60, k=1, n=15, delta=0, reason="hold")  # in the skew bound
        ex.on_selection(ahead)  # a rogue's that passes: the ACL's to stop, not the sequence's
        # the honest decision maker's next: stamped at its window's end, before the rogue's stamp
        nxt = Selection(t_ns=t - 2 * S, seq=61, k=9, n=15, delta=1, reason="rest")
        ex.on_selection(nxt)
        assert ex.chosen.selection == nxt
        state = ex.telemetry.snapshot()
        assert state.selection_seq == 61  # what the decision maker numbers after


async def test_twenty_signals_at_once_while_nothing_waits_bank_nothing_and_a_wait_takes_one() -> None:
    signals, stop = Signals({"part_a2", "part_c2"}, early={"part_c2": 2.0}), asyncio.Event()
    for i in range(20):
        with pytest.raises(Rejected) as r:
            signals.receive(OperatorSignal(t_ns=i, seq=i, name="part_a2", source="hmi"))
        assert r.value.code == "not_waiting"
    waiting = asyncio.create_task(signals.wait("part_a2", stop, timeout_s=0.05))
    assert await waiting == "late"  # none of the twenty counts for the wait that opened after them
    waiting = asyncio.create_task(signals.wait("part_a2", stop))
    await asyncio.sleep(0)
    signals.receive(OperatorSignal(t_ns=100, seq=0, name="part_a2", source="hmi"))
    with pytest.raises(Rejected, match="its wait has its signal already"):
        signals.receive(OperatorSignal(t_ns=101, seq=1, name="part_a2", source="hmi"))
    assert await waiting == "arrived"
    # declared early: the latest signal before the wait counts for it, once
    for i in range(5):
        signals.receive(OperatorSignal(t_ns=200 + i, seq=i, name="part_c2", source="twin"))
    assert await signals.wait("part_c2", stop, timeout_s=0.05) == "arrived"
    assert await signals.wait("part_c2", stop, timeout_s=0.05) == "late"
    assert signals.received == {"part_a2": 1, "part_c2": 1}


async def test_a_signal_stamped_a_day_ago_or_an_hour_ahead_is_refused_on_arrival_and_ends_no_wait(
    tmp_path: Path, task_file: Path
) -> None:
    """A signal is a fact about now: one stamped a day ago and one an hour ahead each ended an open wait.
    Refused on arrival (before the queue), counted as ``stale`` and ``ahead``; one stamped now passes."""
    async with serving(Executor, sim_settings(task_file, signal_max_age_s=60.0), tmp_path) as run:
        key = run.test.key(OPERATOR_SIGNAL.suffix)
        await run.test.until_subscribed(key, 10)
        taken: list[OperatorSignal] = []
        run.node.cycles.signals.receive = taken.append  # type: ignore[method-assign]  (what passed)
        t = now_ns()
        for stamp in (t - 86_400 * S, t + 3600 * S, t - 61 * S, t + 60 * S, now_ns()):
            run.test.put_raw(key, encode(OperatorSignal(t_ns=stamp, seq=0, name="part", source="hmi")))
        await run.network.settle()
        rejected = run.node.ctx.bus.rejected
        assert (rejected[(key, "stale")], rejected[(key, "ahead")]) == (2, 2)
        assert len(taken) == 1 and abs(taken[0].t_ns - t) < 60 * S
    signals, stop = Signals({"part"}, max_age_s=60.0, skew_s=0.05), asyncio.Event()
    waiting = asyncio.create_task(signals.wait("part", stop, timeout_s=0.2))
    await asyncio.sleep(0)
    for stamp in (t - 86_400 * S, t + 3600 * S):
        sig = OperatorSignal(t_ns=stamp, seq=0, name="part", source="hmi")
        with pytest.raises(Rejected):
            signals.admit(sig, t)
    assert await waiting == "late"


async def test_a_payload_nested_50000_maps_deep_is_a_counted_decode_error_logged_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    nested = b"\x81\xa1a" * 50_000 + b"\xc0"
    bus: Bus = MemoryNetwork().bus(role="executor")
    decoder = msgspec.msgpack.Decoder(OperatorSignal)
    key = bus.key("operator/signal")
    with caplog.at_level(logging.WARNING):
        for _ in range(2000):
            assert bus.decode(key, nested, decoder) is None
    assert bus.decode_errors[key] == 2000
    lines = [r for r in caplog.records if "malformed" in r.getMessage()]
    assert len(lines) == 1
    assert "RecursionError" in lines[0].getMessage()
    await bus.close()
