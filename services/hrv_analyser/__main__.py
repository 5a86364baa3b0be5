"""hrv_analyser: ``ecg/samples`` → R peaks, cleaned RR, windows → ``hrv/beats``, ``hrv/window``
(DESIGN §1, §4, §6). All on data time: a replay at any speed gives the same windows as live.

``input = "rr"`` takes the device's RR intervals (``ecg/rr``) instead, for a source that sends no ECG;
the H10's own RR leaves out premature beats, so samples are the default and the better input.

A chunk far from the stream's data time, or at another sample rate, is dropped and counted; a run of
them that agree with each other starts the stream afresh there (common/hrv/live.py). The strap's
accelerometer (``ecg/acc``), when its source has one, gives each window the wearer's movement.

It keeps its last windows and answers for them (``hrv/window?after=<end_ns>``: the first one ending after
it), so a decision maker that was restarting or stopped while one was published asks for what it missed
(DESIGN §9) instead of stepping several windows' worth at once."""

from __future__ import annotations

import logging
import sys
from collections import deque
from typing import Annotated, Any, Literal

import msgspec

from common.hrv.live import LiveHrv, Taken
from common.runtime.bus import QueryError, Request
from common.runtime.node import Node, Out, admitted, answers, node_main, on
from common.runtime.service import service_main
from schemas.ecg import AccChunk, EcgChunk, RrIntervals
from schemas.hrv import Beats, HrvWindow
from schemas.topology import ECG_ACC, ECG_RR, ECG_SAMPLES, HRV_WINDOW, Topic
from services.registry import ANALYSER

NAME = ANALYSER.name
log = logging.getLogger("cadence.hrv_analyser")
KEPT_WINDOWS = 64  # half an hour of 30 s windows: what a decision maker that was down may ask for


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    window_s: Annotated[float, msgspec.Meta(ge=5.0, le=600.0)] = 30.0
    input: Literal["samples", "rr"] = "samples"


class HrvAnalyser(Node):
    role = NAME

    async def setup(self) -> None:
        self.live = LiveHrv(self.ctx.settings.window_s, self.ctx.settings.input, self.ctx.common.clock_skew_s)
        self.recent: deque[HrvWindow] = deque(maxlen=KEPT_WINDOWS)

    def reads(self, topic: Topic[Any]) -> bool:  # ecg/rr only with input = rr, ecg/samples only without
        return topic is ECG_ACC or (topic.suffix == ECG_RR.suffix) == (self.ctx.settings.input == "rr")

    @on(ECG_SAMPLES, maxsize=10_000)
    async def on_chunk(self, chunk: EcgChunk) -> Out:
        return self.sent(self.live.samples(chunk, self.ctx.common.clock.now_ns()))

    @on(ECG_RR, maxsize=10_000)
    async def on_rr(self, msg: RrIntervals) -> Out:
        return self.sent(self.live.rr(msg, self.ctx.common.clock.now_ns()))

    @on(ECG_ACC, maxsize=10_000)
    async def on_acc(self, chunk: AccChunk) -> Out:
        admitted(self.live.acc(chunk, self.ctx.common.clock.now_ns()))
        self.ctx.counters["acc_chunks"] += 1
        return []

    def sent(self, taken: Taken) -> Out:
        if (verdict := admitted(taken.verdict)) is not None and verdict.action == "restart":
            self.ctx.counters["stream_restarts"] += 1
        for m in taken.out:
            if isinstance(m, Beats):
                self.ctx.counters["beats"] += len(m.rr_s)
            else:
                self.ctx.counters["windows"] += 1
                self.ctx.counters["windows_without_movement"] += m.movement_mg is None
                self.recent.append(m)
                rr = f"{m.mean_rr_s:.3f} s" if m.mean_rr_s is not None else "none"
                moved = f", movement {m.movement_mg:.0f} mg" if m.movement_mg is not None else ""
                log.info("window of %.0f s: mean RR %s over %d beats, %s%s", (m.end_ns - m.start_ns) / 1e9,
                         rr, m.n_beats, m.quality, moved)  # fmt: skip
        return taken.out

    @answers(HRV_WINDOW)
    async def window_after(self, req: Request) -> HrvWindow:
        """The first window kept that ends after ``after`` (ns): one at a time, in order."""
        try:
            after = int(req.params.get("after", ""))
        except ValueError:
            raise QueryError("expected after=<end_ns>, the end of the last window answered") from None
        for w in self.recent:
            if w.end_ns > after:
                return w
        raise QueryError("no window after it")


main = node_main(HrvAnalyser)


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv)


if __name__ == "__main__":
    sys.exit(run())
