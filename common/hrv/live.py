"""The HRV analyser's stream on the wire (DESIGN §4, §6, §9): messages in, messages out, on data time.

``HrvStream`` works in seconds from its own start; this keeps what the wire adds around it: the stream's
origin in ns, the time line that admits a chunk or drops it (common/runtime/admission.py), the restart
when a run of chunks agrees on another data time (the old stream flushed first), the sequence numbers of
what it sends, and the wearer's movement (common/hrv/movement.py) from the accelerometer's own stream,
which has a time line of its own and lands on each window as it is sent.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import msgspec
import numpy as np

from common.hrv.movement import Movement
from common.hrv.stream import RR_RESYNC_S, Beat, HrvStream, Window, beats_message, window_message
from common.runtime.admission import SKEW_S, TimeLine, Verdict
from schemas.ecg import AccChunk, EcgChunk, RrIntervals
from schemas.hrv import Beats, HrvWindow

RR_RESOLUTION_HZ = 1024.0  # device RR comes in 1/1024 s; no detector runs on this input
# A source comes back from a BLE drop within this much data time (the H10 takes 20–30 s to restart its
# ECG); a chunk further ahead, or behind, is out of line until this many chunks in a row agree with it.
MAX_GAP_S = 120.0
CONFIRM_CHUNKS = 10  # about 5.6 s of H10 ECG
CHUNK_TOLERANCE_S = 0.012  # a chunk may start this much before the last one ended (1.5 samples at 130 Hz)
CONFIRM_RR = 5  # notifications, about 5 s
# an accelerometer chunk may start this much before the last one ended: the strap's nominal 25 Hz is
# 25.3 Hz measured, so a frame's first sample, reckoned at the nominal rate, lands a little early
ACC_TOLERANCE_S = 0.1


@dataclass
class Taken:
    """What one message gave: the time line's verdict (None for an empty chunk) and what to send."""

    verdict: Verdict | None
    out: list[Beats | HrvWindow] = field(default_factory=list)


class LiveHrv:
    def __init__(self, window_s: float, source: Literal["samples", "rr"], skew_s: float = SKEW_S) -> None:
        self.window_s = window_s
        self.line = (
            TimeLine(MAX_GAP_S, tolerance_s=RR_RESYNC_S, confirm=CONFIRM_RR, skew_s=skew_s)
            if source == "rr"
            else TimeLine(MAX_GAP_S, tolerance_s=CHUNK_TOLERANCE_S, confirm=CONFIRM_CHUNKS, skew_s=skew_s)
        )
        self.stream: HrvStream | None = None
        self.origin_ns = 0
        self.seq = {"beats": 0, "windows": 0}
        self.acc_line = TimeLine(
            MAX_GAP_S, tolerance_s=ACC_TOLERANCE_S, confirm=CONFIRM_CHUNKS, skew_s=skew_s
        )
        self.movement = Movement()

    def acc(self, chunk: AccChunk, clock_ns: int) -> Verdict | None:
        """Accelerometer samples: kept for the windows to come; None for an empty chunk."""
        if not chunk.x_mg:
            return None
        end_ns = chunk.t_ns + round(len(chunk.x_mg) * 1e9 / chunk.fs_hz)
        verdict = self.acc_line.admit(chunk.t_ns, end_ns, chunk.fs_hz, clock_ns=clock_ns)
        if verdict.acted_on:
            xyz = np.column_stack([chunk.x_mg, chunk.y_mg, chunk.z_mg]).astype(float)
            self.movement.feed(chunk.t_ns, chunk.fs_hz, xyz, chunk.gap or verdict.action == "restart")
        return verdict

    def samples(self, chunk: EcgChunk, clock_ns: int) -> Taken:
        if not chunk.samples_uv:
            return Taken(None)  # nothing to analyse; a gap shows in the next chunk's data time
        end_ns = chunk.t_ns + round(len(chunk.samples_uv) * 1e9 / chunk.fs_hz)
        verdict, out = self._admit(chunk.t_ns, end_ns, chunk.fs_hz, clock_ns)
        if verdict.acted_on:
            stream = self._stream(chunk.fs_hz, chunk.t_ns)
            out += self._messages(
                *stream.feed((chunk.t_ns - self.origin_ns) / 1e9, chunk.samples_uv, chunk.gap)
            )
        return Taken(verdict, out)

    def rr(self, msg: RrIntervals, clock_ns: int) -> Taken:
        verdict, out = self._admit(
            msg.t_ns - round(sum(msg.rr_s) * 1e9), msg.t_ns, RR_RESOLUTION_HZ, clock_ns
        )
        if verdict.acted_on:
            stream = self._stream(RR_RESOLUTION_HZ, msg.t_ns)
            out += self._messages(*stream.feed_rr((msg.t_ns - self.origin_ns) / 1e9, msg.rr_s, msg.gap))
        return Taken(verdict, out)

    def _admit(
        self, start_ns: int, end_ns: int, fs: float, clock_ns: int
    ) -> tuple[Verdict, list[Beats | HrvWindow]]:
        """The time line's word, and what a restart flushed of the old stream (a new one starts)."""
        verdict = self.line.admit(start_ns, end_ns, fs, clock_ns=clock_ns)
        if verdict.action != "restart" or self.stream is None:
            return verdict, []
        flushed, self.stream = self._messages(*self.stream.flush()), None
        return verdict, flushed

    def _stream(self, fs: float, t_ns: int) -> HrvStream:
        if self.stream is None:
            self.stream, self.origin_ns = HrvStream(fs, self.window_s), t_ns
        return self.stream

    def _messages(self, beats: list[Beat], wins: list[Window]) -> list[Beats | HrvWindow]:
        out: list[Beats | HrvWindow] = []
        if beats:
            out.append(beats_message(beats, self.origin_ns, self._next("beats")))
        for w in wins:
            msg = window_message(w, self.origin_ns, self._next("windows"))
            mg, moving = self.movement.over(msg.start_ns, msg.end_ns)
            out.append(msgspec.structs.replace(msg, movement_mg=mg, moving_fraction=moving))
        return out

    def _next(self, what: str) -> int:
        self.seq[what] += 1
        return self.seq[what] - 1
