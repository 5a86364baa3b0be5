"""ecg_gateway: an ECG source → ``ecg/samples`` and ``ecg/rr`` (DESIGN §1, §6). Sources behind one
interface: ``polar`` (the H10 over BLE) and ``replay`` (a recording). A cell without a strap runs the
operator twin (services/operator_twin) in this service's place."""

from __future__ import annotations

import logging
import sys
from typing import Annotated, Literal

import msgspec

from common.runtime.config import CommonSettings
from common.runtime.errors import ConfigError
from common.runtime.service import ServiceContext, first_of, service_main
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


async def main(ctx: ServiceContext) -> None:
    source = make_source(ctx.settings)
    samples_out, rr_out = ctx.bus.publisher(ECG_SAMPLES), ctx.bus.publisher(ECG_RR)
    if source.waits_for_listener:
        ctx.state = "waiting for a subscriber of ecg/samples"
        try:
            await first_of(samples_out.until_subscribed(LISTENER_WAIT_S), ctx.stop.wait())
        except TimeoutError:
            log.warning(
                "nobody subscribes to %s after %.0f s: replaying anyway", samples_out.key, LISTENER_WAIT_S
            )
        if ctx.stop.is_set():
            return
        ctx.state = "running"
    async for chunk in source.chunks():
        if isinstance(chunk, RrChunk):
            rr_out.put(
                RrIntervals(t_ns=chunk.t_ns, seq=rr_out.next_seq(), rr_s=chunk.rr_s, source=source.name)
            )
            continue
        ecg = EcgChunk(
            t_ns=chunk.t_ns,
            seq=samples_out.next_seq(),
            fs_hz=FS_HZ,
            samples_uv=chunk.samples_uv,
            gap=chunk.gap,
            source=source.name,
        )
        samples_out.put(ecg)
        ctx.counters["chunks"] = samples_out.seq
        ctx.counters["gaps"] += int(chunk.gap)
        if ctx.stop.is_set():
            break
    ctx.state = "source ended"


def prepare(settings: Settings, common: CommonSettings) -> None:
    make_source(settings)  # a missing or broken record stops the service at start


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv, prepare)


if __name__ == "__main__":
    sys.exit(run())
