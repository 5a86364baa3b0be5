"""`cadence record` / `cadence replay`: MCAP files that MCAP tools read, and replay exactness: replaying only
``ecg/samples`` into a fresh HRV analyser and decision maker gives exactly the recorded windows and
selections, at 1× and at 10× the recorded pace."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest
from mcap.reader import make_reader

from cadence.tools.recording import Recorder, read, record, replay
from common.runtime.bus import Bus, BusConfig
from schemas import HrvWindow, Selection
from services.decision_maker.__main__ import Settings as DecisionSettings
from services.decision_maker.__main__ import main as decision_main
from services.ecg_gateway.__main__ import Settings as GatewaySettings
from services.ecg_gateway.__main__ import main as gateway_main
from services.hrv_analyser.__main__ import Settings as AnalyserSettings
from services.hrv_analyser.__main__ import main as analyser_main
from tests.support.cell import CELL, InProcessService, now_ns, put
from tests.support.data import needs_data, record_cut

WINDOWS = 2


def content(msg: msgspec.Struct) -> dict:
    """A message without its sender's sequence number (a restarted sender counts afresh)."""
    return {k: v for k, v in msgspec.structs.asdict(msg).items() if k != "seq"}


async def chain(bus: Bus, tmp: Path, endpoint: str) -> tuple[InProcessService, InProcessService]:
    """A fresh analyser and decision maker, both listening (their subscriptions known to the test's
    session: call it before the test subscribes to their keys)."""
    decider = InProcessService(
        "decision_maker",
        decision_main,
        DecisionSettings(rr_rest_s=0.85, republish_s=600),
        tmp / "d",
        endpoint,
    )
    analyser = InProcessService("hrv_analyser", analyser_main, AnalyserSettings(), tmp / "a", endpoint)
    await analyser.listening(bus, "ecg/samples")
    await analyser.reaches("hrv/window")  # its windows reach the decision maker
    return decider, analyser


async def outputs(wins, sels) -> tuple[list[dict], list[dict]]:
    """The first WINDOWS windows and the selection answering each."""
    got_w, got_s = [], []
    async with asyncio.timeout(60):
        while len(got_w) < WINDOWS:
            got_w.append((await anext(wins))[1])
        while len(got_s) < WINDOWS:
            _, s = await anext(sels)
            if s.window_end_ns in {w.end_ns for w in got_w}:
                got_s.append(s)
    return [content(w) for w in got_w], [content(s) for s in got_s]


@needs_data
@pytest.mark.asyncio
async def test_replay_of_ecg_samples_gives_the_recorded_windows_and_selections(
    tmp_path: Path, endpoint: str
) -> None:
    csv, _ = record_cut(tmp_path, "100", 70)
    mcap = tmp_path / "live.mcap"
    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as bus:
        stop = asyncio.Event()
        services = await chain(bus, tmp_path / "live", endpoint)  # before the recorder subscribes to all
        recording = asyncio.ensure_future(record(bus, mcap, [bus.key("**")], stop))
        subs = [
            bus.subscribe(bus.key("hrv/window"), HrvWindow),
            bus.subscribe(bus.key("decision/selection"), Selection),
        ]
        wins, sels = map(aiter, subs)
        gateway = InProcessService(
            "ecg_gateway",
            gateway_main,
            GatewaySettings(record=str(csv), speed=40.0, start_ns=now_ns() - 70 * 1_000_000_000),
            tmp_path / "g",
            endpoint,
        )
        live = await outputs(wins, sels)
        for svc in (gateway, *services):
            await svc.close()
        stop.set()
        rec = await recording

        replayed = {}
        for speed in (1.0, 10.0):
            for sub in subs:  # the test's own subscribers would satisfy chain()'s waits
                sub.undeclare()
            services = await chain(bus, tmp_path / f"x{speed}", endpoint)
            subs = [
                bus.subscribe(bus.key("hrv/window"), HrvWindow),
                bus.subscribe(bus.key("decision/selection"), Selection),
            ]
            wins, sels = map(aiter, subs)
            sent = await replay(bus, mcap, speed, keys=[bus.key("ecg/samples")])
            replayed[speed] = await outputs(wins, sels)
            for svc in services:
                await svc.close()
    assert rec.count > sent > 0
    assert rec.undecodable == 0
    # what the file itself holds is what the services said live
    in_file = [
        msgspec.msgpack.decode(m.data, type=HrvWindow) for m in read(mcap, [f"cadence/{CELL}/hrv/window"])
    ]
    assert [content(w) for w in in_file[:WINDOWS]] == live[0]
    assert replayed[1.0] == live
    assert replayed[10.0] == live
    assert all(w["quality"] == "good" for w in live[0])


def test_a_recording_opens_in_mcap_tools_with_schemas_and_a_broken_one_is_one_line(tmp_path: Path) -> None:
    from cadence.tools.recording import Recorder
    from schemas.topology import encode

    path = tmp_path / "r.mcap"
    rec = Recorder(path)
    sel = Selection(t_ns=5, seq=0, k=8, n=15, delta=0, reason="initial", window_end_ns=0)
    rec.write(f"cadence/{CELL}/decision/selection", encode(sel))
    rec.write(f"cadence/{CELL}/decision/selection", b"\xc1 not msgpack")  # kept, counted
    rec.close()
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        (schema,) = summary.schemas.values()
        assert schema.name == "decision.selection.v1"
        assert schema.encoding == "jsonschema"
        assert b'"k"' in schema.data
        messages = list(reader.iter_messages())
    assert [m.publish_time for _, _, m in messages] == [5, 0]
    assert rec.undecodable == 1

    broken = tmp_path / "broken.mcap"
    broken.write_bytes(path.read_bytes()[:40])
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "replay", str(broken), "--speed", "0"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1, r.stderr
    assert "broken.mcap" in r.stderr, r.stderr


@pytest.mark.asyncio
async def test_cadence_record_loses_nothing_on_sigterm(tmp_path: Path, endpoint: str) -> None:
    """Whatever the recorder received is in the file after SIGTERM: its own count, in order, no gap."""
    import re
    import signal

    path = tmp_path / "rec.mcap"
    cell = "rectest"  # a cell of its own: no other test's session can be the subscriber it waits for
    async with await Bus.open(BusConfig(listen=[endpoint]), cell) as bus:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cadence", "record", "-o", str(path), "--connect", endpoint, "--cell", cell,
            stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        try:
            first = await asyncio.wait_for(proc.stderr.readline(), 60)  # its signal handlers are in place
            assert b"recording" in first, first
            await bus.until_subscribed(bus.key("decision/selection"), 30)  # and it is listening
            sel = Selection(t_ns=1, seq=0, k=8, n=15, delta=0, reason="initial", window_end_ns=0)
            for i in range(1, 2001):
                put(bus, bus.key("decision/selection"), msgspec.structs.replace(sel, seq=i), block=True)
            async with asyncio.timeout(60):  # at least one arrived: the check below is not vacuous
                while (
                    b"first message: cadence/rectest/decision/selection" not in await proc.stderr.readline()
                ):
                    pass
            proc.send_signal(signal.SIGTERM)
            _, err = await asyncio.wait_for(proc.communicate(), 60)  # reads stderr while it finishes
        finally:
            if proc.returncode is None:
                proc.kill()
        said = err.decode()
        assert proc.returncode == 0, said
    count = int(re.search(r"(\d+) messages written", said).group(1))
    seqs = [msgspec.msgpack.decode(m.data, type=Selection).seq for m in read(path)]
    assert count == len(seqs) > 0
    assert seqs == list(range(1, count + 1))


def test_cadence_record_never_overwrites_a_recording_unless_forced(tmp_path: Path) -> None:
    """`cadence record -o run.mcap` once truncated a recording already there, silently: the evidence of
    an earlier run lost to a repeated command line. Refused in one line before the bus opens; the writer
    itself takes the name exclusively, so a second recording started meanwhile is refused too."""
    path = tmp_path / "run.mcap"
    path.write_bytes(b"an earlier run")
    r = subprocess.run([sys.executable, "-m", "cadence", "record", "-o", str(path), "--duration", "1"],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "exists" in r.stderr and "--force" in r.stderr, r.stderr
    assert path.read_bytes() == b"an earlier run"
    with pytest.raises(FileExistsError):
        Recorder(path, replace=False)
    assert path.read_bytes() == b"an earlier run"
    rec = Recorder(path)  # forced (`--force`): the file is a new recording
    rec.close()
    assert [m.topic for m in read(path)] == [] and path.read_bytes()[:5] == b"\x89MCAP"


def test_a_json_recording_reads_as_the_msgpack_one_for_report_and_replay(tmp_path: Path) -> None:
    """`record --json` (what Foxglove decodes) and the default MessagePack file give the same messages to
    `cadence report` and `cadence replay`."""
    from cadence.lab.report import from_mcap
    from cadence.tools.recording import Recorder, read
    from schemas import CycleReport, HrvWindow
    from schemas.topology import decode_any, encode

    s = 10**9
    window = HrvWindow(
        t_ns=30 * s, seq=0, start_ns=s, end_ns=30 * s, mean_rr_s=0.8, n_beats=37, excluded_fraction=0.0,
        quality="good",
    )  # fmt: skip
    msgs = [
        (
            f"cadence/{CELL}/decision/selection",
            Selection(t_ns=5 * s, seq=0, k=8, n=15, delta=0, reason="initial"),
        ),
        (f"cadence/{CELL}/hrv/window", window),
        (
            f"cadence/{CELL}/robot/cycle",
            CycleReport(t_ns=40 * s, seq=0, cycle=0, cycle_time_s=12.5, k_per_path={"p": 8}),
        ),
    ]
    for name, as_json in (("m.mcap", False), ("j.mcap", True)):
        rec = Recorder(tmp_path / name, json=as_json)
        for key, m in msgs:
            rec.write(key, encode(m))
        rec.close()
    got = {
        n: [(r.key, r.encoding, decode_any(r.data)) for r in read(tmp_path / n)] for n in ("m.mcap", "j.mcap")
    }
    assert got["j.mcap"] == got["m.mcap"] == [(k, "msgpack", m) for k, m in msgs]
    runs = [from_mcap(tmp_path / n) for n in ("m.mcap", "j.mcap")]
    assert runs[0].cycles == runs[1].cycles
    assert runs[0].windows == runs[1].windows
    assert len(runs[1].cycles) == 1


def test_a_replay_that_nothing_received_says_so_and_exits_1(tmp_path: Path) -> None:
    """Zenoh drops a put with no subscriber silently: "426 messages replayed", exit 0, was a dead end
    (issue 28). A replay on a private port, with nobody there, says nothing received it."""
    from cadence.tools.recording import Recorder
    from schemas.topology import encode

    rec = Recorder(tmp_path / "one.mcap")
    sel = Selection(t_ns=5, seq=0, k=8, n=15, delta=0, reason="initial")
    rec.write(f"cadence/{CELL}/decision/selection", encode(sel))
    rec.close()
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "replay", str(tmp_path / "one.mcap"), "--speed", "0"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 1, r.stderr
    assert "no subscriber matched" in r.stderr, r.stderr


def test_a_recording_cut_without_its_footer_is_read_up_to_its_last_chunk(tmp_path: Path) -> None:
    """A recorder killed with SIGKILL left a file that `cadence report` refused whole (2,039 of 2,830
    messages could be read), and its last in-memory chunk was gone. It flushes every second now, and a
    file without a footer is read as far as it goes, and said so."""
    from cadence.tools.recording import Recorder, read
    from schemas import Selection
    from schemas.topology import encode

    path = tmp_path / "killed.mcap"
    rec = Recorder(path)
    for i in range(3000):
        sel = Selection(t_ns=i + 1, seq=i, k=1 + i % 15, n=15, delta=0, reason="hold")
        rec.write(f"cadence/{CELL}/decision/selection", encode(sel), log_time_ns=i + 1)
        if i == 2499:
            rec.flush()  # the last flush before the kill
    rec._file.close()  # killed: no finish, no footer (what was not flushed is lost, as in a kill)
    notes: list[str] = []
    got = list(read(path, notes=notes))
    assert len(got) == 2500
    assert [m.log_time for m in got] == list(range(1, 2501))
    assert len(notes) == 1
    assert "ends without its footer" in notes[0]
    assert "2500 messages" in notes[0]


@pytest.mark.asyncio
async def test_a_plant_recording_keeps_every_cells_derived_keys_and_no_raw_signal(
    tmp_path: Path, endpoint: str
) -> None:
    """`cadence record --plant` (issue 58): windows, selections, statuses of two cells, not the raw ECG or
    the arm's state (health data, and most of a cell's bytes); a service's status once a minute, a
    selection only when it is a new one."""
    from cadence.tools.recording import PlantThinning, plant_keys
    from schemas import EcgChunk, RobotState, ServiceStatus

    def status(state: str, seq: int) -> ServiceStatus:
        return ServiceStatus(t_ns=5, seq=seq, service="executor", state=state, uptime_s=1.0, counters={})

    window = HrvWindow(t_ns=2, seq=0, start_ns=0, end_ns=2, mean_rr_s=0.8, n_beats=3, excluded_fraction=0.0,
                       quality="good")  # fmt: skip
    sel = Selection(t_ns=3, seq=0, k=8, n=15, delta=0, reason="initial", window_end_ns=2)
    sent = [
        ("pc1/ecg/samples", EcgChunk(t_ns=1, seq=0, fs_hz=130.0, samples_uv=[1, 2, 3])),
        ("pc1/robot/state", RobotState(t_ns=1, seq=0, q=[0.0] * 6, qd=[0.0] * 6, tcp=[0.0] * 6)),
        ("pc1/hrv/window", window),
        ("pc2/hrv/window", window),
        ("pc1/health/executor", status("serving", 1)),
        ("pc1/health/executor", status("serving", 2)),  # within the minute: left out
        ("pc1/health/executor", status("stopped", 3)),  # so is this (its events say what changed)
        ("pc2/decision/selection", sel),
        ("pc2/decision/selection", sel),  # republished, no new decision: left out
        ("pc2/decision/selection", msgspec.structs.replace(sel, seq=1, k=7)),
    ]
    stop, arrived = asyncio.Event(), []
    thin = PlantThinning()

    def keep(key: str, payload: bytes) -> bool:  # what reached the recorder: all of it, then stop
        arrived.append(key)
        if len(arrived) == sum(1 for k, _ in sent if "/ecg/" not in k and "/robot/state" not in k):
            stop.set()
        return thin(key, payload)

    async with (
        await Bus.open(BusConfig(listen=[endpoint]), "pc1") as recorder,
        await Bus.open(BusConfig(mode="client", connect=[endpoint]), "pc1") as cell,
    ):
        recording = asyncio.ensure_future(
            record(recorder, tmp_path / "plant.mcap", plant_keys(), stop, keep=keep)
        )
        for key in ("pc1/hrv/window", "pc2/hrv/window", "pc1/health/executor", "pc2/decision/selection"):
            await cell.until_subscribed(f"cadence/{key}", 30)
        for key, msg in sent:
            put(cell, f"cadence/{key}", msg, block=True)
        await asyncio.wait_for(stop.wait(), 30)
        rec = await recording
    got = [(m.key.removeprefix("cadence/"), msgspec.msgpack.decode(m.data).get("state"))
           for m in read(tmp_path / "plant.mcap")]  # fmt: skip
    want = [("pc1/hrv/window", None), ("pc2/hrv/window", None), ("pc1/health/executor", "serving"),
            ("pc2/decision/selection", None), ("pc2/decision/selection", None)]  # fmt: skip
    assert sorted(got, key=str) == sorted(want, key=str)
    assert rec.count == 5


def test_plant_thinning_keeps_a_status_a_minute_and_each_new_selection() -> None:
    from cadence.tools.recording import PlantThinning
    from schemas import ServiceStatus
    from schemas.topology import encode

    now = [0.0]
    thin = PlantThinning(clock=lambda: now[0])
    status = encode(
        ServiceStatus(t_ns=1, seq=0, service="executor", state="moving", uptime_s=1.0, counters={})
    )
    kept = []
    for t in (0.0, 30.0, 59.9, 60.0, 61.0, 125.0):
        now[0] = t
        kept += [t] if thin("cadence/c1/health/executor", status) else []
    assert kept == [0.0, 60.0, 125.0]
    assert thin("cadence/c2/health/executor", status)  # each key its own minute
    sel = Selection(t_ns=3, seq=4, k=8, n=15, delta=0, reason="initial")
    again = [
        thin("cadence/c1/decision/selection", encode(msgspec.structs.replace(sel, seq=s))) for s in (4, 4, 5)
    ]
    assert again == [True, False, True]
    assert thin("cadence/c1/hrv/window", b"anything")
