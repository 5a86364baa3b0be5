"""What each part of the executor is handed by its node, and all it reaches of it.

The executor's parts (the supervisor, the reactions to a person's distance, the records on disk, the
selection in force, the motions on the servo loop, the task program, the telemetry) each get a ``Kit``,
their own settings and the other parts they call, never the node: what a part may touch is in its
constructor's signature, and a change of the node's context moves no part. A part that changes the safety
state or speaks of it holds the supervisor as ``Safety``, all it may use of it; only the node and the task
program hold the supervisor itself.
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any, Protocol

from common.runtime.clock import Clock
from common.safety.states import Event, Motion
from schemas.base import Message
from schemas.robot import EventKind, RobotEvent


@dataclass(frozen=True, slots=True)
class Kit:
    """The node's means a part may use: the clocks, the counters, the stop, publish, its own word in
    the status, and a place for work beside the cycles. Owns nothing itself."""

    clock: Clock  # data time (common/runtime/clock.py)
    speed: float  # data time per second of the event loop's clock: the cell's speed, or 1 in lockstep
    clock_skew_s: float  # how far the cell's clocks may disagree (CommonSettings.clock_skew_s)
    counters: Counter[str]  # the service's, in its status
    stop: asyncio.Event  # set when the service stops
    publish: Callable[[Message], None]  # to the output of the message's type (``Node.publish``)
    note: Callable[[str], Callable[[str], None]]  # a part's own say in the status's detail, by part
    set_state: Callable[[str], None]  # the status's state: the safety state's words, the supervisor's only
    # work beside the cycles, in the node's task group (``Node.start_soon``): None while the node does not run
    start_soon: Callable[[Coroutine[Any, Any, Any], str], asyncio.Task[Any] | None]


class Safety(Protocol):
    """The supervisor (services/executor/supervisor.py) as the parts see it: the state, its changes
    through ``fire``, and the executor's events."""

    @property
    def motion(self) -> Motion: ...
    def fire(self, event: Event, reason: str = "") -> Motion: ...
    def ready(self) -> None: ...
    def event(
        self,
        kind: EventKind,
        message: str,
        path_id: str | None = None,
        repeat: bool = False,
        change: tuple[str, str] | None = None,
    ) -> RobotEvent: ...
