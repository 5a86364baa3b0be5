"""A stop that comes before a service runs. A supervisor (systemd, the demo's process cell) may stop a
service while it is still importing: a restart the cell is stopped during, on a loaded host. Nothing has
begun then, so it is a clean exit (0), not death by SIGTERM (systemd's ExecMainStatus 15, issue 53). The
package a service starts from puts this in place first thing; the service's own handler takes over once it
runs (common/runtime/service.py)."""

from __future__ import annotations

import signal
from types import FrameType


def _not_started(signum: int, frame: FrameType | None) -> None:
    raise SystemExit(0)


def exit_cleanly_until_started() -> None:
    signal.signal(signal.SIGTERM, _not_started)
