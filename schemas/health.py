"""``health/<service>``: a liveliness token plus this periodic status."""

from __future__ import annotations

from typing import Annotated

import msgspec

from schemas.base import Message, Name, NonNegInt, Seconds, Text


class ServiceStatus(Message, frozen=True, tag="health.status.v1"):
    """``counters`` also holds what the service dropped: ``decode_errors``, ``rejected/<key>/<reason>``
    and ``handler_errors/<key>/<error>`` (README "Bad input")."""

    service: Name
    state: Text
    uptime_s: Seconds
    counters: Annotated[dict[Name, NonNegInt], msgspec.Meta(max_length=1000)]
    detail: Text = ""
