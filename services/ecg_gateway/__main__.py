"""ecg_gateway: an ECG source → ``ecg/samples`` (DESIGN §1, §6). Sources: ``replay`` now; ``polar`` and
``twin`` behind the same interface next."""

from __future__ import annotations

import sys
from typing import Literal

import msgspec

from common.errors import ConfigError
from common.service import CommonSettings, ServiceContext, service_main
from schemas.ecg import EcgChunk
from services.ecg_gateway.sources import FS_HZ, EcgSource, ReplaySource

NAME = "ecg_gateway"


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    source: Literal["replay"] = "replay"
    record: str | None = None  # replay: WFDB record path without extension, or a CSV
    speed: float = 1.0  # replay: × real time; 0 = as fast as possible
    start_ns: int | None = None  # replay: data time of the first sample (default: now)


def make_source(settings: Settings) -> EcgSource:
    if settings.record is None:
        raise ConfigError(f"[{NAME}] record: the replay source needs a record (WFDB path or CSV)")
    return ReplaySource(settings.record, settings.speed, settings.start_ns)


async def main(ctx: ServiceContext) -> None:
    source = make_source(ctx.settings)
    key = ctx.bus.key("ecg/samples")
    seq = 0
    async for chunk in source.chunks():
        ctx.bus.put(
            key,
            EcgChunk(
                t_ns=chunk.t_ns,
                seq=seq,
                fs_hz=FS_HZ,
                samples_uv=chunk.samples_uv,
                gap=chunk.gap,
                source=source.name,
            ),
            block=True,
        )
        seq += 1
        ctx.counters["chunks"] = seq
        if ctx.stop.is_set():
            break
    ctx.state = "source ended"


def prepare(settings: Settings, common: CommonSettings) -> None:
    make_source(settings)  # a missing or broken record stops the service at start


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv, prepare)


if __name__ == "__main__":
    sys.exit(run())
