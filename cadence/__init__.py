"""Cadence's command line and the lab's tools (README "Layout")."""

import os
import signal
import sys
from types import FrameType


def _not_started(signum: int, frame: FrameType | None) -> None:
    raise SystemExit(0)


# A service's unit runs `cadence run NAME`: a stop that comes while it is still importing (a restart the
# cell is stopped during, on a loaded host) finds nothing begun, and is a clean exit, not death by
# SIGTERM (ExecMainStatus 15). The service puts its own handler in place once it runs (service.py).
if os.path.basename(sys.argv[0]) == "cadence" and sys.argv[1:2] == ["run"]:
    signal.signal(signal.SIGTERM, _not_started)

from importlib.metadata import PackageNotFoundError  # noqa: E402
from importlib.metadata import version as _version  # noqa: E402


def version() -> str:
    """The installed distribution's version: what a session file records and `cadence --version` says."""
    try:
        return _version("cadence")
    except PackageNotFoundError:
        return "0+unknown (not installed)"
