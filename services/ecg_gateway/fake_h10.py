"""A fake Polar H10 behind the GATT client interface ``PolarSource`` uses: it answers the PMD control
point like the strap and streams real PMD ECG frame bytes (73 int24 µV samples, the H10's 2000-epoch
clock) from a recording, and, once asked, accelerometer frames (frame type 1: int16 x, y, z in mg) on the
same clock, so the whole BLE path runs without a strap. For tests and trying the gateway."""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Callable

import numpy as np

from common.hrv.polar import HR_MEASUREMENT, PMD_ACC, PMD_CONTROL, PMD_DATA, PMD_ECG
from common.runtime.clock import pause
from services.ecg_gateway.polar import POLAR_EPOCH_NS
from services.ecg_gateway.sources import CHUNK, FS_HZ


def ecg_frame_bytes(last_sample_ns_polar: int, samples: list[int]) -> bytes:
    return (
        bytes([0])
        + struct.pack("<Q", last_sample_ns_polar)
        + bytes([0])
        + b"".join(int(s).to_bytes(3, "little", signed=True) for s in samples)
    )


def acc_frame_bytes(last_sample_ns_polar: int, xyz_mg: np.ndarray, frame_type: int = 1) -> bytes:
    """An accelerometer frame: frame type 0, 1 or 2 packs each axis in 1, 2 or 3 bytes."""
    width = frame_type + 1
    body = b"".join(int(v).to_bytes(width, "little", signed=True) for v in np.asarray(xyz_mg).ravel())
    return bytes([PMD_ACC]) + struct.pack("<Q", last_sample_ns_polar) + bytes([frame_type]) + body


class FakeH10:
    """One connection to the fake strap. ``frames`` are played from ``start``; after ``drop_after``
    frames the link drops (the disconnect callback fires); ``garbage_every`` injects a garbled frame."""

    def __init__(
        self,
        uv: np.ndarray,
        start_unix_ns: int,
        on_disconnect: Callable[[], None],
        speed: float = 0.0,
        start: int = 0,
        drop_after: int | None = None,
        garbage_every: int | None = None,
        silent_after: int | None = None,
        acc: np.ndarray | None = None,
        acc_hz: int = 25,
        acc_stops_after: int | None = None,
        rate_hz: float = FS_HZ,
        already_streaming: bool = False,
        mtu_size: int = 247,
    ) -> None:
        """``acc``: (n, 3) mg at ``acc_hz`` from the ECG's first sample; None: a strap that refuses it.
        ``acc_stops_after``: ECG frames after which the accelerometer goes quiet and ECG goes on.
        ``rate_hz``: the strap's own clock (a real H10's 130 Hz is off by up to about 1 %), which its
        timestamps follow. ``already_streaming``: still streaming from before a reconnect, it answers an
        ECG start with status 6, "already in state". ``mtu_size``: what the BLE link negotiated."""
        self.uv = np.rint(uv).astype(int)
        self.start_unix_ns = start_unix_ns
        self.on_disconnect = on_disconnect
        self.speed = speed
        self.frame = start
        self.drop_after = drop_after
        self.silent_after = silent_after
        self.garbage_every = garbage_every
        self.callbacks: dict[str, Callable] = {}
        self._task: asyncio.Task | None = None
        self.sent = 0
        self.acc, self.acc_hz, self.acc_stops_after = acc, acc_hz, acc_stops_after
        self.acc_on = False
        self.rate_hz, self.already_streaming, self.mtu_size = rate_hz, already_streaming, mtu_size
        self.acc_sent = int(start * CHUNK / FS_HZ * acc_hz)  # samples sent (a reconnect goes on from there)

    async def start_notify(self, uuid: str, callback: Callable) -> None:
        self.callbacks[uuid] = callback

    async def write_gatt_char(self, uuid: str, data: bytes, response: bool) -> None:
        if uuid == PMD_CONTROL and data[:2] == bytes([0x02, PMD_ECG]):
            status = 0x06 if self.already_streaming else 0x00
            self.callbacks[PMD_CONTROL](None, bytearray([0xF0, 0x02, PMD_ECG, status, 0x00]))
            self._task = asyncio.ensure_future(self._stream())
        elif uuid == PMD_CONTROL and data[:2] == bytes([0x02, PMD_ACC]):
            status = 0x00 if self.acc is not None else 0x05  # 5: not supported
            self.callbacks[PMD_CONTROL](None, bytearray([0xF0, 0x02, PMD_ACC, status, 0x00]))
            self.acc_on = self.acc is not None

    def _send_acc(self, until_s: float) -> None:
        """The accelerometer frames whose last sample is before ``until_s`` of the recording."""
        assert self.acc is not None
        per = self.acc_hz // 5  # 0.2 s frames
        while self.acc_sent + per <= len(self.acc) and (self.acc_sent + per - 1) / self.acc_hz <= until_s:
            i, self.acc_sent = self.acc_sent, self.acc_sent + per
            last_ns = self.start_unix_ns + round((i + per - 1) * 1e9 / self.acc_hz) - POLAR_EPOCH_NS
            self.callbacks[PMD_DATA](None, bytearray(acc_frame_bytes(last_ns, self.acc[i : i + per])))

    async def _stream(self) -> None:
        while (self.frame + 1) * CHUNK <= len(self.uv):
            if self.drop_after is not None and self.sent >= self.drop_after:
                self.on_disconnect()
                return
            if self.silent_after is not None and self.sent >= self.silent_after:
                return  # the link goes quiet with no disconnect callback
            i = self.frame * CHUNK
            last_ns = self.start_unix_ns + round((i + CHUNK - 1) * 1e9 / self.rate_hz) - POLAR_EPOCH_NS
            if self.garbage_every and self.sent and self.sent % self.garbage_every == 0:
                self.callbacks[PMD_DATA](None, bytearray(b"\x00\x01\x02"))
            self.callbacks[PMD_DATA](
                None, bytearray(ecg_frame_bytes(last_ns, self.uv[i : i + CHUNK].tolist()))
            )
            if self.acc_on and (self.acc_stops_after is None or self.sent < self.acc_stops_after):
                self._send_acc((i + CHUNK - 1) / FS_HZ)
            if self.sent % 2 == 0 and HR_MEASUREMENT in self.callbacks:
                self.callbacks[HR_MEASUREMENT](None, bytearray([0x10, 72]) + struct.pack("<H", 820))
            self.frame += 1
            self.sent += 1
            await pause(CHUNK / FS_HZ / self.speed if self.speed else 0)

    async def disconnect(self) -> None:
        if self._task is not None:
            self._task.cancel()
