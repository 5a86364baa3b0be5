"""The run's folder: one demo's alone, and started afresh (a rested operator, an arm no earlier demo left
stopped)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import IO

from common.hrv.calibration import CALIBRATION_FILE
from common.runtime.errors import InputError
from services.decision_maker import STATE_FILE
from services.executor.persist import ExecutorStore
from services.registry import EXECUTOR

LOCK_FILE = ".cadence-demo.lock"


def claim(folder: Path, force: bool = False) -> IO[str] | None:
    """The run's folder for this run alone: two demos into one folder both said "written", and one's log
    was lost. Held (an advisory lock) for as long as the returned file is open; ``force``: not taken."""
    import fcntl

    if force:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        f = (folder / LOCK_FILE).open("a+")
    except OSError as exc:
        raise InputError(f"{folder}: cannot be used for the run: {exc.strerror or exc}") from None
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.seek(0)
        who = f.read().strip() or "another process"
        f.close()
        raise InputError(f"{folder}: another demo writes there ({who}): give another --out, or --force "
                         "to share it") from None  # fmt: skip
    f.seek(0)
    f.truncate()
    f.write(f"pid {os.getpid()}\n")
    f.flush()
    return f


def fresh_start(data: Path) -> None:
    """A demo starts from a rested operator and a simulated arm no earlier demo left stopped or killed
    mid-path (a real executor's restart keeps both as a stop: services/executor/persist.py)."""
    for stale in (STATE_FILE, CALIBRATION_FILE):
        (data / stale).unlink(missing_ok=True)
    executor = ExecutorStore(data / EXECUTOR.name)
    executor.load()
    executor.forget_stop()  # an unchanged record is not written


PREVIOUS = "previous"
STAYS = ("data", LOCK_FILE, PREVIOUS)  # the services' data, the lock, the runs kept: the rest is a run's own


def keep_previous(folder: Path) -> Path | None:
    """A finished run's summary, report, figures and logs in ``folder`` moved aside, into
    ``previous/<when it ended>``, so that the new run overwrites nothing of it (a second demo into one
    folder replaced the first's report without a word). The services' data stays: the next run starts
    from it afresh (``fresh_start``). Where they went, or None when there was no finished run."""
    summary = folder / "summary.json"
    if not summary.is_file():
        return None
    ended = time.strftime("%Y%m%d-%H%M%S", time.localtime(summary.stat().st_mtime))
    aside = folder / PREVIOUS / ended
    n = 1
    while aside.exists():  # two runs ended within a second
        n += 1
        aside = folder / PREVIOUS / f"{ended}-{n}"
    try:
        aside.mkdir(parents=True)
        for entry in sorted(folder.iterdir()):
            if entry.name not in STAYS:
                entry.rename(aside / entry.name)
    except OSError as exc:
        raise InputError(f"{folder}: the last run's report cannot be kept in {aside}: {exc.strerror or exc}; "
                         "give another --out") from None  # fmt: skip
    return aside
