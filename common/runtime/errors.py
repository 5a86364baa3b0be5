"""Cadence's error tree. Foreign errors (msgspec, tomllib, zenoh, bleak, ur-rtde) are translated at the
adapter that meets them, with ``raise … from exc``, so callers catch these and nothing else.

    CadenceError
    ├── InputError            bad input from a person: exit code 2, one line naming file and field
    │   ├── TaskError         a task program (TOML) that cannot be planned or run
    │   └── ConfigError       a deployment config (TOML, CADENCE_* variables) with a bad key or value
    ├── BusError              Zenoh failed (zenoh.ZError translated) or the bus is used after close
    ├── PlanningError         a path has no feasible trajectory within its bounds (raise κ or the limits)
    └── TrajectoryRejected    a trajectory over a limit or off its path: it never reaches the robot
"""

from __future__ import annotations


class CadenceError(Exception):
    """Base of every error Cadence raises on purpose."""


class InputError(CadenceError):
    """Input a person gave us is wrong; the message is one line that says what and where."""


class TaskError(InputError):
    """A task program is invalid. ``str()`` reads ``FILE: path 'ID': FIELD: what is wrong``."""

    def __init__(self, file: str, field: str, message: str, path_id: str | None = None) -> None:
        self.file = file
        self.field = field
        self.path_id = path_id
        self.reason = message
        where = f"path '{path_id}': " if path_id is not None else ""
        super().__init__(f"{file}: {where}{field}: {message}")


class ConfigError(InputError):
    """A service's configuration is invalid; the message names the file (or variable) and the key."""


class BusError(CadenceError):
    """The bus could not do what was asked; the reason says what Zenoh said."""


class PlanningError(CadenceError):
    """The planner found nothing feasible; the message names the path and what to change."""


class TrajectoryRejected(CadenceError):
    """A trajectory failed validation; ``problems`` lists every check it failed."""

    def __init__(self, path_id: str, problems: list[str]) -> None:
        self.path_id = path_id
        self.problems = problems
        super().__init__(f"path '{path_id}': trajectory refused: " + "; ".join(problems))


class Rejected(Exception):
    """Raised by an input handler for a message that decoded but must not be acted on (the rules of
    common/runtime/admission.py): counted and logged by the bus under ``code``, like a malformed one."""

    def __init__(self, code: str, detail: str = "") -> None:
        super().__init__(detail or code)
        self.code, self.detail = code, detail
