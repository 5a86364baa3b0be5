"""The 500 Hz servo loop (DESIGN §8, §11): one thread of its own, pinned to a core, SCHED_FIFO when
permitted, garbage collection frozen and off during motion, memory locked when permitted.

Inside the loop there is no logging, no bus I/O and no container that grows: the targets are prepared
before the motion starts, the per-tick timing goes into a preallocated ring, and the loop only indexes,
waits and sends. Deadlines are absolute (tick i is due at t0 + i·period), so a late tick never shifts the
ones after it: the thread sleeps until a few hundred µs before the deadline, then spins. The spin holds
the GIL, and Python's default switch interval (5 ms) is longer than the spin, so no other thread takes the
GIL from it before the deadline; a shorter interval was measured to make the tail worse, not better.

Faster than real time (``speed`` > 1, sim only): a tick of 2 ms·steps/speed wall time sends ``steps``
consecutive samples, so the arm still sees one 2 ms step per sample and the CPU is not spent spinning.

A simulated arm (``realtime=False``) has no controller waiting on the wall clock: its time is the samples
it was sent, one controller step each, however close together they come. A late tick is still counted as
an overrun (the host's timing, reported as ever), but no run of them stops the arm: the ticks after a
short stall come at once until the loop is back on its deadlines, so the arm keeps the pace of the data
time the rest of the cell runs on. A stall past the controller's watchdog does stop it, in the backend
(``SimBackend``), as a real controller would have during the silence. A real robot (``ur_rtde``, the
emulator) keeps the overrun stop exactly as it is.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import gc
import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol, cast

import numpy as np
from numpy.typing import NDArray

from common.runtime.lifetime import name_this_thread
from common.trajectory.scaling import Curve, Ramp
from services.executor.cores import CoreClaim, claim_core, default_lock_dir
from services.executor.playback import Owned, Playback, Samples
from services.executor.settings import Settings
from services.executor.timing import TickSummary, summarise

log = logging.getLogger("cadence.executor")
Array = NDArray[np.float64]
PERIOD_NS = 2_000_000  # 500 Hz: one e-Series controller step
MCL_CURRENT, MCL_FUTURE = 1, 2
PR_SET_TIMERSLACK = 29


class ServoBackend(Protocol):
    """What the loop needs of a backend; every call here runs inside the loop."""

    def servo(self, target: object) -> bool: ...  # False: the arm refused (protective stop, lost link)
    def brake(self) -> bool: ...  # one step of a decelerating stop; True once at rest
    def settled(self, target: object) -> bool: ...
    def target(self, q: Array) -> object: ...  # joints in the form servo takes


def playback_on(
    backend: ServoBackend,
    curve: Curve,
    ramp: Ramp,
    notify: Callable[[], None],
    clock: Callable[[], float],
    hold: object | None,
) -> Playback:
    """A path's playback, its targets (and the joints ``hold``) in the form ``backend`` servos."""
    convert = backend.target
    return Playback(curve, ramp, convert, notify, clock, None if hold is None else convert(cast(Array, hold)))


Outcome = Literal["done", "stopped", "fault", "overruns"]


@dataclass(frozen=True, slots=True)
class MotionResult:
    """How one motion on the loop ended, and what it cost in samples, ticks and missed deadlines."""

    outcome: Outcome
    samples_sent: int
    ticks: int
    overruns: int


class Source(Protocol):
    """What a motion sends (services/executor/playback.py): the next target, None once it has ended."""

    last: object

    @property
    def done(self) -> bool: ...
    def next(self) -> object | None: ...


def source_of(targets: Sequence[object] | Source | Owned) -> Source:
    """What a loop plays: a playback as it is (in this process, it is one), a list of targets in order."""
    if hasattr(targets, "next"):
        return cast(Source, targets)
    return Samples(cast(Sequence[object], targets))


@dataclass(slots=True)
class _Job:
    source: Source
    settle_ticks: int
    future: Future[MotionResult]


OK, FAULT, AT_REST = 0, 1, 2  # what one tick's steps came to


class _Motion:
    """One motion's steps, as both loops take them: the next target or the last one held, a braking
    stop's decelerating steps, and whether the arm has settled. Its counters are the motion's."""

    __slots__ = ("backend", "last", "loop", "sent", "settle_ticks", "source")

    def __init__(self, loop: ServoLoop | LockstepServo, source: Source, settle_ticks: int) -> None:
        self.loop, self.backend, self.source = loop, loop.backend, source
        self.last, self.sent, self.settle_ticks = source.last, 0, settle_ticks

    def step(self, steps: int, braking: bool) -> int:
        """``steps`` controller steps: OK, FAULT (the arm refused one) or AT_REST (a stop is done)."""
        backend, source = self.backend, self.source
        for _ in range(steps):
            if braking:
                if backend.brake():
                    return AT_REST
                continue
            if not source.done:
                target = source.next()
                if target is None:  # it ended at this step: hold the last
                    target = self.last
                    self.settle_ticks -= 1
                else:
                    self.loop.index = self.sent
                    self.sent += 1
                ok = backend.servo(target)
            else:
                ok = backend.servo(self.last)
                self.settle_ticks -= 1
            if not ok:
                return FAULT
        return OK

    def settled(self) -> bool:
        return self.source.done and (self.settle_ticks <= 0 or self.backend.settled(self.last))


class ServoLoop:
    """Owns the 500 Hz thread (on its claimed core, at FIFO priority where granted) and its timing: one
    motion at a time, handed over through a queue, its result a future."""

    def __init__(
        self,
        backend: ServoBackend,
        *,
        core: int | None = None,
        fifo_priority: int = 80,
        lock_memory: bool = True,
        speed: float = 1.0,
        spin_us: int = 400,
        ring: int = 1 << 17,
        overrun_limit: int = 5,
        realtime: bool = True,
        between: Callable[[], None] | None = None,
        errors_ns: NDArray[np.int64] | None = None,
    ) -> None:
        """``between``: called once a tick after its steps were sent (a servo process serves its mailbox
        there: services/executor/servo_process.py); ``errors_ns``: the ring of tick errors, where it is
        not this process's to read (shared memory: its executor takes the percentiles, not a tick)."""
        if speed <= 1.0:
            self.steps, self.period_ns = 1, round(PERIOD_NS / speed)
        else:
            self.steps = math.ceil(speed)
            self.period_ns = round(PERIOD_NS * self.steps / speed)
        self.backend = backend
        self.core, self.fifo_priority, self.lock_memory = core, fifo_priority, lock_memory
        self.spin_ns = spin_us * 1000
        self.overrun_limit = overrun_limit
        self.realtime = realtime
        self.between = between
        self.errors_ns = np.zeros(ring, dtype=np.int64) if errors_ns is None else errors_ns  # |late|, ns
        self.ticks = 0  # since the last reset
        self.overruns = 0
        self.longest_run = 0  # of consecutive overruns, ever
        self.index = -1  # the sample being sent: read by the state publisher, written only here
        self.warnings: list[str] = []  # what the set-up could not get (FIFO, mlock), for the service to log
        self._stop = False
        self._jobs: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._main, name="servo", daemon=True)

    def start(self) -> None:
        self._thread.start()
        self._ready.wait()

    def playback(
        self, curve: Curve, ramp: Ramp, notify: Callable[[], None], clock: Callable[[], float], hold: object
    ) -> Playback:
        """A path's playback on this loop's backend (``PathRun``'s ``make``)."""
        return playback_on(self.backend, curve, ramp, notify, clock, hold)

    def run(self, targets: Sequence[object] | Source | Owned, settle_ticks: int = 0) -> Future[MotionResult]:
        """Queue one motion: the targets (a list, one per sample, or a playback), then up to
        ``settle_ticks`` ticks holding the last one until the backend says the arm has settled on it."""
        fut: Future[MotionResult] = Future()
        self._jobs.put(_Job(source_of(targets), settle_ticks, fut))
        return fut

    def request_stop(self) -> None:
        """A decelerating stop of the current motion (SIGTERM, a shutdown); final: motions queued after
        it only brake."""
        self._stop = True

    def close(self) -> None:
        """End the thread; a loop never started (the arm was never reached) has nothing to end."""
        self._stop = True
        self._jobs.put(None)
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def summary(self) -> TickSummary:
        return summarise(self.errors_ns, self.ticks, self.overruns, self.period_ns, self.longest_run)

    # --- the thread -------------------------------------------------------------------------------

    def _main(self) -> None:
        self.setup()
        self._ready.set()
        while (job := self._jobs.get()) is not None:
            try:
                result = self.play(job.source, job.settle_ticks)
            except BaseException as exc:  # the future carries it to the service
                if job.future.set_running_or_notify_cancel():
                    job.future.set_exception(exc)
            else:
                # a waiter that was cancelled meanwhile (the service ending) wants no result
                if job.future.set_running_or_notify_cancel():
                    job.future.set_result(result)

    def setup(self) -> None:
        """The calling thread becomes the servo's: its name, core, priority and locked memory (the loop's
        own thread, or a servo process's only one). What it could not get goes into ``warnings``."""
        name_this_thread("servo")
        if self.core is not None:
            try:
                os.sched_setaffinity(0, {self.core})
            except OSError as exc:
                self.warnings.append(f"could not pin the servo thread to core {self.core}: {exc.strerror}")
        if self.fifo_priority > 0:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.fifo_priority))
            except OSError as exc:
                self.warnings.append(
                    f"SCHED_FIFO not permitted ({exc.strerror}); the servo thread runs at normal priority. "
                    "Grant LimitRTPRIO= in the unit."
                )
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        with contextlib.suppress(AttributeError):
            libc.prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0)  # wake at the deadline, not 50 µs later
        if self.lock_memory and libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
            self.warnings.append(
                f"memory not locked ({os.strerror(ctypes.get_errno())}); grant LimitMEMLOCK= in the unit"
            )

    def play(self, source: Source, settle_ticks: int) -> MotionResult:
        """One motion, in the calling thread (the servo's: after ``setup``), with the garbage collector
        frozen and off: a collection inside a tick cost milliseconds."""
        gc.collect()
        gc.freeze()
        gc.disable()
        try:
            return self._play(source, settle_ticks)
        finally:
            gc.enable()
            gc.unfreeze()
            self.index = -1

    def _play(self, source: Source, settle_ticks: int) -> MotionResult:
        errors, ring = self.errors_ns, self.errors_ns.size
        between = self.between
        motion = _Motion(self, source, settle_ticks)
        period, spin, steps, limit = self.period_ns, self.spin_ns, self.steps, self.overrun_limit
        clock, sleep = time.perf_counter_ns, time.sleep
        tick = run_of_overruns = overruns = 0
        outcome: Outcome = "done"
        braking = False  # a decelerating stop, paced like any motion
        t0 = clock() + period
        while True:
            deadline = t0 + tick * period
            ahead = deadline - clock() - spin
            if ahead > 0:
                sleep(ahead * 1e-9)
            now = clock()
            while now < deadline:
                now = clock()
            errors[self.ticks % ring] = now - deadline
            self.ticks += 1  # live: a servo process's state says them while a motion lasts
            tick += 1
            if self._stop and not braking:
                braking, outcome = True, "stopped"
            step = motion.step(steps, braking)
            if step == FAULT:
                outcome = "fault"
                break
            if step == AT_REST:
                break
            if between is not None:
                between()
            if clock() > deadline + period:
                overruns += 1
                self.overruns += 1
                run_of_overruns += 1
                if run_of_overruns > self.longest_run:
                    self.longest_run = run_of_overruns
                if run_of_overruns >= limit and self.realtime and not braking:
                    braking, outcome = True, "overruns"
            else:
                run_of_overruns = 0
            if not braking and motion.settled():
                break
        return MotionResult(outcome, motion.sent, tick, overruns)


class Servo(Protocol):
    """What the executor drives: the 500 Hz loop in a process of its own (services/executor/remote.py
    ``ServoProcess``) or a thread (``ServoLoop``), or a lockstep cell's task."""

    warnings: list[str]

    @property
    def index(self) -> int: ...
    @property
    def ticks(self) -> int: ...
    @property
    def overruns(self) -> int: ...

    def start(self) -> None: ...
    def playback(
        self, curve: Curve, ramp: Ramp, notify: Callable[[], None], clock: Callable[[], float], hold: object
    ) -> Owned: ...
    def run(
        self, targets: Sequence[object] | Source | Owned, settle_ticks: int = 0
    ) -> Future[MotionResult] | asyncio.Future[MotionResult]: ...
    def request_stop(self) -> None: ...
    def close(self) -> None: ...
    def summary(self) -> TickSummary: ...


class LockstepServo:
    """The servo loop of a lockstep cell (common/runtime/lockstep.py): a task on the cell's own event loop,
    one controller step per 2 ms of its data time, sent ``batch`` steps at a time. Nothing waits on the
    wall, so there are no deadlines to miss and no overruns; what the arm does at each step is what
    ``ServoLoop`` has it do (the same source, settling, braking and fault outcomes)."""

    def __init__(self, backend: ServoBackend, batch: int = 5) -> None:
        self.backend, self.batch = backend, batch
        self.period_ns = PERIOD_NS
        self.ticks = 0
        self.overruns = 0  # none: its time waits for it
        self.index = -1
        self.warnings: list[str] = []
        self._stop = False
        self._one_at_a_time = asyncio.Lock()

    def start(self) -> None:
        pass

    def playback(
        self, curve: Curve, ramp: Ramp, notify: Callable[[], None], clock: Callable[[], float], hold: object
    ) -> Playback:
        """A path's playback on this loop's backend (``PathRun``'s ``make``)."""
        return playback_on(self.backend, curve, ramp, notify, clock, hold)

    def run(
        self, targets: Sequence[object] | Source | Owned, settle_ticks: int = 0
    ) -> asyncio.Future[MotionResult]:
        return asyncio.ensure_future(self._motion(source_of(targets), settle_ticks))

    def request_stop(self) -> None:
        self._stop = True

    def close(self) -> None:
        self._stop = True

    def summary(self) -> TickSummary:
        return summarise(np.zeros(0, dtype=np.int64), self.ticks, 0, self.period_ns)

    async def _motion(self, source: Source, settle_ticks: int) -> MotionResult:
        async with self._one_at_a_time:
            try:
                return await self._servo(source, settle_ticks)
            finally:
                self.index = -1

    async def _servo(self, source: Source, settle_ticks: int) -> MotionResult:
        motion = _Motion(self, source, settle_ticks)
        tick = 0
        outcome: Outcome = "done"
        braking = False
        while True:
            await asyncio.sleep(self.batch * PERIOD_NS / 1e9)  # the loop's time: data time
            tick += self.batch
            if self._stop and not braking:
                braking, outcome = True, "stopped"
            step = motion.step(self.batch, braking)
            if step == FAULT:
                outcome = "fault"
                break
            if step == AT_REST or (not braking and motion.settled()):
                break
        self.ticks += tick
        return MotionResult(outcome, motion.sent, tick, 0)


def servo_for(
    backend: ServoBackend, settings: Settings, speed: float, realtime: bool, lockstep: bool = False
) -> tuple[Servo, CoreClaim]:
    """The executor's loop, on a core it claimed (cores.py); FIFO only there, so that two executors on one
    host never share a core at FIFO priority. In a lockstep cell: a task on its loop, and no core."""
    if lockstep:
        return LockstepServo(backend), CoreClaim(None, None)
    s = settings
    claim, fifo, warnings = claim_for(s)
    loop = ServoLoop(backend, core=claim.core, fifo_priority=fifo, lock_memory=s.lock_memory, speed=speed,
                     spin_us=s.spin_us, overrun_limit=s.overrun_limit, realtime=realtime)  # fmt: skip
    loop.warnings += warnings
    return loop, claim


def claim_for(s: Settings) -> tuple[CoreClaim, int, list[str]]:
    """A core for the servo (cores.py), the FIFO priority it may take there, and what it goes without:
    FIFO only on a core of its own, so that two executors on one host never share a core at FIFO."""
    claim = claim_core(os.sched_getaffinity(0), Path(s.lock_dir or default_lock_dir()), s.servo_core)
    fifo = s.fifo_priority if claim.core is not None else 0
    warnings = []
    if claim.core is None:  # no core of its own: no FIFO either (two FIFO threads would share a core)
        warnings.append(claim.note)
    elif s.fifo_priority == 0:
        warnings.append("fifo_priority = 0: the servo runs at normal priority (set it, 1–99)")
    if not s.lock_memory:
        warnings.append("lock_memory = false: the servo loop's memory may be paged out (set it true)")
    return claim, fifo, warnings
