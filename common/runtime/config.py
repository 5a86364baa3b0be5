"""Configuration (DESIGN §10): one TOML file per deployment with a table per service, plus ``[cadence]``
(cell, data folder, data time) and ``[bus]``; every key can be overridden by ``CADENCE_<SECTION>_<KEY>``
(a TOML value, or a bare string). Decoding is strict: an unknown or mistyped key, or an unknown table,
is a ``ConfigError`` naming the file (or variable) and the key.
"""

from __future__ import annotations

import os
import re
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import msgspec

from common.runtime.clock import Clock
from common.runtime.errors import ConfigError
from schemas.base import TimeNs
from schemas.topology import DEFAULT_CELL, SERVICES

T = TypeVar("T")

# The tables a deployment config may have: these and a table per service. Anything else is a typo
# (``[decisionmaker]``) that would otherwise be ignored in silence.
CONFIG_SECTIONS = frozenset({"cadence", "bus", *SERVICES})  # the UR emulator reads no config


class CommonSettings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    cell: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_\-]{1,64}$")] = DEFAULT_CELL  # a key chunk
    data_dir: str = "~/.local/share/cadence"
    log_format: Literal["auto", "text", "json"] = "auto"
    status_period_s: Annotated[float, msgspec.Meta(ge=0.05, le=3600.0)] = 5.0
    # data time (common/runtime/clock.py): one epoch and speed for every process of a simulated run
    speed: Annotated[float, msgspec.Meta(gt=0.0, le=1000.0)] = 1.0
    epoch_ns: TimeNs | None = None
    # a lockstep cell (common/runtime/lockstep.py, simulation only): data time is its event loop's
    lockstep: bool = False
    # the most two hosts' clocks of the cell may differ (NTP on a LAN: milliseconds; PTP: microseconds):
    # data stamped further ahead of a receiver's clock is refused, not believed (DESIGN §4)
    clock_skew_s: Annotated[float, msgspec.Meta(ge=0.0, le=10.0)] = 0.05

    @property
    def data_path(self) -> Path:
        return Path(self.data_dir).expanduser()

    @property
    def clock(self) -> Clock:
        return Clock(self.speed, self.epoch_ns, self.lockstep)


def read_config(path: str | None) -> dict[str, Any]:
    if path is None:
        return {}
    try:
        with open(path, "rb") as f:
            raw = tomllib.load(f)
    except OSError as exc:
        raise ConfigError(f"{path}: (file): {exc.strerror or exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: (syntax): {exc}") from exc
    for name, table in raw.items():
        if name not in CONFIG_SECTIONS:
            raise ConfigError(
                f"{path}: [{name}]: unknown section; expected one of {', '.join(sorted(CONFIG_SECTIONS))}"
            )
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: {name}: expected a table [{name}], got {type(table).__name__}")
    return raw


def _env_value(text: str) -> object:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def section(
    raw: Mapping[str, Any],
    name: str,
    kind: type[T],
    source: str = "<defaults>",
    env: Mapping[str, str] | None = None,
) -> T:
    """One table of the config, overridden by ``CADENCE_<NAME>_<KEY>`` variables, decoded strictly."""
    env = os.environ if env is None else env
    table = dict(raw.get(name, {}))
    prefix = f"CADENCE_{name.upper()}_"
    from_env = {}
    for var, text in env.items():
        if var.startswith(prefix):
            k = var[len(prefix) :].lower()
            table[k] = _env_value(text)
            from_env[k] = var
    try:
        return msgspec.convert(table, kind, strict=False)
    except msgspec.ValidationError as exc:
        text = str(exc)
        where = text.rsplit(" - at `$.", 1)
        keyname = where[1].rstrip("`") if len(where) == 2 else ""
        unknown = re.search(r"unknown field `([^`]+)`", text)
        if unknown and not keyname:  # msgspec names an unknown key in its message, not in the path
            keyname = unknown.group(1)
        origin = from_env.get(keyname.split(".")[0].split("[")[0], source)
        raise ConfigError(f"{origin}: [{name}] {keyname or '(table)'}: {where[0]}") from exc
