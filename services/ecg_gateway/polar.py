"""The Polar H10 over BLE (bleak), behind ``EcgSource`` (DESIGN §6, §11).

The source asks a *connector* for a connected GATT client. The real one scans with bleak and connects
through bleak-retry-connector's ``establish_connection``; tests pass a fake client with the same methods
(``fake_h10.py``). Then it starts the PMD ECG stream at 130 Hz and the heart-rate notifications, and,
once the strap has started ECG, its accelerometer (``acc_hz``; None: not asked); it yields chunks on
data time. The H10's clock counts from 2000-01-01 and stamps each frame's last sample, ECG and
accelerometer alike. A strap that refuses the accelerometer keeps streaming ECG (``accelerometer``
turns False, and the gateway says so).

A link can go silent without a disconnect callback, so a data-gap watchdog reconnects after
``gap_timeout_s`` without a frame. Connection failures are retried with back-off. The first chunk after
any interruption carries ``gap=True``: the gap is reported, never papered over. The H10 can take 20–30 s
to restart its ECG stream; that is a gap, not an error.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Protocol, cast

from common.hrv.polar import (
    HR_MEASUREMENT,
    PMD_ACC,
    PMD_CONTROL,
    PMD_DATA,
    PMD_ECG,
    FrameError,
    acc_start_request,
    ecg_start_request,
    measurement_type,
    parse_acc_frame,
    parse_control_response,
    parse_ecg_frame,
    parse_heart_rate,
)
from services.ecg_gateway.sources import FS_HZ, AccSamples, Chunk, EcgSource, Item, RrChunk

log = logging.getLogger("cadence.ecg_gateway.polar")

POLAR_EPOCH_NS = 946_684_800_000_000_000  # 2000-01-01T00:00:00Z in Unix ns: the H10's clock origin
BACKOFF_S = (1.0, 2.0, 4.0, 8.0, 16.0, 30.0)


class StrapError(Exception):
    """The strap could not be found, connected or started; the message says which."""


class GattClient(Protocol):
    async def start_notify(self, uuid: str, callback: Callable[[object, bytearray], None]) -> None: ...

    async def write_gatt_char(self, uuid: str, data: bytes, response: bool) -> None: ...

    async def disconnect(self) -> None: ...


Connector = Callable[[Callable[[], None]], Awaitable[GattClient]]


def bleak_connector(strap: str, scan_timeout_s: float = 10.0) -> Connector:
    """Connect with bleak: ``strap`` is a MAC address or (part of) the advertised name, e.g. 'Polar H10'."""

    async def connect(on_disconnect: Callable[[], None]) -> GattClient:
        from bleak import BleakScanner
        from bleak.exc import BleakError
        from bleak_retry_connector import BleakClientWithServiceCache, establish_connection

        try:
            if re.fullmatch(r"([0-9A-Fa-f]{2}:){5}[0-9A-Fa-f]{2}", strap):
                device = await BleakScanner.find_device_by_address(strap, timeout=scan_timeout_s)
            else:
                device = await BleakScanner.find_device_by_filter(
                    lambda d, _ad: d.name is not None and strap in d.name, timeout=scan_timeout_s
                )
            if device is None:
                raise StrapError(f"no strap matching {strap!r} within {scan_timeout_s:.0f} s of scanning")
            client = await establish_connection(
                BleakClientWithServiceCache,
                device,
                device.name or strap,
                disconnected_callback=lambda _client: on_disconnect(),
            )
        except BleakError as exc:
            raise StrapError(f"BLE: {exc}") from exc
        # bleak's client is a GattClient; its callbacks take wider types than the protocol names
        return cast(GattClient, client)

    return connect


def _feeder(queue: asyncio.Queue, kind: str | None) -> Callable[..., None]:
    """A callback bound to one connection's queue: a late callback of an old client cannot reach the next
    connection's. ``kind=None`` is the disconnect callback (it puts the end marker)."""
    if kind is None:
        return lambda *_: queue.put_nowait(None)
    return lambda _char, data: queue.put_nowait((kind, bytes(data)))


class PolarSource(EcgSource):
    name = "polar"

    def __init__(
        self,
        connector: Connector,
        gap_timeout_s: float = 5.0,
        backoff_s: tuple[float, ...] = BACKOFF_S,
        acc_hz: int | None = 25,
    ):
        self.connector = connector
        self.gap_timeout_s = gap_timeout_s
        self.backoff_s = backoff_s
        self.acc_hz = acc_hz
        self.accelerometer = acc_hz is not None
        self.bad_frames = 0
        self.reconnects = 0
        self.acc_expected_ns: int | None = None
        self.acc_gap = False  # accelerometer samples were lost (a reconnect) before the next chunk

    def _acc(self, data: bytes) -> AccSamples:
        assert self.acc_hz is not None
        frame = parse_acc_frame(data)
        n, fs = len(frame.samples_mg), float(self.acc_hz)
        first_ns = POLAR_EPOCH_NS + frame.timestamp_ns - round((n - 1) * 1e9 / fs)
        expected, self.acc_expected_ns = self.acc_expected_ns, first_ns + round(n * 1e9 / fs)
        gap = self.acc_gap or (expected is not None and abs(first_ns - expected) > 1.5e9 / fs)
        self.acc_gap = False
        return AccSamples(first_ns, fs, frame.samples_mg, gap)

    async def chunks(self) -> AsyncIterator[Item]:
        attempt = 0
        gap = False
        expected_ns: int | None = None
        while True:
            queue: asyncio.Queue[tuple[str, bytes] | None] = asyncio.Queue()
            try:
                client = await self.connector(_feeder(queue, None))
            except (StrapError, TimeoutError, OSError) as exc:
                delay = self.backoff_s[min(attempt, len(self.backoff_s) - 1)]
                log.warning("strap not connected (%s); trying again in %.0f s", exc, delay)
                attempt += 1
                gap = gap or expected_ns is not None
                await asyncio.sleep(delay)
                continue
            attempt = 0
            try:
                await client.start_notify(PMD_CONTROL, _feeder(queue, "control"))
                await client.start_notify(PMD_DATA, _feeder(queue, "pmd"))
                await client.start_notify(HR_MEASUREMENT, _feeder(queue, "hr"))
                await client.write_gatt_char(PMD_CONTROL, ecg_start_request(), response=True)
                while True:
                    # the data-gap watchdog: a silent link is a lost link
                    item = await asyncio.wait_for(queue.get(), self.gap_timeout_s)
                    if item is None:
                        raise StrapError("the strap disconnected")
                    kind, data = item
                    try:
                        if kind == "control":
                            resp = parse_control_response(data)
                            if resp.measurement == PMD_ACC and not resp.ok:
                                log.warning("the strap refused its accelerometer (status %d): ECG only",
                                            resp.status)  # fmt: skip
                                self.accelerometer = False
                            elif not resp.ok:
                                raise StrapError(f"the strap refused to start ECG (status {resp.status})")
                            elif resp.measurement == PMD_ECG and self.accelerometer and self.acc_hz:
                                request = acc_start_request(self.acc_hz)
                                await client.write_gatt_char(PMD_CONTROL, request, response=True)
                        elif kind == "pmd" and measurement_type(data) == PMD_ACC:
                            if self.accelerometer:
                                yield self._acc(data)
                        elif kind == "hr":
                            hr = parse_heart_rate(data)
                            if hr.rr_s and expected_ns is not None:
                                yield RrChunk(expected_ns, hr.rr_s)
                        else:
                            frame = parse_ecg_frame(data)
                            n = len(frame.samples_uv)
                            first_ns = POLAR_EPOCH_NS + frame.timestamp_ns - round((n - 1) * 1e9 / FS_HZ)
                            if expected_ns is not None and abs(first_ns - expected_ns) > 1.5e9 / FS_HZ:
                                gap = True
                            expected_ns = first_ns + round(n * 1e9 / FS_HZ)
                            yield Chunk(first_ns, frame.samples_uv, gap)
                            gap = False
                    except FrameError as exc:
                        self.bad_frames += 1
                        log.debug("skipped a bad %s payload: %s", kind, exc)
            except (StrapError, TimeoutError, OSError) as exc:
                log.warning("ECG stream interrupted (%s); reconnecting", exc or "no data")
                self.reconnects += 1
                gap = True
                self.acc_gap, self.acc_expected_ns = self.acc_expected_ns is not None, None
            finally:
                with contextlib.suppress(Exception):
                    await client.disconnect()
