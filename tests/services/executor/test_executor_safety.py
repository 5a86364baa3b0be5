"""The executor's fault paths, as the issue reproduced them: a stop is a latch (no motion until a resume),
a restart never moves at initial_k silently, and two executors never share a servo core. With the sim
backend, and with the real ur-rtde client against the emulator; on the in-memory bus."""

from __future__ import annotations

import asyncio
import contextlib
import math
import signal
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from common.runtime.bus import Bus
from schemas import CycleReport, RobotEvent, RobotState, Selection, ServiceStatus
from services.executor.__main__ import Settings
from services.executor.__main__ import main as executor_main
from services.executor.backends import SimBackend, UrRtdeBackend
from services.executor.persist import ExecutorStore
from tests.support.cell import Cell, put
from tests.support.executor import SPEED, TASK, next_of, operator_resumes, sim_settings, store_serving

pytestmark = pytest.mark.asyncio
STALL_S = 0.02  # a servo call this slow is an overrun at any speed
RUN = 25  # overruns in a row that stop the robot here: half a second of a stall, rarer than CI's jitter


@pytest.fixture
def task_file(tmp_path: Path) -> Path:
    p = tmp_path / "shuttle.toml"
    p.write_text(TASK)
    return p


def stall(
    monkeypatch: pytest.MonkeyPatch, backend: type, realtime: bool = True, calls: int | None = None
) -> dict[str, Any]:
    """The machine stalls (as a loaded VM does) while ``on["stall"]``: every servo call takes 20 ms.
    ``calls``: from the start, for that many servo calls (``on["left"]`` counts them down).
    ``realtime``: the arm is paced as a controller paces a real one, so overruns stop it (the sim's own
    time is the samples sent, and nothing stops it). The stall is patched into this process, so the
    executors of these tests run their servo loop as a thread of it (``servo = "thread"``): the servo
    process's own timing is tested in test_servo_process.py and on the wall clock (test_walk_in.py)."""
    import time

    on: dict[str, Any] = {"stall": calls is not None, "left": calls or 0}
    real = backend.servo

    def slow(self, target):
        if on["stall"]:
            time.sleep(STALL_S)
            if calls is not None:
                on["left"] -= 1
                on["stall"] = on["left"] > 0
        return real(self, target)

    monkeypatch.setattr(backend, "servo", slow)
    monkeypatch.setattr(backend, "realtime", realtime)
    return on


@contextlib.asynccontextmanager
async def stalling(cell: Cell, task_file: Path, tmp_path: Path, **changes: object) -> AsyncIterator[Any]:
    """A sim executor whose host the test stalls (``stall``), at k = 2: (bus, events, states, cycles,
    ``operator``). Once the test has resumed the stop it made, ``operator()`` has an operator clear what
    comes: a loaded host's own misses can stop this real-time arm again, as they would a real one."""
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
        cycles = aiter(bus.subscribe(bus.key("robot/cycle"), CycleReport))
        settings = sim_settings(task_file, overrun_limit=RUN, initial_k=2, servo="thread", **changes)
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        clearing: list[asyncio.Task[None]] = []
        try:
            yield (
                bus,
                events,
                states,
                cycles,
                lambda: clearing.append(asyncio.create_task(operator_resumes(bus))),
            )
        finally:
            for task in clearing:
                task.cancel()
            await ex.close()
            await store.close()


async def still_while_stopped(states, n: int = 100) -> RobotState:
    """The next ``n`` robot states (2 s at 50 Hz) once stopped and at rest: all stopped, none moving."""
    await next_of(states, lambda s: s.state == "stopped" and max(map(abs, s.qd)) == 0.0, timeout=30)
    last = None
    for _ in range(n):
        last = await next_of(states, timeout=10)
        assert last.state == "stopped", last
        assert last.mode != "moving", last
        assert max(map(abs, last.qd)) == 0.0, f"the arm moved while stopped: {last.qd}"
    assert last is not None
    return last


async def resume(bus: Bus, by: str = "the test") -> str:
    (reply,) = await bus.get(f"{bus.key('robot/resume')}?by={by}", RobotEvent, timeout=20)
    assert reply.message is not None, reply.error
    return reply.message.message


async def test_an_overrun_stop_holds_the_sim_arm_still_until_resumed(
    task_file: Path, tmp_path: Path, cell: Cell, monkeypatch: pytest.MonkeyPatch
) -> None:
    on = stall(monkeypatch, SimBackend)
    async with stalling(cell, task_file, tmp_path, cycles=0) as (bus, events, states, cycles, operator):
        await next_of(states, lambda s: s.mode == "moving")
        on["stall"] = True
        stop = await next_of(events, lambda e: e.kind == "protective_stop")
        on["stall"] = False  # the machine is fine again: still, nothing moves until a person says so
        held = await still_while_stopped(states)
        said = await resume(bus)
        operator()
        report = await next_of(cycles, timeout=120)
    assert "overruns in a row" in stop.message
    assert "overruns in a row" in held.reason
    assert said.startswith("ready")
    assert "resumed by the test" in said
    assert report.k_per_path == {"there": 2, "back": 2}


async def test_a_path_cut_short_by_a_stop_goes_on_from_where_the_arm_stopped_once_resumed(
    task_file: Path, tmp_path: Path, cell: Cell, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A resume goes on with the path from where the arm stopped, not from the path's start: going back
    and running it whole again is what a loaded host's next stop interrupted, and an executor without
    real-time priority beside busy loops never ended a cycle (issue 53). Joint 0 of 'there' only rises, so
    it never goes back towards 0."""
    on = stall(monkeypatch, SimBackend)
    async with stalling(cell, task_file, tmp_path) as (bus, events, states, cycles, operator):
        await next_of(states, lambda s: s.path_id == "there" and s.q[0] > math.radians(10), timeout=30)
        on["stall"] = True
        await next_of(events, lambda e: e.kind == "protective_stop")
        on["stall"] = False
        stopped = await still_while_stopped(states, 10)
        await resume(bus)
        operator()
        going_on = await next_of(events, lambda e: "goes on from where it stopped" in e.message)
        seen = []
        async with asyncio.timeout(120):
            while (s := await next_of(states, timeout=30)).path_id != "back":
                seen.append(s)
        report = await next_of(cycles, timeout=60)
    after = [s for s in seen if s.t_ns > going_on.t_ns]
    assert after and any(s.mode == "moving" for s in after)
    # at most a short move back onto the curve (the braking stop left the arm off it, past the last
    # sample), never the way back to the start (joint 0 at 0)
    assert min(s.q[0] for s in after) >= stopped.q[0] - 0.02, "the arm went back along 'there'"
    assert not any("the start of 'there'" in s.reason for s in after)
    assert max(s.q[0] for s in after) == pytest.approx(math.radians(45), abs=1e-3)  # and ended it
    said = float(going_on.message.split("s = ")[1].split(" s")[0])
    assert 0.0 < said < float(going_on.message.split(" of ")[1].split(" s")[0])
    assert report.k_per_path == {"there": 2, "back": 2}


async def test_a_latched_stop_outlives_a_restart_until_a_person_resumes(
    task_file: Path, tmp_path: Path, cell: Cell, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stop is latched on disk: an executor restarted while stopped (it crashed, the host rebooted, a
    library died with the controller's link) comes up stopped, still until a person resumes; the resume
    clears it there too, so the next restart moves. A restart once forgot the stop and moved the arm."""
    on = stall(monkeypatch, SimBackend)
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
        settings = sim_settings(task_file, overrun_limit=RUN, cycles=0, initial_k=2, servo="thread")
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        await next_of(states, lambda s: s.mode == "moving")
        on["stall"] = True
        await next_of(events, lambda e: e.kind == "protective_stop")
        on["stall"] = False
        await still_while_stopped(states, 5)
        await ex.close()
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        said = await next_of(events, lambda e: e.kind == "protective_stop" and "last run" in e.message)
        held = await still_while_stopped(states)
        answer = await resume(bus)
        await next_of(states, lambda s: s.mode == "moving", timeout=30)
        await ex.close()
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        again = await next_of(states, lambda s: s.mode == "moving" or s.state == "stopped", timeout=30)
        await ex.close()
        await store.close()
    assert "overruns in a row" in said.message and "until `cadence robot resume`" in said.message
    assert held.reason.endswith("(latched before a restart)") and "overruns in a row" in held.reason
    assert "resumed by the test" in answer
    assert again.mode == "moving"  # the resume cleared it on disk


async def test_a_run_that_died_during_a_motion_restarts_stopped_until_a_person_resumes(
    task_file: Path, tmp_path: Path, cell: Cell
) -> None:
    """The executor says on disk that the arm may move before each path's first step, and that it no longer
    does once the path ended in order: a run that died during a motion (a crash of ur-rtde when its
    controller vanished, a kill, a power cut), before it could latch its stop, leaves the first said, and
    the restart comes up stopped until a person resumes."""
    ExecutorStore(tmp_path / "ex" / "executor").moving("there")  # as a run killed during 'there' left it
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
        settings = sim_settings(task_file, cycles=0, initial_k=2)
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        said = await next_of(events, lambda e: e.kind == "protective_stop" and "last run" in e.message)
        held = await still_while_stopped(states, 20)
        answer = await resume(bus)
        await next_of(states, lambda s: s.mode == "moving", timeout=30)
        await ex.close()
        await store.close()
    assert "ended during 'there' with no stop" in said.message
    assert "ended during 'there'" in held.reason
    assert "resumed by the test" in answer


async def test_a_stalled_host_never_stops_the_sim_arm(
    task_file: Path, tmp_path: Path, cell: Cell, monkeypatch: pytest.MonkeyPatch
) -> None:
    # stalls for twice the run of overruns that stops a real arm (8 servo calls a tick)
    on = stall(monkeypatch, SimBackend, realtime=False, calls=8 * 2 * RUN)
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        cycles = aiter(bus.subscribe(bus.key("robot/cycle"), CycleReport))
        settings = sim_settings(task_file, overrun_limit=RUN, cycles=1, initial_k=2, servo="thread")
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        report = await next_of(cycles, timeout=60)
        await ex.close()
        await store.close()
        kinds = [e.kind for e in await _drained(events)]
    assert on["left"] == 0, kinds
    assert "overrun" in kinds, kinds  # the stalls were counted, as ever …
    assert "protective_stop" not in kinds  # … and the arm went on through them
    assert report.k_per_path == {"there": 2, "back": 2}


async def _drained(sub) -> list[RobotEvent]:
    """The messages a subscription holds now, without waiting for more."""
    out = []
    while True:
        try:
            _, msg = await asyncio.wait_for(anext(sub), 0.01)
        except TimeoutError:
            return out
        out.append(msg)


@pytest.mark.lockstep
async def test_a_resume_when_nothing_is_stopped_is_refused_with_the_state(
    task_file: Path, tmp_path: Path, cell: Cell
) -> None:
    async with cell.session() as bus:
        states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
        settings = Settings(task=str(task_file), fifo_priority=0, start_selection="wait")
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        await next_of(states, lambda s: s.state == "waiting_for_selection")
        (reply,) = await bus.get(bus.key("robot/resume"), RobotEvent, timeout=20)
        await ex.close()
    assert reply.message is None
    assert "nothing to resume: the robot is waiting_for_selection" in reply.error


async def test_the_sim_resumes_by_itself_only_when_configured_and_with_a_back_off(
    task_file: Path, tmp_path: Path, cell: Cell, monkeypatch: pytest.MonkeyPatch
) -> None:
    on = stall(monkeypatch, SimBackend)
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        cycles = aiter(bus.subscribe(bus.key("robot/cycle"), CycleReport))
        settings = sim_settings(
            task_file,
            overrun_limit=RUN,
            cycles=0,
            initial_k=2,
            resume_policy="auto",
            auto_resume_s=0.5,
            servo="thread",
        )
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        on["stall"] = True
        await next_of(events, lambda e: e.kind == "protective_stop")
        on["stall"] = False
        auto = await next_of(events, lambda e: e.kind == "state" and "resumed automatically" in e.message)
        await next_of(cycles)
        await ex.close()
        await store.close()
    assert "after 0 s" in auto.message or "after 1 s" in auto.message


@pytest.mark.parametrize("policy", ["last", "wait"])
@pytest.mark.lockstep
async def test_a_restart_with_the_decision_maker_unreachable_never_moves_at_initial_k(
    policy: str, task_file: Path, tmp_path: Path, cell: Cell
) -> None:
    """The reproduction: k = 1 decided, the executor restarted, the decision maker frozen: it moved at
    initial_k (8). Now it goes on at the persisted k ("last"), or waits ("wait") until a selection. The
    persisted k is the newest decided, not the last applied: a selection that came while the last path
    ran (k 2) was once forgotten for the one that path ran at."""
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        cycles = aiter(bus.subscribe(bus.key("robot/cycle"), CycleReport))
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
        decided = Selection(t_ns=1, seq=7, k=1, n=15, delta=-2, reason="stress")
        common = dict(
            task=str(task_file), fifo_priority=0, wait_for_signals=False, initial_k=8,
            switch_within_path=False,
        )  # fmt: skip

        # the first run: the decision maker answers (the test stands in for it) and k = 1 runs a cycle
        async def answer(req):
            return decided

        stand_in = bus.serve(bus.key("decision/selection"), answer)
        ex = cell.service("executor", executor_main, Settings(**common, cycles=1), tmp_path / "ex")
        await ex.listening(bus, "decision/selection")
        await next_of(states, lambda s: s.mode == "moving" and s.path_id == "back", timeout=60)
        newer = Selection(t_ns=2, seq=8, k=2, n=15, delta=1, reason="rest")  # during the last path
        put(bus, bus.key("decision/selection"), newer, block=True)
        assert (await next_of(cycles, timeout=60)).k_per_path == {"there": 1, "back": 1}
        await asyncio.wait_for(ex.task, 15)
        stand_in.undeclare()  # the decision maker is gone (frozen: it answers nothing)

        settings = Settings(**common, cycles=1, start_selection=policy)
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        chose = await next_of(events, lambda e: "the decision maker does not answer" in e.message, timeout=30)
        if policy == "wait":
            waiting = [await next_of(states, lambda s: s.state == "waiting_for_selection") for _ in range(50)]
            assert all(max(map(abs, s.qd)) == 0.0 and s.mode != "moving" for s in waiting)
            later = Selection(t_ns=3, seq=9, k=3, n=15, delta=1, reason="rest")
            await ex.listening(bus, "decision/selection")
            put(bus, bus.key("decision/selection"), later, block=True)
        report = await next_of(cycles, timeout=60)
        await asyncio.wait_for(ex.task, 15)
        await store.close()
    if policy == "last":
        assert "going on at the newest selection it decided, k = 2" in chose.message
        assert report.k_per_path == {"there": 2, "back": 2}
    else:
        assert 'waiting for a selection (start_selection = "wait")' in chose.message
        assert report.k_per_path == {"there": 3, "back": 3}


@pytest.mark.lockstep
async def test_with_nothing_on_file_the_sim_waits_then_moves_at_the_first_selection(
    task_file: Path, tmp_path: Path, cell: Cell
) -> None:
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        cycles = aiter(bus.subscribe(bus.key("robot/cycle"), CycleReport))
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        settings = Settings(task=str(task_file), fifo_priority=0, wait_for_signals=False, cycles=1)
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        chose = await next_of(events, lambda e: "the decision maker does not answer" in e.message, timeout=30)
        await ex.listening(bus, "decision/selection")
        put(
            bus,
            bus.key("decision/selection"),
            Selection(t_ns=2, seq=1, k=4, n=15, delta=0, reason="hold"),
            block=True,
        )
        report = await next_of(cycles, timeout=60)
        await asyncio.wait_for(ex.task, 15)
        await store.close()
    assert "waiting for a selection (no selection on file)" in chose.message
    assert report.k_per_path == {"there": 4, "back": 4}


async def test_two_executors_on_one_host_get_different_servo_cores(
    task_file: Path, tmp_path: Path, cell: Cell
) -> None:
    async with cell.session() as bus:
        cores = {}
        execs = []
        for name in ("a", "b"):  # two cells on one host
            other = Cell(name, network=cell.network)
            health = aiter(bus.subscribe(other.key("health/executor"), ServiceStatus, maxsize=1))
            settings = Settings(
                task=str(task_file),
                fifo_priority=0,
                start_selection="wait",
                lock_dir=str(tmp_path),
            )
            execs.append(other.service("executor", executor_main, settings, tmp_path / name))
            st = await next_of(health, lambda s: "servo_core" in s.counters or s.detail != "", timeout=30)
            cores[name] = st.counters.get("servo_core")
        for ex in execs:
            await ex.close()
    assert None not in cores.values(), cores
    assert cores["a"] != cores["b"], cores


# --- the real ur-rtde client against the emulator -------------------------------------------------


async def test_with_a_ur_controller_an_overrun_stop_and_a_bump_hold_until_resumed(
    task_file: Path, tmp_path: Path, cell: Cell, monkeypatch: pytest.MonkeyPatch
) -> None:
    from tests.support.emulator import WATCHDOG_HZ, EmulatorProcess, free_loopback

    on = stall(monkeypatch, UrRtdeBackend)
    emu = EmulatorProcess(free_loopback(), q0_deg=[0.0, -90.0, 90.0, -90.0, -90.0, 0.0])  # the task's start
    try:
        async with cell.session() as bus:
            store = await store_serving(bus, task_file, tmp_path / "store", cell)
            events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
            states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
            settings = Settings(
                task=str(task_file),
                backend="ur_rtde",
                host=emu.host,
                fifo_priority=0,
                realtime="optional",
                servo="thread",
                overrun_limit=RUN,
                wait_for_signals=False,
                start_selection="initial",
                initial_k=1,
                watchdog_hz=WATCHDOG_HZ,
            )
            ex = cell.service("executor", executor_main, settings, tmp_path / "ex")
            await next_of(states, lambda s: s.mode == "moving", timeout=60)
            on["stall"] = True
            overrun = await next_of(events, lambda e: e.kind == "protective_stop", timeout=30)
            on["stall"] = False
            await still_while_stopped(states)
            assert (await resume(bus)).startswith("ready")

            # a bump against the arm: the controller's own protective stop, which its dashboard unlocks
            def bumps() -> int:
                return sum("external force" in line for line in emu.lines)

            for _ in range(3):
                await next_of(states, lambda s: s.mode == "moving", timeout=60)
                before = bumps()
                emu.proc.send_signal(signal.SIGUSR1)
                bumped = await next_of(events, lambda e: e.kind == "protective_stop", timeout=30)
                if "protective stop" in bumped.message:
                    with contextlib.suppress(TimeoutError):  # the emulator's line comes on its own pipe
                        await next_of(states, lambda s, n=before: bumps() > n, timeout=5)
                    if bumps() > before:
                        break
                # a loaded machine's stall tripped the controller's watchdog first, or the late samples'
                # jump its own protective stop: clear it and bump again
                async with asyncio.timeout(30):
                    while not (await resume(bus)).startswith("ready"):
                        await next_of(states, timeout=10)
            held = await still_while_stopped(states, n=25)
            early = await resume(bus)  # within 5 s of the stop: the controller refuses
            async with asyncio.timeout(30):
                while not (said := await resume(bus)).startswith("ready"):
                    await next_of(states, timeout=10)  # a state later (20 ms), ask again
            moving = await next_of(states, lambda s: s.mode == "moving", timeout=60)
            await ex.close()
            await store.close()
    finally:
        emu.stop()
    # the stall stops the robot by its overruns, or first by the controller's watchdog (kicks late too)
    assert "overruns in a row" in overrun.message or "control script stopped" in overrun.message
    assert "protective stop" in bumped.message
    assert "protective stop" in held.reason
    assert early.startswith("stopped")
    assert "Cannot unlock protective stop until 5s" in early
    assert "resumed by the test" in said
    assert moving.state == "moving"
    assert any("external force" in line for line in emu.lines)


@pytest.mark.lockstep
async def test_a_cycle_cut_short_by_a_restart_is_said(task_file: Path, tmp_path: Path, cell: Cell) -> None:
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        settings = sim_settings(task_file, cycles=0)
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        await next_of(states, lambda s: s.mode == "moving" and s.path_id == "there")
        await ex.close()  # SIGTERM mid-motion, as systemd stops it
        ex = cell.service("executor", executor_main, settings, tmp_path / "ex", speed=SPEED)
        said = await next_of(events, lambda e: "cut short by a restart" in e.message)
        await ex.close()
        await store.close()
    assert said.kind == "info"
    assert said.message.startswith("cycle 0 of the last run")
