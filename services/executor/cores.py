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
    order = [explicit] if explicit is not None else sorted(set(candidates), reverse=True)
    try:
        lock_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return CoreClaim(None, None, f"cannot make {lock_dir} ({exc.strerror or exc}): the servo thread "
                                     "runs unpinned and at normal priority")  # fmt: skip
    unusable: list[str] = []  # lock files this user may not open (another's, a root run's): said, skipped
    for core in order:
        path = lock_dir / f"servo-core-{core}.lock"
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            unusable.append(f"{path}: {exc.strerror or exc}")
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        skipped = f"skipped {'; '.join(unusable)}" if unusable else ""
        return CoreClaim(core, fd, skipped)
    taken = ", ".join(str(c) for c in order)
    why = f" (skipped {'; '.join(unusable)})" if unusable else ""
    cores = f"core{'s' if len(order) > 1 else ''} {taken}"
    return CoreClaim(
        None,
        None,
        f"{cores} already serve other executors ({_owners(lock_dir, order)}locks in {lock_dir}){why}: the "
        "servo thread runs unpinned and at normal priority",
    )


def _owners(lock_dir: Path, cores: Iterable[int]) -> str:
    """The processes that hold the cores' locks, as each wrote its pid: whom to stop for a core."""
    pids = set()
    for core in cores:
        with contextlib.suppress(OSError, ValueError):
            pids.add(int((lock_dir / f"servo-core-{core}.lock").read_text().split()[0]))
    return f"pid {', '.join(str(p) for p in sorted(pids))}; " if pids else ""
