"""Pure parsing of the Polar H10's GATT payloads (DESIGN §6), tested from bytes; no BLE here.

- Heart Rate Measurement (service 0x180D, characteristic 0x2A37): flags, heart rate (uint8 or uint16),
  optional energy expended, optional RR intervals in 1/1024 s.
- Polar Measurement Data (PMD) service: control-point requests and responses, and data frames: a
  measurement type, a uint64 timestamp in ns of the frame's last sample, a frame type, then samples. ECG
  is measurement type 0 (frame type 0: int24 µV samples at 130 Hz); the accelerometer is type 2, x, y, z
  in mg, each an int8, int16 or int24 by frame type 0, 1 or 2 (the H10 sends type 1). A frame type with
  its top bit set is delta-compressed: the H10 does not send it for these streams, so it is refused.

A truncated or garbled payload raises ``FrameError``; the gateway counts it and skips the frame.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

HR_SERVICE = "0000180d-0000-1000-8000-00805f9b34fb"
HR_MEASUREMENT = "00002a37-0000-1000-8000-00805f9b34fb"
PMD_SERVICE = "fb005c80-02e7-f387-1cad-8acd2d8df0c8"
PMD_CONTROL = "fb005c81-02e7-f387-1cad-8acd2d8df0c8"
PMD_DATA = "fb005c82-02e7-f387-1cad-8acd2d8df0c8"

PMD_ECG = 0x00
PMD_ACC = 0x02
ECG_FS_HZ = 130
ACC_RANGE_G = 8  # ±8 g: a person's trunk stays far inside it
_OP_GET_SETTINGS, _OP_START, _OP_STOP = 0x01, 0x02, 0x03
_SETTING_SAMPLE_RATE, _SETTING_RESOLUTION, _SETTING_RANGE = 0x00, 0x01, 0x02


class FrameError(ValueError):
    """A payload that is not what its characteristic carries (too short, unknown type, bad length)."""


@dataclass(frozen=True, slots=True)
class HeartRate:
    bpm: int
    contact: bool | None  # None: the sensor does not report contact
    energy_kj: int | None
    rr_s: list[float]


def parse_heart_rate(data: bytes) -> HeartRate:
    if len(data) < 2:
        raise FrameError(f"heart rate measurement of {len(data)} bytes")
    flags = data[0]
    i = 1
    if flags & 0x01:
        if len(data) < 3:
            raise FrameError("uint16 heart rate truncated")
        bpm = struct.unpack_from("<H", data, i)[0]
        i += 2
    else:
        bpm = data[i]
        i += 1
    contact = bool(flags & 0x02) if flags & 0x04 else None
    energy = None
    if flags & 0x08:
        if len(data) < i + 2:
            raise FrameError("energy expended truncated")
        energy = struct.unpack_from("<H", data, i)[0]
        i += 2
    rr: list[float] = []
    if flags & 0x10:
        rest = data[i:]
        if len(rest) % 2:
            raise FrameError("RR intervals truncated")
        rr = [v / 1024.0 for (v,) in struct.iter_unpack("<H", rest)]
    return HeartRate(bpm, contact, energy, rr)


def ecg_start_request() -> bytes:
    """Control-point request: start ECG at 130 Hz, 14-bit resolution (the H10's only ECG setting)."""
    return (
        bytes([_OP_START, PMD_ECG, _SETTING_SAMPLE_RATE, 0x01])
        + struct.pack("<H", ECG_FS_HZ)
        + bytes([_SETTING_RESOLUTION, 0x01])
        + struct.pack("<H", 14)
    )


def ecg_stop_request() -> bytes:
    return bytes([_OP_STOP, PMD_ECG])


def acc_start_request(fs_hz: int = 25) -> bytes:
    """Control-point request: start the accelerometer at ``fs_hz`` (25, 50, 100 or 200), 16 bits, ±8 g."""
    if fs_hz not in (25, 50, 100, 200):
        raise ValueError(f"the H10's accelerometer runs at 25, 50, 100 or 200 Hz, not {fs_hz}")
    return (
        bytes([_OP_START, PMD_ACC, _SETTING_SAMPLE_RATE, 0x01])
        + struct.pack("<H", fs_hz)
        + bytes([_SETTING_RESOLUTION, 0x01])
        + struct.pack("<H", 16)
        + bytes([_SETTING_RANGE, 0x01])
        + struct.pack("<H", ACC_RANGE_G)
    )


@dataclass(frozen=True, slots=True)
class ControlResponse:
    op: int
    measurement: int
    status: int  # 0 = success

    @property
    def ok(self) -> bool:
        return self.status == 0


def parse_control_response(data: bytes) -> ControlResponse:
    """Responses start with 0xF0, then the op code, the measurement type and the status."""
    if len(data) < 4 or data[0] != 0xF0:
        raise FrameError(f"not a PMD control-point response: {data[:4].hex()}")
    return ControlResponse(data[1], data[2], data[3])


@dataclass(frozen=True, slots=True)
class EcgFrame:
    timestamp_ns: int  # sensor clock, time of the last sample
    samples_uv: list[int]


def _frame(data: bytes, measurement: int, what: str) -> tuple[int, int, bytes]:
    """A data frame's timestamp, frame type and samples' bytes, once it is one of ``measurement``."""
    if len(data) < 10:
        raise FrameError(f"PMD frame of {len(data)} bytes")
    if data[0] != measurement:
        raise FrameError(f"PMD measurement type {data[0]} is not {what}")
    return struct.unpack_from("<Q", data, 1)[0], data[9], data[10:]


def parse_ecg_frame(data: bytes) -> EcgFrame:
    ts, frame_type, body = _frame(data, PMD_ECG, "ECG")
    if frame_type != 0x00:
        raise FrameError(f"ECG frame type {frame_type} is not supported (expected 0: raw int24)")
    if len(body) % 3 or not body:
        raise FrameError(f"ECG payload of {len(body)} bytes is not a whole number of int24 samples")
    samples = [int.from_bytes(body[k : k + 3], "little", signed=True) for k in range(0, len(body), 3)]
    return EcgFrame(ts, samples)


@dataclass(frozen=True, slots=True)
class AccFrame:
    timestamp_ns: int  # sensor clock, time of the last sample
    samples_mg: list[tuple[int, int, int]]  # x, y, z


_ACC_BYTES = {0x00: 1, 0x01: 2, 0x02: 3}  # frame type: bytes per axis value


def measurement_type(data: bytes) -> int:
    """What a PMD data frame carries (its first byte): ``PMD_ECG``, ``PMD_ACC``, or another stream."""
    if not data:
        raise FrameError("empty PMD frame")
    return data[0]


def parse_acc_frame(data: bytes) -> AccFrame:
    ts, frame_type, body = _frame(data, PMD_ACC, "the accelerometer")
    width = _ACC_BYTES.get(frame_type)
    if width is None:
        what = "a compressed frame" if frame_type & 0x80 else "unknown"
        raise FrameError(f"accelerometer frame type {frame_type:#04x} is not supported ({what})")
    step = 3 * width
    if len(body) % step or not body:
        raise FrameError(f"accelerometer payload of {len(body)} bytes is not whole x, y, z samples")
    values = [int.from_bytes(body[k : k + width], "little", signed=True) for k in range(0, len(body), width)]
    return AccFrame(ts, [(values[i], values[i + 1], values[i + 2]) for i in range(0, len(values), 3)])
