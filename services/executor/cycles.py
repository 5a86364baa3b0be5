"""The executor's task program, cycle after cycle (DESIGN §8, §9): each path at the selection in force at
its start (services/executor/selection.py), checked and played on the servo loop (motions.py) once its
record is on disk (records.py); the task's gripper, wait and ``wait_for`` steps; a report per cycle. It
never changes the safety state but through the supervisor (supervisor.py), and a motion starts only from
``ready``.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter, deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from common.decision import k_for_path
from common.runtime.clock import first_of, monotonic, pause
from common.runtime.errors import TrajectoryRejected
from common.runtime.node import Rejected
from common.safety.separation import Figures
from common.safety.states import Event, IllegalTransition, State
from common.trajectory.scaling import Curve, resume_at
from common.trajectory.task import PathPlan, Step, Task
from schemas.operator import OperatorError, OperatorSignal
from schemas.robot import CycleReport
from services.executor.backends import Backend
from services.executor.kit import Kit
from services.executor.motions import Motions
from services.executor.records import Records
from services.executor.selection import SelectionInForce
from services.executor.sets import SetCache
from services.executor.settings import Settings
from services.executor.supervisor import Supervisor
from services.registry import EXECUTOR

log = logging.getLogger("cadence.executor")
Again = Literal["again"]
AGAIN: Again = "again"  # a path to be tried again (Cycles.move)


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

    def __init__(
        self,
        names: set[str],
        early: dict[str, float] | None = None,
        max_age_s: float = 60.0,
        skew_s: float = 0.05,
    ) -> None:
        """``early``: per name, how long before its wait opens a signal still counts (loop seconds).
        ``max_age_s`` and ``skew_s``: the admission window of a stamp (data seconds, ``admit``)."""
        self.names, self.early = names, early or {}
        self.max_age_s, self.skew_s = max_age_s, skew_s
        self.received: Counter[str] = Counter()  # signals that met a wait
        self.seen: dict[str, deque[tuple[int, str | None]]] = {
            name: deque(maxlen=self.KEPT) for name in names
        }
        self.open: str | None = None  # the name the robot waits for now
        self.met = False  # the open wait has its signal
        self.came_early: dict[str, float] = {}  # name: when a signal for it came while nothing waited
        self.arrived = asyncio.Event()

    def admit(self, sig: OperatorSignal, now_ns: int) -> None:
        """On arrival, before any queue: a signal is a fact about now. One stamped more than ``max_age_s``
        before the receiver's clock (``stale``) or ahead of it by more than the skew bound (``ahead``) is
        refused and counted: a press stamped a day ago, or an hour ahead, once ended an open wait."""
        age_s, who = (now_ns - sig.t_ns) / 1e9, f"'{sig.name}' from {sig.source or 'unnamed'}"
        if age_s < -self.skew_s:
            raise Rejected("ahead", f"{who} stamped {-age_s:.3f} s ahead of the executor's clock (the cell's "
                           f"skew bound is {self.skew_s:g} s)")  # fmt: skip
        if age_s > self.max_age_s:
            raise Rejected("stale", f"{who} stamped {age_s:.1f} s ago (signal_max_age_s is "
                           f"{self.max_age_s:g} s): about another moment")  # fmt: skip

    def receive(self, sig: OperatorSignal) -> None:
        """A signal as it arrives: meets the open wait, or is kept as early for a step that allows it;
        one said again (same stamp and source) counts once, so a stuck button cannot run cycles."""
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
                timer = [pause(left)] if left is not None else []
                await first_of(self.arrived.wait(), stop.wait(), *timer)
            return "arrived"
        finally:
            self.open, self.met = None, False


@dataclass(frozen=True, slots=True)
class Paused:
    """A path a protective stop cut short (a run of overruns, the arm's or the controller's fault): it goes
    on from where the arm stopped once a person resumes, as a UR program does, on the curve it was on (a
    switch within it included), at its k; a selection decided meanwhile takes over from the next path.
    It went back to its start and ran whole again: on a loaded host without real-time priority a stop
    came in most of those moves, and a cycle never ended (issue 53: 158 stops in 900 s)."""

    pid: str
    curve: Curve
    figures: Figures
    k: int
    s: float  # the path time of the last sample sent


class Cycles:
    """Owns the task program's run: its cycles and steps, the operator's signals, the path a stop cut
    short (``paused``), and what a restart finds on disk of the last run."""

    def __init__(
        self,
        kit: Kit,
        settings: Settings,
        task: Task,
        safety: Supervisor,
        backend: Backend,
        sets: SetCache,
        records: Records,
        chosen: SelectionInForce,
        motions: Motions,
    ) -> None:
        self.kit, self.task, self.safety, self.backend = kit, task, safety, backend
        self.sets, self.records, self.chosen, self.motions = sets, records, chosen, motions
        self.clock, self.settings = kit.clock, settings
        self.say_files = kit.note("files")
        self.signals = Signals({s.wait_for for s in task.cycle if s.wait_for is not None},
                               {s.wait_for: self.clock.loop_s(s.early) for s in task.cycle
                                if s.wait_for is not None and s.early is not None},
                               settings.signal_max_age_s, kit.clock_skew_s)  # fmt: skip
        self.waiting_for: str | None = None
        self.cut_short: int | None = None  # the cycle a restart cut short, said when the cycles start
        self.latched: str | None = None  # a stop the last run latched and nobody resumed: why
        self.paused: Paused | None = None  # the path a protective stop cut short, to go on with

    def load(self) -> None:
        """What the last run left on disk: cached sets, the last selection applied, its cycle."""
        self.sets.load()
        loaded = self.records.store.load()
        self.say_files("; ".join(p for p in (*self.sets.problems, loaded.problem) if p))
        if (last := loaded.value) is not None:
            self.cut_short, self.latched = last.cycle_in_progress, last.latched
            if self.latched is None and last.moving is not None:
                self.latched = f"the last run ended during '{last.moving}' with no stop (a crash or a kill)"

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
        await self.chosen.start()
        await self.sets.fetch_missing(self.settings.query_timeout_s)
        sel = self.chosen.selection
        self.safety.event(
            "started",
            f"task '{self.task.name}', {len(self.task.paths)} paths, k = {sel.k if sel else 'none yet'}",
        )

    async def until_changed(self, at_most_s: float = 5.0) -> None:
        """Wait for something that could resolve a refusal (a new selection, a new set), a stop, or a
        while (a person may have moved the arm)."""
        self.chosen.changed.clear()
        self.sets.changed.clear()
        self.safety.changed.clear()
        await first_of(
            self.chosen.changed.wait(),
            self.sets.changed.wait(),
            self.safety.changed.wait(),
            self.kit.stop.wait(),
            pause(at_most_s),
        )

    async def run_path(self, pid: str) -> int | None:
        """Run one path with the selection current at its start; its k, or None when stopped."""
        own: PathPlan = self.task.paths[pid]
        stop = self.kit.stop
        while not stop.is_set():
            if self.safety.stopped:
                if not await self.safety.while_stopped():
                    return None
                continue
            sel = self.chosen.selection
            if sel is None:
                await first_of(self.chosen.changed.wait(), stop.wait())
                continue
            if fault := self.backend.fault():  # a stop at rest (the controller's, a lost link)
                self.safety.event("protective_stop", f"before '{pid}': {fault}", pid)
                self.safety.fire(Event.FAULT, fault)
                continue
            if (paused := self.paused) is not None and paused.pid == pid:  # its curve, k and figures kept
                self.safety.ready()
                k, curve, figures = paused.k, paused.curve, paused.figures
                at = await self.resumed_at(paused)
            else:
                s = self.sets.sets.get(pid)
                if s is None:
                    self.safety.event("refused", f"no Pareto set for '{pid}' yet; waiting for the store", pid)
                    self.safety.fire(Event.SET_MISSING, f"no Pareto set for '{pid}'")
                    await self.until_changed()
                    continue
                self.safety.ready()
                k, at = k_for_path(sel.k, len(s.solutions)), 0.0
                h = np.array(s.solutions[k - 1].h)
                try:
                    curve, figures = await asyncio.to_thread(self.motions.prepare, h, own,
                                                             np.array(s.waypoints))  # fmt: skip
                except TrajectoryRejected as exc:
                    self.safety.event("refused", f"k = {k}: {exc}", pid)
                    self.safety.fire(Event.REFUSE, f"k = {k} of '{pid}' refused")
                    self.sets.discard(pid, str(exc))  # never cached for good: the store is asked again
                    await self.until_changed()
                    continue
            async with self.records.in_motion(pid) as said:  # a crash before it ends leaves the stop latched
                outcome = await self.move(pid, own, k, curve, figures, at) if said else None
            if outcome != AGAIN:
                return outcome
        return None

    async def resumed_at(self, paused: Paused) -> float:
        """Where a path cut short goes on: the point of its curve nearest the arm (said as an event)."""
        at = await asyncio.to_thread(resume_at, paused.curve, self.backend.actual_q(), paused.s)
        self.safety.event("info", f"'{paused.pid}' goes on from where it stopped: s = {at:.3f} s of "
                          f"{paused.curve.t_f:.3f} s, at k = {paused.k}", paused.pid)  # fmt: skip
        return at

    async def move(
        self, pid: str, own: PathPlan, k: int, curve: Curve, figures: Figures, at: float = 0.0
    ) -> int | Again | None:
        """One path from its start, or from path time ``at`` within it (``resumed_at``): its k (a switch
        within it may have changed it), None when stopped, ``AGAIN`` when the path is to be tried again (a
        refusal, a fault handled, a hold for the disk)."""
        first, where = own.waypoints[0], "the start of"
        if at > 0.0:
            first, where = curve.at(np.array([at]), order=0)[0, 0], f"where it stopped (s = {at:.3f} s) on"
        if not await self.motions.reach(first, pid, where):
            if self.safety.motion.state is State.REFUSED:
                await self.until_changed()
            return AGAIN
        sel = self.chosen.selection
        assert sel is not None  # run_path waited for one, and one is never taken back
        start = None
        if at > 0.0:  # the selection it runs at was applied when it began
            start = await self.motions.resume_ramp(curve, figures, at)
            if start is None:
                self.paused = None
                self.safety.event("info", f"'{pid}' cannot go on from s = {at:.3f} s inside the limits: "
                                  "from its start again", pid)  # fmt: skip
                return AGAIN
        elif not await self.records.applied(sel):
            return None
        if self.safety.motion.state is not State.READY:  # held for the disk meanwhile: look again
            return AGAIN
        if self.kit.stop.is_set():  # the stop came while the path was prepared: no motion begins after it
            return None
        try:
            self.safety.fire(Event.MOVE, f"'{pid}' at k = {k}")
        except IllegalTransition as exc:  # a stop came in between: no motion
            log.warning("%s", exc)
            return AGAIN
        self.safety.path_id = pid
        self.chosen.running_at(k)
        self.paused = None
        result, run = await self.motions.play(own, curve, figures, k, start)
        k = run.k  # a switch within the path may have changed it
        self.chosen.running_at(k)
        self.kit.counters["paths"] += 1
        if result.outcome == "done":
            self.safety.fire(Event.DONE)
            return k
        if result.outcome == "stopped":
            self.safety.event("info", f"stopped during '{pid}' (decelerating stop)", pid)
            self.safety.fire(Event.SHUTDOWN)
            return None
        pb = run.playback
        if not pb.finished:
            self.paused = Paused(pid, pb.curve, run.figures, k, pb.s)
        if result.outcome == "overruns":
            why = f"{self.settings.overrun_limit} servo overruns in a row during '{pid}'"
        else:
            why = f"during '{pid}': {self.backend.fault() or 'refused by the arm'}"
        self.motions.protective_stop(why, pid)
        return AGAIN

    async def wait_for(self, step: Step, cycle: int) -> Literal["arrived", "stopped", "late"]:
        """A ``wait_for`` step; past its deadline the part is late: an operator error (kind ``late``),
        then the robot keeps waiting or goes on without it, as the task program says."""
        assert step.wait_for is not None
        timeout = None if step.deadline is None else self.clock.loop_s(step.deadline)
        got = await self.signals.wait(step.wait_for, self.kit.stop, timeout)
        if got != "late":
            return got
        assert step.deadline is not None
        then = "kept waiting" if step.on_late == "wait" else "went on without it"
        self.kit.counters["late"] += 1
        self.kit.publish(
            OperatorError(
                t_ns=self.clock.now_ns(),
                seq=0,
                cycle=cycle,
                kind="late",
                description=f"'{step.wait_for}' not there {step.deadline:g} s after the robot came: {then}",
                source=EXECUTOR.name,
            )
        )
        if step.on_late == "wait":
            return await self.signals.wait(step.wait_for, self.kit.stop)
        return "late"

    async def run(self) -> None:
        cycle, stop = 0, self.kit.stop
        while not stop.is_set() and (self.settings.cycles == 0 or cycle < self.settings.cycles):
            started, ks = self.clock.now_ns(), {}
            if not await self.records.cycle(cycle):
                return
            for step in self.task.cycle:
                if stop.is_set():
                    return
                if step.move is not None:
                    k = await self.run_path(step.move)
                    if k is None:
                        return
                    ks[step.move] = k
                elif step.gripper is not None:
                    await asyncio.to_thread(self.backend.set_gripper, step.gripper == "on")
                elif step.wait is not None:
                    await first_of(self.clock.sleep(step.wait), stop.wait())
                elif step.wait_for is not None and self.settings.wait_for_signals:
                    self.safety.fire(Event.WAIT_OPERATOR, f"waiting for '{step.wait_for}'")
                    self.waiting_for = step.wait_for
                    got = await self.wait_for(step, cycle)
                    self.waiting_for = None
                    if got == "stopped":
                        return
                    self.safety.fire(Event.OPERATOR)
            end = self.clock.now_ns()
            if not await self.records.cycle(None):
                return
            self.kit.publish(
                CycleReport(
                    t_ns=end,
                    seq=0,
                    cycle=cycle,
                    cycle_time_s=(end - started) / 1e9,
                    k_per_path=ks,
                )
            )
            self.kit.counters["cycles"] = cycle = cycle + 1
