"""`cadence bench executor --load`: the executor as it runs in a cell (a process behind a Zenoh router, its
servo in a process of its own, the sim arm), kept busy, beside ``cyclictest`` on the servo's core.

The load is the one that starved the servo when it was a thread of the executor (issue 73): about 5,000
messages every 50 ms that the executor must decode on arrival, on a key that does not hold the arm
(signal_flood.py); two busy loops; and an honest sensor at 20 Hz on its own key, a person walking between
1.5 and 6 m of the arm at 1.6 m/s, so that the scale ramps all the time and each reading's adoption (its
arrival at the separation guard → the first servo sample that plays its scale, by the executor's ramp or the
servo's own) is measured, with the executor's own looks beside it.
``cyclictest`` (rt-tests) runs on the same core at the same priority in the same window: what this host
gives any real-time thread there, the yardstick the servo is judged against.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.runtime.bus import Bus, BusConfig
from common.runtime.resources import EXAMPLE_TASK
from common.trajectory.shipped import shipped_or_planned
from common.trajectory.task import load_task
from schemas import Separation, ServiceStatus
from schemas.topology import encode, source_chunk
from services.registry import EXECUTOR

CELL = "bench"
SENSOR = "sensor"
NEAR_M, FAR_M, WALK_M_S, RATE_HZ = 1.5, 6.0, 1.6, 20.0
PERIOD_US = 2000


@dataclass
class LoadBench:
    seconds: float
    servo: dict[str, Any]
    cyclictest: dict[str, Any]
    adoption: dict[str, Any]
    flood: dict[str, Any]
    load: tuple[float, float, float]
    warnings: list[str] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        return {"servo": self.servo, "cyclictest": self.cyclictest, "adoption": self.adoption,
                "flood": self.flood, "load": list(self.load), "seconds": self.seconds}  # fmt: skip


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def distance_at(t: float) -> float:
    """The person walking between NEAR_M and FAR_M at WALK_M_S, t s after the start."""
    span = FAR_M - NEAR_M
    x = (t * WALK_M_S) % (2 * span)
    return FAR_M - (x if x <= span else 2 * span - x)


def cyclictest(core: int, seconds: float, histogram: Path) -> subprocess.Popen[bytes] | str:
    """cyclictest on ``core`` at the servo's priority and period, or why it cannot run."""
    exe = shutil.which("cyclictest")
    if exe is None:
        return "cyclictest is not installed (the rt-tests package: apt install rt-tests)"
    length = f"{max(1, round(seconds))}"
    cmd = [exe, "-q", "-m", "-a", str(core), "-p", "80", "-i", str(PERIOD_US), "-D", length, "-h", "20000",
           f"--histfile={histogram}"]  # fmt: skip
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def read_histogram(text: str) -> dict[str, Any]:
    """cyclictest's histogram (µs, count per line; '# Histogram Overflows' past its range): the figures
    the servo's are set beside. ``late``: wakes a whole period late or more, as an overrun is."""
    lat, counts, overflow = [], [], 0
    for line in text.splitlines():
        if line.startswith("# Histogram Overflows:"):
            overflow = int(line.split(":")[1].split()[0])
        if not line or line.startswith("#"):
            continue
        a, b = line.split()[:2]
        if int(b):
            lat.append(int(a))
            counts.append(int(b))
    n = sum(counts) + overflow
    if n == 0:
        return {"error": "cyclictest recorded no wake"}
    cum = np.cumsum(counts)

    def q(p: float) -> float:
        i = int(np.searchsorted(cum, p * n))
        return float(lat[i]) if i < len(lat) else float("inf")

    late = sum(c for x, c in zip(lat, counts, strict=True) if x >= PERIOD_US) + overflow
    return {"ticks": n, "late": late, "p50_us": q(0.5), "p99_us": q(0.99), "p99_9_us": q(0.999),
            "max_us": float(lat[-1]) if not overflow else float("inf")}  # fmt: skip


def executor_env(endpoint: str, data: Path) -> dict[str, str]:
    source = f'[{{ name = "{SENSOR}", detects = "body", to_robot = true }}]'
    return {**os.environ, "CADENCE_BUS_CONNECT": f"['{endpoint}']", "CADENCE_DATA_DIR": str(data),
            "CADENCE_CADENCE_CELL": CELL, "CADENCE_CADENCE_STATUS_PERIOD_S": "1",
            "CADENCE_EXECUTOR_START_SELECTION": "initial", "CADENCE_EXECUTOR_INITIAL_K": "15",
            "CADENCE_EXECUTOR_WAIT_FOR_SIGNALS": "false", "CADENCE_EXECUTOR_SEPARATION": "true",
            "CADENCE_EXECUTOR_SEPARATION_SOURCES": source, "CADENCE_EXECUTOR_RESUME_POLICY": "auto",
            "CADENCE_EXECUTOR_AUTO_RESUME_S": "0.5"}  # fmt: skip


async def run(seconds: float, busy: int = 2) -> LoadBench:
    task = load_task(EXAMPLE_TASK)
    with tempfile.TemporaryDirectory(prefix="cadence-bench-") as tmp:
        data = Path(tmp) / "data"
        cache = data / EXECUTOR.name
        cache.mkdir(parents=True)
        for path in task.paths.values():  # the sets a store would serve, in the executor's cache
            (cache / f"{path.id}.msgpack").write_bytes(encode(shipped_or_planned(path, task)))
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        async with await Bus.open(BusConfig(mode="router", listen=[endpoint]), CELL) as bus:
            health = bus.subscribe(bus.key(f"health/{EXECUTOR.name}"), ServiceStatus, maxsize=1000)
            log = (Path(tmp) / f"{EXECUTOR.name}.log").open("wb")
            run = [sys.executable, "-m", f"services.{EXECUTOR.name}"]
            env = executor_env(endpoint, data)
            executor = subprocess.Popen(
                run, stdout=log, stderr=subprocess.STDOUT, env=env, preexec_fn=EXECUTOR.start_as_unit
            )
            procs: list[subprocess.Popen[bytes]] = [executor]
            try:
                return await measure(bus, health, procs, endpoint, seconds, busy, Path(tmp))
            except BaseException:
                log.flush()
                print((Path(tmp) / f"{EXECUTOR.name}.log").read_text()[-4000:], file=sys.stderr)
                raise
            finally:
                for p in procs:
                    p.terminate()
                for p in procs:
                    try:
                        p.wait(30)
                    except subprocess.TimeoutExpired:
                        p.kill()
                        p.wait()


async def measure(bus: Bus, health: Any, procs: list[subprocess.Popen[bytes]], endpoint: str,
                  seconds: float, busy: int, tmp: Path) -> LoadBench:  # fmt: skip
    key = bus.key(f"operator/separation/{source_chunk(SENSOR)}")
    await bus.until_subscribed(key, 120)
    status = None
    async with asyncio.timeout(120):  # the arm running a path
        while status is None or not status.state.startswith("moving"):
            status = (await health.receive(120))[1]
    warnings = [status.detail] if status.detail else []
    core = int(status.counters.get("servo_core", max(os.sched_getaffinity(0))))
    for _ in range(busy):
        procs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"]))
    flood = subprocess.Popen([sys.executable, "-m", "cadence.bench.signal_flood", endpoint,
                              bus.key("operator/signal"), str(seconds)], stdout=subprocess.PIPE)  # fmt: skip
    procs.append(flood)
    hist = tmp / "cyclictest.hist"
    ct = cyclictest(core, seconds, hist)
    if not isinstance(ct, str):
        procs.append(ct)
    start, sent = time.monotonic(), 0
    while (t := time.monotonic() - start) < seconds:
        sep = Separation(t_ns=time.time_ns(), seq=0, distance_m=distance_at(t), source=SENSOR, to_robot=True)
        bus.put_raw(key, encode(sep))
        sent += 1
        await asyncio.sleep(1 / RATE_HZ)
    load = os.getloadavg()
    out, _ = await asyncio.to_thread(flood.communicate, timeout=60)
    flooded = json.loads(out.decode().strip().splitlines()[-1]) if out.strip() else {"error": "no word"}
    if isinstance(ct, str):
        yardstick: dict[str, Any] = {"error": ct}
    else:
        _, err = await asyncio.to_thread(ct.communicate, timeout=60)
        failed = {"error": f"cyclictest: {err.decode().strip()[-300:] or ct.returncode}"}
        yardstick = read_histogram(hist.read_text()) if ct.returncode == 0 and hist.exists() else failed
    ended = time.monotonic()
    counters: dict[str, Any] = {}
    async with asyncio.timeout(30):  # a status whose timing was taken after the window
        while time.monotonic() - ended < 2.5 or not counters:
            counters = dict((await health.receive(30))[1].counters)
    c, why = counters, f"rejected/operator/separation/{source_chunk(SENSOR)}/"
    servo = {"ticks": c.get("servo_ticks", 0), "overruns": c.get("overruns", 0),
             "longest_overrun_run": c.get("servo_longest_overrun_run", 0), "p50_us": c.get("servo_p50_us"),
             "p99_us": c.get("servo_p99_us"), "p99_9_us": c.get("servo_p99.9_us"),
             "max_us": c.get("servo_max_us")}  # fmt: skip
    # the reaction: each fall of the guard's σ (a reading's arrival there) → the servo step playing it, by
    # the executor's ramp or the servo's own (services/executor/guard_process.py); beside it, the executor's
    # looks alone, from its own arrival (after the flood it decodes first)
    looks = {"n": c.get("adoption_n", 0), "p50_ms": c.get("adoption_p50_ms"),
             "p99_9_ms": c.get("adoption_p99.9_ms"), "max_ms": c.get("adoption_max_ms"),
             "late": c.get("adoption_late", 0)}  # fmt: skip
    adoption = {"n": c.get("guard_n", 0), "p50_ms": c.get("guard_p50_ms"),
                "p99_9_ms": c.get("guard_p99.9_ms"), "max_ms": c.get("guard_max_ms"),
                "cuts": c.get("guard_cuts", 0), "readings": sent,
                "refused": {k.rsplit("/", 1)[1]: v for k, v in c.items() if k.startswith(why)},
                "looks": looks, "lease_lapses": c.get("lease_lapses", 0)}  # fmt: skip
    return LoadBench(seconds, servo, yardstick, adoption, flooded, load, warnings)


def bench_executor_load(seconds: float, busy: int = 2) -> LoadBench:
    return asyncio.run(run(seconds, busy))
