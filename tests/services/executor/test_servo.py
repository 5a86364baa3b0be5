"""The servo loop (services/executor/servo.py) on the sim backend: outcomes, pacing, stops, overruns."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import cast

import numpy as np
import pytest

from common.trajectory.task import load_task
from common.trajectory.validate import validated_samples
from services.executor.backends import SimBackend, backend_for
from services.executor.servo import PERIOD_NS, ServoLoop
from services.executor.settings import Settings
from tests.support.paths import EXAMPLE_TASK


@pytest.fixture(scope="module")
def samples() -> np.ndarray:
    task = load_task(EXAMPLE_TASK)
    path = task.paths["b2_to_a2"]
    return validated_samples(np.full(len(path.waypoints) + 1, 0.4), path, task.limits)


class Scripted(SimBackend):
    """The sim arm, with something happening at a given step: a test's hook into the loop."""

    def __init__(self, q0: np.ndarray, at: int, what, **kw) -> None:
        super().__init__(q0, **kw)
        self.at, self.what, self.calls = at, what, 0

    def servo(self, target: object) -> bool:
        self.calls += 1
        if self.calls >= self.at:
            ok = self.what(self)
            if ok is not None:
                return ok
        return super().servo(target)


# Tests not about overruns: this VM stalls for up to 9 ms now and then (more when CI shares it), and a
# stall of five periods is a run of five overruns that would end a motion the test is about.
CALM = 1000


def run(
    backend: SimBackend, q: np.ndarray, speed: float = 1.0, overrun_limit: int = CALM, realtime: bool = True
):
    loop = ServoLoop(
        backend,
        core=None,
        fifo_priority=0,
        lock_memory=False,
        speed=speed,
        overrun_limit=overrun_limit,
        realtime=realtime,
    )
    loop.start()
    try:
        return loop, loop.run(backend.prepare(q), settle_ticks=250).result(timeout=60)
    finally:
        loop.close()


def test_a_motion_is_sent_sample_by_sample_and_the_arm_settles_on_its_end(samples: np.ndarray) -> None:
    sim = SimBackend(samples[0])
    loop, r = run(sim, samples)
    assert r.outcome == "done"
    assert r.samples_sent == len(samples)
    assert len(samples) <= r.ticks <= len(samples) + 250
    assert np.max(np.abs(sim.arm.q - samples[-1])) <= 1e-4
    assert not sim.fault()
    s = loop.summary()
    assert s.ticks == r.ticks
    assert s.period_us == PERIOD_NS // 1000
    assert s.p50_err_us <= s.max_err_us


def test_faster_than_real_time_sends_several_samples_per_tick(samples: np.ndarray) -> None:
    sim = SimBackend(samples[0], speed=10.0)
    _, r = run(sim, samples, speed=10.0)
    assert r.outcome == "done"
    assert r.samples_sent == len(samples)
    assert r.ticks <= len(samples) / 10 + 26
    assert sim.arm.steps >= len(samples)  # the arm still took one 2 ms step per sample


def test_a_stop_request_brakes_to_rest_before_the_end(samples: np.ndarray) -> None:
    loop_ref: list[ServoLoop] = []
    sim = Scripted(samples[0], len(samples) // 2, lambda b: loop_ref[0].request_stop(), speed=20.0)
    loop = ServoLoop(sim, core=None, fifo_priority=0, lock_memory=False, speed=20.0, overrun_limit=CALM)
    loop_ref.append(loop)
    loop.start()
    r = loop.run(sim.prepare(samples), 250).result(timeout=60)
    loop.close()
    assert r.outcome == "stopped"
    assert r.samples_sent < len(samples)
    assert np.all(sim.arm.qd == 0.0)
    assert np.max(np.abs(sim.arm.q - samples[-1])) > 0.01


def test_a_run_of_overruns_stops_the_robot(samples: np.ndarray) -> None:
    def stall(b: SimBackend) -> None:
        time.sleep(0.005)  # 2.5 periods

    sim = Scripted(samples[0], 100, stall)
    _, r = run(sim, samples, overrun_limit=4)
    assert r.outcome == "overruns"
    assert r.overruns >= 4
    assert r.samples_sent < len(samples)
    assert np.all(sim.arm.qd == 0.0)


def test_a_short_stall_of_the_host_is_caught_up_and_never_stops_a_simulated_arm(samples: np.ndarray) -> None:
    def stall(b: SimBackend) -> bool | None:
        if b.calls <= 140:
            time.sleep(0.005)  # 2.5 periods, 41 ticks in a row
        return None

    sim = Scripted(samples[0], 100, stall, watchdog_s=0.1)  # each silence 5 ms: within the watchdog
    _, r = run(sim, samples, overrun_limit=4, realtime=False)
    assert r.outcome == "done"
    assert r.samples_sent == len(samples)
    assert r.overruns >= 41
    assert np.max(np.abs(sim.arm.q - samples[-1])) <= 1e-4
    assert not sim.fault()


class Silent:
    """A clock a test moves: the silence of a starved servo thread, without waiting for one."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_a_silence_past_the_watchdog_stops_the_simulated_arm_where_its_controller_would(
    samples: np.ndarray,
) -> None:
    """A starved executor (its servo thread too) once left the sim arm standing mid-motion with its
    speed, to run on from there after the stall: a stop that began only once the person was in reach."""
    clock = Silent()
    sim = SimBackend(samples[0], watchdog_s=0.1, clock=clock)
    sim.prepare(samples[:1])
    for row in samples[: len(samples) // 2]:  # mid-path, moving
        clock.t += 0.002
        assert sim.servo(row)
    q, qd = sim.actual_q(), sim.actual_qd()
    assert np.max(np.abs(qd)) > 0.1
    clock.t += 0.09  # within the watchdog: the arm is as it was, and the next target is taken
    assert np.array_equal(sim.actual_q(), q) and np.array_equal(sim.actual_qd(), qd)
    clock.t += 0.05  # past it: a read while the servo thread is still starved sees the stop already taken
    seen_q, seen_qd = sim.actual_q(), sim.actual_qd()
    assert np.all(seen_qd == 0.0)
    assert np.all((seen_q - q) * qd >= 0.0)  # the braking way, along the way it moved
    assert np.max(np.abs(seen_q - q)) > 1e-3
    assert not sim.fault() and np.array_equal(sim.arm.q, q)  # nothing taken yet: a read changes nothing
    assert not sim.servo(samples[len(samples) // 2])  # the loop back: the stop is the arm's now
    assert "watchdog" in sim.fault() and "0.140 s" in sim.fault()
    assert np.array_equal(sim.actual_q(), seen_q) and np.all(sim.actual_qd() == 0.0)
    sim.motion_ended()
    sim.reset_fault()  # a person's resume; between motions nothing watches
    clock.t += 10.0
    assert not sim.fault() and np.array_equal(sim.actual_q(), seen_q)
    sim.prepare(samples[:1])
    assert sim.servo(seen_q)  # held where it stands: at rest, a silence stops nothing
    clock.t += 1.0
    assert sim.servo(seen_q) and not sim.fault()
    clock.t += 10.0
    assert not sim.fault() and np.array_equal(sim.actual_q(), seen_q)


def test_in_the_servo_loop_a_silence_past_the_watchdog_ends_the_motion_as_a_fault(
    samples: np.ndarray,
) -> None:
    clock = Silent()

    def starve(b: SimBackend) -> None:
        clock.t += 0.5 if b.calls == 100 else 0.002

    sim = Scripted(samples[0], 1, starve, watchdog_s=0.1, clock=clock)
    _, r = run(sim, samples)
    assert r.outcome == "fault"
    assert r.samples_sent == 100
    assert "watchdog" in sim.fault()
    assert np.all(sim.arm.qd == 0.0)


def test_a_lockstep_arm_a_sped_up_one_and_one_no_person_stands_beside_have_no_watchdog(
    samples: np.ndarray,
) -> None:
    task, settings = load_task(EXAMPLE_TASK), Settings(separation=True)
    assert cast(SimBackend, backend_for(settings, task, 1.0)).watchdog_s == 1.0 / settings.watchdog_hz
    assert cast(SimBackend, backend_for(settings, task, 16.0)).watchdog_s is None  # the process demo's pace
    assert cast(SimBackend, backend_for(Settings(), task, 1.0)).watchdog_s is None  # no person watched
    sim = cast(SimBackend, backend_for(settings, task, math.inf))  # a lockstep cell's
    assert sim.watchdog_s is None
    clock = sim.clock = Silent()
    sim.arm.q[:] = samples[0]  # this test's path, not the task's first
    for row in samples[:50]:
        assert sim.servo(row)
    clock.t += 100.0
    assert sim.servo(samples[50]) and not sim.fault()


def test_a_refusing_arm_ends_the_motion_as_a_fault(samples: np.ndarray) -> None:
    sim = Scripted(samples[0], 50, lambda b: b.arm.protect("light curtain"), speed=20.0)
    _, r = run(sim, samples, speed=20.0)
    assert r.outcome == "fault"
    assert r.samples_sent == 50
    assert sim.fault() == "light curtain"


def test_a_lock_file_it_cannot_open_is_skipped_and_said_not_a_crash(tmp_path: Path) -> None:
    """A root run of `cadence bench executor` leaves root's lock files in /run/cadence, which the
    service's user may not open: its executor died at start with PermissionError. Any lock file it cannot
    open (here a folder in its place, which root cannot open either) is skipped, and the note says which."""
    from services.executor.cores import claim_core

    (tmp_path / "servo-core-1.lock").mkdir()
    claim = claim_core([0, 1], tmp_path)
    try:
        assert claim.core == 0
        assert "servo-core-1.lock: Is a directory" in claim.note
    finally:
        claim.release()
    (tmp_path / "servo-core-0.lock").unlink()
    (tmp_path / "servo-core-0.lock").mkdir()
    none = claim_core([0, 1], tmp_path)
    assert none.core is None
    assert "skipped" in none.note
    assert "unpinned" in none.note


def test_the_servo_thread_carries_its_name_for_the_os(samples: np.ndarray) -> None:
    """`top -H` tells the loops apart: the servo thread is `servo` to the OS, not the interpreter's name."""
    loop = ServoLoop(SimBackend(samples[0]), fifo_priority=0, lock_memory=False)
    loop.start()
    try:
        tid = loop._thread.native_id
        assert Path(f"/proc/self/task/{tid}/comm").read_text().strip() == "servo"
    finally:
        loop.close()


@pytest.mark.parametrize(
    ("changes", "says"),
    [
        ({"fifo_priority": 0}, "fifo_priority = 0: the servo runs at normal priority"),
        ({"lock_memory": False}, "lock_memory = false"),
        ({"every_core_taken": True}, "already serve other executors (pid {pid}"),  # this test's own
    ],
)
def test_with_a_real_robot_a_servo_loop_that_cannot_be_real_time_refuses_to_start_in_one_line(
    tmp_path: Path, changes: dict, says: str
) -> None:
    """No silent downgrade (issue 73): with ur_rtde (or realtime = "required"), an executor whose servo
    loop would run without SCHED_FIFO, locked memory or a core of its own refuses to start, in one line
    saying which and how to grant it; nothing reaches for the robot (its host is no controller here). The
    sim runs on and says so in its status."""
    import os
    import subprocess
    import sys

    from services.executor.cores import claim_core

    held = []
    if changes.pop("every_core_taken", False):  # another executor holds every core this one may use
        held = [claim_core([c], tmp_path) for c in os.sched_getaffinity(0)]
    env = {**os.environ, "CADENCE_EXECUTOR_BACKEND": "ur_rtde", "CADENCE_EXECUTOR_HOST": "127.0.0.9",
           "CADENCE_EXECUTOR_LOCK_DIR": str(tmp_path), "CADENCE_DATA_DIR": str(tmp_path / "data"),
           **{f"CADENCE_EXECUTOR_{k.upper()}": str(v).lower() for k, v in changes.items()}}  # fmt: skip
    try:
        run = [sys.executable, "-m", "services.executor"]
        r = subprocess.run(run, env=env, capture_output=True, text=True, timeout=120)
    finally:
        for claim in held:
            claim.release()
    assert r.returncode == 2, r.stderr
    (said,) = [line for line in r.stderr.splitlines() if "error" in line]  # one line
    assert "the servo loop cannot run in real time with a real robot" in said
    assert says.format(pid=os.getpid()) in said
