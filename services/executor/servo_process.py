"""The servo process (DESIGN §8): the 500 Hz loop, the path it plays and the robot's backend, alone in a
process of its own, single-threaded, on its core at SCHED_FIFO with its memory locked.

Why a process: a thread is not real-time while another thread of its process runs. The GIL has no
priority inheritance, so a FIFO servo thread waits for whatever ordinary thread of the executor holds it,
and a loaded host deschedules that one: 77 % of ticks overran beside one busy thread, and a reading took
up to 1.5 s to reach the arm (issue 73). Here no other thread exists to hold it.

It talks to its executor through shared memory only (``Channel``, common/runtime/mailbox.py), and never
waits for it: commands come through a ring read between ticks (a path's curves, an offer of a ramp or a
switch, the stop kept ready, a call into the backend), the lease and a stop through a latest-wins block,
and it writes back the arm's state every tick, what it did with each offer as it does it (``events``),
and the calls' answers (``replies``). The lease lives here: when the executor's renewals stop (a stalled or
dead executor, a starved event loop), the playback takes the stop kept ready by itself (playback.py).
The executor supervises it (services/executor/remote.py): a death here is a latched protective stop.

It imports what a tick needs: no Zenoh, no scipy, and no thread of numpy's (OPENBLAS_NUM_THREADS=1).
Started as ``python -m services.executor.servo_process FD WAKE BELL`` with its configuration pickled on
stdin: FD a memfd of ``Channel.SIZE`` bytes, WAKE a pipe's write end (a byte there wakes the executor's
loop), BELL a pipe's read end (a byte there wakes it at rest: a command came).
"""

from __future__ import annotations

import contextlib
import mmap
import os
import pickle
import select
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.trajectory.task import load_task
from services.executor.backends import Backend, SimBackend, UrRtdeBackend, backend_for
from services.executor.channel import Channel
from services.executor.playback import SIGMA_EPS, InForce, Offer, Playback, Samples, Switch
from services.executor.servo import MotionResult, ServoLoop, Source, playback_on
from services.executor.settings import Settings

# the share of the adoption budget the executor's own ramp has before the guard's σ is taken here: the
# rest is the guard's hop (a reading → its σ, a few ms) and the step that plays it
GUARD_GRACE = 0.25
GUARD_SILENT_S = 0.05  # a guard not heard for this long is not heard at all (the executor alone scales)
IDLE_S = 0.05  # at rest, the arm's state is rewritten this often; a command rings the bell meanwhile
SLOW_EVERY = 25  # ticks: the fault, the inputs and the tool's pose are read at 20 Hz during a motion
# what the executor may call on the backend through the mailbox (the rest is state, or the loop's own)
CALLS = frozenset(
    {"connect", "close", "reconnect", "reset_fault", "prepare", "motion_ended", "move_j", "set_gripper"}
)


@dataclass(frozen=True, slots=True)
class Config:
    """What the servo process is started with (pickled on its stdin)."""

    settings: Settings
    speed: float
    core: int | None
    fifo_priority: int
    q0: tuple[float, ...] | None = None  # a sim arm restarted where the last one stood


Ref = tuple[int, Any]  # (tag, the object itself the first time it crosses, else None)


class Server:
    """Serves the executor between ticks and while idle: its commands in, the arm's state and the
    playback's changes out."""

    def __init__(self, ch: Channel, backend: Backend, loop: ServoLoop, wake: int, bell: int) -> None:
        self.ch, self.backend, self.loop, self.wake, self.bell = ch, backend, loop, wake, bell
        self.parent = os.getppid()
        self.objs: dict[int, Any] = {}  # tag → the executor's curve, ramp or switch
        self.tags: dict[int, int] = {}  # id(object) → its tag
        self.made = 0  # tags of objects made here (a lapse's unchecked stop): negative
        self.pb: Playback | None = None
        self.run_id = 0
        self.version = 0  # counts the playback's InForce replacements
        self.in_force: InForce | None = None
        self.offer: tuple[Offer, int] | None = None  # the last offer put in the mailbox, and its number
        self.seen_seq = 0
        self.renewals = 0.0
        self.next_run: tuple[int, Source, int] | None = None
        self.ticks = 0
        self.exiting = False
        self.figures: tuple[float, float, float] | None = None  # the curve's: v_r, T_s, B / v_r (the guard's)
        self.heed: Heed | None = None  # the separation guard's word (None: separation off)
        self._fault = ""
        self.crash = ""  # what the backend raised inside a tick: the fault from then on

    # --- objects that cross -------------------------------------------------------------------------

    def obj(self, ref: Ref | None) -> Any:
        if ref is None:
            return None
        tag, o = ref
        if o is not None:
            self.objs[tag], self.tags[id(o)] = o, tag
        return self.objs[tag]

    def switch(self, ref: Ref | None) -> Switch | None:
        """A switch crosses as (s, its curve's ref, max σ): its curve is then the same object as a curve's."""
        if ref is None:
            return None
        tag, parts = ref
        if parts is not None:
            sw = Switch(parts[0], self.obj(parts[1]), parts[2])
            self.objs[tag], self.tags[id(sw)] = sw, tag
        return self.objs[tag]

    def ref(self, o: object | None) -> Ref | None:
        if o is None:
            return None
        tag = self.tags.get(id(o))
        if tag is not None:
            return tag, None
        self.made -= 1
        self.objs[self.made], self.tags[id(o)] = o, self.made
        return self.made, o

    # --- the executor's commands ----------------------------------------------------------------------

    def handle(self, m: tuple[Any, ...]) -> None:
        kind = m[0]
        if kind == "call":
            _, n, name, args = m
            try:
                if name not in CALLS:
                    raise ValueError(f"the servo process takes no call '{name}'")
                answer: tuple[Any, ...] = (n, True, getattr(self.backend, name)(*args))
            except Exception as exc:  # the executor raises it where it called
                answer = (n, False, exc)
            self.publish(slow=True)  # what the call changed (a fault, the inputs), before its answer
            self.reply(answer)
        elif kind == "run":
            self.begin(*m[1:])
        elif kind == "offer" and self.pb is not None:
            _, seq, version, ramp, switch = m
            offer = Offer(self.base(version), self.obj(ramp), self.switch(switch))
            self.offer, self.pb.mailbox = (offer, seq), offer
        elif kind == "fallback" and self.pb is not None:
            _, version, ramp = m
            self.pb.fallback = Offer(self.base(version), ramp=self.obj(ramp))
        elif kind == "stop_s" and self.pb is not None:
            self.pb.stop_s = m[1]
        elif kind == "figures":
            self.figures = m[1]
        elif kind == "exit":
            self.exiting = True

    def reply(self, answer: tuple[Any, ...]) -> None:
        try:
            ok = self.ch.replies.put(answer)
        except Exception as exc:  # an answer that does not pickle: its words do
            ok = self.ch.replies.put((answer[0], False, RuntimeError(f"{answer[2]!r}: {exc}")))
        if ok:
            self._wake()

    def base(self, version: int) -> InForce:
        """The state an offer was planned from: the one in force if its version is current, else one that
        is never in force (the playback then drops the offer, as it would a stale one)."""
        pb = self.pb
        assert pb is not None
        return pb.now if version == self.version else InForce(pb.now.ramp, pb.now.curve)

    def begin(self, run_id: int, spec: tuple[Any, ...], settle: int, stop_s: float) -> None:
        self.objs.clear()
        self.tags.clear()
        self.run_id, self.version, self.offer, self.seen_seq = run_id, 0, None, 0
        self.figures = None
        if self.heed is not None:
            self.heed.begin(run_id)
        source: Source
        if spec[0] == "path":
            _, curve, ramp, hold = spec
            clock = time.monotonic  # the host's: the executor's loop's too
            pb = self.pb = playback_on(
                self.backend, self.obj(curve), self.obj(ramp), self.changed, clock, hold
            )
            pb.stop_s = stop_s
            self.in_force = pb.now
            source = pb
        else:
            target = self.backend.target
            source = Samples([target(np.asarray(row, dtype=float)) for row in spec[1]])
        self.next_run = (run_id, source, settle)

    # --- what goes back -------------------------------------------------------------------------------

    def _wake(self) -> None:
        with contextlib.suppress(BlockingIOError, BrokenPipeError):  # a byte is there, or nobody reads
            os.write(self.wake, b"\0")

    def changed(self) -> None:
        """The playback's notification (once per change, from inside a tick): its state, by tags."""
        pb = self.pb
        if pb is None:
            return
        if pb.now is not self.in_force:
            self.version, self.in_force = self.version + 1, pb.now
        if self.offer is not None and pb.seen is self.offer[0]:
            self.seen_seq = self.offer[1]
        now, began = pb.now, pb.began
        self.ch.events.put(("state", self.run_id, self.version, self.ref(now.ramp), self.ref(now.curve),
                            self.ref(now.pending_ramp), self.ref(now.pending_switch), self.seen_seq,
                            None if began is None else (self.ref(began[0]), began[1]), pb.finished,
                            pb.lapses, pb.unchecked, pb.t, pb.s, pb.sigma))  # fmt: skip
        self._wake()

    def publish(self, slow: bool) -> None:
        st, at, b, loop = self.ch.state, Channel.AT, self.backend, self.loop
        v = st.view
        v[at["run"]], v[at["index"]], v[at["ticks"]] = self.run_id, loop.index, loop.ticks
        v[at["longest"]] = loop.longest_run
        v[at["overruns"]], v[at["beat"]], v[at["moving"]] = (
            loop.overruns,
            time.monotonic(),
            self.pb is not None,
        )
        pb = self.pb
        if pb is not None:
            v[at["t"]], v[at["s"]], v[at["sigma"]] = pb.t, pb.s, pb.sigma
        v[at["v_r"] : at["v_r"] + 3] = self.figures or (np.nan, np.nan, np.nan)
        if self.heed is not None:
            v[at["cuts"]], v[at["adopted"]], v[at["unheard"]] = (
                self.heed.cuts,
                self.heed.adopted,
                self.heed.unheard,
            )
        v[at["q"] : at["q"] + 6] = b.actual_q()
        v[at["qd"] : at["qd"] + 6] = b.actual_qd()
        text = None
        if slow:
            v[at["tcp"] : at["tcp"] + 6] = b.tcp_pose()
            v[at["inputs"]], v[at["lost"]] = b.digital_inputs(), b.link_lost()
            if (fault := self.crash or b.fault()) != self._fault:
                self._fault, text = fault, fault.encode()
        st.write(text)

    # --- the loop -------------------------------------------------------------------------------------

    def serve(self) -> None:
        """Between two ticks (``ServoLoop.between``), and while idle (``idle``): the stop and the lease,
        a few commands, and whether the executor is still there."""
        self.ticks += 1
        ctrl = self.ch.ctrl.read()
        if ctrl is not None:
            stop, lease, renewals = ctrl[0]
            if stop:
                self.loop.request_stop()
            if renewals != self.renewals and self.pb is not None:
                self.renewals = renewals
                self.pb.renew(lease)
        for _ in range(8):  # a few a tick: a burst waits for the next ticks, never the tick
            m = self.ch.cmd.get()
            if m is None:
                break
            self.handle(m)
        if self.heed is not None and self.pb is not None:
            self.heed.step(self.pb)
        if self.ticks % 50 == 0 and os.getppid() != self.parent:  # the executor is gone: stop, then end
            self.loop.request_stop()
            self.exiting = True
        self.publish(slow=self.pb is None or self.ticks % SLOW_EVERY == 0)

    def run(self) -> None:
        while not self.exiting:
            self.serve()
            if self.next_run is None:
                if not self.ch.cmd.pending():  # at rest until the executor rings, or the state is due
                    select.select([self.bell], [], [], IDLE_S)
                with contextlib.suppress(BlockingIOError):
                    os.read(self.bell, 4096)
                continue
            run_id, source, settle = self.next_run
            self.next_run = None
            try:
                result = self.loop.play(source, settle)
            except Exception as exc:  # the backend raised inside a tick: a fault, said
                result = MotionResult("fault", 0, 0, 0)
                self.crash = f"the servo process: {exc!r}"
            self.changed()  # the playback's last word: where it ended
            self.pb = None
            self.publish(slow=True)  # the arm and its fault as the motion left them, before its result
            self.ch.events.put(("result", run_id, result))
            self._wake()


class Heed:
    """The separation guard's word (services/executor/guard_process.py), heard each step of a path: the
    oldest fall of its σ not yet in force (the guard's clock, s), and what heeding it cost."""

    def __init__(self, ch: Channel, grace_s: float) -> None:
        self.ch, self.grace_s = ch, grace_s
        self.run_id = 0
        self.demand: float | None = None
        self.kept_at = -np.inf  # the last step the scale in force was within the guard's
        self.cuts = self.adopted = 0
        # how often a guard heard during a run fell silent (its process starved past GUARD_SILENT_S): the
        # only way the lease of a stalled executor runs out while the guard runs (a stop, and the safe one)
        self.unheard, self.heard = 0, False

    def begin(self, run_id: int) -> None:
        self.run_id, self.demand, self.kept_at, self.heard = run_id, None, -np.inf, False

    def step(self, pb: Playback) -> None:
        """The guard's σ against the scale in force, each step of a path: timed from the guard's fall (the
        adoption of the reading that caused it), and past its grace taken here, by the playback itself
        (``Playback.cut``); a scale it allows renews the lease (its word confirms the scale as a look of
        the executor's does: an executor's loop starved by a flood then stops nothing the readings allow).
        A silent guard, or one that judged another run, is not heard: the executor's lease alone holds."""
        grace = self.grace_s
        got = self.ch.guard.read(tries=3)
        now = time.monotonic()
        if got is None or not now - got[0][Channel.GUARD_AT["beat"]] < GUARD_SILENT_S:
            self.unheard += self.heard
            self.demand, self.heard = None, False
            return
        g, at = got[0], Channel.GUARD_AT
        sigma = float(g[at["sigma"]])
        if int(g[at["run"]]) != self.run_id or sigma != sigma:
            self.demand = None
            return
        self.heard = True
        now_ = pb.now
        if now_.ramp.target <= sigma + SIGMA_EPS:  # in force
            if self.demand is not None:
                self.ch.adoptions[self.adopted % Channel.ADOPTIONS] = now - self.demand
                self.adopted += 1
                self.demand = None
            self.kept_at = now
            self.confirm(pb, now + grace)
            return
        since = float(g[at["since"]])
        if since <= self.kept_at:  # a word that stood while the scale rose past it: no grace, and no reading
            self.demand = None  # waits on this (the executor's ramp up read an older one)
            if pb.cut(sigma):
                self.cuts += 1
        else:
            if self.demand is None:  # a fall: its reading's adoption is timed from it
                self.demand = since
            if now - self.demand >= grace and pb.cut(sigma):  # the owner's ramp, if any, begins too late
                self.cuts += 1
        self.confirm(pb, now + grace)  # the cut to σ is taken in time: no lease need stop the arm for it

    @staticmethod
    def confirm(pb: Playback, until: float) -> None:
        """The guard's word as a renewal of the executor's lease (never a lease where there is none): while
        the guard is heard, the arm runs at what it allows, or heads there within its grace; a stop for a
        late look of the executor's (its loop starved by a flood) would stop what the readings allow."""
        if pb.lease is not None:
            pb.renew(max(pb.lease, until))


def watchdog_of(backend: Backend) -> float | None:
    """How long the controller waits for a target before it stops the arm (None: no watchdog)."""
    if isinstance(backend, SimBackend):
        return backend.watchdog_s
    if isinstance(backend, UrRtdeBackend):
        return 1.0 / backend.watchdog_hz
    return None


def main(argv: list[str]) -> int:
    # a terminal's Ctrl-C or systemd's SIGTERM to the unit's group is the executor's to answer: it stops
    # the arm through here, and then ends this process
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    fd, wake, bell = int(argv[1]), int(argv[2]), int(argv[3])
    os.set_blocking(bell, False)
    config: Config = pickle.loads(sys.stdin.buffer.read())
    ch = Channel(memoryview(mmap.mmap(fd, Channel.SIZE)))
    s = config.settings
    backend = backend_for(s, load_task(s.task), config.speed, config.q0)
    loop = ServoLoop(backend, core=config.core, fifo_priority=config.fifo_priority, lock_memory=s.lock_memory,
                     speed=config.speed, spin_us=s.spin_us, overrun_limit=s.overrun_limit,
                     realtime=backend.realtime, errors_ns=ch.errors_ns)  # fmt: skip
    server = Server(ch, backend, loop, wake, bell)
    if s.separation:
        server.heed = Heed(ch, s.adoption_budget_s * GUARD_GRACE)
    loop.between = server.serve
    loop.setup()
    threads = (
        len(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else threading.active_count()
    )
    server.publish(slow=True)
    heavy = [m for m in ("zenoh", "scipy") if m in sys.modules]  # imported for nothing a tick does
    server.reply((0, True, {"warnings": loop.warnings, "name": backend.name, "realtime": backend.realtime,
                            "threads": threads, "pid": os.getpid(), "heavy": heavy,
                            "period_ns": loop.period_ns, "watchdog_s": watchdog_of(backend)}))  # fmt: skip
    try:
        server.run()
    finally:
        try:
            backend.close()
        except Exception as exc:  # said by the executor's close, which waits for nothing more
            print(f"servo process: closing the {backend.name} backend: {exc}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
