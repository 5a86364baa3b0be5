"""decision_maker: each ``hrv/window`` → the paper's Alg. 1 → ``decision/selection`` (DESIGN §7, §11).

The selection is state, not an event: it is republished every ``republish_s`` and answered on query, so a
publication lost while a router was down is not lost for long. k and RR_{i-1} are written atomically to
the data folder after every window, before the selection is announced, so a restarted service goes on
where it stopped. A window it has answered already (a replay, a duplicate) or one far from the windows'
data time is dropped and counted (common/runtime/admission.py). Without a calibration it publishes nothing and
says so on its status, rather than guess the subject's resting RR.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys
from collections import deque
from pathlib import Path
from typing import Annotated, Literal

import msgspec

from common.decision import fixed_k
from common.hrv.calibration import load_calibration as load_stored_calibration
from common.runtime.bus import QueryError, Request
from common.runtime.service import ServiceContext, service_main
from schemas.base import RrSeconds
from schemas.decision import MAX_N, Selection
from schemas.hrv import HrvWindow
from schemas.operator import Calibration
from schemas.topology import CALIBRATION, CALIBRATION_NOT_YET, DECISION_CONDITION, HRV_WINDOW, SELECTION
from services.decision_maker.state import (
    CONDITION_FILE,
    Condition,
    Decider,
    load_condition,
    load_record,
    same_calibration,
    store_condition,
)

log = logging.getLogger("cadence.decision_maker")
NAME = "decision_maker"


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
    fixed_k: Annotated[int, msgspec.Meta(ge=1, le=MAX_N)] | Literal["a", "b"] = "a"

    def __post_init__(self) -> None:
        fixed_k(self.fixed_k, self.n)  # a k above n is a mistake in the config, said at start


def fixed_selection(preset: int | str, n: int, t_ns: int) -> Selection:
    """A fixed condition's selection: one k, stated once, republished like any other."""
    return Selection(t_ns=t_ns, seq=0, k=fixed_k(preset, n), n=n, delta=0, reason="fixed")


def parse_condition(p: dict[str, str], n: int, t_ns: int) -> Condition:
    """``mode=fixed;k=a`` (``a``, ``b`` or a number) or ``mode=adaptive``, with ``by=<who>``: a QueryError
    says what is wrong, so the session that asked can tell its user."""
    mode, k, by = p.get("mode", ""), p.get("k", "a"), p.get("by", "")[:200]
    if mode not in ("adaptive", "fixed"):
        raise QueryError(f"mode={mode!r}: expected mode=adaptive or mode=fixed;k=a|b|<1…{n}>")
    preset: int | str = int(k) if k.isdecimal() else k
    try:
        fixed_k(preset, n)
    except ValueError as exc:
        raise QueryError(f"k={k}: {exc}") from None
    return Condition(mode=mode, fixed_k=preset, t_ns=t_ns, by=by)  # type: ignore[arg-type]


def load_calibration(data_dir: Path, settings: Settings, problems: list[str]) -> Calibration | None:
    """The calibration `cadence calibrate` stored, else one from ``rr_rest_s`` in the config."""
    loaded = load_stored_calibration(data_dir)
    if loaded.problem:
        problems.append(loaded.problem)
    if loaded.value is not None:
        return loaded.value
    if settings.rr_rest_s is not None:
        return Calibration(t_ns=0, seq=0, subject="config", rr_rest_s=settings.rr_rest_s)
    return None


def start(decider: Decider, data: Path, settings: Settings) -> list[str]:
    """Resume the persisted state, or start at the initial k; what was wrong with the files on disk."""
    problems: list[str] = []
    cal = load_calibration(data, settings, problems)
    loaded = load_record(decider.path)
    if loaded.problem:
        problems.append(loaded.problem)
    rec = loaded.value
    if rec is not None and rec.n != settings.n:
        log.info("%s was written for n = %d, not %d: starting afresh", decider.path, rec.n, settings.n)
        rec = None
    if rec is not None and (cal is None or same_calibration(rec.calibration, cal)):
        decider.commit(rec, resumed=True)
        log.info("resumed at k = %d", rec.k)
    elif cal is not None and (fresh := decider.calibrated(cal, 0)) is not None:
        decider.commit(fresh)
    for p in problems:
        log.error("%s", p)
    return problems


async def main(ctx: ServiceContext) -> None:
    settings: Settings = ctx.settings
    bus = ctx.bus
    data = ctx.common.data_path
    decider = Decider(data, settings.n)
    selections = bus.publisher(SELECTION)  # numbered by the decider: its seq is persisted state
    problems = await asyncio.to_thread(start, decider, data, settings)
    stored = await asyncio.to_thread(load_condition, data)
    if stored.problem:
        problems.append(stored.problem)
    condition = Condition(mode=settings.mode, fixed_k=settings.fixed_k)
    if stored.value is not None:
        try:
            fixed_k(stored.value.fixed_k, settings.n)
            condition = stored.value
            log.info("condition %s from %s (set by %r), over the config's", condition.mode, CONDITION_FILE,
                     condition.by)  # fmt: skip
        except ValueError as exc:
            problems.append(f"{CONDITION_FILE}: {exc} (n = {settings.n}); the config's condition holds")
    if problems:  # said until the service restarts: the operator should look at the file moved aside
        ctx.detail = "; ".join(problems) + "; started at the initial k, waiting for a fresh window"
    fixed: Selection | None = None

    def apply(c: Condition, t_ns: int) -> None:
        nonlocal condition, fixed
        condition = c
        fixed = fixed_selection(c.fixed_k, settings.n, t_ns) if c.mode == "fixed" else None
        if fixed is not None:
            ctx.state = f"fixed at k = {fixed.k} of {fixed.n} (fixed_k = {c.fixed_k!r})"
        else:
            ctx.state = "running" if decider.params else "waiting for calibration"

    apply(condition, ctx.common.clock.now_ns())

    def current() -> Selection | None:
        return fixed or decider.selection

    def publish() -> None:
        if (sel := current()) is not None:
            selections.put(sel)

    async def on_window(key: str, w: HrvWindow) -> None:
        ctx.counters["windows"] += 1
        if fixed is not None:
            return
        if decider.params is None:
            ctx.counters["windows_without_calibration"] += 1
            return
        verdict = decider.line.admit(w.start_ns, w.end_ns, clock_ns=ctx.common.clock.now_ns())
        if not verdict.acted_on:
            bus.reject(key, verdict.code, verdict.detail)
            return
        if verdict.action == "restart":
            log.warning("hrv/window: %s", verdict.detail)
            ctx.counters["window_line_restarts"] += 1
        record = decider.answer(w)
        await asyncio.to_thread(decider.persist, record)  # persisted before it is announced
        decider.commit(record)
        publish()

    calibrations_seen: deque[int] = deque(maxlen=16)  # their t_ns: a session asks after its own

    async def on_calibration(_: str, cal: Calibration) -> None:
        record = decider.calibrated(cal, cal.t_ns)
        if record is not None:
            log.info("calibration for %s: RR_r = %.3f s", cal.subject, cal.rr_rest_s)
            await asyncio.to_thread(decider.persist, record)
            decider.commit(record)
            if fixed is None:
                ctx.state = "running"
            publish()
        calibrations_seen.append(cal.t_ns)  # once in force: a session's (c) starts from it

    async def on_query(req: Request) -> Selection:
        if (sel := current()) is None:
            raise QueryError("no calibration yet: run `cadence calibrate` or set rr_rest_s")
        return sel

    async def on_condition(req: Request) -> Selection:
        """A session sets its condition: stored, then in force, then announced; the reply is the
        selection it starts with, whose t_ns is the data time the condition took effect."""
        now = ctx.common.clock.now_ns()
        c = parse_condition(req.params, settings.n, now)
        # a session that has just calibrated names its calibration: the topic and this query travel
        # apart, and condition (c) must start from the new RR_r, not the one before
        wanted = req.params.get("calibration")
        if wanted is not None and (not wanted.isdecimal() or int(wanted) not in calibrations_seen):
            raise QueryError(f"{CALIBRATION_NOT_YET}: calibration {wanted[:40]}")
        if c.mode == "adaptive":
            cal = decider.record.calibration if decider.record is not None else None
            if cal is None:
                raise QueryError("no calibration yet: condition (c) needs RR_r (`cadence calibrate`)")
            record = decider.calibrated(cal, now, again=True)  # Alg. 1 from the initial k
            assert record is not None
            await asyncio.to_thread(decider.persist, record)
            decider.commit(record)
        await asyncio.to_thread(store_condition, data, c)
        apply(c, now)
        log.info("condition %s%s set by %r", c.mode, f" (k {c.fixed_k})" if c.mode == "fixed" else "", c.by)
        publish()
        sel = current()
        assert sel is not None
        return sel

    bus.handle(CALIBRATION, on_calibration)
    bus.handle(HRV_WINDOW, on_window)
    bus.serve(SELECTION, on_query)
    bus.serve(DECISION_CONDITION, on_condition)
    while not ctx.stop.is_set():
        publish()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(ctx.stop.wait(), settings.republish_s)


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv)


if __name__ == "__main__":
    sys.exit(run())
