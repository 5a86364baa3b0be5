"""Children die with their parent: a SIGKILLed store left its planning worker running for ever
(PPID 1, 100 MB), and a SIGKILLed ``cadence demo`` left five services as orphans. Linux's parent-death
signal asks the kernel itself, so it holds whatever way the parent went: no pipe to watch, no timer.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PARENT_ENV = "CADENCE_PARENT_PID"  # set by a supervisor (the demo) for the services it starts
_PR_SET_PDEATHSIG = 1
_PR_SET_NAME = 15


def die_with_parent(parent_pid: int | None = None, sig: int = signal.SIGTERM) -> bool:
    """Have ``sig`` sent to this process when its parent dies; SIGTERM, so a service stops as on
    ``systemctl stop`` (the executor brings the arm to rest). False where the OS has no such thing.

    The kernel tracks the thread that forked this process: the parent must start children from a thread
    that lives as long as it does (its main thread, or its event loop's)."""
    if not sys.platform.startswith("linux"):
        return False
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
        return False
    if parent_pid is not None and os.getppid() != parent_pid:
        os.kill(os.getpid(), sig)  # the parent died before the call: nobody would send it now
    return True


def name_this_thread(name: str) -> None:
    """The OS's name of the calling thread (``top -H``, ``ps -L``, ``/proc/<pid>/task/<tid>/comm``), so
    that a service's loops are told apart (the executor's event loop from its servo loop): Python names its
    threads only for itself. At most 15 bytes; where prctl fails the name stays as it was."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0)


def die_with_supervisor() -> None:
    """For a service: if a supervisor said so in the environment, die with it."""
    text = os.environ.get(PARENT_ENV)
    if text and text.isdigit():
        die_with_parent(int(text))
