"""hrv_analyser: ``ecg/samples`` → R peaks, cleaned RR, windows → ``hrv/beats``, ``hrv/window``
(DESIGN §1, §4, §6). All on data time: a replay at any speed gives the same windows as live.

``input = "rr"`` takes the device's RR intervals (``ecg/rr``) instead, for a source that sends no ECG;
the H10's own RR leaves out premature beats, so samples are the default and the better input.

A chunk far from the stream's data time, or at another sample rate, is dropped and counted; a run of
them that agree with each other starts the stream afresh there (common/runtime/admission.py)."""

from __future__ import annotations

import sys
from typing import Annotated, Literal

import msgspec

from common.hrv.stream import RR_RESYNC_S, Beat, HrvStream, Window, beats_message, window_message
from common.runtime.admission import TimeLine
from common.runtime.service import ServiceContext, service_main
from schemas.ecg import EcgChunk, RrIntervals
from schemas.topology import ECG_RR, ECG_SAMPLES, HRV_BEATS, HRV_WINDOW

NAME = "hrv_analyser"
RR_RESOLUTION_HZ = 1024.0  # device RR comes in 1/1024 s; no detector runs on this input


# A source comes back from a BLE drop within this much data time (the H10 takes 20–30 s to restart its
# ECG); a chunk further ahead, or behind, is out of line until this many chunks in a row agree with it.
MAX_GAP_S = 120.0
CONFIRM_CHUNKS = 10  # about 5.6 s of H10 ECG
CHUNK_TOLERANCE_S = 0.012  # a chunk may start this much before the last one ended (1.5 samples at 130 Hz)
CONFIRM_RR = 5  # notifications, about 5 s


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    window_s: Annotated[float, msgspec.Meta(ge=5.0, le=600.0)] = 30.0
    input: Literal["samples", "rr"] = "samples"


async def main(ctx: ServiceContext) -> None:
    settings: Settings = ctx.settings
    bus = ctx.bus
    beats_out, windows_out = bus.publisher(HRV_BEATS), bus.publisher(HRV_WINDOW)
    stream: HrvStream | None = None
    origin_ns = 0
    line = (
        TimeLine(MAX_GAP_S, tolerance_s=RR_RESYNC_S, confirm=CONFIRM_RR)
        if settings.input == "rr"
        else TimeLine(MAX_GAP_S, tolerance_s=CHUNK_TOLERANCE_S, confirm=CONFIRM_CHUNKS)
    )

    def publish(beats: list[Beat], wins: list[Window]) -> None:
        if beats:
            beats_out.put(beats_message(beats, origin_ns, beats_out.next_seq()))
            ctx.counters["beats"] += len(beats)
        for w in wins:
            windows_out.put(window_message(w, origin_ns, windows_out.next_seq()))
            ctx.counters["windows"] += 1

    def admitted(key: str, start_ns: int, end_ns: int, fs: float) -> bool:
        """The time line's word on a message; a restart flushes the old stream and starts a new one."""
        nonlocal stream
        verdict = line.admit(start_ns, end_ns, fs, clock_ns=ctx.common.clock.now_ns())
        if not verdict.acted_on:
            bus.reject(key, verdict.code, verdict.detail)
            return False
        if verdict.action == "restart":
            ctx.counters["stream_restarts"] += 1
            if stream is not None:
                publish(*stream.flush())
            stream = None
        return True

    async def on_chunk(key: str, chunk: EcgChunk) -> None:
        nonlocal stream, origin_ns
        if not chunk.samples_uv:
            return  # nothing to analyse; a gap shows in the next chunk's data time
        end_ns = chunk.t_ns + round(len(chunk.samples_uv) * 1e9 / chunk.fs_hz)
        if not admitted(key, chunk.t_ns, end_ns, chunk.fs_hz):
            return
        if stream is None:
            stream, origin_ns = HrvStream(chunk.fs_hz, settings.window_s), chunk.t_ns
        publish(*stream.feed((chunk.t_ns - origin_ns) / 1e9, chunk.samples_uv, chunk.gap))

    async def on_rr(key: str, msg: RrIntervals) -> None:
        nonlocal stream, origin_ns
        if not admitted(key, msg.t_ns - round(sum(msg.rr_s) * 1e9), msg.t_ns, RR_RESOLUTION_HZ):
            return
        if stream is None:
            stream, origin_ns = HrvStream(RR_RESOLUTION_HZ, settings.window_s), msg.t_ns
        publish(*stream.feed_rr((msg.t_ns - origin_ns) / 1e9, msg.rr_s, msg.gap))

    if settings.input == "rr":
        bus.handle(ECG_RR, on_rr, maxsize=10_000)
    else:
        bus.handle(ECG_SAMPLES, on_chunk, maxsize=10_000)
    await ctx.stop.wait()


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv)


if __name__ == "__main__":
    sys.exit(run())
