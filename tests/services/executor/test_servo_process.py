"""The servo process (services/executor/servo_process.py, remote.py): alone in its process, it plays what
its executor hands it; its death mid-motion is a fault of that motion, latched until a person's resume,
and a new one starts, stopped, where the arm stood."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from schemas import RobotEvent, RobotState
from services.executor.remote import RemoteBackend, ServoProcess
from services.executor.settings import Settings
from tests.support.executor import TASK, executor_processes, next_of

pytestmark = pytest.mark.asyncio


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    task = tmp_path / "shuttle.toml"
    task.write_text(TASK)
    return Settings(task=str(task), fifo_priority=0, lock_memory=False)


def slow_move(q0: np.ndarray, seconds: float) -> list[np.ndarray]:
    """Joint 0 turning 0.2 rad over ``seconds``, one target per controller step."""
    n = round(seconds * 500)
    return [q0 + np.array([0.2 * i / n, 0, 0, 0, 0, 0]) for i in range(1, n + 1)]


async def test_the_servo_process_runs_alone_and_plays_what_it_is_handed(settings: Settings) -> None:
    proc = ServoProcess(settings, 1.0, None, 0)
    proc.start()
    try:
        arm = RemoteBackend(proc)
        assert proc.info["threads"] == 1  # nothing of the executor's, nor numpy's, beside the loop
        assert proc.info["heavy"] == []  # no Zenoh, no scipy: what a tick needs
        q0 = arm.actual_q()
        targets = slow_move(q0, 0.5)
        result = await asyncio.wrap_future(proc.run(targets, settle_ticks=500))
        assert result.outcome == "done"
        assert result.samples_sent == len(targets)
        assert np.allclose(arm.actual_q(), targets[-1], atol=1e-3)
        assert proc.ticks >= len(targets)
    finally:
        proc.close()


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSEGV], ids=["SIGKILL", "SIGSEGV"])
async def test_a_servo_process_that_dies_mid_motion_is_a_latched_fault_until_a_resume(
    settings: Settings, sig: signal.Signals
) -> None:
    """SIGSEGV as the robot's library segfaulting (its process ends by that signal, as it would there)."""
    deaths: list[str] = []
    proc = ServoProcess(settings, 1.0, None, 0, deaths.append)
    proc.start()
    try:
        arm = RemoteBackend(proc)
        q0 = arm.actual_q()
        motion = asyncio.wrap_future(proc.run(slow_move(q0, 5.0)))
        async with asyncio.timeout(30):
            while proc.index < 250:  # half a second in
                await asyncio.sleep(0.01)
        first = proc.info["pid"]
        os.kill(first, sig)
        result = await asyncio.wait_for(motion, 30)
        assert result.outcome == "fault"
        assert deaths == []  # in motion: the motion's fault is the stop, said once by its caller
        assert f"the servo process died (killed by {sig.name})" in arm.fault()
        assert proc.restarting is not None
        await asyncio.to_thread(proc.restarting.join, 60)
        assert proc.info["pid"] != first
        stood = arm.actual_q()
        assert 0.0 < stood[0] - q0[0] < 0.2  # the new arm stands where the old one stopped, mid-move
        again = await asyncio.wrap_future(proc.run(slow_move(stood, 0.2)))
        assert again.outcome == "fault"  # nothing moves until a person resumes
        assert arm.fault().startswith("the servo process died")
        await asyncio.to_thread(arm.reset_fault)
        assert arm.fault() == ""
        resumed = await asyncio.wrap_future(proc.run(slow_move(stood, 0.2), settle_ticks=500))
        assert resumed.outcome == "done"
        # between motions a death is said at once, through the executor's callback
        os.kill(proc.info["pid"], signal.SIGKILL)
        async with asyncio.timeout(30):
            while not deaths:
                await asyncio.sleep(0.01)
        assert "killed by SIGKILL" in deaths[0]
    finally:
        if proc.restarting is not None:
            await asyncio.to_thread(proc.restarting.join, 60)
        proc.close()


async def test_a_starved_servo_process_past_its_watchdog_shows_no_speed_the_arm_no_longer_has(
    settings: Settings,
) -> None:
    """SIGSTOP of the servo process mid-motion with the controller's watchdog armed (a person watched):
    the speed it last wrote stays in the block, but past the watchdog's period the state is not the arm's
    (``measured`` False: the executor sends no robot/state), and once the process runs again the arm is
    at rest where the watchdog's stop left it, its fault saying so."""
    watched = msgspec.structs.replace(settings, separation=True)
    proc = ServoProcess(watched, 1.0, None, 0)
    proc.start()
    stopped = False
    try:
        assert proc.info["watchdog_s"] == pytest.approx(1.0 / watched.watchdog_hz)
        arm = RemoteBackend(proc)
        motion = asyncio.wrap_future(proc.run(slow_move(arm.actual_q(), 5.0)))
        async with asyncio.timeout(30):
            while proc.index < 250:  # half a second in
                await asyncio.sleep(0.01)
        assert arm.measured()
        os.kill(proc.info["pid"], signal.SIGSTOP)
        stopped, at = True, time.monotonic()
        async with asyncio.timeout(30):
            while arm.measured():
                await asyncio.sleep(0.005)
        assert time.monotonic() - at >= proc.info["watchdog_s"] - 0.01  # not before the watchdog's period
        assert np.abs(arm.actual_qd()).max() > 0.01  # what the block still says: the speed before the stall
        os.kill(proc.info["pid"], signal.SIGCONT)
        stopped = False
        result = await asyncio.wait_for(motion, 30)
        assert result.outcome == "fault"
        assert "watchdog" in arm.fault()
        assert arm.measured() and np.abs(arm.actual_qd()).max() == 0.0
    finally:
        if stopped:
            os.kill(proc.info["pid"], signal.SIGCONT)
        proc.close()


def children(pid: int) -> set[int]:
    """The processes ``pid`` started, from any of its threads (a restarted servo comes from another)."""
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(FileNotFoundError):
            out |= {int(c) for c in (task / "children").read_text().split()}
    return out


async def test_the_executors_servo_process_segfaulting_mid_path_is_a_stop_until_a_person_resumes(
    tmp_path: Path, example_sets: Path
) -> None:
    """The executor and the store as processes on the wall clock: the servo process ends by SIGSEGV (as a
    segfault in the robot's library ends it) while the arm runs a path; the executor latches a protective
    stop saying so, the arm stays at rest, and only a person's resume moves it again, on a new one."""
    async with executor_processes(tmp_path, example_sets, {}) as cell:
        bus = cell.bus
        states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        moving = await next_of(states, lambda s: s.state == "moving" and max(map(abs, s.qd)) > 0.05, 120)
        (servo,) = children(cell.executor.pid)
        os.kill(servo, signal.SIGSEGV)
        stop = await next_of(events, lambda e: e.kind == "protective_stop", 30)
        held = await next_of(states, lambda s: s.state == "stopped" and max(map(abs, s.qd)) == 0.0, 30)
        for _ in range(50):  # a second of states: stopped, at rest
            s = await next_of(states, timeout=10)
            assert s.state == "stopped" and max(map(abs, s.qd)) == 0.0, s
            assert np.allclose(s.q, held.q, atol=1e-6), (s.q, held.q)  # where it stopped, restarted or not
        (reply,) = await bus.get(f"{bus.key('robot/resume')}?by=the test", RobotEvent, timeout=60)
        again = await next_of(states, lambda s: s.state == "moving" and max(map(abs, s.qd)) > 0.0, 60)
        (new,) = children(cell.executor.pid)
    assert moving.path_id is not None
    assert "the servo process died (killed by SIGSEGV)" in stop.message
    assert "servo process died" in held.reason
    assert reply.message is not None and reply.message.message.startswith("ready"), reply
    assert again.t_ns > reply.message.t_ns
    assert new != servo
