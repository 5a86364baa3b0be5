"""The shared memory between the executor, its servo process and its separation guard (``Channel``, over
common/runtime/mailbox.py), laid out the same in all three, and what starting such a child takes."""

from __future__ import annotations

import signal
from typing import ClassVar

import numpy as np

from common.runtime.mailbox import Latest, Ring

# numpy and its BLAS start no threads of their own in the executor's children (the servo, the guard)
QUIET = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def said(returncode: int) -> str:
    if returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = f"signal {-returncode}"
        return f"killed by {name}"
    return f"exit status {returncode}"


class Channel:
    """The shared memory's layout, the same on all sides: ``ctrl`` (the executor's: stop, lease until,
    renewals), ``state`` (the servo's, rewritten every tick), ``guard`` (the separation guard's word:
    services/executor/guard_process.py), three rings, and the rings of tick errors and guard adoptions."""

    CTRL, STATE, FAULT_BYTES, ERRORS, GUARD, ADOPTIONS = 3, 40, 1024, 1 << 17, 6, 1 << 14
    RINGS: ClassVar[dict[str, int]] = {"cmd": 4 << 20, "events": 1 << 20, "replies": 1 << 20}
    # state's values by name (``q``, ``qd``, ``tcp`` are 6 wide)
    AT: ClassVar[dict[str, int]] = {"run": 0, "index": 1, "ticks": 2, "overruns": 3, "t": 4, "s": 5,
                                    "sigma": 6, "inputs": 7, "lost": 8, "beat": 9, "moving": 10, "q": 11,
                                    "qd": 17, "tcp": 23, "longest": 29, "v_r": 30, "t_s": 31, "b_s": 32,
                                    "cuts": 33, "adopted": 34, "unheard": 35}  # fmt: skip
    NAME_BYTES = 256  # the guard's text: the nearest's source (or why none), for what the executor says
    # the guard's values by name: the run it judged, σ allowed, since when (its last fall), its beat, the
    # nearest room S − C (NaN: none, a hold)
    GUARD_AT: ClassVar[dict[str, int]] = {"run": 0, "sigma": 1, "since": 2, "beat": 3, "distance": 4}
    # the blocks and rings, each rounded up to 8 bytes, in whole pages
    SIZE = (Latest.nbytes(CTRL) + Latest.nbytes(STATE, FAULT_BYTES) + Latest.nbytes(GUARD, NAME_BYTES)
            + sum(RINGS.values()) + 8 * (ERRORS + ADOPTIONS) + 8192) // 4096 * 4096  # fmt: skip

    def __init__(self, buf: memoryview) -> None:
        at = 0

        def take(n: int) -> memoryview:
            nonlocal at
            part, at = buf[at : at + n], (at + n + 7) // 8 * 8
            return part

        self.ctrl = Latest(take(Latest.nbytes(self.CTRL)), self.CTRL)
        self.state = Latest(take(Latest.nbytes(self.STATE, self.FAULT_BYTES)), self.STATE, self.FAULT_BYTES)
        self.guard = Latest(take(Latest.nbytes(self.GUARD, self.NAME_BYTES)), self.GUARD, self.NAME_BYTES)
        self.cmd, self.events, self.replies = (Ring(take(n)) for n in self.RINGS.values())
        self.errors_ns = np.frombuffer(take(8 * self.ERRORS), dtype=np.int64)  # the loop's tick errors
        # the guard's adoptions (s): its word that σ must fall → the step that plays it, ``adopted`` counts
        self.adoptions = np.frombuffer(take(8 * self.ADOPTIONS), dtype=np.float64)
