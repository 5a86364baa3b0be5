"""The ECG chain over real Zenoh: a replayed recording → ecg_gateway → hrv_analyser → decision_maker.
The windows equal the offline ones for the same recording, and the selections equal Alg. 1 on them."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from common.decision import Params, State, step
from common.hrv.calibration import CALIBRATION_FILE
from common.hrv.records import read_record
from common.hrv.rpeaks import detect_peaks
from common.hrv.stream import intervals, peak_intervals, windows
from common.runtime.bus import Bus, BusConfig
from schemas import HrvWindow, Selection
from services.decision_maker.__main__ import Settings as DecisionSettings
from services.decision_maker.__main__ import main as decision_main
from services.ecg_gateway.__main__ import Settings as GatewaySettings
from services.ecg_gateway.__main__ import main as gateway_main
from services.hrv_analyser.__main__ import Settings as AnalyserSettings
from services.hrv_analyser.__main__ import main as analyser_main
from tests.support.cell import CELL, InProcessService, now_ns, put
from tests.support.data import ECG, needs_data, record_cut

pytestmark = pytest.mark.asyncio


@needs_data
async def test_replay_to_windows_to_selections(tmp_path: Path, endpoint: str) -> None:
    csv, x = record_cut(tmp_path, "100", 125)
    START_NS = now_ns()  # one cell clock at 40×, and the replay on it (DESIGN §4)
    expected = windows(peak_intervals(detect_peaks(x, 130.0), 130.0), 30.0, end_s=len(x) / 130.0)

    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as bus:
        cell = {"speed": 40.0, "epoch_ns": START_NS}
        decider = InProcessService(
            "decision_maker",
            decision_main,
            DecisionSettings(rr_rest_s=0.85, republish_s=60),
            tmp_path / "d",
            endpoint,
            **cell,
        )
        analyser = InProcessService(
            "hrv_analyser", analyser_main, AnalyserSettings(), tmp_path / "a", endpoint, **cell
        )
        await analyser.listening(bus, "ecg/samples")  # and the replay waits for it too
        await analyser.reaches("hrv/window")  # its windows reach the decision maker (nobody else yet)
        wins = aiter(bus.subscribe(bus.key("hrv/window"), HrvWindow))
        sels = aiter(bus.subscribe(bus.key("decision/selection"), Selection))
        gateway = InProcessService(
            "ecg_gateway",
            gateway_main,
            GatewaySettings(record=str(csv), speed=40.0, start_ns=START_NS),
            tmp_path / "g",
            endpoint,
            **cell,
        )
        got_windows, got_k = [], []
        async with asyncio.timeout(30):
            while len(got_windows) < len(expected) - 1:  # the last window closes only at flush
                _, w = await anext(wins)
                got_windows.append(w)
                while True:
                    _, sel = await anext(sels)
                    if sel.window_end_ns == w.end_ns:
                        got_k.append(sel.k)
                        break
        for svc in (gateway, analyser, decider):
            await svc.close()

    assert len(got_windows) == len(expected) - 1 == 3
    for w, e in zip(got_windows, expected, strict=False):
        assert (w.start_ns - START_NS, w.end_ns - START_NS) == (round(e.start_s * 1e9), round(e.end_s * 1e9))
        assert w.mean_rr_s == pytest.approx(e.mean_rr_s, abs=1e-9)
        assert w.quality == e.quality
        assert w.n_beats == e.n_beats
    p, s, ks = Params.of(0.85), None, []
    s = State.initial(p)
    for e in expected[: len(got_k)]:
        s = step(p, s, e.mean_rr_s, e.quality == "good").state
        ks.append(s.k)
    assert got_k == ks


@needs_data
async def test_calibrate_records_resting_windows_stores_and_publishes_rr_rest(
    tmp_path: Path, endpoint: str
) -> None:
    import msgspec

    from cadence.lab.calibrate import calibrate, calibration_screen
    from schemas import Calibration, RobotState

    csv, x = record_cut(tmp_path, "103", 100)
    START_NS = now_ns() - 100 * 1_000_000_000  # replayed 40× faster than the clock: it ends by now
    offline = [
        w
        for w in windows(peak_intervals(detect_peaks(x, 130.0), 130.0), 30.0, end_s=len(x) / 130.0)[:2]
        if w.quality == "good"
    ]

    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as bus:
        published = aiter(bus.subscribe(bus.key("operator/calibration"), Calibration))
        analyser = InProcessService(
            "hrv_analyser", analyser_main, AnalyserSettings(), tmp_path / "a", endpoint
        )
        await analyser.listening(bus, "ecg/samples")
        arm: list[bool] = []
        task = asyncio.ensure_future(calibrate(bus, 1.0, "s07", tmp_path, measured_sigma=False, arm=arm))
        moving = RobotState(t_ns=START_NS, seq=0, q=[0.0] * 6, qd=[0.1] * 6, tcp=[0.0] * 6, path_id="p", k=8,
                            mode="moving", state="moving")  # fmt: skip
        gateway = InProcessService(
            "ecg_gateway",
            gateway_main,
            GatewaySettings(record=str(csv), speed=40.0, start_ns=START_NS),
            tmp_path / "g",
            endpoint,
        )
        async with asyncio.timeout(30):
            while not arm:  # a robot working beside the person meanwhile (its state, as the executor's)
                put(bus, bus.key("robot/state"), moving)
                await asyncio.sleep(0.05)
            cal, level = await task
            _, sent = await anext(published)
        for svc in (gateway, analyser):
            await svc.close()
    assert level.good == len(offline) == 2
    assert cal.rr_rest_s == pytest.approx(np.mean([w.mean_rr_s for w in offline]), abs=1e-6)
    assert cal.sigma_rest_s == 0.14
    assert cal.subject == "s07"
    assert sent == cal
    screen = " ".join(calibration_screen(cal, level, False, arm))
    assert "NOT AT REST: the arm moved in" in screen
    assert "--posture working" in screen
    assert "NOT AT REST" not in " ".join(calibration_screen(cal, level, False, [False, False]))
    assert msgspec.json.decode((tmp_path / CALIBRATION_FILE).read_bytes(), type=Calibration) == cal


@needs_data
async def test_device_rr_only_source_gives_windows(tmp_path: Path, endpoint: str) -> None:
    from schemas import RrIntervals
    from tests.support.data import device_rr

    beats = read_record(str(ECG / "100"), fs=130.0).beats_s
    START_NS = now_ns() - 100 * 1_000_000_000  # 100 s of intervals that have happened
    beats = beats[beats < 100.0]
    expected = windows(intervals(beats), 30.0, start_s=float(beats[0]), end_s=float(beats[-1]))

    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as bus:
        wins = aiter(bus.subscribe(bus.key("hrv/window"), HrvWindow))
        analyser = InProcessService(
            "hrv_analyser", analyser_main, AnalyserSettings(input="rr"), tmp_path / "a", endpoint
        )
        await analyser.listening(bus, "ecg/rr")  # not its status: that can come before its subscription
        for i, (t, rr) in enumerate(device_rr(beats)):
            msg = RrIntervals(t_ns=START_NS + round(t * 1e9), seq=i, rr_s=rr)
            put(bus, bus.key("ecg/rr"), msg, block=True)
        got = []
        async with asyncio.timeout(10):
            while len(got) < len(expected) - 1:  # the last window closes only when data time passes it
                got.append((await anext(wins))[1])
        await analyser.close()
    for w, e in zip(got, expected, strict=False):
        assert w.start_ns - START_NS == pytest.approx(e.start_s * 1e9, abs=2)
        assert w.mean_rr_s == pytest.approx(e.mean_rr_s, abs=1e-9)
        assert w.n_beats == e.n_beats
        assert w.quality == e.quality == "good"
