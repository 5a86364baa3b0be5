"""Cadence's command line and the lab's tools (docs/design.md, "Layout")."""

import os
import sys

# A service's unit runs `cadence run NAME`: a stop before it runs is a clean exit (common/runtime/early.py)
if os.path.basename(sys.argv[0]) == "cadence" and sys.argv[1:2] == ["run"]:
    from common.runtime.early import exit_cleanly_until_started

    exit_cleanly_until_started()


def version() -> str:
    """The installed distribution's version: what a session file records and `cadence --version` says.
    importlib.metadata is imported here, not at start: it costs 40-50 ms every command would pay."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as _version

    try:
        return _version("cadence")
    except PackageNotFoundError:
        return "0+unknown (not installed)"
