"""Polar H10 GATT payloads parsed from bytes: every flag combination, truncation and garbage."""

from __future__ import annotations

import itertools
import struct

import pytest

from common.hrv.polar import (
    PMD_ACC,
    FrameError,
    acc_start_request,
    ecg_start_request,
    measurement_type,
    parse_acc_frame,
    parse_control_response,
    parse_ecg_frame,
    parse_heart_rate,
)


def hr_bytes(u16: bool, contact: bool | None, energy: int | None, rr: list[int]) -> bytes:
    flags = (0x01 if u16 else 0) | (0x04 | (0x02 if contact else 0) if contact is not None else 0)
    flags |= (0x08 if energy is not None else 0) | (0x10 if rr else 0)
    out = bytes([flags]) + (struct.pack("<H", 72) if u16 else bytes([72]))
    if energy is not None:
        out += struct.pack("<H", energy)
    return out + b"".join(struct.pack("<H", v) for v in rr)


@pytest.mark.parametrize(
    ("u16", "contact", "energy", "rr"),
    list(itertools.product([False, True], [None, False, True], [None, 300], [[], [820], [820, 1024, 790]])),
)
def test_every_heart_rate_flag_combination(
    u16: bool, contact: bool | None, energy: int | None, rr: list[int]
) -> None:
    hr = parse_heart_rate(hr_bytes(u16, contact, energy, rr))
    assert hr.bpm == 72
    assert hr.contact == contact
    assert hr.energy_kj == energy
    assert hr.rr_s == [v / 1024 for v in rr]


@pytest.mark.parametrize("data", [b"", b"\x01", b"\x01\x48", b"\x10\x48\x34", b"\x08\x48\x01"])
def test_truncated_heart_rate_payloads_are_frame_errors(data: bytes) -> None:
    with pytest.raises(FrameError):
        parse_heart_rate(data)


def ecg_frame(ts: int, samples: list[int]) -> bytes:
    return (
        bytes([0])
        + struct.pack("<Q", ts)
        + bytes([0])
        + b"".join(s.to_bytes(3, "little", signed=True) for s in samples)
    )


def test_an_ecg_frame_gives_its_timestamp_and_signed_int24_samples() -> None:
    f = parse_ecg_frame(ecg_frame(599_000_000_000, [0, 1, -1, 8_388_607, -8_388_608, -350]))
    assert f.timestamp_ns == 599_000_000_000
    assert f.samples_uv == [0, 1, -1, 8_388_607, -8_388_608, -350]


@pytest.mark.parametrize(
    "data",
    [
        b"",
        bytes(9),
        bytes([2]) + bytes(12),
        bytes([0]) + bytes(8) + bytes([1, 0, 0, 0]),
        ecg_frame(1, [5])[:-1],
        ecg_frame(1, []),
    ],
    ids=["empty", "short", "not ecg", "frame type", "partial sample", "no samples"],
)
def test_garbled_ecg_frames_are_frame_errors(data: bytes) -> None:
    with pytest.raises(FrameError):
        parse_ecg_frame(data)


def test_the_start_request_asks_for_130_hz_ecg_and_a_response_is_parsed() -> None:
    req = ecg_start_request()
    assert req[:2] == bytes([0x02, 0x00])
    assert struct.unpack_from("<H", req, 4)[0] == 130
    ok = parse_control_response(bytes([0xF0, 0x02, 0x00, 0x00, 0x00]))
    assert ok.ok
    assert ok.op == 0x02
    assert not parse_control_response(bytes([0xF0, 0x02, 0x00, 0x06])).ok
    with pytest.raises(FrameError):
        parse_control_response(bytes([0x02, 0x00]))


def test_the_accelerometer_start_request_asks_for_its_rate_16_bits_and_8_g() -> None:
    req = acc_start_request(50)
    # start, measurement 2; sample rate (0x00), one value, 50; resolution (0x01), 16; range (0x02), 8 g
    assert req == bytes([0x02, 0x02, 0x00, 0x01, 50, 0, 0x01, 0x01, 16, 0, 0x02, 0x01, 8, 0])
    with pytest.raises(ValueError, match="25, 50, 100 or 200"):
        acc_start_request(52)


def acc_frame(ts: int, frame_type: int, xyz: list[tuple[int, int, int]]) -> bytes:
    fmt = {0: "<3b", 1: "<3h"}
    if frame_type in fmt:
        body = b"".join(struct.pack(fmt[frame_type], *v) for v in xyz)
    else:  # int24: three bytes each, little-endian, signed
        body = b"".join(int(a).to_bytes(3, "little", signed=True) for v in xyz for a in v)
    return bytes([PMD_ACC]) + struct.pack("<Q", ts) + bytes([frame_type]) + body


@pytest.mark.parametrize(
    ("frame_type", "xyz"),
    [
        (0, [(-100, 3, 127), (-128, 0, 1)]),
        (1, [(-993, 30, -237), (-1000, 29, -239), (32_767, -32_768, 0)]),
        (2, [(-993, 30, -237), (8_388_607, -8_388_608, 5)]),
    ],
    ids=["int8", "int16 (the H10's)", "int24"],
)
def test_an_accelerometer_frame_gives_its_timestamp_and_signed_x_y_z(
    frame_type: int, xyz: list[tuple[int, int, int]]
) -> None:
    data = acc_frame(674_467_737_249_392_677, frame_type, xyz)
    assert measurement_type(data) == PMD_ACC
    f = parse_acc_frame(data)
    assert f.timestamp_ns == 674_467_737_249_392_677
    assert f.samples_mg == xyz
    with pytest.raises(FrameError):
        measurement_type(b"")


@pytest.mark.parametrize(
    "data",
    [
        b"",
        bytes([PMD_ACC]) + bytes(8),
        acc_frame(1, 1, [(1, 2, 3)])[:-1],  # an axis cut short
        acc_frame(1, 1, [(1, 2, 3)])[:-2],  # a whole sample less one axis
        acc_frame(1, 1, []),
        acc_frame(1, 1, [(1, 2, 3)])[:9] + bytes([0x81]) + bytes(6),  # delta-compressed
        acc_frame(1, 1, [(1, 2, 3)])[:9] + bytes([0x07]) + bytes(6),  # unknown frame type
        bytes([0x00]) + acc_frame(1, 1, [(1, 2, 3)])[1:],  # an ECG frame
    ],
    ids=[
        "empty",
        "short",
        "partial axis",
        "partial sample",
        "no samples",
        "compressed",
        "unknown type",
        "ecg",
    ],
)
def test_garbled_accelerometer_frames_are_frame_errors(data: bytes) -> None:
    with pytest.raises(FrameError):
        parse_acc_frame(data)
