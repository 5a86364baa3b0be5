"""A fake Polar H10 behind the GATT client interface ``PolarSource`` uses: it answers the PMD control
point like the strap and streams real PMD ECG frame bytes (73 int24 µV samples, the H10's 2000-epoch
clock) from a recording, so the whole BLE path runs without a strap. For tests and trying the gateway."""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Callable

import numpy as np

from common.hrv.polar import HR_MEASUREMENT, PMD_CONTROL, PMD_DATA
from services.ecg_gateway.polar import POLAR_EPOCH_NS
from services.ecg_gateway.sources import CHUNK, FS_HZ


def ecg_frame_bytes(last_sample_ns_polar: int, samples: list[int]) -> bytes:
    return (
        bytes([0])
        + struct.pack("<Q", last_sample_ns_polar)
        + bytes([0])
        + b"".join(int(s).to_bytes(3, "little", signed=True) for s in samples)
    )


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
    ) -> None:
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

    async def start_notify(self, uuid: str, callback: Callable) -> None:
        self.callbacks[uuid] = callback

    async def write_gatt_char(self, uuid: str, data: bytes, response: bool) -> None:
        if uuid == PMD_CONTROL and data[:2] == bytes([0x02, 0x00]):
            self.callbacks[PMD_CONTROL](None, bytearray([0xF0, 0x02, 0x00, 0x00, 0x00]))
            self._task = asyncio.ensure_future(self._stream())

    async def _stream(self) -> None:
        while (self.frame + 1) * CHUNK <= len(self.uv):
            if self.drop_after is not None and self.sent >= self.drop_after:
                self.on_disconnect()
                return
            if self.silent_after is not None and self.sent >= self.silent_after:
                return  # the link goes quiet with no disconnect callback
            i = self.frame * CHUNK
            last_ns = self.start_unix_ns + round((i + CHUNK - 1) * 1e9 / FS_HZ) - POLAR_EPOCH_NS
            if self.garbage_every and self.sent and self.sent % self.garbage_every == 0:
                self.callbacks[PMD_DATA](None, bytearray(b"\x00\x01\x02"))
            self.callbacks[PMD_DATA](
                None, bytearray(ecg_frame_bytes(last_ns, self.uv[i : i + CHUNK].tolist()))
            )
            if self.sent % 2 == 0 and HR_MEASUREMENT in self.callbacks:
                self.callbacks[HR_MEASUREMENT](None, bytearray([0x10, 72]) + struct.pack("<H", 820))
            self.frame += 1
            self.sent += 1
            await asyncio.sleep(CHUNK / FS_HZ / self.speed if self.speed else 0)

    async def disconnect(self) -> None:
        if self._task is not None:
            self._task.cancel()
