"""ecg_gateway: an ECG source → ``ecg/samples``, ``ecg/rr`` and the strap's accelerometer, ``ecg/acc``
(DESIGN §1, §6). Sources behind one interface: ``polar`` (the H10 over BLE), ``replay`` (a recording,
with a Polar accelerometer export beside it if there is one) and ``e4`` (an Empatica E4 export: RR
intervals with gaps, no ECG; the analyser reads it with ``input = "rr"``). A cell without a strap runs
the operator twin (services/operator_twin) in this service's place.

A source without an accelerometer, or whose accelerometer stops while its ECG goes on, works as before
(the windows carry no movement, and Alg. 1 reads every window as it always did); the status says so."""

from __future__ import annotations

import logging
import sys
from collections.abc import AsyncIterator
from typing import Annotated, Literal

import msgspec

from common.runtime.config import CommonSettings
from common.runtime.errors import ConfigError
from common.runtime.node import Node, Out, node_main
from common.runtime.service import service_main
from schemas.base import TimeNs
from schemas.ecg import AccChunk, EcgChunk, RrIntervals
from schemas.topology import ECG_RR, ECG_SAMPLES
from services.ecg_gateway.polar import PolarSource, bleak_connector
from services.ecg_gateway.sources import AccSamples, E4Source, EcgSource, ReplaySource, RrChunk
from services.registry import GATEWAY

NAME = GATEWAY.name
LISTENER_WAIT_S = 30.0
ACC_SILENT_S = 5.0  # ECG this far past the accelerometer's last sample: it has stopped
log = logging.getLogger("cadence.ecg_gateway")


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    source: Literal["replay", "polar", "e4"] = "replay"  # e4: an Empatica E4 export folder in ``record``
    strap: str = "Polar H10"  # polar: MAC address or (part of) the advertised name
    gap_timeout_s: Annotated[float, msgspec.Meta(ge=0.5, le=300.0)] = 5.0  # polar: reconnect after this
    record: str | None = None  # replay: WFDB record path without extension, or a CSV
    speed: Annotated[float, msgspec.Meta(ge=0.0, le=1000.0)] = 1.0  # replay: × real time; 0 = at once
    start_ns: TimeNs | None = None  # replay: data time of the first sample (default: now)
    acc_record: str | None = None  # replay: a Polar Sensor Logger accelerometer export (…_ACC.txt)
    acc_hz: Literal[25, 50, 100, 200, 0] = 25  # polar: the accelerometer's rate; 0: do not ask for it
    e4_accelerometer: bool = False  # e4: send the wrist's accelerometer too (sources.py E4Source: why not)


def make_source(settings: Settings) -> EcgSource:
    if settings.source == "polar":
        acc_hz = settings.acc_hz or None
        return PolarSource(bleak_connector(settings.strap), settings.gap_timeout_s, acc_hz=acc_hz)
    if settings.record is None:
        what = "an E4 export folder" if settings.source == "e4" else "WFDB path or CSV"
        raise ConfigError(f"[{NAME}] record: the {settings.source} source needs a record ({what})")
    if settings.source == "e4":
        return E4Source(settings.record, settings.speed, settings.start_ns, settings.e4_accelerometer)
    return ReplaySource(settings.record, settings.speed, settings.start_ns, settings.acc_record)


class EcgGateway(Node):
    role = NAME
    ends_with_work = True

    async def setup(self) -> None:
        self.source = make_source(self.ctx.settings)
        self.acc_until_ns: int | None = None  # where the accelerometer's data ends, so far

    def say_accelerometer(self, ecg_ns: int) -> None:
        """The status says when the windows are read without movement, and why."""
        if not self.source.accelerometer:
            self.ctx.detail = "no accelerometer: windows are read without movement (heart only)"
        elif self.acc_until_ns is not None and ecg_ns - self.acc_until_ns > ACC_SILENT_S * 1e9:
            self.ctx.detail = (f"no accelerometer for {(ecg_ns - self.acc_until_ns) / 1e9:.0f} s: windows "
                               "are read without movement until it comes back")  # fmt: skip
        else:
            self.ctx.detail = ""

    async def stream(self) -> AsyncIterator[Out]:
        if self.source.waits_for_listener:
            topic = ECG_SAMPLES if self.source.ecg else ECG_RR
            self.ctx.state = f"waiting for a subscriber of {topic.suffix}"
            try:
                await self.until_read(topic, LISTENER_WAIT_S)
            except TimeoutError:
                log.warning(
                    "nobody subscribes to %s after %.0f s: replaying anyway", topic.suffix, LISTENER_WAIT_S
                )
            self.ctx.state = "running"
        name = self.source.name
        async for chunk in self.source.chunks():
            if isinstance(chunk, RrChunk):
                if not self.source.ecg:
                    self.say_accelerometer(chunk.t_ns)
                    self.ctx.counters["gaps"] += int(chunk.gap)
                yield [RrIntervals(t_ns=chunk.t_ns, seq=0, rr_s=chunk.rr_s, gap=chunk.gap,
                                   source=name)]  # fmt: skip
                continue
            if isinstance(chunk, AccSamples):
                self.ctx.counters["acc_chunks"] += 1
                self.acc_until_ns = chunk.t_ns + round(len(chunk.xyz_mg) * 1e9 / chunk.fs_hz)
                x, y, z = (list(axis) for axis in zip(*chunk.xyz_mg, strict=True))
                yield [AccChunk(t_ns=chunk.t_ns, seq=0, fs_hz=chunk.fs_hz, x_mg=x, y_mg=y, z_mg=z,
                                gap=chunk.gap, source=name)]  # fmt: skip
                continue
            self.say_accelerometer(chunk.t_ns)
            self.ctx.counters["chunks"] += 1
            # what the strap sent that did not parse: truncated, garbled, an unknown stream or frame type
            self.ctx.counters["bad_frames"] = getattr(self.source, "bad_frames", 0)
            self.ctx.counters["gaps"] += int(chunk.gap)
            yield [EcgChunk(t_ns=chunk.t_ns, seq=0, fs_hz=chunk.fs_hz,
                            samples_uv=chunk.samples_uv, gap=chunk.gap, source=name)]  # fmt: skip
        self.ctx.state = "source ended"


main = node_main(EcgGateway)


def prepare(settings: Settings, common: CommonSettings) -> None:
    make_source(settings)  # a missing or broken record stops the service at start


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv, prepare)


if __name__ == "__main__":
    sys.exit(run())
