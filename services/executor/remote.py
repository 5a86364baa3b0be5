"""The executor's side of its servo process (services/executor/servo_process.py): the process started,
watched and restarted (``ServoProcess``, the ``Servo`` the motions drive), the robot as the parts see it
across the process boundary (``RemoteBackend``), and a mirror of the path's playback for its owner
(``RemotePlayback``, the ``Owned`` that ``PathRun`` plans on).

Nothing here waits on the servo: offers, the stop kept ready and the lease are written and left; the
servo's word on them comes back as events, drained on the executor's loop when the servo's wake-up byte
arrives. Only calls into the backend (connect, a resume, the gripper) wait for their answer, in the worker
threads that make them. A servo process that dies (a segfault in the robot's library, a kill) is seen at
once (its pidfd), the motion in flight ends as a fault, the stop is latched until a person's resume, and a
new process is started, stopped, where the arm stands.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import mmap
import os
import pickle
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from common.safety.separation import Figures
from common.trajectory.scaling import DT, Curve, Ramp
from services.executor.backends import AT_REST, RobotUnavailable
from services.executor.channel import QUIET, Channel, said
from services.executor.playback import InForce, Offer, Owned, Switch
from services.executor.servo import PERIOD_NS, MotionResult, Source
from services.executor.servo_process import Config, Ref
from services.executor.settings import Settings
from services.executor.timing import TickSummary, summarise

Array = NDArray[np.float64]
log = logging.getLogger("cadence.executor")
START_S = 60.0  # a servo process's start (numpy's import on a loaded host, a robot's library)
CALL_S = 60.0  # a call into the backend (a controller's connect, a benchmark's moveJ)
POLL_S = 0.0005  # how often a call's waiter looks for its answer


class RemotePlayback:
    """The owner's picture of the playback in the servo process: ``now`` changes when the servo says it
    changed, as one ``InForce`` built from the executor's own objects, so that ``base is now`` and ``ramp is
    now.ramp`` mean what they mean beside a playback in the servo's thread (playback.py)."""

    def __init__(
        self, proc: ServoProcess, curve: Curve, ramp: Ramp, notify: Callable[[], None], hold: object
    ):
        self.proc, self.notify, self.hold = proc, notify, hold
        self.run_id = 0  # given when it runs
        self.objs: dict[int, Any] = {}  # tag → object (the executor's, or one the servo made)
        self.tags: dict[int, int] = {}  # id(object) → tag
        self.now = InForce(ramp, curve)
        self.version = 0
        self.mailbox: Offer | None = None
        self._mail_seq = self._seen_seq = 0
        self._fallback: Offer | None = None
        self._stop_s = 1.0
        self._figures: Figures | None = None
        self.began: tuple[Ramp, float] | None = None
        self.lapses = self.unchecked = 0
        self.finished = False
        self._last = (0.0, 0.0, float(ramp.c[0]))  # t, s, σ the servo last said, for a playback not live
        self._held: list[tuple[Any, ...]] = []  # commands before it runs: sent after its start
        self.started = False

    # --- objects that cross -------------------------------------------------------------------------

    def ref(self, o: object | None) -> Ref | None:
        if o is None:
            return None
        if (tag := self.tags.get(id(o))) is not None:
            return tag, None
        tag = len(self.objs) + 1
        self.objs[tag], self.tags[id(o)] = o, tag
        if isinstance(o, Switch):
            return tag, (o.s, self.ref(o.curve), o.max_sigma)
        return tag, o

    def obj(self, ref: Ref | None) -> Any:
        if ref is None:
            return None
        tag, o = ref
        if o is not None:  # made by the servo (an unchecked stop)
            self.objs[tag], self.tags[id(o)] = o, tag
        return self.objs[tag]

    def send(self, m: tuple[Any, ...]) -> None:
        if self.started:
            self.proc.put(m)
        else:
            self._held.append(m)

    def begin(self, run_id: int) -> tuple[Any, ...]:
        """The run's command (its curve, ramp and hold): the commands held until then follow it."""
        self.run_id = run_id
        return ("path", self.ref(self.now.curve), self.ref(self.now.ramp), self.hold)

    def flush(self) -> None:
        self.started = True
        held, self._held = self._held, []
        for m in held:
            self.proc.put(m)

    # --- the owner's side (playback.Owned) ------------------------------------------------------------

    def _live(self) -> tuple[float, float, float]:
        if self.started and not self.finished:
            live = self.proc.live(self.run_id)
            if live is not None:
                return live
        return self._last

    @property
    def t(self) -> float:
        return self._live()[0]

    @property
    def s(self) -> float:
        return self._live()[1]

    @property
    def sigma(self) -> float:
        return self._live()[2]

    @property
    def curve(self) -> Curve:
        return self.now.curve

    @property
    def fallback(self) -> Offer | None:
        return self._fallback

    @fallback.setter
    def fallback(self, offer: Offer | None) -> None:
        self._fallback = offer
        if offer is not None and offer.ramp is not None:
            version = self.version if offer.base is self.now else -1
            self.send(("fallback", version, self.ref(offer.ramp)))

    @property
    def figures(self) -> Figures | None:
        return self._figures

    @figures.setter
    def figures(self, figures: Figures | None) -> None:
        if figures is not None and figures != self._figures:
            self.send(("figures", (figures.speed_m_s, figures.stop_time_s, figures.stop_travel_s)))
        self._figures = figures

    @property
    def stop_s(self) -> float:
        return self._stop_s

    @stop_s.setter
    def stop_s(self, value: float) -> None:
        if value != self._stop_s:
            self._stop_s = value
            self.send(("stop_s", value))

    def offer(
        self, ramp: Ramp | None = None, switch: Switch | None = None, base: InForce | None = None
    ) -> bool:
        base = base or self.now
        t, s, _ = self._live()
        late = (ramp is not None and ramp.t0 < t + DT / 2) or (switch is not None and switch.s <= s)
        if base is not self.now or self.finished or late:
            return False
        self._mail_seq += 1
        self.mailbox = Offer(base, ramp, switch)
        self.send(("offer", self._mail_seq, self.version, self.ref(ramp), self.ref(switch)))
        return True

    def renew(self, until: float) -> None:
        self.proc.renew(until)

    def settled(self, offer: Offer | None = None) -> bool:
        offer = offer or self.mailbox
        return self.finished or (offer is self.mailbox and self._seen_seq >= self._mail_seq)

    def state(self) -> Ramp:
        return self.now.ramp.rebased(self.t)

    # --- the servo's word -----------------------------------------------------------------------------

    def apply(self, e: tuple[Any, ...]) -> None:
        (_, _, version, ramp, curve, pending_ramp, pending_switch, seen, began, finished, lapses, unchecked,
         t, s, sigma) = e  # fmt: skip
        parts = (self.obj(ramp), self.obj(curve), self.obj(pending_ramp), self.obj(pending_switch))
        if version != self.version:
            self.now, self.version = InForce(*parts), version
        self._seen_seq = seen
        self.began = None if began is None else (self.obj(began[0]), began[1])
        self.finished, self.lapses, self.unchecked = finished, lapses, unchecked
        self._last = (t, s, sigma)
        self.notify()

    def end(self) -> None:
        """The servo process died under it: nothing more plays."""
        self.finished = True
        self.notify()


class Mailbox:
    """The executor's end of the shared memory (servo_process.py ``Channel``): commands put, the stop and
    the lease written, the state read, and the answer to a call awaited (the one wait, a worker's)."""

    def __init__(self, ch: Channel, ended: Callable[[], str | None], bell: int) -> None:
        """``ended``: None while the servo process runs, else how it ended; ``bell``: a pipe whose byte
        wakes it at rest."""
        self.ch, self.ended, self.bell = ch, ended, bell
        self._put = threading.Lock()  # one writer at a time
        self._call = threading.Lock()  # one call in flight
        self._numbers = itertools.count(1)
        self.renewals, self.stop = 0, 0.0
        # the state a dead servo process left, at rest, until a new one says its own (a restart)
        self.frozen: NDArray[np.float64] | None = None

    def number(self) -> int:
        return next(self._numbers)

    def put(self, m: tuple[Any, ...]) -> None:
        with self._put:
            ok = self.ch.cmd.put(m)
        with contextlib.suppress(BlockingIOError, BrokenPipeError):  # rung already, or nobody to wake
            os.write(self.bell, b"\0")
        if not ok:
            raise RobotUnavailable(
                f"the servo process reads no commands ({self.ended() or 'its mailbox is full'})"
            )

    def ctrl(self, until: float | None = None) -> None:
        """The stop flag and the lease (``until``: a renewal), latest wins."""
        with self._put:
            v = self.ch.ctrl.view
            if until is not None:
                v[1], self.renewals = until, self.renewals + 1
            v[0], v[2] = self.stop, self.renewals
            self.ch.ctrl.write()

    def answer(self, n: int, within_s: float, what: str) -> Any:
        deadline = time.monotonic() + within_s
        while True:
            r = self.ch.replies.get()
            if r is None:
                if (how := self.ended()) is not None:
                    raise RobotUnavailable(f"the servo process ended before it answered {what}: {how}")
                if time.monotonic() > deadline:
                    raise RobotUnavailable(f"the servo process did not answer {what} within {within_s:g} s")
                time.sleep(POLL_S)
                continue
            number, ok, value = r
            if number != n:  # the answer to a call that gave up waiting
                continue
            if ok:
                return value
            raise value

    def hello(self) -> Any:
        """A new servo process's first word (its set-up), read as a call's answer is: one reader."""
        with self._call:
            return self.answer(0, START_S, "to start")

    def call(self, kind: str, *args: object, within_s: float = CALL_S) -> Any:
        """A command of ``kind``, numbered, its answer awaited (a call into the backend: "call")."""
        with self._call:
            n = self.number()
            self.put((kind, n, *args))
            return self.answer(n, within_s, f"'{args[0] if args else kind}'")

    def values(self) -> NDArray[np.float64] | None:
        if self.frozen is not None:
            return self.frozen
        got = self.ch.state.read()
        return None if got is None else got[0]

    def value(self, name: str) -> float:
        v = self.values()
        return 0.0 if v is None else float(v[Channel.AT[name]])

    def live(self, run_id: int) -> tuple[float, float, float] | None:
        """(t, s, σ) of the run now, while the servo plays it."""
        v = self.values()
        at = Channel.AT
        if v is None or int(v[at["run"]]) != run_id or not v[at["moving"]]:
            return None
        return float(v[at["t"]]), float(v[at["s"]]), float(v[at["sigma"]])


class ServoProcess:
    """The servo process as the executor drives it (servo.py's ``Servo``), started, watched and
    restarted here. ``on_death``: called on the executor's loop with why, when it dies between motions
    (a motion in flight ends as a fault, which its caller latches)."""

    def __init__(
        self,
        settings: Settings,
        speed: float,
        core: int | None,
        fifo_priority: int,
        on_death: Callable[[str], None] = lambda why: None,
    ) -> None:
        self.settings, self.speed, self.core, self.fifo_priority = settings, speed, core, fifo_priority
        self.on_death = on_death
        self.fd = os.memfd_create("cadence-servo", 0)
        os.ftruncate(self.fd, Channel.SIZE)
        self.mm = mmap.mmap(self.fd, Channel.SIZE)
        self.ch = Channel(memoryview(self.mm))
        self.wake_r, self.wake_w = os.pipe()  # the servo's word: wakes the executor's loop
        self.bell_r, self.bell_w = os.pipe()  # a command: wakes the servo at rest
        for fd in (self.wake_r, self.wake_w, self.bell_r, self.bell_w):
            os.set_blocking(fd, False)
        self.proc: subprocess.Popen[bytes] | None = None
        self.pidfd: int | None = None
        self.info: dict[str, Any] = {}
        self.warnings: list[str] = []
        self.died = ""  # why the last one ended unasked: a latched fault until a person's resume
        self.restarting: threading.Thread | None = None
        self.mail = Mailbox(self.ch, self.ended, self.bell_w)
        self._runs: dict[int, tuple[Future[MotionResult], RemotePlayback | None]] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closing = False

    # --- the process ----------------------------------------------------------------------------------

    def _spawn(self, q0: Array | None) -> None:
        self.mm[:] = bytes(Channel.SIZE)  # a fresh mailbox: nothing of the last one's
        self.mail.renewals = 0
        config = Config(self.settings, self.speed, self.core, self.fifo_priority,
                        None if q0 is None else tuple(float(x) for x in q0))  # fmt: skip
        # its Python stack in the executor's log, should it crash
        module = "services.executor.servo_process"
        fds = (self.fd, self.wake_w, self.bell_r)
        cmd = [sys.executable, "-X", "faulthandler", "-m", module, *map(str, fds)]
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, pass_fds=fds,
                                env={**os.environ, **QUIET}, start_new_session=True)  # fmt: skip
        assert proc.stdin is not None
        proc.stdin.write(pickle.dumps(config))
        proc.stdin.close()
        self.proc = proc
        ready = self.mail.hello()
        self.mail.frozen = None  # its first state came before its word
        self.info, self.warnings = ready, list(ready["warnings"])

    def start(self) -> None:
        """Start it and wait for its set-up (what it could not get is in ``warnings``); from within the
        executor's loop, its word and its death are watched there."""
        self._spawn(None)
        try:
            self._loop = asyncio.get_running_loop()
        except RuntimeError:
            return
        self._watch()

    def _watch(self) -> None:
        loop, proc = self._loop, self.proc
        if loop is None or proc is None or self._closing:
            return
        loop.add_reader(self.wake_r, self._drain)
        self.pidfd = os.pidfd_open(proc.pid)
        loop.add_reader(self.pidfd, self._exited)

    def _exited(self) -> None:
        """Its pidfd is readable: it ended. Asked to (``close``), or it died: then latched and restarted."""
        proc, loop = self.proc, self._loop
        if self.pidfd is not None and loop is not None:
            loop.remove_reader(self.pidfd)
            os.close(self.pidfd)
            self.pidfd = None
        if proc is None or self._closing:
            return
        self._drain()
        why = f"the servo process died ({said(proc.wait())})"
        self.died = why
        log.error("%s: the arm is stopped; resume after checking the cell", why)
        q0, values = self.where(), self.mail.values()
        if values is not None:  # what the executor says of the arm until the new one runs: still, there
            at = Channel.AT["qd"]
            values[at : at + 6] = 0.0
            self.mail.frozen = values
        in_flight = bool(self._runs)
        for run_id, (fut, pb) in list(self._runs.items()):
            self._runs.pop(run_id)
            if pb is not None:
                pb.end()
            if not fut.done():
                fut.set_result(MotionResult("fault", 0, 0, 0))
        if not in_flight:
            self.on_death(why)
        self.restarting = threading.Thread(target=self.restart, args=(q0,), name="servo-restart", daemon=True)
        self.restarting.start()

    def restart(self, q0: Array | None) -> None:
        if self._closing:
            return
        try:
            self._spawn(q0)
            self.mail.call("call", "connect", ())
        except Exception as exc:  # said; the next resume tries the robot again
            log.error("the servo process could not be restarted: %s", exc)
            return
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._watch)

    def close(self) -> None:
        """Ends it after the motion in flight (``request_stop`` first for a stop of it)."""
        self._closing = True
        restarting = self.restarting
        if restarting is not None and restarting is not threading.current_thread():
            restarting.join(START_S)  # a new one half-started: ended below, its descriptors still open
        proc = self.proc
        if proc is not None and proc.poll() is None:
            self.put(("exit",))
            try:
                proc.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        loop = self._loop
        try:
            here = asyncio.get_running_loop()
        except RuntimeError:  # a worker thread's call (the node's close)
            here = None
        if loop is not None and loop is not here and not loop.is_closed():
            loop.call_soon_threadsafe(self._forget)  # its readers are the loop's to remove
        else:
            self._forget()

    def _forget(self) -> None:
        """Its readers off the executor's loop, and its descriptors closed."""
        loop = self._loop
        for fd in (self.wake_r, self.pidfd):
            if loop is not None and not loop.is_closed() and fd is not None:
                loop.remove_reader(fd)
        for fd in (self.wake_r, self.wake_w, self.bell_r, self.bell_w, self.pidfd, self.fd):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.pidfd = None

    def where(self) -> Array | None:
        """The joints it last said."""
        v = self.mail.values()
        return None if v is None else v[Channel.AT["q"] : Channel.AT["q"] + 6].copy()

    def ended(self) -> str | None:
        proc = self.proc
        return "not started" if proc is None else None if proc.poll() is None else said(proc.returncode)

    def put(self, m: tuple[Any, ...]) -> None:
        self.mail.put(m)

    def renew(self, until: float) -> None:
        self.mail.ctrl(until)

    def request_stop(self) -> None:
        self.mail.stop = 1.0
        self.mail.ctrl()

    def call(self, name: str, *args: object, within_s: float = CALL_S) -> Any:
        """A call into the backend in the servo process, its answer awaited (from a worker thread; one
        made while it restarts waits for the new one)."""
        if self.restarting is not None and self.restarting.is_alive():
            self.restarting.join(START_S)
        return self.mail.call("call", name, args, within_s=within_s)

    def live(self, run_id: int) -> tuple[float, float, float] | None:
        return self.mail.live(run_id)

    def _drain(self) -> None:
        """On the executor's loop, woken by the servo's byte: every event since the last."""
        try:
            while os.read(self.wake_r, 4096):
                pass
        except (BlockingIOError, OSError):
            pass
        while (e := self.ch.events.get()) is not None:
            run = self._runs.get(e[1])
            if run is None:
                continue
            fut, pb = run
            if e[0] == "state" and pb is not None:
                pb.apply(e)
            elif e[0] == "result":
                self._runs.pop(e[1])
                if not fut.done():
                    fut.set_result(e[2])

    # --- Servo ----------------------------------------------------------------------------------------

    @property
    def index(self) -> int:
        return int(self.mail.value("index"))

    @property
    def ticks(self) -> int:
        return int(self.mail.value("ticks"))

    @property
    def overruns(self) -> int:
        return int(self.mail.value("overruns"))

    def playback(
        self, curve: Curve, ramp: Ramp, notify: Callable[[], None], clock: Callable[[], float], hold: object
    ) -> RemotePlayback:
        """A mirror of the playback the servo process will play (its clock is the host's monotonic one,
        the executor's loop's own)."""
        return RemotePlayback(
            self, curve, ramp, notify, None if hold is None else np.asarray(hold, dtype=float)
        )

    def run(self, targets: Sequence[object] | Source | Owned, settle_ticks: int = 0) -> Future[MotionResult]:
        fut: Future[MotionResult] = Future()
        if self.died:
            fut.set_result(MotionResult("fault", 0, 0, 0))
            return fut
        n = self.mail.number()
        pb = targets if isinstance(targets, RemotePlayback) else None
        if pb is not None:
            spec, stop_s = pb.begin(n), pb.stop_s
        else:
            spec, stop_s = (
                ("samples", [np.asarray(t, dtype=float) for t in cast(Sequence[Any], targets)]),
                1.0,
            )
        self._runs[n] = (fut, pb)
        self.put(("run", n, spec, settle_ticks, stop_s))
        if pb is not None:
            pb.flush()
        return fut

    def summary(self) -> TickSummary:
        """Taken here, from the ring it writes: percentiles of 10⁵ ticks are not a tick's work."""
        m = self.mail
        period = int(self.info.get("period_ns", PERIOD_NS))
        return summarise(self.ch.errors_ns.copy(), self.ticks, self.overruns, period, int(m.value("longest")))


class RemoteBackend:
    """The robot as the executor's parts see it when it lives in the servo process: its state read from
    the shared block (rewritten every tick; the fault, inputs and pose at 20 Hz in motion), its actions
    called there. ``target`` is the joints themselves: the servo process puts them in its backend's form."""

    def __init__(self, proc: ServoProcess) -> None:
        self.proc = proc
        self.name = str(proc.info.get("name", "sim"))
        self.realtime = bool(proc.info.get("realtime", False))

    def _six(self, name: str) -> Array:
        v = self.proc.mail.values()
        at = Channel.AT[name]
        return np.zeros(6) if v is None else v[at : at + 6].copy()

    def actual_q(self) -> Array:
        return self._six("q")

    def actual_qd(self) -> Array:
        return self._six("qd")

    def tcp_pose(self) -> Array:
        return self._six("tcp")

    def measured(self) -> bool:
        """False while the servo process has written nothing for longer than its controller's watchdog
        waits, the arm last seen moving: the controller has stopped it meanwhile, where and how only the
        servo will say once it runs again, so the speed read is not the arm's (a walk-in on a loaded host
        read a starved servo's 0.11 m/s for 1.4 s beside a person while the arm stood)."""
        watchdog, v = self.proc.info.get("watchdog_s"), self.proc.mail.values()
        if watchdog is None or v is None:
            return True
        at = Channel.AT
        silent = time.monotonic() - float(v[at["beat"]])
        return not (silent > watchdog and float(np.abs(v[at["qd"] : at["qd"] + 6]).max()) > AT_REST)

    def fault(self) -> str:
        if self.proc.died:
            return self.proc.died
        got = self.proc.ch.state.read()
        return "" if got is None else got[1]

    def link_lost(self) -> bool:
        return bool(self.proc.died) or bool(self.proc.mail.value("lost"))

    def digital_inputs(self) -> int:
        return int(self.proc.mail.value("inputs"))

    def target(self, q: Array) -> object:
        return q

    def connect(self) -> None:
        self.proc.call("connect")

    def close(self) -> None:
        if self.proc.proc is not None and self.proc.proc.poll() is None and not self.proc.died:
            self.proc.call("close")

    def reconnect(self) -> None:
        self.proc.call("reconnect")

    def reset_fault(self) -> None:
        """A person's resume: also of a dead servo process's stop, once the new one runs (started again
        here should its restart have failed)."""
        proc = self.proc
        if proc.died and proc.ended() is not None and not (proc.restarting and proc.restarting.is_alive()):
            proc.restart(proc.where())
        proc.call("reset_fault")
        proc.died = ""

    def prepare(self, q: Array) -> Sequence[object]:
        if self.proc.died:  # the motion after it ends as a fault at once: nothing to arm
            return []
        return cast(Sequence[object], self.proc.call("prepare", q))

    def motion_ended(self) -> None:
        self.proc.call("motion_ended")

    def move_j(self, q: Array, speed: float, acceleration: float) -> bool:
        return bool(self.proc.call("move_j", q, speed, acceleration))

    def set_gripper(self, on: bool) -> None:
        self.proc.call("set_gripper", on)

    def servo(self, target: object) -> bool:
        raise RuntimeError("the servo process servos; the executor does not")

    def brake(self) -> bool:
        raise RuntimeError("the servo process brakes; the executor does not")

    def settled(self, target: object) -> bool:
        raise RuntimeError("the servo process settles; the executor does not")
