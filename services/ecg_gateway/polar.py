"""The Polar H10 over BLE (bleak), behind ``EcgSource`` (DESIGN §6, §11).

The source asks a *connector* for a connected GATT client. The real one scans with bleak and connects
through bleak-retry-connector's ``establish_connection``; tests pass a fake client with the same methods
(``fake_h10.py``). Then it starts the PMD ECG stream at 130 Hz and the heart-rate notifications, and,
once the strap has started ECG, its accelerometer (``acc_hz``; None: not asked); it yields chunks on
data time. The H10's clock counts from 2000-01-01 and stamps each frame's last sample, ECG and
accelerometer alike. A strap that refuses the accelerometer keeps streaming ECG (``accelerometer``
turns False, and the gateway says so).

The strap's 130 Hz is its own crystal's, accurate to about 1 %: the rate is measured from the frames'
timestamps (the first ``RATE_FRAMES`` frames, once per strap) and sent with the samples, so that data time
counted in samples keeps to the strap's clock (at the nominal rate it drifts 5 ms a frame, and the
analyser took each drift past 11 ms for a gap). A strap still streaming from before a reconnect answers a
start with "already in state" (6): that is streaming, not a refusal. PMD's ECG frames need a BLE MTU of
232 bytes; a link that says it has less is told in one line (frames may not come).

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
from common.runtime.clock import pause
from services.ecg_gateway.sources import FS_HZ, AccSamples, Chunk, EcgSource, Item, RrChunk

log = logging.getLogger("cadence.ecg_gateway.polar")

POLAR_EPOCH_NS = 946_684_800_000_000_000  # 2000-01-01T00:00:00Z in Unix ns: the H10's clock origin
BACKOFF_S = (1.0, 2.0, 4.0, 8.0, 16.0, 30.0)
ALREADY_IN_STATE = 6  # PMD control status: the measurement runs already (still streaming after a reconnect)
RATE_FRAMES = 5  # ECG frames whose timestamps measure the strap's own rate (2.2 s of samples)
RATE_TOLERANCE = 0.02  # a measured rate further from 130 Hz than this is a bad measurement, not a crystal
MIN_MTU = 232  # an H10 ECG frame (229 bytes: 73 int24 samples and a header) with ATT's 3


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
        self.rate_hz: float | None = None  # the strap's own ECG rate, measured once from its timestamps
        self.mtu: int | None = None

    def measure_rate(self, frames: list[tuple[int, list[int]]]) -> float:
        """The rate the frames' timestamps (each frame's last sample) give, to 0.01 Hz; the nominal one,
        said, when they give nothing a strap's crystal could."""
        samples = sum(len(s) for _, s in frames[1:])
        dt_ns = frames[-1][0] - frames[0][0]
        measured = samples * 1e9 / dt_ns if dt_ns > 0 else 0.0
        if abs(measured / FS_HZ - 1.0) <= RATE_TOLERANCE:
            return round(measured, 2)
        log.warning("the strap's timestamps give %.2f Hz, not a 130 Hz crystal's: taking 130 Hz", measured)
        return FS_HZ

    async def check_mtu(self, client: GattClient) -> None:
        """PMD's ECG frames need MIN_MTU; a link that says less is told (once per connection). BlueZ says
        23 until asked (bleak's backend acquires it); a value that cannot be read is not guessed."""
        backend = getattr(client, "_backend", None)
        acquire = getattr(backend, "_acquire_mtu", None)
        if acquire is not None:
            with contextlib.suppress(Exception):
                await acquire()
        mtu = getattr(client, "mtu_size", None)
        self.mtu = mtu if isinstance(mtu, int) else None
        if self.mtu is not None and self.mtu < MIN_MTU:
            why = "they may not come (use a BLE adapter or BlueZ that negotiates more)"
            log.warning(
                "the BLE link's MTU is %d bytes; the H10's ECG frames need %d: %s", self.mtu, MIN_MTU, why
            )

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
                await pause(delay)
                continue
            attempt = 0
            held: list[tuple[int, list[int]]] = []  # the first frames, while the rate is measured
            try:
                await self.check_mtu(client)
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
                            running = resp.ok or resp.status == ALREADY_IN_STATE
                            if resp.status == ALREADY_IN_STATE:
                                log.info(
                                    "the strap was still streaming (measurement %d): going on",
                                    resp.measurement,
                                )
                            if resp.measurement == PMD_ACC and not running:
                                log.warning("the strap refused its accelerometer (status %d): ECG only",
                                            resp.status)  # fmt: skip
                                self.accelerometer = False
                            elif not running:
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
                            held.append((POLAR_EPOCH_NS + frame.timestamp_ns, frame.samples_uv))
                            if self.rate_hz is None:
                                if len(held) < RATE_FRAMES:
                                    continue
                                self.rate_hz = self.measure_rate(held)
                                log.info("the strap's ECG runs at %.2f Hz (its own clock)", self.rate_hz)
                            fs = self.rate_hz
                            for last_ns, samples in held:
                                n = len(samples)
                                first_ns = last_ns - round((n - 1) * 1e9 / fs)
                                if expected_ns is not None and abs(first_ns - expected_ns) > 1.5e9 / fs:
                                    gap = True
                                expected_ns = first_ns + round(n * 1e9 / fs)
                                yield Chunk(first_ns, samples, gap, fs)
                                gap = False
                            held.clear()
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
