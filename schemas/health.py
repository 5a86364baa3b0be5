"""``health/<service>``: a liveliness token plus this periodic status."""

from __future__ import annotations

from schemas.base import Message, Seconds


class ServiceStatus(Message, frozen=True, tag="health.status.v1"):
    service: str
    state: str
    uptime_s: Seconds
    counters: dict[str, int]
    detail: str = ""
