"""What each part of the executor is handed by its node, and all it reaches of it.

The executor's parts (the supervisor, the reactions to a person's distance, the records on disk, the
selection in force, the motions on the servo loop, the task program, the telemetry) each get a ``Kit``
and the other parts they call, never the node: what a part may touch is in its constructor's signature,
and a change of the node's context moves no part.
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from common.runtime.clock import Clock
from schemas.base import Message
from services.executor.settings import Settings


@dataclass(frozen=True, slots=True)
class Kit:
    settings: Settings
    clock: Clock  # data time (common/runtime/clock.py)
    speed: float  # data time per second of the event loop's clock: the cell's speed, or 1 in lockstep
    clock_skew_s: float  # how far the cell's clocks may disagree (CommonSettings.clock_skew_s)
    counters: Counter[str]  # the service's, in its status
    stop: asyncio.Event  # set when the service stops
    publish: Callable[[Message], None]  # to the output of the message's type (``Node.publish``)
    note: Callable[[str], Callable[[str], None]]  # a part's own say in the status's detail, by part
    set_state: Callable[[str], None]  # the status's state: the safety state's words, the supervisor's only
