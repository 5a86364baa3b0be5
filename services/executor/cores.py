"""Which core the servo thread gets (DESIGN §8): one of its own, never shared with another Cadence
executor's FIFO thread on the same host (two cells on a line PC, the demo beside a test).

Each executor holds an exclusive ``flock`` on ``<lock_dir>/servo-core-<n>.lock`` while it runs; the
kernel drops the lock when the process dies, however it dies, so a killed executor never keeps its core.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path


def default_lock_dir() -> Path:
    """``/run/cadence`` (the unit's RuntimeDirectory) where it can be written, else a per-user folder."""
    run = Path("/run/cadence")
    with contextlib.suppress(OSError):
        run.mkdir(mode=0o755, exist_ok=True)
    if os.access(run, os.W_OK):
        return run
    return Path(tempfile.gettempdir()) / f"cadence-{os.getuid()}"


class CoreClaim:
    """A core held for one servo thread; ``release`` (or the process's end) gives it back."""

    def __init__(self, core: int | None, fd: int | None, note: str = "") -> None:
        self.core, self._fd, self.note = core, fd, note

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def claim_core(candidates: Iterable[int], lock_dir: Path, explicit: int | None = None) -> CoreClaim:
    """The explicit core if it is free, else the first free one of ``candidates`` counting from the last
    (core 0 takes most interrupts). None, with a note, when every core is taken: the servo thread then
    runs unpinned and not FIFO, rather than share a core with another executor's FIFO thread."""
    lock_dir.mkdir(parents=True, exist_ok=True)
    order = [explicit] if explicit is not None else sorted(set(candidates), reverse=True)
    for core in order:
        fd = os.open(lock_dir / f"servo-core-{core}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        return CoreClaim(core, fd)
    taken = ", ".join(str(c) for c in order)
    return CoreClaim(
        None,
        None,
        f"core{'s' if len(order) > 1 else ''} {taken} already serve other executors (locks in {lock_dir}): "
        "the servo thread runs unpinned and at normal priority",
    )
