"""ecg_gateway: an ECG source → ``ecg/samples`` and ``ecg/rr`` (DESIGN §1, §6). Sources behind one
interface: ``polar`` (the H10 over BLE) and ``replay`` (a recording). A cell without a strap runs the
operator twin (services/operator_twin) in this service's place."""

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
from schemas.ecg import EcgChunk, RrIntervals
from schemas.topology import ECG_RR, ECG_SAMPLES
from services.ecg_gateway.polar import PolarSource, bleak_connector
from services.ecg_gateway.sources import FS_HZ, EcgSource, ReplaySource, RrChunk

NAME = "ecg_gateway"
LISTENER_WAIT_S = 30.0
log = logging.getLogger("cadence.ecg_gateway")


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    source: Literal["replay", "polar"] = "replay"
    strap: str = "Polar H10"  # polar: MAC address or (part of) the advertised name
    gap_timeout_s: Annotated[float, msgspec.Meta(ge=0.5, le=300.0)] = 5.0  # polar: reconnect after this
    record: str | None = None  # replay: WFDB record path without extension, or a CSV
    speed: Annotated[float, msgspec.Meta(ge=0.0, le=1000.0)] = 1.0  # replay: × real time; 0 = at once
    start_ns: TimeNs | None = None  # replay: data time of the first sample (default: now)


def make_source(settings: Settings) -> EcgSource:
    if settings.source == "polar":
        return PolarSource(bleak_connector(settings.strap), settings.gap_timeout_s)
    if settings.record is None:
        raise ConfigError(f"[{NAME}] record: the replay source needs a record (WFDB path or CSV)")
    return ReplaySource(settings.record, settings.speed, settings.start_ns)


class EcgGateway(Node):
    role = NAME
    ends_with_work = True

    async def setup(self) -> None:
        self.source = make_source(self.ctx.settings)

    async def stream(self) -> AsyncIterator[Out]:
        if self.source.waits_for_listener:
            self.ctx.state = "waiting for a subscriber of ecg/samples"
            try:
                await self.until_read(ECG_SAMPLES, LISTENER_WAIT_S)
            except TimeoutError:
                log.warning(
                    "nobody subscribes to ecg/samples after %.0f s: replaying anyway", LISTENER_WAIT_S
                )
            self.ctx.state = "running"
        name = self.source.name
        async for chunk in self.source.chunks():
            if isinstance(chunk, RrChunk):
                yield [RrIntervals(t_ns=chunk.t_ns, seq=self.next_seq(ECG_RR), rr_s=chunk.rr_s, source=name)]
                continue
            self.ctx.counters["chunks"] += 1
            self.ctx.counters["gaps"] += int(chunk.gap)
            yield [EcgChunk(t_ns=chunk.t_ns, seq=self.next_seq(ECG_SAMPLES), fs_hz=FS_HZ,
                            samples_uv=chunk.samples_uv, gap=chunk.gap, source=name)]  # fmt: skip
        self.ctx.state = "source ended"


main = node_main(EcgGateway)


def prepare(settings: Settings, common: CommonSettings) -> None:
    make_source(settings)  # a missing or broken record stops the service at start


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv, prepare)


if __name__ == "__main__":
    sys.exit(run())
