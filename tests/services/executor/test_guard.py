"""The separation guard (services/executor/guard_process.py, guard.py) and the servo's side of it
(servo_process.py ``Server.guarded``): a reading that allows less than the scale in force is in force by
the servo's own hand once the executor let the guard's grace pass, and only then; a silent guard is not
heard; the guard judges real readings from the bus by the executor's own rules."""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path

import numpy as np
import pytest

from common.runtime.bus import Bus, BusConfig
from common.runtime.clock import Clock, wall_monotonic
from common.safety.separation import Figures
from common.trajectory.approach import approach
from common.trajectory.scaling import Curve, Ramp
from common.trajectory.task import load_task
from schemas import Separation
from schemas.topology import encode
from services.executor.channel import Channel
from services.executor.guard import GuardProcess
from services.executor.remote import RemotePlayback, ServoProcess
from services.executor.servo_process import GUARD_GRACE
from services.executor.settings import Settings
from tests.support.executor import TASK, tracked

pytestmark = pytest.mark.asyncio
SOURCE = "scanner_test"


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    task = tmp_path / "shuttle.toml"
    task.write_text(TASK)
    return Settings(task=str(task), fifo_priority=0, lock_memory=False, separation=True,
                    separation_sources=tracked(SOURCE))  # fmt: skip


def long_path(s: Settings) -> Curve:
    """A slow path (about 10 s at σ = 1): the arm is still on it whatever the test waits for."""
    task = load_task(s.task)
    path = next(iter(task.paths.values()))
    own, h = approach(np.array(path.waypoints[0]), np.array(path.waypoints[-1]), 0.1, 10.0, task.limits, "x")
    return Curve.of(h, own)


async def playing(proc: ServoProcess, curve: Curve) -> tuple[RemotePlayback, asyncio.Future[object]]:
    loop = asyncio.get_running_loop()
    pb = proc.playback(curve, Ramp.hold(0.0, 0.0, 1.0), lambda: None, loop.time, None)
    pb.figures = Figures(1.0, 0.3, 0.15)
    pb.stop_s = 0.2
    motion = asyncio.wrap_future(proc.run(pb))
    async with asyncio.timeout(60):
        while proc.live(pb.run_id) is None:
            await asyncio.sleep(0.005)
    return pb, motion


def guard_says(ch: Channel, run: int, sigma: float, since: float, beat: float) -> None:
    g, at = ch.guard, Channel.GUARD_AT
    g.view[at["run"]], g.view[at["sigma"]], g.view[at["since"]], g.view[at["beat"]] = run, sigma, since, beat
    g.write()


def servo_state(ch: Channel, name: str) -> float:
    got = ch.state.read()
    assert got is not None
    return float(got[0][Channel.AT[name]])


async def test_the_servo_takes_the_guards_scale_itself_only_once_the_grace_passed(settings: Settings) -> None:
    proc = ServoProcess(settings, 1.0, None, 0)
    proc.start()
    try:
        pb, motion = await playing(proc, long_path(settings))
        # a silent guard (its beat old) that wants a hold is not heard
        stale = wall_monotonic() - 1.0
        for _ in range(50):
            guard_says(proc.ch, pb.run_id, 0.0, stale, stale)
            await asyncio.sleep(0.004)
        assert servo_state(proc.ch, "cuts") == 0
        assert pb.now.target == 1.0
        # nor one that allows more than the arm runs at, nor one of another run
        for run, sigma in ((pb.run_id, 1.0), (pb.run_id + 1, 0.0)):
            now = wall_monotonic()
            guard_says(proc.ch, run, sigma, now - 1.0, now)
            await asyncio.sleep(0.1)
        assert servo_state(proc.ch, "cuts") == 0
        # it wants 0.3, and nobody offers a ramp: the servo ramps down by itself, once the grace passed
        since = wall_monotonic()
        async with asyncio.timeout(30):
            while pb.now.ramp.target > 0.3 + 1e-9:
                guard_says(proc.ch, pb.run_id, 0.3, since, wall_monotonic())
                await asyncio.sleep(0.004)
        assert pb.now.ramp.target == pytest.approx(0.3)
        assert servo_state(proc.ch, "cuts") == 1
        async with asyncio.timeout(30):  # its adoption, measured from the guard's fall
            while servo_state(proc.ch, "adopted") < 1:
                guard_says(proc.ch, pb.run_id, 0.3, since, wall_monotonic())
                await asyncio.sleep(0.004)
        assert proc.ch.adoptions[0] >= settings.adoption_budget_s * GUARD_GRACE
        proc.request_stop()
        await asyncio.wait_for(motion, 30)
    finally:
        proc.close()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def test_the_guard_reads_the_bus_by_the_executors_rules_and_the_servo_stops_for_a_near_person(
    settings: Settings,
) -> None:
    """Nobody but the guard hears the readings here: a person 0.3 m from the arm holds it, by the guard's
    word and the servo's own ramp; one on another source's key is not taken for theirs."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    async with await Bus.open(BusConfig(mode="router", listen=[endpoint]), "guard") as bus:
        proc = ServoProcess(settings, 1.0, None, 0)
        proc.start()
        guard = GuardProcess.beside(proc.fd, proc.ch, settings, BusConfig(connect=[endpoint]), "guard",
                                    Clock(), 0.05, 0)  # fmt: skip
        assert guard is not None
        guard.start()
        try:
            key = bus.key(f"operator/separation/{SOURCE}")
            await bus.until_subscribed(key, 60)
            pb, motion = await playing(proc, long_path(settings))

            def reading(distance: float) -> bytes:
                return encode(Separation(t_ns=Clock().now_ns(), seq=0, distance_m=distance, source=SOURCE,
                                         to_robot=True))  # fmt: skip

            async with asyncio.timeout(60):  # far: the guard allows full speed, and the servo leaves it be
                while not guard.ch.guard.read() or guard.ch.guard.read()[0][Channel.GUARD_AT["sigma"]] != 1.0:  # type: ignore[index]
                    bus.put_raw(key, reading(8.0))
                    await asyncio.sleep(0.02)
            impostor = bus.key("operator/separation/scanner_other")
            seen: list[float | None] = []  # the guard's nearest room as it judged each round
            put_at = [wall_monotonic()]
            for _ in range(10):
                bus.put_raw(impostor, reading(0.3))  # under SOURCE's name on another key: not SOURCE's
                bus.put_raw(key, reading(8.0))
                put_at.append(wall_monotonic())
                await asyncio.sleep(0.02)
                near = guard.nearest()
                seen.append(None if near is None else near.distance_m)
            assert all(d is None or d > 5.0 for d in seen), seen  # never the impostor's 0.3 m
            # and no cut, unless this loop, starved by a loaded host, let the far reading go stale (a hold)
            stale = max(np.diff(put_at)) >= settings.separation_max_age_s - 0.05
            assert servo_state(proc.ch, "cuts") == 0 or stale, (seen, np.diff(put_at))
            async with asyncio.timeout(60):
                while pb.now.ramp.target > 0.0:
                    bus.put_raw(key, reading(0.3))
                    await asyncio.sleep(0.02)
            assert servo_state(proc.ch, "cuts") == 1
            # the cut's ramp begins at the step after it: adopted then, unless the guard, starved past its
            # silence on a loaded host, was unheard by then (the wait is cleared: guard_unheard says so)
            async with asyncio.timeout(10):
                while guard.figures().get("guard_n", 0) < 1 and guard.figures().get("guard_unheard", 0) < 1:
                    await asyncio.sleep(0.01)
            assert guard.figures()["guard_cuts"] == 1
            proc.request_stop()
            await asyncio.wait_for(motion, 30)
        finally:
            guard.close()
            proc.close()
