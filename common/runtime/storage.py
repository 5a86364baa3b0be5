"""State on disk (DESIGN §9, §10): atomic writes, so a reader sees the old file or the new one, never half of
either; and validated reads, so a damaged file is moved aside and said, never a crash loop."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

import msgspec

from common.runtime.clock import wall_ns

T = TypeVar("T")


def atomic_write(path: str | os.PathLike[str], data: bytes, mode: int = 0o600) -> None:
    """Write to a temporary file in the same folder, fsync, rename over the target. ``mode``: private
    by default (a service's state); 0o644 for what people open (reports, figures)."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        if mode != 0o600:  # mkstemp's
            os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_readable(path: str | os.PathLike[str], data: bytes) -> None:
    """What people open (reports, figures, plans, summaries): atomic, and readable by everyone."""
    atomic_write(path, data, 0o644)


def quarantine(path: str | os.PathLike[str], now_ns: int | None = None) -> Path:
    """Move a file that failed validation aside as ``<name>.corrupt-<UTC time>`` (DESIGN §9): it is kept
    for a person to look at, never silently overwritten, and the service starts from a safe default."""
    import time

    src = Path(path)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime((now_ns or wall_ns()) / 1e9))
    dst = src.with_name(f"{src.name}.corrupt-{stamp}")
    n = 1
    while dst.exists():
        n += 1
        dst = src.with_name(f"{src.name}.corrupt-{stamp}-{n}")
    os.replace(src, dst)
    return dst


def load_checked(path: str | os.PathLike[str], decode: Callable[[bytes], T]) -> Loaded[T]:
    """Read and validate a state file. Missing: ``Loaded(None)``. Unreadable or invalid: the file is
    quarantined and ``problem`` says which file, which field and where it went (one line, for the log
    and the status)."""
    src = Path(path)
    try:
        data = src.read_bytes()
    except FileNotFoundError:
        return Loaded(None)
    except OSError as exc:
        return Loaded(None, f"{src}: cannot be read: {exc.strerror or exc}")
    try:
        return Loaded(decode(data))
    except (msgspec.ValidationError, msgspec.DecodeError, ValueError) as exc:
        moved = quarantine(src)
        return Loaded(None, f"{src}: {_where(exc)}; moved aside to {moved.name}")


def _where(exc: Exception) -> str:
    """msgspec says ``Expected `int`, got `str` - at `$.k```: put the field first."""
    text = str(exc) or type(exc).__name__
    what, sep, at = text.rpartition(" - at `")
    if sep:
        return f"{at.rstrip('`').removeprefix('$').lstrip('.') or '(top level)'}: {what}"
    return f"(file): {text}" if isinstance(exc, msgspec.DecodeError) else text


@dataclass(frozen=True, slots=True)
class Loaded(Generic[T]):
    value: T | None
    problem: str | None = None
