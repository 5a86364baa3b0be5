"""Each hostile message and damaged file found by hand, as a test: none takes a service down, freezes it
or moves the robot, and each is counted with its reason (docs/operations.md, "Bad input")."""

from __future__ import annotations

import asyncio
import json
import logging
import sqlite3
import time
from collections.abc import Awaitable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from common.hrv.calibration import CALIBRATION_FILE
from common.runtime.bus import Bus
from schemas import AccChunk, EcgChunk, HrvWindow, ParetoSet, RobotEvent, Selection, ServiceStatus
from schemas.topology import encode
from services.decision_maker.__main__ import Settings as DecisionSettings
from services.decision_maker.__main__ import main as decision_main
from services.decision_maker.state import STATE_FILE, Decider, resume
from services.hrv_analyser.__main__ import Settings as AnalyserSettings
from services.hrv_analyser.__main__ import main as analyser_main
from services.pareto_store.store import SetStore
from tests.support.cell import Cell, now_ns, put, status_of
from tests.support.data import DAY, S, chunks, synthetic_ecg
from tests.support.decisions import answer, expected, window


def raw(msg: msgspec.Struct, **changes: Any) -> bytes:
    """A message with some fields replaced, as bytes: what a hostile or broken sender puts on the wire
    (building the Struct would refuse some of these values already)."""
    d = msgspec.to_builtins(msg)
    d.update(changes)
    return msgspec.msgpack.encode(d)


# --- the decision maker ----------------------------------------------------------------------------


HOSTILE_WINDOWS = {
    "mean_rr_s = 1e300 (overflowed the decision rule)": {"mean_rr_s": 1e300},
    "mean_rr_s = 1e-300 (sent k to 1)": {"mean_rr_s": 1e-300},
    "mean_rr_s = inf (raised on every window)": {"mean_rr_s": float("inf")},
    "mean_rr_s = nan": {"mean_rr_s": float("nan")},
    "end_ns = 2**63 (froze every later window)": {"end_ns": 2**63, "t_ns": 2**63},
    "starts after it ends": {"start_ns": 10**12 * 30, "end_ns": 30 * S},
    "excluded_fraction = 2": {"excluded_fraction": 2.0},
    "n_beats = -1": {"n_beats": -1},
}


@pytest.mark.asyncio
async def test_impossible_windows_never_move_k_and_the_next_honest_window_is_answered(
    tmp_path: Path, cell: Cell
) -> None:
    honest = [window(i, rr) for i, rr in enumerate([0.85, 0.81, 0.75, 0.70, 0.80])]
    settings = DecisionSettings(rr_rest_s=0.85, republish_s=0.2)
    async with cell.session() as bus:
        svc = cell.service("decision_maker", decision_main, settings, tmp_path)
        await svc.listening(bus, "hrv/window")
        sels = aiter(bus.subscribe(bus.key("decision/selection"), Selection))
        key = bus.key("hrv/window")
        seen: list[Selection] = []

        async def answered(w: HrvWindow) -> Selection:
            put(bus, key, w, block=True)
            async with asyncio.timeout(10):
                async for _, sel in sels:
                    seen.append(sel)
                    if sel.window_end_ns == w.end_ns:
                        return sel
            raise AssertionError("unreachable")

        got = [(await answered(honest[0])).k]
        for changes in HOSTILE_WINDOWS.values():
            bus.put_raw(key, raw(honest[1], **changes), block=True)
        # valid on the wire, impossible for the stream: 30 days after the last window
        put(
            bus,
            key,
            msgspec.structs.replace(
                honest[1], start_ns=honest[1].start_ns + 30 * DAY, end_ns=honest[1].end_ns + 30 * DAY
            ),
            block=True,
        )
        mark = len(seen)
        got += [(await answered(w)).k for w in honest[1:3]]
        status = await status_of(bus, "decision_maker", lambda s: s.counters.get("decode_errors", 0) >= 8)
        await svc.close()

        # a restart resumes: no crash loop on what was persisted
        svc = cell.service("decision_maker", decision_main, settings, tmp_path)
        await svc.listening(bus, "hrv/window")
        got += [(await answered(w)).k for w in honest[3:]]
        await svc.close()

    assert got == expected(honest, 0.85)
    assert len(set(got)) > 2
    # between the first answer and the second, k stayed where the first answer put it
    assert {sel.k for sel in seen[:mark]} == {got[0]}
    assert status.counters["decode_errors"] == len(HOSTILE_WINDOWS)
    assert status.counters["rejected/hrv/window/ahead"] == 1
    assert json.loads((tmp_path / STATE_FILE).read_text())["k"] == got[-1]


@pytest.mark.asyncio
async def test_a_run_of_windows_from_the_decision_makers_future_is_refused_and_the_honest_ones_answered(
    tmp_path: Path, zenoh_cell: Cell
) -> None:
    """20 contiguous relaxed windows up to 600 s ahead of its clock once moved the decision maker's time
    line, the honest windows after them were dropped as duplicates, and k stood for ten minutes. Over
    real Zenoh: what a planting sender would use."""
    cell = zenoh_cell
    honest = [window(i, rr) for i, rr in enumerate([0.85, 0.81, 0.75, 0.70, 0.80])]
    ahead = now_ns() + 5 * S  # 20 contiguous 30 s windows, ending 35 s to 605 s ahead of the clock
    planted = [
        msgspec.structs.replace(
            honest[0],
            start_ns=ahead + i * 30 * S,
            end_ns=ahead + (i + 1) * 30 * S,
            t_ns=ahead + (i + 1) * 30 * S,
            seq=100 + i,
            mean_rr_s=1.2,
        )
        for i in range(20)
    ]
    settings = DecisionSettings(rr_rest_s=0.85, republish_s=0.2)
    async with cell.session() as bus:
        svc = cell.service("decision_maker", decision_main, settings, tmp_path)
        await svc.listening(bus, "hrv/window")
        sels = aiter(bus.subscribe(bus.key("decision/selection"), Selection))
        key = bus.key("hrv/window")

        got = [(await answer(bus, sels, honest[0])).k]
        for w in planted:
            put(bus, key, w, block=True)
        got += [(await answer(bus, sels, w)).k for w in honest[1:]]
        status = await status_of(
            bus, "decision_maker", lambda s: s.counters.get("rejected/hrv/window/ahead", 0) >= len(planted)
        )
        await svc.close()
    assert got == expected(honest, 0.85)
    assert status.counters["rejected/hrv/window/ahead"] == len(planted)
    assert status.counters.get("window_line_restarts", 0) == 0
    # refused on arrival: none of them asked the analyser for the windows "missed" before it (4,000 planted
    # windows once made 259 queries and pushed an honest window out of the queue)
    assert status.counters.get("missed_queries", 0) == 0


CORRUPT_STATES = {
    "a list": "[1, 2, 3]",
    "k is text": None,  # filled from a valid record below
    "rr_prev is NaN": None,
    "last_end_ns is 2**70": None,
    "garbage": "\x00\x17 not json",
    "empty": "",
}


def _valid_record(tmp_path: Path) -> dict:
    decider = Decider(tmp_path, 15)
    resume(decider, tmp_path, 0.85)
    assert decider.record is not None
    return msgspec.to_builtins(decider.record)


@pytest.mark.parametrize("case", list(CORRUPT_STATES))
def test_a_corrupt_state_file_is_moved_aside_named_and_the_service_starts_at_the_initial_k(
    case: str, tmp_path: Path
) -> None:
    doc = _valid_record(tmp_path)
    text = CORRUPT_STATES[case]
    if text is None:
        field, value = {
            "k is text": ("k", "abc"),
            "rr_prev is NaN": ("rr_prev", "NaN"),
            "last_end_ns is 2**70": ("last_end_ns", 2**70),
        }[case]
        doc[field] = value
        text = json.dumps(doc)
    (tmp_path / STATE_FILE).write_text(text)

    decider = Decider(tmp_path, 15)
    problems = resume(decider, tmp_path, 0.85)

    (moved,) = tmp_path.glob(f"{STATE_FILE}.corrupt-*")
    assert moved.read_text() == text  # kept as it was, for a person to look at
    assert not (tmp_path / STATE_FILE).exists()
    (problem,) = problems
    assert STATE_FILE in problem
    assert moved.name in problem
    assert "\n" not in problem
    if case in ("k is text", "rr_prev is NaN", "last_end_ns is 2**70"):
        assert case.split()[0] in problem  # the field is named
    assert decider.record is not None
    assert (decider.record.k, decider.record.reason) == (8, "initial")


@pytest.mark.asyncio
async def test_the_status_says_the_state_file_was_moved_aside(tmp_path: Path, cell: Cell) -> None:
    (tmp_path / STATE_FILE).write_text('{"k": "abc"}')
    async with cell.session() as bus:
        svc = cell.service("decision_maker", decision_main, DecisionSettings(rr_rest_s=0.85), tmp_path)
        status = await status_of(bus, "decision_maker", lambda s: bool(s.detail))
        await svc.close()
    assert status.state == "running"
    assert "moved aside" in status.detail
    assert "initial k" in status.detail


def test_a_corrupt_calibration_file_is_moved_aside_and_the_config_rr_rest_used(tmp_path: Path) -> None:
    (tmp_path / CALIBRATION_FILE).write_text('{"type": "operator.calibration.v1", "rr_rest_s": -0.8}')
    decider = Decider(tmp_path, 15)
    (problem,) = resume(decider, tmp_path, 0.9)
    assert CALIBRATION_FILE in problem
    assert "rr_rest_s" in problem
    assert list(tmp_path.glob(f"{CALIBRATION_FILE}.corrupt-*"))
    assert decider.record is not None
    assert decider.record.calibration.rr_rest_s == 0.9


# --- the HRV analyser ------------------------------------------------------------------------------


async def windows_of(
    bus: Bus, honest: list[EcgChunk], hostile_at: dict[int, list[bytes]], n: int
) -> list[HrvWindow]:
    key = bus.key("ecg/samples")
    wins = aiter(bus.subscribe(bus.key("hrv/window"), HrvWindow))
    for i, c in enumerate(honest):
        for payload in hostile_at.get(i, []):
            bus.put_raw(key, payload, block=True)
        put(bus, key, c, block=True)
    out = []
    async with asyncio.timeout(20):
        while len(out) < n:
            out.append((await anext(wins))[1])
    return out


@pytest.mark.asyncio
async def test_hostile_chunks_leave_the_analysers_windows_as_the_honest_stream_gives_them(
    tmp_path: Path, cell: Cell
) -> None:
    T0 = now_ns() - 100 * S  # 100 s that have happened: nothing from the analyser's future is taken
    honest = chunks(synthetic_ecg(100), T0)
    c = honest[50]
    hostile = [
        raw(c, t_ns=c.t_ns + 30 * DAY),  # decodes: 30 days ahead (gave 86,398 empty windows)
        raw(c, t_ns=2**63 - 1),  # blocked the event loop
        raw(c, fs_hz=1e9),  # 3.5 GB
        raw(c, samples_uv=[0] * 10**6),  # stopped windows for the rest of the run
        raw(c, fs_hz=250.0),  # decodes: another rate than the stream's
        raw(c, t_ns=c.t_ns - 60 * S),  # decodes: a minute behind
    ]
    async with cell.session() as bus:
        svc = cell.service("hrv_analyser", analyser_main, AnalyserSettings(), tmp_path)
        await svc.listening(bus, "ecg/samples")
        got = await windows_of(bus, honest, {51: hostile}, 3)
        status = await status_of(bus, "hrv_analyser", lambda s: s.counters.get("decode_errors", 0) >= 3)
        await svc.close()
    assert [(w.start_ns - T0) // S for w in got] == [0, 30, 60]
    assert all(w.quality == "good" and w.mean_rr_s == pytest.approx(0.8, abs=2e-3) for w in got)
    c = status.counters
    assert c["decode_errors"] == 3
    assert c["rejected/ecg/samples/ahead"] == 1
    assert c["rejected/ecg/samples/changed"] == 1
    assert c["rejected/ecg/samples/behind"] == 1
    assert c.get("stream_restarts", 0) == 0


@pytest.mark.asyncio
async def test_a_hostile_first_chunk_does_not_lock_the_honest_stream_out(tmp_path: Path, cell: Cell) -> None:
    T0 = now_ns() - 100 * S
    honest = chunks(synthetic_ecg(100), T0)
    first = raw(honest[0], t_ns=T0 + 30 * DAY)
    async with cell.session() as bus:
        svc = cell.service("hrv_analyser", analyser_main, AnalyserSettings(), tmp_path)
        await svc.listening(bus, "ecg/samples")
        got = await windows_of(bus, honest, {0: [first]}, 2)
        await svc.close()
    # the hostile chunk is far from the analyser's clock and has no stream to be in line with: dropped;
    # the honest stream's first chunk is near the clock and starts the stream
    assert [w.start_ns for w in got] == [T0, T0 + 30 * S]
    assert all(w.quality == "good" for w in got)


@pytest.mark.asyncio
async def test_planted_accelerometer_ahead_of_the_clock_is_refused_counted_said_once_and_the_honest_goes_on(
    tmp_path: Path, zenoh_cell: Cell, caplog: pytest.LogCaptureFixture
) -> None:
    """1,000 s of ±16 g planted in under a second once made the next windows read 5,399–7,833 mg against
    an honest 14 mg, and held Alg. 1 for movement for 17 minutes. Over real Zenoh, into the service: the
    planted chunks are refused as from its future and counted, and the honest stream's windows carry the
    honest movement."""
    T0 = now_ns() - 100 * S  # 100 s that have happened
    rng = np.random.default_rng(3)

    def acc(i: int, t_ns: int, loud: bool) -> AccChunk:
        if loud:
            x = [16_000, -16_000] * 12 + [16_000]
            return AccChunk(t_ns=t_ns, seq=i, fs_hz=25.0, x_mg=x, y_mg=x, z_mg=x)
        still = rng.normal(0.0, 8.0, (3, 25)).round().astype(int) + np.array([[0], [0], [1000]])
        x, y, z = still.tolist()
        return AccChunk(t_ns=t_ns, seq=i, fs_hz=25.0, x_mg=x, y_mg=y, z_mg=z)

    def counted(name: str, n: int) -> Awaitable[ServiceStatus]:
        return status_of(bus, "hrv_analyser", lambda s: s.counters.get(name, 0) >= n, timeout=60)

    honest = [acc(i, T0 + i * S, loud=False) for i in range(100)]
    began = time.monotonic()
    async with zenoh_cell.session() as bus:
        svc = zenoh_cell.service("hrv_analyser", analyser_main, AnalyserSettings(), tmp_path)
        await svc.listening(bus, "ecg/samples", "ecg/acc")
        # a minute ahead of the analyser's clock once it listens, however long a loaded host took to start it
        ahead_ns = time.time_ns() + 60 * S
        planted = [acc(1000 + j, ahead_ns + j * S, loud=True) for j in range(1000)]
        key = bus.key("ecg/acc")
        for i, c in enumerate(honest):
            put(bus, key, c, block=True)
            if i == 30:  # in the middle of the honest stream, as fast as a sender can
                await counted("acc_chunks", 31)
                # in bursts the analyser's queue holds (256; a larger one drops its oldest, counted as
                # queue_full: the bus's rule, tested with the bus)
                for b in range(0, len(planted), 200):
                    for p in planted[b : b + 200]:
                        put(bus, key, p, block=True)
                    await counted("rejected/ecg/acc/ahead", b + 200)
        # the accelerometer taken before the ECG's windows close: they carry what had come (a loaded host
        # once closed them before it handled the honest chunks behind the planted ones)
        await counted("acc_chunks", len(honest))
        got = await windows_of(bus, chunks(synthetic_ecg(100), T0), {}, 3)
        status = await status_of(
            bus, "hrv_analyser", lambda s: s.counters.get("rejected/ecg/acc/ahead", 0) >= len(planted)
        )
        await svc.close()
    assert [(w.start_ns - T0) // S for w in got] == [0, 30, 60]
    for w in got:
        assert w.movement_mg is not None
        assert w.movement_mg < 100  # the honest, still wearer's
    assert status.counters["rejected/ecg/acc/ahead"] == len(planted)
    assert status.counters["acc_chunks"] == len(honest)  # every honest chunk taken
    # the run of refusals is said once, then at most once per 10 s of it (however slow the host)
    said = [r for r in caplog.records if "(ahead) on cadence/cell1/ecg/acc" in r.getMessage()]
    assert 1 <= len(said) <= 1 + (time.monotonic() - began) // 10


# --- the Pareto store's database ------------------------------------------------------------------


def test_a_corrupt_sqlite_store_is_moved_aside_and_a_new_one_made(tmp_path: Path) -> None:
    db = tmp_path / "pareto.sqlite"
    db.write_bytes(b"this is not a database" * 100)
    store, problem = SetStore.open(db)
    assert problem is not None
    assert "pareto.sqlite" in problem
    assert "planned again" in problem
    (moved,) = tmp_path.glob("pareto.sqlite.corrupt-*")
    assert moved.read_bytes().startswith(b"this is not")
    assert store.load("p", "h") is None
    store.close()
    assert sqlite3.connect(db).execute("PRAGMA quick_check").fetchone() == ("ok",)


def test_a_stored_set_that_does_not_decode_is_deleted_so_it_is_planned_again(tmp_path: Path) -> None:
    db = tmp_path / "pareto.sqlite"
    store, _ = SetStore.open(db)
    store._db.execute("INSERT INTO pareto_sets VALUES ('p', 'h', 0, ?)", (b"\xc1garbage",))
    assert store.load("p", "h") is None
    assert store._db.execute("SELECT COUNT(*) FROM pareto_sets").fetchone() == (0,)
    store.close()


# --- handler failures -----------------------------------------------------------------------------


@pytest.mark.asyncio
async def test_a_failing_handler_is_counted_logged_once_per_10_s_and_the_next_message_handled(
    cell: Cell, caplog: pytest.LogCaptureFixture
) -> None:
    from common.runtime.config import CommonSettings
    from common.runtime.service import ServiceContext

    async with cell.session() as bus:
        handled: list[int] = []
        done = asyncio.Event()

        async def handler(_: str, sel: Selection) -> None:
            if sel.seq % 2 == 0:
                raise ZeroDivisionError("boom")
            handled.append(sel.seq)
            if len(handled) == 50:
                done.set()

        bus.handle(bus.key("decision/selection"), Selection, handler, maxsize=1000)
        with caplog.at_level(logging.WARNING, logger="cadence.bus"):
            for i in range(100):
                sel = Selection(t_ns=1, seq=i, k=1, n=15, delta=0, reason="hold")
                put(bus, bus.key("decision/selection"), sel, block=True)
            async with asyncio.timeout(10):
                await done.wait()
        ctx = ServiceContext("x", bus, CommonSettings(), None, asyncio.Event())
        status = ctx.status(0)
    assert handled == list(range(1, 100, 2))
    assert status.counters["handler_errors/decision/selection/ZeroDivisionError"] == 50
    lines = [r.getMessage() for r in caplog.records if "handler failed" in r.getMessage()]
    assert len(lines) == 1
    assert "ZeroDivisionError: boom" in lines[0]
    assert "test_hostile.py" in lines[0]


# --- the executor ---------------------------------------------------------------------------------


@pytest.mark.asyncio
async def test_absurd_pareto_sets_are_never_used_or_cached_and_a_refused_cache_is_fetched_again(
    tmp_path: Path, zenoh_cell: Cell
) -> None:
    from schemas import CycleReport
    from services.executor.__main__ import main as executor_main
    from tests.support.executor import SPEED, TASK, next_of, sim_settings, store_serving

    task_file = tmp_path / "shuttle.toml"
    task_file.write_text(TASK)
    cache = tmp_path / "ex" / "executor"
    cache.mkdir(parents=True)
    async with zenoh_cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", zenoh_cell)
        there = (await bus.get(bus.key("pareto/there"), ParetoSet))[0].message
        back = (await bus.get(bus.key("pareto/back"), ParetoSet))[0].message
        await store.close()  # the store is down until the end
        # on disk: one set damaged, one refused by the executor's own check (twice as fast as planned)
        (cache / "back.msgpack").write_bytes(raw(back, solutions=[]))  # crashed it for good
        fast = [msgspec.structs.replace(s, h=[x / 2 for x in s.h], t_f=s.t_f / 2) for s in there.solutions]
        (cache / "there.msgpack").write_bytes(encode(msgspec.structs.replace(there, solutions=fast)))

        # the store's stand-in answers absurd sets first
        absurd = [
            raw(there, solutions=[]),
            raw(there, solutions=[{**msgspec.to_builtins(there.solutions[0]), "h": [1e5] * 4, "t_f": 4e5}]),
        ]
        answered = asyncio.Event()

        def on_query(query: Any) -> None:
            with query:
                query.reply(query.key_expr, absurd[0] if "there" in str(query.key_expr) else absurd[1])
                answered.set()

        fake = bus.transport.session.declare_queryable(bus.key("pareto/**"), on_query)
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent))
        cycles = aiter(bus.subscribe(bus.key("robot/cycle"), CycleReport))
        settings = sim_settings(task_file)
        ex = zenoh_cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        refused = await next_of(events, lambda e: e.kind == "refused" and "over its limit" in e.message)
        async with asyncio.timeout(20):
            await answered.wait()
        status = await status_of(bus, "executor", lambda s: s.counters.get("decode_errors", 0) >= 2)
        fake.undeclare()
        assert not (cache / "there.msgpack").exists()  # the refused set is not kept
        assert list(cache.glob("back.msgpack.corrupt-*"))
        assert "back.msgpack" in status.detail
        assert "solutions" in status.detail

        store = await store_serving(bus, task_file, tmp_path / "store", zenoh_cell)
        report = await next_of(cycles, timeout=60)
        await asyncio.wait_for(ex.task, 15)
        await store.close()
    assert refused.path_id == "there"
    assert report.k_per_path == {"there": 3, "back": 3}
    assert sorted(p.name for p in cache.glob("*.msgpack")) == ["back.msgpack", "there.msgpack"]
