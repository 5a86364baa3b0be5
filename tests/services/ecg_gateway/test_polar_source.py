"""The Polar H10 source through its whole BLE path, against a fake strap that speaks real PMD bytes."""

from __future__ import annotations

import numpy as np
import pytest

from services.ecg_gateway.fake_h10 import FakeH10
from services.ecg_gateway.polar import PolarSource, StrapError
from services.ecg_gateway.sources import CHUNK, AccSamples, Chunk, RrChunk

pytestmark = pytest.mark.asyncio
START = 1_800_000_000_000_000_000
UV = (np.sin(np.arange(CHUNK * 200) / 7.0) * 900).round()


def connector(*plans: dict, fail_first: int = 0):
    """A connector that hands out one fake connection per plan, after ``fail_first`` failures."""
    calls = {"n": 0}

    async def connect(on_disconnect):
        calls["n"] += 1
        if calls["n"] <= fail_first:
            raise StrapError("no strap in range")
        plan = plans[min(calls["n"] - fail_first - 1, len(plans) - 1)]
        return FakeH10(UV, START, on_disconnect, **plan)

    return connect


async def take(source: PolarSource, n: int) -> tuple[list[Chunk], list[RrChunk]]:
    chunks, rr = [], []
    async for c in source.chunks():
        (chunks if isinstance(c, Chunk) else rr).append(c)
        if len(chunks) == n:
            break
    return chunks, rr


def frame_of(c: Chunk) -> int:
    return round((c.t_ns - START) * 130 / 1e9) // CHUNK


async def test_frames_become_chunks_on_data_time_with_device_rr() -> None:
    chunks, rr = await take(PolarSource(connector({})), 40)
    assert [frame_of(c) for c in chunks] == list(range(40))
    assert chunks[5].samples_uv == UV[5 * CHUNK : 6 * CHUNK].astype(int).tolist()
    assert not any(c.gap for c in chunks)
    assert rr
    assert rr[0].rr_s == [820 / 1024]


async def test_garbled_frames_are_counted_and_skipped() -> None:
    source = PolarSource(connector({"garbage_every": 5}))
    chunks, _ = await take(source, 30)
    assert [frame_of(c) for c in chunks] == list(range(30))
    assert source.bad_frames >= 5


async def test_a_dropped_link_reconnects_and_reports_the_gap() -> None:
    source = PolarSource(connector({"drop_after": 20}, {"start": 30}))
    chunks, _ = await take(source, 40)
    frames = [frame_of(c) for c in chunks]
    assert frames[:20] == list(range(20))
    assert frames[20] == 30
    assert chunks[20].gap
    assert not any(c.gap for i, c in enumerate(chunks) if i != 20)
    assert source.reconnects == 1


async def test_a_silent_link_is_caught_by_the_data_gap_watchdog() -> None:
    source = PolarSource(connector({"silent_after": 10}, {"start": 12}), gap_timeout_s=0.2)
    chunks, _ = await take(source, 15)
    assert frame_of(chunks[10]) == 12
    assert chunks[10].gap
    assert source.reconnects == 1


async def test_a_strap_out_of_range_is_retried_with_back_off() -> None:
    source = PolarSource(connector({}, fail_first=2), backoff_s=(0.01, 0.02))
    chunks, _ = await take(source, 5)
    assert [frame_of(c) for c in chunks] == [0, 1, 2, 3, 4]
    assert not chunks[0].gap


# 2 s of a person leaning and swinging: x, y, z in mg at 25 Hz, from the ECG's first sample
ACC = (
    np.column_stack(
        [-990 + 200 * np.sin(np.arange(25 * 60) / 3.0), 30 + np.arange(25 * 60) % 7, np.full(25 * 60, -240)]
    )
    .round()
    .astype(int)
)


async def take_all(source: PolarSource, n_ecg: int) -> tuple[list[Chunk], list[AccSamples]]:
    ecg, acc = [], []
    async for c in source.chunks():
        if isinstance(c, AccSamples):
            acc.append(c)
        elif isinstance(c, Chunk):
            ecg.append(c)
            if len(ecg) == n_ecg:
                break
    return ecg, acc


async def test_the_accelerometer_comes_beside_ecg_on_the_same_clock_byte_for_byte() -> None:
    """The strap is asked for its accelerometer once it has started ECG; every sample arrives as sent
    (int16 frames), each chunk's data time on the ECG's clock (the H10's 2000 epoch, last-sample stamps)."""
    source = PolarSource(connector({"acc": ACC}), acc_hz=25)
    ecg, acc = await take_all(source, 80)
    assert source.accelerometer
    assert ecg[0].t_ns == START
    got = np.array([v for c in acc for v in c.xyz_mg])
    assert len(got) >= 25 * 40
    assert (got == ACC[: len(got)]).all()
    for c in acc:  # 0.2 s frames, each starting where the samples before it ended
        i = round((c.t_ns - START) * 25 / 1e9)
        assert abs(c.t_ns - (START + round(i * 1e9 / 25))) <= 1
        assert c.fs_hz == 25.0
        assert not c.gap
    assert [round((c.t_ns - START) * 25 / 1e9) for c in acc] == list(range(0, 5 * len(acc), 5))


async def test_a_strap_that_refuses_its_accelerometer_or_stops_it_keeps_streaming_ecg() -> None:
    refusing = PolarSource(connector({"acc": None}), acc_hz=25)
    ecg, acc = await take_all(refusing, 40)
    assert len(ecg) == 40
    assert acc == []
    assert not refusing.accelerometer
    stopping = PolarSource(connector({"acc": ACC, "acc_stops_after": 10}), acc_hz=25)
    ecg, acc = await take_all(stopping, 40)
    assert len(ecg) == 40
    assert 0 < len(acc) <= 10 * 73 / 130 * 5 + 1
    assert acc[-1].t_ns < ecg[-1].t_ns - 10 * 10**9  # the ECG went on well past it


async def test_after_a_dropped_link_the_accelerometer_says_its_gap() -> None:
    source = PolarSource(connector({"acc": ACC, "drop_after": 20}, {"acc": ACC, "start": 30}), acc_hz=25)
    ecg, acc = await take_all(source, 45)
    gaps = [c for c in acc if c.gap]
    assert len(gaps) == 1
    assert gaps[0].t_ns > ecg[19].t_ns  # the first after the reconnect


async def test_accelerometer_frames_of_an_unknown_type_or_stream_are_counted_and_skipped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Frames the strap should not send (a compressed accelerometer frame, a stream nobody asked for)
    are bad frames: counted and skipped; the ECG goes on, and the samples they held show as a gap."""
    from services.ecg_gateway import fake_h10

    real, sent = fake_h10.acc_frame_bytes, [0]

    def sometimes_odd(last_ns: int, xyz: np.ndarray, frame_type: int = 1) -> bytes:
        sent[0] += 1
        if sent[0] % 4 == 0:
            return real(last_ns, xyz)[:9] + bytes([0x81]) + bytes(30)  # delta-compressed
        if sent[0] % 4 == 1:
            return bytes([0x09]) + real(last_ns, xyz)[1:]  # measurement type 9
        return real(last_ns, xyz)

    monkeypatch.setattr(fake_h10, "acc_frame_bytes", sometimes_odd)
    source = PolarSource(connector({"acc": ACC}), acc_hz=25)
    ecg, acc = await take_all(source, 40)
    assert [frame_of(c) for c in ecg] == list(range(40))
    assert source.bad_frames >= 20
    assert len(acc) >= 20
    assert sum(c.gap for c in acc) >= 10


async def test_the_straps_own_rate_is_measured_and_its_samples_keep_to_its_clock() -> None:
    """The H10's 130 Hz is accurate to about 1 %: counted at the nominal rate its samples drift 5 ms a
    frame from its timestamps, and the analyser took each 11 ms of drift for a gap (issue 40)."""
    from common.hrv.stream import HrvStream

    source = PolarSource(connector({"rate_hz": 131.3}))
    chunks, _ = await take(source, 100)
    assert source.rate_hz == pytest.approx(131.3, abs=0.01)
    assert {c.fs_hz for c in chunks} == {source.rate_hz}
    assert not any(c.gap for c in chunks)
    last = START + round((100 * CHUNK - 1) * 1e9 / 131.3)
    assert chunks[-1].t_ns + round((CHUNK - 1) * 1e9 / chunks[-1].fs_hz) == pytest.approx(last, abs=1e5)
    stream = HrvStream(chunks[0].fs_hz, 30.0)
    for c in chunks:
        stream.feed((c.t_ns - START) / 1e9, c.samples_uv, c.gap)
    assert stream.segments == 1  # one stream: no drift taken for a gap


async def test_a_strap_still_streaming_after_a_reconnect_is_streaming_not_refusing() -> None:
    """It answers an ECG start with status 6, "already in state": once "refused to start ECG" and a
    reconnect loop."""
    source = PolarSource(connector({"already_streaming": True}))
    chunks, _ = await take(source, 20)
    assert len(chunks) == 20
    assert source.reconnects == 0


async def test_a_link_whose_mtu_is_too_small_for_ecg_frames_is_said(caplog: pytest.LogCaptureFixture) -> None:
    source = PolarSource(connector({"mtu_size": 23}))
    await take(source, 10)
    assert source.mtu == 23
    assert "MTU is 23 bytes; the H10's ECG frames need 232" in caplog.text
