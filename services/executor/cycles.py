"""The executor's task program, cycle after cycle (DESIGN §8, §9): each path at the selection current at its
start, checked against the executor's own limits and waypoints and handed to the servo loop; the task's
gripper, wait and ``wait_for`` steps; a report per cycle. It never changes the safety state but through the
supervisor (services/executor/supervisor.py), and a motion starts only from ``ready``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
from collections import Counter, deque
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import Literal

import numpy as np

from common.decision import k_for_path
from common.runtime.clock import monotonic
from common.runtime.errors import TrajectoryRejected
from common.runtime.node import Node, Rejected
from common.runtime.service import first_of
from common.safety.separation import Figures
from common.safety.states import Event, IllegalTransition, State
from common.trajectory.approach import approach
from common.trajectory.scaling import Curve, Ramp
from common.trajectory.task import PathPlan, Step, Task
from common.trajectory.validate import check_trajectory
from schemas.decision import Selection
from schemas.operator import OperatorError, OperatorSignal
from schemas.robot import CycleReport
from schemas.topology import SELECTION
from services.executor.backends import Backend
from services.executor.pathrun import PathRun
from services.executor.persist import ExecutorStore
from services.executor.reaction import Reactions
from services.executor.servo import MotionResult, Servo
from services.executor.sets import SetCache
from services.executor.settings import Settings
from services.executor.supervisor import Supervisor

log = logging.getLogger("cadence.executor")
RATE_HZ = 500.0
Again = Literal["again"]
AGAIN: Again = "again"  # a path to be tried again (Cycles.move)


def _lowest_priority() -> None:
    """This thread only (Linux: a thread's nice value is its own), the least the scheduler gives."""
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)


class Signals:
    """Operator signals by name, each a fact about now (DESIGN §8). A signal counts once, for the wait open
    for its name when it comes; a step's ``early`` lets one that came at most that long before the wait
    opened count for it (a part put down as the robot comes), the latest such one, never more. A signal
    for a name nothing waits for is refused (``not_waiting``, counted and said), not banked for a later
    wait: twenty presses must not let the arm through twenty waits. Only the names the task waits for
    are known: any other is refused, so a flood of names cannot grow the table. A signal is state its
    sender says again while it holds (DESIGN §9): a copy of one already taken (same name, sender and
    stamp) counts nothing, so a signal lost once (the executor stopped for a while) comes again."""

    KEPT = 32  # stamps remembered per name, to know a copy when it comes again

    def __init__(self, names: set[str], early: dict[str, float] | None = None) -> None:
        """``early``: per name, how long before its wait opens a signal still counts (loop seconds)."""
        self.names, self.early = names, early or {}
        self.received: Counter[str] = Counter()  # signals that met a wait
        self.seen: dict[str, deque[tuple[int, str | None]]] = {
            name: deque(maxlen=self.KEPT) for name in names
        }
        self.open: str | None = None  # the name the robot waits for now
        self.met = False  # the open wait has its signal
        self.came_early: dict[str, float] = {}  # name: when a signal for it came while nothing waited
        self.arrived = asyncio.Event()

    def admit(self, sig: OperatorSignal) -> None:
        if sig.name not in self.names:
            raise Rejected("unknown_signal", f"no step of the task waits for '{sig.name}'")
        said = (sig.t_ns, sig.source)
        if said in self.seen[sig.name]:
            return  # said again while it holds: counted once
        self.seen[sig.name].append(said)
        if self.open == sig.name and not self.met:
            self.met = True
            self.received[sig.name] += 1
            self.arrived.set()
        elif sig.name in self.early and self.open != sig.name:
            self.came_early[sig.name] = monotonic()  # the latest one only: not banked
        else:
            why = (
                "its wait has its signal already"
                if self.open == sig.name
                else "the robot does not wait for it"
            )
            raise Rejected("not_waiting", f"'{sig.name}' from {sig.source or 'unnamed'}: {why} (not kept)")

    async def wait(
        self, name: str, stop: asyncio.Event, timeout_s: float | None = None
    ) -> Literal["arrived", "stopped", "late"]:
        """``timeout_s``: wall seconds to wait at most (a step's deadline at the clock's speed)."""
        end = None if timeout_s is None else monotonic() + timeout_s
        early = self.came_early.pop(name, None)
        self.open, self.met = name, early is not None and monotonic() - early <= self.early.get(name, 0.0)
        if self.met:
            self.received[name] += 1
        try:
            while not self.met:
                if stop.is_set():
                    return "stopped"
                left = None if end is None else end - monotonic()
                if left is not None and left <= 0:
                    return "late"
                self.arrived.clear()
                timer = [asyncio.sleep(left)] if left is not None else []
                await first_of(self.arrived.wait(), stop.wait(), *timer)
            return "arrived"
        finally:
            self.open, self.met = None, False


class Cycles:
    def __init__(
        self,
        node: Node,
        safety: Supervisor,
        task: Task,
        backend: Backend,
        loop: Servo,
        reactions: Reactions,
    ) -> None:
        self.node, self.ctx, self.safety, self.reactions = node, node.ctx, safety, reactions
        self.task, self.backend, self.loop = task, backend, loop
        self.settings: Settings = node.ctx.settings
        self.clock = node.ctx.common.clock
        # data time per second of the loop's clock: the demo's speed, or 1 in a lockstep cell (its loop's
        # time is data time)
        self.speed = 1.0 if self.clock.driven else node.ctx.common.speed
        self.notes: list[str] = []  # what was wrong with the files on disk, for the status
        folder = node.ctx.common.data_path / "executor"
        self.sets = SetCache(node.ctx.bus, folder, task)
        self.store = ExecutorStore(folder)
        self.signals = Signals({s.wait_for for s in task.cycle if s.wait_for is not None},
                               {s.wait_for: self.clock.loop_s(s.early) for s in task.cycle
                                if s.wait_for is not None and s.early is not None})  # fmt: skip
        self.selection: Selection | None = None
        self.selection_changed = asyncio.Event()
        self.k: int | None = None
        self.waiting_for: str | None = None
        self.cut_short: int | None = None  # the cycle a restart cut short, said when the cycles start
        self.latched: str | None = None  # a stop the last run latched and nobody resumed: why
        self.carried = Ramp.hold(0.0, 0.0, 1.0)  # the σ-state the last path ended with
        self.switching: asyncio.Task[None] | None = None
        self.unwritten: str | None = None  # what could not be written (a full disk), while it cannot
        self.held_unwritten = False  # the arm held for it: said once, apart from the first refusal
        self.writes: set[asyncio.Task[bool]] = set()  # records written in the background

    def load(self) -> None:
        """What the last run left on disk: cached sets, the last selection applied, its cycle."""
        self.sets.load()
        loaded = self.store.load()
        self.notes = [p for p in (*self.sets.problems, loaded.problem) if p]
        self.ctx.detail = "; ".join(self.notes)
        if (last := loaded.value) is not None:
            self.cut_short, self.latched = last.cycle_in_progress, last.latched
            if self.latched is None and last.moving is not None:
                self.latched = f"the last run ended during '{last.moving}' with no stop (a crash or a kill)"
        self.safety.on_latch = self.remember_latch

    def select(self, sel: Selection) -> None:
        """A selection is a sequence (DESIGN §8): one that is no newer than the newest applied, by its seq
        and by its stamp both, is refused (``Rejected``, counted as ``stale``): a captured selection
        replayed, or a copy of the current one with another k. Either alone may go back legitimately (a
        fixed condition is numbered with the decider's last seq, a calibration restarts the stamps from
        its own), never both. The decision maker's republishing of the current one is no new decision."""
        cur = self.selection
        if cur is not None and sel.seq <= cur.seq and sel.t_ns <= cur.t_ns:
            if (sel.seq, sel.t_ns, sel.k, sel.n) == (cur.seq, cur.t_ns, cur.k, cur.n):
                return  # said again while it holds
            older = f"{(cur.t_ns - sel.t_ns) / 1e9:.3f} s older"
            raise Rejected("stale", f"a selection (k = {sel.k}, seq {sel.seq}) no newer than the one applied "
                           f"(k = {cur.k}, seq {cur.seq}): {older}")  # fmt: skip
        self.selection = sel
        self.selection_changed.set()
        self.remember(sel)
        self.safety.fire(Event.SELECTION)
        run = self.reactions.run
        if run is not None and self.settings.switch_within_path and self.switching is None:
            self.switching = asyncio.create_task(self.switch_within(run))

    def remember(self, sel: Selection) -> None:
        """Kept on disk in the background (a restart goes on at the newest k decided); a disk that
        cannot take it is said once, as any record the executor keeps."""
        self.in_background(partial(self.store.received, sel))

    def remember_latch(self, why: str | None) -> None:
        """A stop latched (or cleared by a resume), kept on disk as a selection is."""
        self.in_background(partial(self.store.latch, why))

    def in_background(self, write: Callable[[], None]) -> None:
        task = asyncio.create_task(self.keep(write, hold=False))
        self.writes.add(task)
        task.add_done_callback(self.writes.discard)

    async def switch_within(self, run: PathRun) -> None:
        """A new selection during a path: the rest of it at the new k, when that can join within the
        limits and at the scale the person's distance allows on it (services/executor/pathrun.py);
        otherwise, as ever, from the next path start."""
        try:
            s = self.sets.sets.get(run.path.id)
            n = len(s.solutions) if s is not None else 0

            def wanted() -> int:
                return k_for_path(self.selection.k, n) if self.selection is not None else 0

            while s is not None and self.selection is not None and self.reactions.run is run:
                k, sel, k_was = wanted(), self.selection, run.k
                if k == run.k:
                    return
                lead = self.settings.switch_lead_s
                took, why = await run.switch(k, np.array(s.solutions[k - 1].h), wanted, lead,
                                             self.reactions.allowed)  # fmt: skip
                if not took:
                    if why != "no longer wanted":
                        self.safety.event("info", f"{why}: k = {k} from the next path", run.path.id)
                    return
                text = (f"k {k_was} → {k} within '{run.path.id}' at s = {run.switched_at:.3f} s; it now ends "
                        f"at {run.playback.curve.t_f:.3f} s, at most {run.figures.speed_m_s:.2f} m/s, "
                        f"stopping within {run.figures.stop_time_s:.2f} s")  # fmt: skip
                self.safety.event("switch", text, run.path.id)
                self.k = k
                await self.keep(partial(self.store.applied, sel), hold=False)  # the arm is moving
        finally:
            self.switching = None

    async def start(self) -> None:
        """Before the first cycle: what a restart cut short, the current selection, the sets."""
        if self.cut_short is not None:
            self.safety.event(
                "info",
                f"cycle {self.cut_short} of the last run was cut short by a restart; "
                "it has no report, and cycles count again from 0",
            )
        if self.latched is not None:  # a restart does not clear a stop: a person does
            again = " (latched before a restart)"
            self.safety.fire(Event.FAULT, self.latched.removesuffix(again) + again)
            self.safety.event("protective_stop", f"the last run ended stopped ({self.latched}); the robot "
                              "stays stopped until `cadence robot resume`")  # fmt: skip
        await self.start_selection()
        await self.sets.fetch_missing(self.settings.query_timeout_s)
        k = self.selection.k if self.selection is not None else None
        self.safety.event(
            "started", f"task '{self.task.name}', {len(self.task.paths)} paths, k = {k if k else 'none yet'}"
        )

    async def ask_selection(self) -> bool:
        """Selections are state: ask for the current one at start (DESIGN §11). True when one came."""
        for r in await self.ctx.bus.get(SELECTION, timeout=self.settings.query_timeout_s):
            if r.message is not None:
                try:
                    self.select(r.message)
                except Rejected as exc:  # a newer one came on the key meanwhile: that one stands
                    self.ctx.bus.reject(self.ctx.bus.key(SELECTION.suffix), exc.code, exc.detail)
                return True
        return False

    async def start_selection(self) -> None:
        """No motion without a current selection: the decision maker's, or, when it cannot be reached, what
        ``start_selection`` allows. What was chosen, and why, is an event."""
        # answered, or published meanwhile (the fallbacks below must not override the decision maker's)
        if await self.ask_selection() or self.selection is not None:
            assert self.selection is not None
            self.safety.event("info", f"selection from the decision maker: k = {self.selection.k}")
            return
        policy = self.settings.start_selection or ("wait" if self.settings.backend == "ur_rtde" else "last")
        last = self.store.record.newest
        max_age = self.settings.last_selection_max_age_s
        unreachable = "the decision maker does not answer"
        if policy == "last" and last is not None and last.age_s() <= max_age:
            self.select(last.selection())
            self.safety.event(
                "info",
                f"{unreachable}: going on at the newest selection it decided, k = {last.k} (n = {last.n}), "
                f'{last.age_s():.0f} s ago (start_selection = "last")',
            )
        elif policy == "initial":
            k = self.settings.initial_k
            # stamped 0: the executor's own, older than any the decision maker makes
            self.select(Selection(t_ns=0, seq=0, k=k, n=k, delta=0, reason="initial"))
            self.safety.event(
                "info",
                f'{unreachable}: starting at initial_k = {k}, as configured (start_selection = "initial")',
            )
        else:
            why = (
                'start_selection = "wait"'
                if policy == "wait"
                else "no selection on file"
                if last is None
                else f"the last one on file is {last.age_s():.0f} s old, over {max_age:.0f} s"
            )
            self.safety.event("info", f"{unreachable}: waiting for a selection ({why})")

    async def keep_sets(self) -> None:
        """Fetch what is missing (the store may still be planning; a refused set was dropped), and wait
        while nothing is."""
        while not self.ctx.stop.is_set():
            if not self.sets.missing():
                self.sets.wanted.clear()
                await first_of(self.sets.wanted.wait(), self.ctx.stop.wait())
                continue
            why = await self.sets.fetch_missing(self.settings.query_timeout_s)
            waiting = [f"waiting for Pareto sets: {', '.join(why)}"] if why else []
            self.ctx.detail = "; ".join([*self.notes, *waiting])
            if why:
                await first_of(asyncio.sleep(2.0), self.ctx.stop.wait())

    async def keep(self, write: Callable[[], None], hold: bool = True) -> bool:
        """Write the executor's record before what depends on it (a cycle, a path at a selection). A disk
        that cannot take it (full, read-only) is a state, not a crash (DESIGN §9): said once (an event, the
        status, one log line naming the file), and with ``hold`` the arm stays still, the write tried again
        every 2 s until it goes through, then the cycles go on by themselves. False when stopped first."""
        while True:
            try:
                await asyncio.to_thread(write)
            except OSError as exc:
                if self.unwritten is None:
                    self.unwritten = f"cannot write {self.store.path}: {exc.strerror or exc}"
                    self.ctx.detail = "; ".join([*self.notes, self.unwritten])
                    self.ctx.counters["write_errors"] += 1
                    if not hold:
                        self.safety.event("info", f"{self.unwritten}; going on without it")
                if not hold:
                    return True
                # a disk that first refused a write the arm did not wait for (a selection received while
                # it moved) was said as going on: the hold that follows is news, said once too
                if not self.held_unwritten:
                    self.held_unwritten = True
                    self.safety.event("refused", f"{self.unwritten}; holding the arm still until it can")
                if self.safety.motion.state is State.READY:
                    self.safety.fire(Event.REFUSE, self.unwritten)
                await first_of(asyncio.sleep(2.0), self.ctx.stop.wait())
                if self.ctx.stop.is_set():
                    return False
                continue
            if self.unwritten is not None:
                self.safety.event("info", f"{self.store.path} written again: going on")
                self.unwritten, self.held_unwritten, self.ctx.detail = None, False, "; ".join(self.notes)
                self.safety.ready()
            return True

    async def prefetch_figures(self) -> None:
        """With separation monitoring: the figures of every path at every k, the k in force first, found
        in a thread of its own at the lowest priority while the arm works, so that a path at a new k does
        not wait for them (some tenths of a second each), and nothing that must be on time waits for
        this. Again whenever the sets change."""
        if not self.settings.separation:
            return
        loop = asyncio.get_running_loop()
        background = ThreadPoolExecutor(1, "figures", initializer=_lowest_priority)
        try:
            while not self.ctx.stop.is_set():
                self.sets.arrived.clear()
                k = self.selection.k if self.selection is not None else 1
                for pid, s in list(self.sets.sets.items()):
                    path = self.task.paths[pid]
                    for i in sorted(range(len(s.solutions)), key=lambda i: abs(i + 1 - k)):
                        h = np.array(s.solutions[i].h)
                        if not self.reactions.known(path, h) and not self.ctx.stop.is_set():
                            find = partial(self.reactions.figures, path, h, Curve.of(h, path))
                            await loop.run_in_executor(background, find)
                await first_of(self.sets.arrived.wait(), self.ctx.stop.wait())
        finally:
            background.shutdown(wait=False, cancel_futures=True)  # the loop never waits on it

    async def until_changed(self, at_most_s: float = 5.0) -> None:
        """Wait for something that could resolve a refusal (a new selection, a new set), a stop, or a
        while (a person may have moved the arm)."""
        self.selection_changed.clear()
        self.sets.changed.clear()
        self.safety.changed.clear()
        await first_of(
            self.selection_changed.wait(),
            self.sets.changed.wait(),
            self.safety.changed.wait(),
            self.ctx.stop.wait(),
            asyncio.sleep(at_most_s),
        )

    async def reach(self, q_start: np.ndarray, path_id: str) -> bool:
        """Start-up safety: the arm must be at the path's first waypoint before the path runs."""
        q = self.backend.actual_q()
        off = float(np.max(np.abs(q - q_start)))
        if off <= self.settings.start_tolerance_rad:
            return True
        if self.settings.start_policy == "refuse":
            why = f"the arm is {off:.4f} rad from the start of '{path_id}'; not moving"
            self.safety.event("refused", why, path_id)
            self.safety.fire(Event.REFUSE, why)
            return False
        self.safety.event(
            "info", f"the arm is {off:.4f} rad from the start of '{path_id}': moving there slowly", path_id
        )
        self.safety.fire(Event.MOVE, f"moving slowly to the start of '{path_id}'")
        s = self.settings
        own, h = approach(q, q_start, s.start_speed, s.start_acceleration,
                          self.task.limits, f"approach to {path_id}")  # fmt: skip
        curve = Curve.of(h, own)
        figures = await asyncio.to_thread(self.reactions.figures, own, h, curve, False)  # made once
        result, _ = await self.play(own, curve, figures, 0)  # no solution of a set: no k
        arrived = float(np.max(np.abs(self.backend.actual_q() - q_start))) <= s.start_tolerance_rad
        if result.outcome == "done" and arrived:
            self.safety.fire(Event.DONE)
            return True
        if result.outcome == "stopped" or self.ctx.stop.is_set():
            self.safety.fire(Event.SHUTDOWN)
            return False
        self.protective_stop(
            f"the move to the start of '{path_id}' did not arrive: {self.backend.fault() or result.outcome}",
            path_id,
        )
        return False

    def protective_stop(self, why: str, pid: str) -> None:
        """A motion ended by a fault (the arm's, the controller's, a run of overruns): latched, and said."""
        self.safety.event("protective_stop", why, pid)
        self.safety.fire(Event.FAULT, why)
        self.ctx.counters["protective_stops"] += 1

    async def run_path(self, pid: str) -> int | None:
        """Run one path with the selection current at its start; its k, or None when stopped."""
        own: PathPlan = self.task.paths[pid]
        while not self.ctx.stop.is_set():
            if self.safety.stopped:
                if not await self.safety.while_stopped():
                    return None
                continue
            if self.selection is None:
                await first_of(self.selection_changed.wait(), self.ctx.stop.wait())
                continue
            if fault := self.backend.fault():  # a stop at rest (the controller's, a lost link)
                self.safety.event("protective_stop", f"before '{pid}': {fault}", pid)
                self.safety.fire(Event.FAULT, fault)
                continue
            s = self.sets.sets.get(pid)
            if s is None:
                self.safety.event("refused", f"no Pareto set for '{pid}' yet; waiting for the store", pid)
                self.safety.fire(Event.SET_MISSING, f"no Pareto set for '{pid}'")
                await self.until_changed()
                continue
            self.safety.ready()
            k = k_for_path(self.selection.k, len(s.solutions))
            h = np.array(s.solutions[k - 1].h)
            try:
                curve, figures = await asyncio.to_thread(self.prepare_path, h, own, np.array(s.waypoints))
            except TrajectoryRejected as exc:
                self.safety.event("refused", f"k = {k}: {exc}", pid)
                self.safety.fire(Event.REFUSE, f"k = {k} of '{pid}' refused")
                self.sets.discard(pid, str(exc))  # never cached for good: the store is asked again
                await self.until_changed()
                continue
            async with self.in_motion(pid) as said:  # a crash before it ends leaves the stop latched
                outcome = await self.move(pid, own, k, curve, figures) if said else None
            if outcome != AGAIN:
                return outcome
        return None

    @contextlib.asynccontextmanager
    async def in_motion(self, pid: str) -> AsyncIterator[bool]:
        """The arm may move inside: so it says on disk before the first step (the arm held until the disk
        takes it; False: the service stopped first, and nothing may move), and only a body that ends in
        order (a return, a fault handled) says it no longer does. A run that dies inside (a crash, a kill,
        a power cut) leaves it said, and the restart comes up stopped until a person resumes (``load``)."""
        said = await self.keep(partial(self.store.moving, pid))
        yield said
        if said:
            await self.keep(partial(self.store.moving, None), hold=False)

    async def move(
        self, pid: str, own: PathPlan, k: int, curve: Curve, figures: Figures
    ) -> int | Again | None:
        """One path from its start: its k (a switch within it may have changed it), None when stopped,
        ``AGAIN`` when the path is to be tried again (a refusal, a fault handled, a hold for the disk)."""
        if not await self.reach(own.waypoints[0], pid):
            if self.safety.motion.state is State.REFUSED:
                await self.until_changed()
            return AGAIN
        assert self.selection is not None  # run_path waited for one, and one is never taken back
        if not await self.keep(partial(self.store.applied, self.selection)):
            return None
        if self.safety.motion.state is not State.READY:  # held for the disk meanwhile: look again
            return AGAIN
        if self.ctx.stop.is_set():  # the stop came while the path was prepared: no motion begins after it
            return None
        try:
            self.safety.fire(Event.MOVE, f"'{pid}' at k = {k}")
        except IllegalTransition as exc:  # a stop came in between: no motion
            log.warning("%s", exc)
            return AGAIN
        self.safety.path_id, self.k = pid, k
        result, run = await self.play(own, curve, figures, k)
        k = self.k = run.k  # a switch within the path may have changed it
        self.ctx.counters["paths"] += 1
        if result.outcome == "done":
            self.safety.fire(Event.DONE)
            return k
        if result.outcome == "stopped":
            self.safety.event("info", f"stopped during '{pid}' (decelerating stop)", pid)
            self.safety.fire(Event.SHUTDOWN)
            return None
        if result.outcome == "overruns":
            why = f"{self.settings.overrun_limit} servo overruns in a row during '{pid}'"
        else:
            why = f"during '{pid}': {self.backend.fault() or 'refused by the arm'}"
        self.protective_stop(why, pid)
        return AGAIN

    def prepare_path(self, h: np.ndarray, own: PathPlan, claimed: np.ndarray) -> tuple[Curve, Figures]:
        """In a worker thread, before the motion: the trajectory checked against the executor's own
        limits and waypoints (raises TrajectoryRejected), its curve, and with separation monitoring on,
        its top speed and longest stop (S_p's v_r and T_s)."""
        check_trajectory(h, own, self.task.limits, claimed)
        curve = Curve.of(h, own)
        return curve, self.reactions.figures(own, h, curve)

    async def play(
        self, own: PathPlan, curve: Curve, figures: Figures, k: int
    ) -> tuple[MotionResult, PathRun]:
        """One motion on the servo loop, a task's path or the slow move to its start: at the scale the
        person's distance allows, under the lease on it and the controller's watchdog."""
        # prepare() arms a controller's watchdog, here, outside the loop; each step's target is then only
        # converted to the form servo takes (backend.target), touching nothing
        self.backend.prepare(own.waypoints[:1])
        start = self.reactions.start_ramp(own, self.carried, figures)
        run = self.reactions.run = PathRun(own, curve, figures, k, start, self.backend.target,
                                           self.task.limits, self.speed, self.reactions.arm)  # fmt: skip
        self.reactions.lease(run)  # the first look may be late: the scale it starts at is leased too
        settle = round(self.settings.settle_s * RATE_HZ)
        try:
            result: MotionResult = await run.play(self.loop, settle)
        finally:
            self.reactions.run = None
            self.ctx.counters["ramps"] += run.ramps
            self.ctx.counters["ramps_refused"] += run.ramps_refused
            self.ctx.counters["lease_lapses"] += run.playback.lapses
            self.ctx.counters["unchecked_stops"] += run.playback.unchecked
            self.carried = run.playback.state()
            self.reactions.idle_scale = run.playback.sigma  # what the arm ended at, until the next look
        await asyncio.to_thread(self.backend.motion_ended)
        self.ctx.counters["overruns"] = self.loop.overruns
        pid = own.id
        if result.overruns:
            self.safety.event("overrun", f"{result.overruns} servo overruns during '{pid}'", pid, repeat=True)
        if lapses := run.playback.lapses:  # the looks at the distance stopped coming: the loop stopped
            unchecked = run.playback.unchecked
            why = f" ({unchecked} unchecked: no planned stop fitted)" if unchecked else ""
            said = f"the scale's lease ran out {lapses} times during '{pid}': the servo took its stop{why}"
            self.safety.event("scale", said, pid, repeat=True)
        return result, run

    async def wait_for(self, step: Step, cycle: int) -> Literal["arrived", "stopped", "late"]:
        """A ``wait_for`` step; past its deadline the part is late: an operator error (kind ``late``),
        then the robot keeps waiting or goes on without it, as the task program says."""
        assert step.wait_for is not None
        timeout = None if step.deadline is None else self.clock.loop_s(step.deadline)
        got = await self.signals.wait(step.wait_for, self.ctx.stop, timeout)
        if got != "late":
            return got
        assert step.deadline is not None
        then = "kept waiting" if step.on_late == "wait" else "went on without it"
        self.ctx.counters["late"] += 1
        self.node.publish(
            OperatorError(
                t_ns=self.clock.now_ns(),
                seq=0,
                cycle=cycle,
                kind="late",
                description=f"'{step.wait_for}' not there {step.deadline:g} s after the robot came: {then}",
                source="executor",
            )
        )
        if step.on_late == "wait":
            return await self.signals.wait(step.wait_for, self.ctx.stop)
        return "late"

    async def run(self) -> None:
        cycle = 0
        while not self.ctx.stop.is_set() and (self.settings.cycles == 0 or cycle < self.settings.cycles):
            started, ks = self.clock.now_ns(), {}
            if not await self.keep(partial(self.store.cycle, cycle)):
                return
            for step in self.task.cycle:
                if self.ctx.stop.is_set():
                    return
                if step.move is not None:
                    k = await self.run_path(step.move)
                    if k is None:
                        return
                    ks[step.move] = k
                elif step.gripper is not None:
                    await asyncio.to_thread(self.backend.set_gripper, step.gripper == "on")
                elif step.wait is not None:
                    await first_of(self.clock.sleep(step.wait), self.ctx.stop.wait())
                elif step.wait_for is not None and self.settings.wait_for_signals:
                    self.safety.fire(Event.WAIT_OPERATOR, f"waiting for '{step.wait_for}'")
                    self.waiting_for = step.wait_for
                    got = await self.wait_for(step, cycle)
                    self.waiting_for = None
                    if got == "stopped":
                        return
                    self.safety.fire(Event.OPERATOR)
            end = self.clock.now_ns()
            if not await self.keep(partial(self.store.cycle, None)):
                return
            self.node.publish(
                CycleReport(
                    t_ns=end,
                    seq=0,
                    cycle=cycle,
                    cycle_time_s=(end - started) / 1e9,
                    k_per_path=ks,
                )
            )
            self.ctx.counters["cycles"] = cycle = cycle + 1
