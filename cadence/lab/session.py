"""A live study session (`cadence session`, paper §III-C): the cell checked ready, the subject's
calibration, the condition asked of the decision maker, the session recorded into its file
(cadence/lab/session_file.py) while the experimenter's keys mark errors and signals, and the file closed
with its end. The terminal it shows is cadence/lab/live.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import msgspec

from cadence.lab.calibrate import at_the_slowest
from cadence.lab.marks import counted
from cadence.lab.session_file import CLOCKED, SessionWriter, software, task_digest
from common.hrv.calibration import SETTLED_WINDOWS, settled
from common.runtime.bus import Bus
from common.runtime.errors import CadenceError, InputError
from common.runtime.numeric import numeric_build
from common.trajectory.shipped import digest_of_all
from common.trajectory.task import load_task
from schemas import (
    Calibration,
    CycleReport,
    HrvWindow,
    OperatorError,
    RobotState,
    Selection,
    ServiceStatus,
)
from schemas.operator import ErrorKind, OperatorSignal, Posture
from schemas.pareto import ParetoSet
from schemas.session import Condition, SessionEnd, SessionInfo, Tlx
from schemas.topology import (
    DEFAULT_CELL,
    OPERATOR_ERROR,
    OPERATOR_SIGNAL,
    PARETO_SET,
    cell_roster,
    decode_any,
)
from schemas.topology import key as key_of

# the executor's states in which the robot works or is about to: anything else, and the cell is not ready
ROBOT_READY = ("ready", "moving", "waiting_for_operator", "waiting_for_selection")
STALE_S = 10.0  # wall seconds without a clocked message: the live view says the cell went quiet


@dataclass(frozen=True, slots=True)
class SessionOptions:
    subject: str
    condition: Condition
    minutes: float
    out: Path
    data_dir: Path  # where `cadence calibrate` stored the calibration, and where a new one is stored
    task: Path
    cell: str = DEFAULT_CELL
    calibrate_minutes: float | None = None
    measured_sigma: bool = False
    ready_timeout_s: float = 120.0
    notes: str = ""
    posture: Posture = "rest"  # of a calibration this session takes (--calibrate)
    settle_timeout_s: float | None = 600.0  # data time the settle gate waits; None: no gate
    training_minutes: float = 0.0  # data time in the condition before it counts (recorded, not analysed)
    yoked_k: int | None = None  # condition y: the k it holds
    study: str = ""  # with a study plan: its name, the session's place, the last session's end (data time)
    period: int | None = None
    previous_end_ns: int | None = None


@dataclass
class Watch:
    """What the session sees of the cell, updated on the loop thread as messages are written."""

    statuses: dict[str, ServiceStatus] = field(default_factory=dict)
    robot: RobotState | None = None
    window: HrvWindow | None = None
    recent: deque[HrvWindow] = field(default_factory=lambda: deque(maxlen=SETTLED_WINDOWS))
    selection: Selection | None = None
    data_ns: int = 0  # the latest data time a clocked key carried
    data_wall: float = 0.0  # when it came (monotonic)
    start_ns: int | None = None
    cycles: int = 0
    marked: list[OperatorError] = field(default_factory=list)  # the errors since the condition began
    isolation: str | None = None  # ``Bus.isolation()`` as last checked
    changed: asyncio.Event = field(default_factory=asyncio.Event)

    def on(self, key: str, payload: bytes) -> None:
        try:
            msg = decode_any(payload)
        except msgspec.DecodeError:
            return
        suffix = key.split("/", 2)[-1]
        if suffix in CLOCKED and msg.t_ns > self.data_ns:
            self.data_ns, self.data_wall = msg.t_ns, time.monotonic()
        counting = self.start_ns is not None and msg.t_ns > self.start_ns
        if isinstance(msg, ServiceStatus):
            self.statuses[msg.service] = msg
        elif isinstance(msg, RobotState):
            self.robot = msg
        elif isinstance(msg, HrvWindow):
            self.window = msg
            self.recent.append(msg)
        elif isinstance(msg, Selection):
            self.selection = msg
        elif isinstance(msg, CycleReport) and counting:
            self.cycles += 1
        elif isinstance(msg, OperatorError) and counting:
            self.marked.append(msg)
        self.changed.set()

    @property
    def errors(self) -> int:
        return len(counted(self.marked))

    def moving_at(self, selection: Selection) -> int | None:
        """The data time of a robot state after ``selection`` that moves at its k; None while none has."""
        r = self.robot
        if r is None or r.t_ns < selection.t_ns or r.k != selection.k or r.mode != "moving":
            return None
        return r.t_ns

    async def next_change(self, timeout_s: float) -> None:
        """Until the next message, or ``timeout_s``: the live view's pace when nothing comes."""
        self.changed.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self.changed.wait(), timeout_s)

    def readiness(self) -> dict[str, str | None]:
        """Each check and what is wrong with it (None: fine)."""
        missing = [s for s in cell_roster(self.statuses) if s not in self.statuses]
        robot, w = self.robot, self.window
        return {
            "bus": self.isolation,
            "services": f"no status yet from {', '.join(missing)}" if missing else None,
            "robot": "no robot/state yet"
            if robot is None
            else None
            if robot.state in ROBOT_READY
            else f"the executor is {robot.state}: {robot.reason}",
            "strap": "no HRV window yet"
            if w is None
            else None
            if w.quality == "good"
            else f"the last window is of {w.quality} quality ({w.reason or 'no beats'}): check the strap",
        }


async def until_settled(
    watch: Watch,
    rr_rest_s: float,
    opts: SessionOptions,
    stop: asyncio.Event,
    show: Callable[[str, Watch, SessionOptions], None],
) -> None:
    """Wait until the person's recent windows are settled near ``rr_rest_s``; counted in the person's
    (data) time, not the host's: on a sped-up cell (the demo's 16x) 600 s of wall time is hours of
    heart, on a loaded host minutes of it. Data that stops coming is the cell's fault, said as such."""
    assert opts.settle_timeout_s is not None
    watch.recent.clear()  # windows from now on
    deadline_ns = watch.data_ns + round(opts.settle_timeout_s * 1e9)
    while not stop.is_set() and (why := settled(watch.recent, rr_rest_s)) is not None:
        show(f"waiting for the person to settle: {why}", watch, opts)
        if watch.data_ns > deadline_ns:
            raise CadenceError(
                f"the person has not settled near the baseline RR_r = {rr_rest_s:.3f} s after "
                f"{opts.settle_timeout_s:g} s: {why} (let them rest or work at the slowest pace, or "
                "calibrate again)"
            )
        if time.monotonic() - watch.data_wall > opts.ready_timeout_s:
            raise CadenceError(
                f"no data from the cell for {opts.ready_timeout_s:g} s while waiting for the person to "
                f"settle: {watch.readiness()['robot'] or 'the cell stopped sending'}"
            )
        await watch.next_change(0.5)


def check_ready(readiness: dict[str, str | None]) -> str | None:
    problems = [f"{what}: {why}" for what, why in readiness.items() if why is not None]
    return "; ".join(problems) or None


def condition_parameters(opts: SessionOptions, calibrated_ns: int | None = None) -> str:
    """What `decision/condition` is asked: (c) is Alg. 1; (a), (b) and the yoked (y) are a fixed k."""
    if opts.condition == "y" and opts.yoked_k is None:
        raise InputError("condition y holds the subject's mean k of (c): none given (their (c) session?)")
    k = opts.yoked_k if opts.condition == "y" else opts.condition
    mode = "mode=adaptive" if opts.condition == "c" else f"mode=fixed;k={k}"
    params = f"{mode};by=session {opts.subject}/{opts.condition}"
    return params if calibrated_ns is None else f"{params};calibration={calibrated_ns}"


async def ask_condition(
    bus: Bus, opts: SessionOptions, timeout: float, calibrated_ns: int | None = None
) -> Selection:
    """Set the condition; ``calibrated_ns``: the calibration this session just published, which the
    decision maker must have before it starts (c) from it (it says "not received yet" until then)."""
    from schemas.topology import CALIBRATION_NOT_YET, DECISION_CONDITION

    params = condition_parameters(opts, calibrated_ns)
    give_up = time.monotonic() + timeout
    while True:
        replies = await bus.get(DECISION_CONDITION, timeout=timeout, parameters=params)
        if not replies:
            raise CadenceError(
                f"no decision maker answered on cadence/{opts.cell}/decision/condition within {timeout:g} s"
            )
        r = replies[0]
        if r.message is not None:
            return r.message
        if CALIBRATION_NOT_YET not in (r.error or "") or time.monotonic() > give_up:
            raise CadenceError(f"the decision maker refused condition {opts.condition}: {r.error}")
        await asyncio.sleep(0.2)  # the calibration is on its way; ask again


async def served_sets(bus: Bus, paths: Iterable[str], timeout: float = 2.0) -> dict[str, ParetoSet]:
    """The sets the cell's store serves now, of those of ``paths`` it answers for."""
    found = {}
    for pid in paths:
        replies = await bus.get(PARETO_SET.at(pid), timeout=timeout)
        if replies and replies[0].message is not None:
            found[pid] = replies[0].message
    return found


async def sets_in_use(bus: Bus, task: Path, timeout: float = 2.0) -> str:
    """The digest of the sets the cell's store serves for ``task``'s paths (common/trajectory/shipped.py),
    recorded in the session file; "" when a path's set is not served (yet): the file then says nothing."""
    paths = list(load_task(task).paths)
    return digest_of_all(await served_sets(bus, paths, timeout), paths)


def stored_calibration(opts: SessionOptions) -> Calibration:
    from common.hrv.calibration import calibration_path, load_calibration

    loaded = load_calibration(opts.data_dir)
    cal = loaded.value
    if cal is None:
        raise InputError(
            f"no calibration in {calibration_path(opts.data_dir)}"
            + (f" ({loaded.problem})" if loaded.problem else "")
            + ": run the session with --calibrate MINUTES, or `cadence calibrate` first"
        )
    if cal.subject != opts.subject:
        raise InputError(
            f"{calibration_path(opts.data_dir)} is subject {cal.subject}'s, not {opts.subject}'s: "
            "calibrate this subject (--calibrate MINUTES)"
        )
    return cal


ERROR_KEYS: dict[str, ErrorKind] = {"e": "wrong_object", "l": "late", "o": "other", "u": "undo"}


def key_message(key: str, signals: list[str], t_ns: int) -> OperatorError | OperatorSignal | None:
    """What a key in the live view means: ``e``/``l``/``o`` the experimenter marks an error (wrong object,
    late, other), ``u`` withdraws their last mark; ``1``…``9`` a part placed, the task's n-th
    ``wait_for`` signal; anything else nothing."""
    if key in ERROR_KEYS:
        return OperatorError(t_ns=t_ns, seq=0, kind=ERROR_KEYS[key], source="experimenter",
                             description="marked in the session's live view")  # fmt: skip
    if key.isdecimal() and 1 <= int(key) <= len(signals):
        return OperatorSignal(t_ns=t_ns, seq=0, name=signals[int(key) - 1], source="keyboard")
    return None


async def run_session(
    bus: Bus,
    opts: SessionOptions,
    stop: asyncio.Event,
    show: Callable[[str, Watch, SessionOptions], None],
    calibrate: Callable[[], Awaitable[Calibration]],
    keys: asyncio.Queue[str] | None = None,
    questionnaire: Callable[[], Awaitable[Tlx | None]] | None = None,
) -> SessionEnd:
    """Check the cell, calibrate (``calibrate``: `cadence calibrate`'s, bound to this bus) or take the
    stored calibration, train (``training_minutes`` in the condition, recorded and not analysed), set the
    condition, and record until ``minutes`` of data time have passed or ``stop``. ``show(phase, watch,
    opts)`` is called as things change (the live view); ``keys`` are the experimenter's keys in it
    (``key_message``), acted on while the condition runs; ``questionnaire`` asks the subject's NASA-TLX
    once the condition has ended, and its answer is kept in the end record."""
    cal = None if opts.calibrate_minutes else stored_calibration(opts)
    signals = list(dict.fromkeys(s.wait_for for s in load_task(opts.task).cycle if s.wait_for))
    errors_out, signals_out = bus.publisher(OPERATOR_ERROR), bus.publisher(OPERATOR_SIGNAL)

    last_ns = 0

    def act(key: str) -> None:
        # now, on the cell's clock: the latest data time seen, never before the session began, and each
        # key its own stamp (two parts put down are two signals: a signal's stamp tells a copy apart)
        nonlocal last_ns
        last_ns = max(watch.data_ns, (watch.start_ns or 0) + 1, last_ns + 1)
        msg = key_message(key, signals, last_ns)
        if isinstance(msg, OperatorError):
            errors_out.put(msgspec.structs.replace(msg, seq=errors_out.next_seq()))
        elif isinstance(msg, OperatorSignal):
            signals_out.put(msgspec.structs.replace(msg, seq=signals_out.next_seq()))

    writer = SessionWriter(opts.out, opts.cell)
    watch = Watch()

    def on(key: str, payload: bytes) -> None:
        writer.recorder.write(key, payload)
        watch.on(key, payload)

    sub = bus.subscribe_raw(key_of(opts.cell, "**"), on)
    wall0 = time.monotonic()
    end = SessionEnd(end_ns=1, complete=False, reason="stopped before the condition took effect")
    began = False
    try:
        # 1. the cell is ready: every service's status, the robot, the strap
        deadline = wall0 + opts.ready_timeout_s
        while not stop.is_set():
            watch.isolation = bus.isolation()
            if (problem := check_ready(watch.readiness())) is None:
                break
            show("checking the cell", watch, opts)
            if time.monotonic() > deadline:
                raise CadenceError(f"the cell is not ready after {opts.ready_timeout_s:g} s: {problem}")
            await watch.next_change(0.5)
        # 2. the calibration, if asked: at rest, or at work at the slowest solution
        if opts.calibrate_minutes and not stop.is_set():
            show(
                "calibrating at rest" if opts.posture == "rest" else "calibrating at work (k = 1)",
                watch,
                opts,
            )
            cal = await _until(stop, calibrate())
        # 3. training: the condition in force, recorded, before the span the analysis reads
        fresh = cal.t_ns if cal is not None and opts.calibrate_minutes else None
        training_ns = None
        if opts.training_minutes and cal is not None and not stop.is_set():
            trial = await ask_condition(bus, opts, timeout=10.0, calibrated_ns=fresh)
            training_ns, fresh = trial.t_ns, None
            until = trial.t_ns + round(opts.training_minutes * 60e9)
            while watch.data_ns < until and not stop.is_set():
                show("training (recorded, not analysed)", watch, opts)
                await watch.next_change(0.25)
        # 3b. right before the condition: the person has settled near the baseline, as Alg. 1 starts from
        # RR_{-1} = RR_r (after the training, not before it: the training moves the heart too)
        if cal is not None and opts.settle_timeout_s is not None and not stop.is_set():
            # the last condition's pace lowered their RR: they settle at the slowest (at rest, anyway)
            by = f"session {opts.subject}/{opts.condition}: settling"
            await at_the_slowest(bus, by, "while the person settles")
            await until_settled(watch, cal.rr_rest_s, opts, stop, show)
        # 4. the condition, set afresh ((c) starts Alg. 1 again), and from then on the session counts
        #    (counted from when the robot moves at the condition's k, not from the decision maker's answer:
        #    a path in flight ends at the old k, and on a slow or held cell that is seconds of data time)
        began_ns: int | None = None
        if not stop.is_set() and cal is not None:
            first = await ask_condition(bus, opts, timeout=10.0, calibrated_ns=fresh)
            deadline = time.monotonic() + opts.ready_timeout_s
            while not stop.is_set() and (began_ns := watch.moving_at(first)) is None:
                show(f"waiting for the robot to move at k = {first.k}", watch, opts)
                if time.monotonic() > deadline:
                    raise CadenceError(
                        f"the robot has not moved at k = {first.k} within {opts.ready_timeout_s:g} s of the "
                        f"condition: {watch.readiness()['robot'] or 'it is held or waiting'}"
                    )
                await watch.next_change(0.5)
        if began_ns is not None:
            watch.start_ns = began_ns
            rest = (
                None if opts.previous_end_ns is None else max(0.0, (first.t_ns - opts.previous_end_ns) / 1e9)
            )
            writer.begin(
                SessionInfo(
                    subject=opts.subject,
                    condition=opts.condition,
                    cell=opts.cell,
                    calibration=cal,
                    start_ns=began_ns,
                    minutes=opts.minutes,
                    task=opts.task.name,
                    task_sha256=task_digest(opts.task),
                    software=software(),
                    sets_sha256=await sets_in_use(bus, opts.task),
                    build=numeric_build(),
                    notes=opts.notes,
                    study=opts.study,
                    period=opts.period,
                    break_s=rest,
                    training_start_ns=training_ns,
                    yoked_k=opts.yoked_k,
                )
            )
            began = True
            planned = began_ns + round(opts.minutes * 60e9)
            while watch.data_ns < planned and not stop.is_set():
                while keys is not None and not keys.empty():
                    act(keys.get_nowait())
                show("running", watch, opts)
                await watch.next_change(0.25)
            if stop.is_set():
                end = SessionEnd(end_ns=max(watch.data_ns, began_ns + 1), complete=False,
                                 reason="interrupted (Ctrl-C or a stop signal)")  # fmt: skip
            else:
                end = SessionEnd(end_ns=planned, complete=True, reason="on time")
            if questionnaire is not None:
                show("questionnaire (NASA-TLX)", watch, opts)
                end = msgspec.structs.replace(end, tlx=await questionnaire())
    except BaseException as exc:
        if began:
            end = SessionEnd(end_ns=max(watch.data_ns, (watch.start_ns or 0) + 1), complete=False,
                             reason=f"{type(exc).__name__}: {exc}"[:4000])  # fmt: skip
        raise
    finally:
        sub.undeclare()
        await asyncio.sleep(0)  # what Zenoh handed over before the undeclare is written
        if began:
            end = msgspec.structs.replace(end, wall_s=round(time.monotonic() - wall0, 3))
            writer.close(end)
        else:
            writer.recorder.close()
            opts.out.unlink(missing_ok=True)  # no condition took effect: not a session
    show("done", watch, opts)
    return end


async def _until(stop: asyncio.Event, work: Awaitable[Calibration]) -> Calibration | None:
    """``work``'s result, or None when ``stop`` comes first."""
    task = asyncio.ensure_future(work)
    stopper = asyncio.ensure_future(stop.wait())
    done, _ = await asyncio.wait({task, stopper}, return_when=asyncio.FIRST_COMPLETED)
    for t in (task, stopper):
        if t not in done:
            t.cancel()
    return task.result() if task in done else None
