"""Cadence's command line and the lab's tools (README "Layout")."""

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version


def version() -> str:
    """The installed distribution's version: what a session file records and `cadence --version` says."""
    try:
        return _version("cadence")
    except PackageNotFoundError:
        return "0+unknown (not installed)"
