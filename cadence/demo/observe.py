"""The demo's observer on the cell's bus: what the live view, the summary and the report are made of,
on data time, with the messages it missed counted by their senders' numbers."""

from __future__ import annotations

import itertools
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from cadence.lab.marks import counted
from cadence.lab.report import event_row, scale_row, thresholds, window_row
from cadence.tools.gaps import Gaps
from common.runtime.bus import Bus
from common.safety.states import routine_change
from schemas import (
    CycleReport,
    HrvWindow,
    OperatorError,
    Selection,
)
from schemas.topology import (
    HRV_WINDOW,
    OPERATOR_ERROR,
    ROBOT_CYCLE,
    ROBOT_EVENT,
    ROBOT_STATE,
    SELECTION,
)
from services.registry import EXECUTOR


@dataclass
class Observed:
    """What the demo saw on the bus, on data time (seconds from the epoch)."""

    epoch_ns: int
    windows: list[dict] = field(default_factory=list)
    selections: list[dict] = field(default_factory=list)
    cycles: list[CycleReport] = field(default_factory=list)
    marked: list[OperatorError] = field(default_factory=list)  # operator/error as it came
    events: list[dict] = field(default_factory=list)
    scale: list[dict] = field(default_factory=list)  # report.scale_row
    gaps: Gaps = field(default_factory=Gaps)  # what the senders' numbers say this observer missed

    def watch(self, key: str, fn: Callable[[Any], None]) -> Callable[[str, Any], Awaitable[None]]:
        """A handler of one sender's key that also notes the message's number."""

        async def handler(_: str, msg: Any) -> None:
            self.gaps.note(key, msg.seq)
            fn(msg)

        return handler

    @property
    def n_cycles(self) -> int:
        """The cycles the executor reported, by its numbers: those seen and those it sent unseen."""
        return len(self.cycles) + sum(n for k, n in self.gaps.missed.items() if k.endswith("/robot/cycle"))

    @property
    def error_times_s(self) -> list[float]:
        """When each error that counts was marked (cadence/lab/marks.py: a withdrawn mark does not)."""
        return [self.t(e.t_ns) for e in counted(self.marked)]

    @property
    def errors(self) -> int:
        return len(self.error_times_s)

    def t(self, t_ns: int) -> float:
        return round((t_ns - self.epoch_ns) / 1e9, 3)

    def on_window(self, w: HrvWindow) -> None:
        self.windows.append(window_row(w, self.t(w.end_ns)))

    def on_selection(self, s: Selection) -> None:
        last = self.selections[-1] if self.selections else None
        key = self.t(s.window_end_ns) if s.window_end_ns else None
        if last is not None and (last["window_end_s"], last["k"]) == (key, s.k):
            return  # the periodic republication of the same decision
        self.selections.append(
            {
                "t_s": max(0.0, self.t(s.t_ns)),
                "k": s.k,
                "delta": s.delta,
                "reason": s.reason,
                "window_end_s": key,
                **thresholds(s),
            }
        )

    def on_event(
        self,
        source: str,
        kind: str,
        message: str,
        t_ns: int,
        change: tuple[str | None, str | None] = (None, None),
    ) -> None:
        """``change``: a state change's (from, to) states."""
        if kind == "state" and routine_change(*change):
            return
        self.events.append(event_row(self.t(t_ns), source, kind, message, change))

    def k_steps(self) -> tuple[int, int]:
        ks = [s["k"] for s in self.selections]
        down = sum(1 for a, b in itertools.pairwise(ks) if b < a)
        up = sum(1 for a, b in itertools.pairwise(ks) if b > a)
        return down, up


def watch(bus: Bus, obs: Observed) -> None:
    """The demo's observer on the cell's bus: what the summary and the report are made of."""
    # each of these has one sender, whose numbers say what this observer missed (cadence/tools/gaps.py)
    bus.handle(HRV_WINDOW, obs.watch(bus.key(HRV_WINDOW.suffix), obs.on_window))
    bus.handle(SELECTION, obs.watch(bus.key(SELECTION.suffix), obs.on_selection))
    bus.handle(ROBOT_CYCLE, obs.watch(bus.key(ROBOT_CYCLE.suffix), obs.cycles.append))
    bus.handle(
        ROBOT_EVENT,
        obs.watch(
            bus.key(ROBOT_EVENT.suffix),
            lambda e: obs.on_event(EXECUTOR.name, e.kind, e.message, e.t_ns, (e.from_state, e.to_state)),
        ),
    )

    bus.handle(OPERATOR_ERROR, handler_of(obs.marked.append))
    bus.handle(ROBOT_STATE, handler_of(lambda m: scale_row(obs.scale, m, obs.t(m.t_ns))))


def handler_of(fn: Callable[[Any], object]) -> Callable[[str, Any], Awaitable[None]]:
    """A bus handler that hands ``fn`` the message alone (the key is the topic's own)."""

    async def handler(_: str, msg: Any) -> None:
        fn(msg)

    return handler
