"""decision_maker: each ``hrv/window`` → the paper's Alg. 1 → ``decision/selection`` (DESIGN §7, §11).

The selection is state, not an event: it is republished every ``republish_s`` and answered on query, so a
publication lost while a router was down is not lost for long. k and RR_{i-1} are written atomically to
the data folder after every window, before the selection is announced, so a restarted service goes on
where it stopped. A window it has answered already (a replay, a duplicate) or one far from the windows'
data time is dropped and counted (common/runtime/admission.py). Without a calibration it publishes nothing and
says so on its status, rather than guess the subject's resting RR. The study's conditions: condition.py.
"""

from __future__ import annotations

import asyncio
import logging
import sys
import time
from typing import Annotated, Literal

import msgspec

from common.decision import Personal, fixed_k
from common.runtime.bus import QueryError, Request
from common.runtime.node import Answer, Node, Out, Rejected, admitted, answers, every, node_main, on
from common.runtime.service import service_main
from schemas.base import Message, RrSeconds
from schemas.decision import MAX_N, Selection
from schemas.hrv import HrvWindow
from schemas.operator import Calibration
from schemas.robot import RobotState
from schemas.topology import CALIBRATION, DECISION_CONDITION, HRV_WINDOW, ROBOT_STATE, SELECTION
from services.decision_maker.condition import Condition, Conditions, FixedK, store_condition
from services.decision_maker.state import Decider, DecisionRecord, MovementRule, resume
from services.registry import DECIDER

log = logging.getLogger("cadence.decision_maker")
NAME = DECIDER.name
MISSED_GAP_NS = 1_000_000_000  # a window starting this long after the last answered one: some were missed
MAX_MISSED = 64  # what the analyser keeps
_MODE = Personal()  # the personal mode's settings as shipped (common/decision.py)


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    n: Annotated[int, msgspec.Meta(ge=1, le=MAX_N)] = 15
    republish_s: Annotated[float, msgspec.Meta(ge=0.1, le=3600.0)] = 2.0
    # For a cell without `cadence calibrate`: the subject's resting mean RR, in seconds.
    rr_rest_s: RrSeconds | None = None
    # The study's conditions (paper §III-B): "adaptive" is Alg. 1, condition (c); "fixed" holds one k,
    # fixed_k: "a" (minimum time, k = n), "b" (minimum jerk, k = 1) or a number. Windows are then
    # counted and not answered. A session's condition (`cadence session`, on decision/condition) wins over
    # these and is kept in condition.json, so that a restart mid-session stays in it.
    mode: Literal["adaptive", "fixed"] = "adaptive"
    fixed_k: FixedK = "a"
    # Movement (DESIGN §7): a window whose movement is over the wearer's level at work by more than this
    # (or three spreads of it), and after one each window until the heart is back (below), is held: mean
    # RR then says nothing of mental load. The level comes from a working calibration, else from the first
    # movement_learn_windows windows at work. Windows without movement (no accelerometer) are never held.
    movement_margin_mg: Annotated[float, msgspec.Meta(ge=5.0, le=2000.0)] = 40.0
    # the hold ends when the window's mean RR is back within movement_back_s of RR_{i-1} (where it was
    # before the effort), or movement_max_hold_s after the last moving window (RR_{i-1} then re-anchored)
    movement_back_s: Annotated[float, msgspec.Meta(ge=0.0, le=0.5)] = 0.02
    movement_max_hold_s: Annotated[float, msgspec.Meta(ge=0.0, le=3600.0)] = 300.0
    movement_learn_windows: Annotated[int, msgspec.Meta(ge=1, le=100)] = 4
    # "paper": Alg. 1 exactly, study condition (c). "personal": beyond the paper, k follows this person's
    # recent mean RR against their own reference (common/decision.py, DESIGN §7), its settings below
    decide: Literal["paper", "personal"] = "paper"
    personal_step_s: Annotated[float, msgspec.Meta(ge=0.002, le=0.2)] = _MODE.step_s
    personal_keep: Annotated[float, msgspec.Meta(ge=0.0, le=0.95)] = _MODE.keep
    personal_hysteresis: Annotated[float, msgspec.Meta(ge=0.0, le=5.0)] = _MODE.hysteresis
    personal_ref_tau_s: Annotated[float, msgspec.Meta(ge=60.0, le=7 * 86400.0)] = _MODE.ref_tau_s
    personal_freeze_s: Annotated[float, msgspec.Meta(ge=0.0, le=0.5)] = _MODE.freeze_s
    personal_effort_tau_s: Annotated[float, msgspec.Meta(ge=1.0, le=86400.0)] = _MODE.effort_tau_s

    def __post_init__(self) -> None:
        fixed_k(self.fixed_k, self.n)  # a k above n is a mistake in the config, said at start

    @property
    def rule(self) -> MovementRule:
        return MovementRule(self.movement_margin_mg, self.movement_back_s, self.movement_max_hold_s,
                            self.movement_learn_windows)  # fmt: skip

    @property
    def personal(self) -> Personal | None:
        if self.decide == "paper":
            return None
        return Personal(
            self.personal_step_s,
            self.personal_keep,
            self.personal_hysteresis,
            self.personal_ref_tau_s,
            self.personal_freeze_s,
            self.personal_effort_tau_s,
        )


class DecisionMaker(Node):
    role = NAME

    async def setup(self) -> None:
        s, self.data = self.ctx.settings, self.ctx.common.data_path
        self.unpersisted: str | None = None  # a write the disk refused, while it refuses
        self.decider = Decider(self.data, s.n, s.rule, self.ctx.common.clock_skew_s, s.personal)
        self.conditions = Conditions(Condition(mode=s.mode, fixed_k=s.fixed_k), s.n)
        problems = await asyncio.to_thread(resume, self.decider, self.data, s.rr_rest_s)
        problems += await asyncio.to_thread(self.conditions.resume, self.data)
        if problems:  # said until the service restarts: the operator should look at the file moved aside
            self.ctx.detail = "; ".join(problems) + "; started at the initial k, waiting for a fresh window"
        self.apply(self.conditions.current, self.ctx.common.clock.now_ns())

    def apply(self, c: Condition, t_ns: int) -> None:
        """A fixed condition's selection is numbered after every one published (DESIGN §8)."""
        seq = self.decider.next_seq()
        self.ctx.state = self.conditions.apply(c, t_ns, self.decider.params is not None, seq)
        if self.conditions.fixed is not None:
            self.decider.issued = max(self.decider.issued, seq)

    @on(ROBOT_STATE, maxsize=1)  # the latest only
    async def on_state(self, s: RobotState) -> Out:
        """The seq of the selection in force at the executor. One past every selection this decider
        published is not its own (its state file moved aside, or a rogue with its account): its current
        selection is said again at once, numbered after it and stamped now, so that the executor holds this
        decider's k again, not from its next window on."""
        if s.selection_seq is None:
            return []
        self.decider.applied = s.selection_seq
        if s.selection_seq <= self.decider.issued or self.selection is None:
            return []
        self.ctx.counters["renumbered"] += 1
        log.warning("the executor holds a selection numbered %d, past this decider's %d: said again as %d",
                    s.selection_seq, self.decider.issued, self.decider.next_seq())  # fmt: skip
        now = self.ctx.common.clock.now_ns()
        if self.conditions.fixed is not None:
            self.apply(self.conditions.current, now)
        elif self.decider.record is not None:
            record = msgspec.structs.replace(self.decider.record, seq=self.decider.next_seq(), t_ns=now)
            await self.adopt(record)
        return await self.current()

    async def adopt(self, record: DecisionRecord) -> None:
        """Persisted before it is announced, so what is published is what a restart resumes. A disk that
        cannot take it (full, read-only) does not stop the deciding: the record is adopted and published
        anyway, and the status says once that k is not persisted (a restart would resume an older one),
        until a write goes through again."""
        try:
            await asyncio.to_thread(self.decider.persist, record)
        except OSError as exc:
            if self.unpersisted is None:
                self.unpersisted = (f"cannot write {self.decider.path}: {exc.strerror or exc}; deciding "
                                    "from memory (a restart would resume an older k)")  # fmt: skip
                log.warning("%s", self.unpersisted)
                self.ctx.detail = self.unpersisted
            self.ctx.counters["unpersisted"] += 1
        else:
            if self.unpersisted is not None:
                log.info("%s written again: k is persisted", self.decider.path)
                self.unpersisted, self.ctx.detail = None, ""
        self.decider.commit(record)

    @property
    def selection(self) -> Selection | None:
        return self.conditions.fixed or self.decider.selection

    @every
    async def current(self) -> Out:
        return [self.selection] if self.selection is not None else []

    def from_the_future(self, w: HrvWindow) -> None:
        """On arrival, before the queue and before any query for missed windows: a window that ends
        ahead of this service's clock is refused (4,000 planted ones once asked the analyser 259 times
        and pushed an honest window out of the queue)."""
        admitted(self.decider.line.future(w.end_ns, self.ctx.common.clock.now_ns()))

    @on(HRV_WINDOW, screen="from_the_future")
    async def on_window(self, w: HrvWindow) -> Out:
        self.ctx.counters["windows"] += 1
        if self.conditions.fixed is not None:
            return []
        if self.decider.params is None:
            self.ctx.counters["windows_without_calibration"] += 1
            return []
        out = await self.missed(before_ns=w.start_ns)
        await self.decide(w)
        return [*out, *await self.current()]

    async def decide(self, w: HrvWindow) -> None:
        self.ctx.counters["window_line_restarts"] += self.decider.admit(w, self.ctx.common.clock.now_ns())
        before = self.decider.record.k if self.decider.record is not None else None
        await self.adopt(record := self.decider.answer(w))
        self.ctx.counters["windows_held_for_movement"] += record.reason == "movement"
        rr = f"{w.mean_rr_s:.3f} s" if w.mean_rr_s is not None else "none"
        log.info("window to %s: mean RR %s (%s): k %s → %d (%s)", _clock(w.end_ns), rr, w.quality, before,
                 record.k, record.reason)  # fmt: skip

    async def missed(self, before_ns: int | None = None) -> Out:
        """The windows published while this service was down or stopped (DESIGN §9: the analyser answers
        for them), decided in order, each selection published: before, a window missed that way was
        never decided, and the next step was several windows' worth at once."""
        record = self.decider.record
        if record is None or record.last_end_ns < 0 or self.decider.params is None:
            return []
        after, out = record.last_end_ns, list[Message]()
        if before_ns is not None and before_ns <= after + MISSED_GAP_NS:
            return []  # contiguous: nothing was missed
        for _ in range(MAX_MISSED):
            self.ctx.counters["missed_queries"] += 1
            replies = await self.ctx.bus.get(HRV_WINDOW, timeout=2.0, parameters=f"after={after}")
            w = next((r.message for r in replies if r.message is not None), None)
            if w is None or (before_ns is not None and w.end_ns > before_ns):
                break
            try:
                await self.decide(w)
            except Rejected as r:  # not in line (a stream that started afresh): not this one's to decide
                self.ctx.bus.reject(self.ctx.bus.key(HRV_WINDOW.suffix), r.code, r.detail)
                break
            self.ctx.counters["missed_windows_decided"] += 1
            out += await self.current()
            after = w.end_ns
        return out

    async def work(self) -> None:
        """At start: what was published while it was down."""
        self.ctx.bus.asks(HRV_WINDOW)
        if (out := await self.missed()) and self.conditions.fixed is None:
            self.publish(*out)

    @on(CALIBRATION)
    async def on_calibration(self, cal: Calibration) -> Out:
        out: Out = []
        # stamped now at the oldest: a calibration stored a while ago decides now, and the executor refuses
        # a selection stamped more than its period before the one in force
        if (
            record := self.decider.calibrated(cal, max(cal.t_ns, self.ctx.common.clock.now_ns()))
        ) is not None:
            log.info("calibration for %s: RR_r = %.3f s", cal.subject, cal.rr_rest_s)
            await self.adopt(record)
            self.apply(self.conditions.current, record.t_ns)
            out = await self.current()
        self.conditions.calibrations_seen.append(cal.t_ns)  # once in force: a session's (c) starts from it
        return out

    @answers(SELECTION)
    async def query(self, req: Request) -> Selection:
        if (sel := self.selection) is None:
            raise QueryError("no calibration yet: run `cadence calibrate` or set rr_rest_s")
        return sel

    @answers(DECISION_CONDITION)
    async def set_condition(self, req: Request) -> Answer:
        """A session sets its condition: stored, then in force, then announced; the reply is the
        selection it starts with, whose t_ns is the data time the condition took effect."""
        now = self.ctx.common.clock.now_ns()
        c = self.conditions.requested(req.params, now)
        if c.mode == "adaptive":
            if self.decider.record is None:
                raise QueryError("no calibration yet: condition (c) needs RR_r (`cadence calibrate`)")
            await self.adopt(self.decider.starting(self.decider.record.calibration, now))
        await asyncio.to_thread(store_condition, self.data, c)
        self.apply(c, now)
        log.info("condition %s%s set by %r", c.mode, f" (k {c.fixed_k})" if c.mode == "fixed" else "", c.by)
        return Answer(await self.query(req), await self.current())


def _clock(t_ns: int) -> str:
    """A data time as people read it in a log: UTC, to the second."""
    return time.strftime("%H:%M:%S", time.gmtime(t_ns / 1e9))


main = node_main(DecisionMaker)


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv)


if __name__ == "__main__":
    sys.exit(run())
