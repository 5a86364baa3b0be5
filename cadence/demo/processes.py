"""`cadence demo --processes`: the process cell, the whole closed loop as systemd would run it.

A Zenoh router on loopback (this process), then every service as its own process, configured the way
systemd would configure it (environment variables over built-in defaults) and supervised the way systemd
would supervise it (a service that dies is restarted). The operator twin is the ECG source, in the ECG
gateway's place (no strap), and the executor runs the simulated UR16e; all of them share one data clock
running ``speed`` times faster than the wall clock. This process only watches the bus: the live view,
``summary.json`` and the figures come from what the services publish.
"""

from __future__ import annotations

import asyncio
import os
import socket
import time
from pathlib import Path

from rich.console import Console
from rich.live import Live

from cadence.demo.folder import fresh_start
from cadence.demo.observe import Observed, handler_of, watch
from cadence.demo.options import ORDER, DemoOptions, demo_settings
from cadence.demo.summary import interrupted_before_data_time, summarise
from cadence.demo.supervise import Supervised
from cadence.demo.view import live_view, taking_the_interrupt
from cadence.lab.session import served_sets
from common.runtime.bus import Bus, BusConfig, Request
from common.runtime.clock import Clock
from common.runtime.errors import CadenceError
from common.trajectory.task import load_task
from schemas import (
    CellClock,
    PlanProgress,
    ServiceStatus,
)
from schemas.topology import (
    CELL_CLOCK,
    DEFAULT_CELL,
    HEALTH,
    PLAN_PROGRESS,
)
from services.registry import PLANNER

STARTUP_TIMEOUT_S = 300.0  # wall time for every service to say it is up


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def service_env(name: str, opts: DemoOptions, endpoint: str, data: Path, epoch_ns: int) -> dict[str, str]:
    """What a systemd unit's EnvironmentFile would hold for this service in the demo."""
    env = {
        **os.environ,
        "CADENCE_BUS_CONNECT": f"['{endpoint}']",
        "CADENCE_DATA_DIR": str(data),
        "CADENCE_CADENCE_SPEED": repr(opts.speed),
        "CADENCE_CADENCE_EPOCH_NS": str(epoch_ns),
        "CADENCE_CADENCE_STATUS_PERIOD_S": "1.0",
        "CADENCE_CADENCE_LOG_FORMAT": "text",
    }
    for key, value in demo_settings(opts).get(name, {}).items():
        env[f"CADENCE_{name.upper()}_{key.upper()}"] = value
    return env


async def run_demo(opts: DemoOptions, console: Console) -> dict:
    task = load_task(opts.task)
    opts.out.mkdir(parents=True, exist_ok=True)
    data, logs = opts.out / "data", opts.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    fresh_start(data)
    endpoint = opts.listen or f"tcp/127.0.0.1:{free_port()}"
    stopping = asyncio.Event()
    procs: dict[str, Supervised] = {}
    tasks: list[asyncio.Task] = []
    obs = Observed(epoch_ns=time.time_ns())
    cut_short_s: float | None = None  # data time run, when Ctrl-C ended it early

    def on_restart(name: str, rc: int) -> None:
        obs.on_event(
            "demo", "restart", f"{name} exited with {rc}; restarted", Clock(opts.speed, obs.epoch_ns).now_ns()
        )

    async def stop_all() -> None:
        """The robot first, the store last, each with SIGTERM; their exit codes are kept."""
        stopping.set()
        for name in reversed(list(procs)):
            await procs[name].stop()
        await asyncio.gather(*tasks, return_exceptions=True)

    def start(name: str, epoch_ns: int) -> None:
        p = Supervised(name, service_env(name, opts, endpoint, data, epoch_ns), logs / f"{name}.log")
        procs[name] = p
        tasks.append(asyncio.create_task(p.supervise(stopping, on_restart)))

    async with await Bus.open(BusConfig(mode="router", listen=[endpoint]), DEFAULT_CELL, role="demo") as bus:
        console.print(
            f"the demo cell's router: {endpoint}; join it with --connect {endpoint} "
            f"(`cadence record -o run.mcap --connect {endpoint}`, `cadence session --connect {endpoint} …`)"
        )
        try:
            # 1. the store first: it plans what it lacks, before the operator's clock starts
            health = aiter(bus.subscribe(HEALTH.at(PLANNER.name), maxsize=1))
            with console.status("planning the task's Pareto sets (once; they are stored) …") as status:

                def on_progress(pr: PlanProgress) -> None:
                    status.update(
                        f"Pareto sets: {pr.done_paths}/{pr.total_paths} ready ('{pr.path_id}' {pr.state})"
                    )

                bus.handle(PLAN_PROGRESS, handler_of(on_progress))
                start(PLANNER.name, obs.epoch_ns)
                async with asyncio.timeout(600):
                    while (await anext(health))[1].state != "serving":
                        pass
            # 2. the clock starts; everyone else joins
            epoch_ns = obs.epoch_ns = time.time_ns()
            clock = Clock(opts.speed, epoch_ns)

            async def tell_clock(_: Request) -> CellClock:  # a tool joining the cell stamps on its time
                return CellClock(t_ns=clock.now_ns(), seq=0, epoch_ns=epoch_ns, speed=opts.speed)

            bus.serve(CELL_CLOCK, tell_clock)
            watch(bus, obs)
            running: set[str] = set()
            all_up = asyncio.Event()

            def on_status(st: ServiceStatus) -> None:
                running.add(st.service)
                if running >= set(ORDER):
                    all_up.set()

            bus.handle(HEALTH, handler_of(on_status))
            for name in (n for n in ORDER if n != PLANNER.name):
                start(name, epoch_ns)
            # the run's duration counts from when every service is up: on a slow or loaded machine their start
            # (imports, sessions) can take longer than a short run, which would then end before it began
            with console.status("starting the services …"):
                try:
                    async with asyncio.timeout(STARTUP_TIMEOUT_S):
                        await all_up.wait()
                except TimeoutError:
                    await stop_all()
                    missing = ", ".join(sorted(set(ORDER) - running))
                    raise CadenceError(
                        f"{missing} did not start within {STARTUP_TIMEOUT_S:.0f} s; their logs are in {logs}"
                    ) from None
        except asyncio.CancelledError:  # Ctrl-C while planning or starting: no data time ran
            taking_the_interrupt(console)
            await stop_all()
            raise interrupted_before_data_time(opts) from None
        kills = sorted(opts.kill, key=lambda k: k[1])
        began_ns = clock.now_ns()
        end_ns = began_ns + round(opts.duration_s * 1e9)
        live = Live(console=console, refresh_per_second=4, transient=False) if opts.live else None
        try:
            if live is not None:
                live.start()
            while (now := clock.now_ns()) < end_ns:
                now_s = (now - epoch_ns) / 1e9
                while kills and kills[0][1] <= now_s:
                    name, _ = kills.pop(0)
                    obs.on_event("demo", "kill", f"SIGKILL {name}", now)
                    procs[name].kill()
                if live is not None:
                    live.update(live_view(obs, opts, now_s, procs))
                await asyncio.sleep(0.1)
        except asyncio.CancelledError:  # Ctrl-C: what ran is still summarised and reported, as cut short
            taking_the_interrupt(console)
            cut_short_s = (clock.now_ns() - began_ns) / 1e9
            console.print(f"interrupted after {cut_short_s:.0f} s of data time: stopping, then the summary")
        finally:
            if live is not None:
                live.stop()
        # 3. the sets the executor used, for the figures, while the store still answers
        sets = await served_sets(bus, task.paths, timeout=5.0)
        # 4. stop; exit codes are checked
        await stop_all()

    ran_s = cut_short_s if cut_short_s is not None else opts.duration_s
    restarts = {n: p.restarts for n, p in procs.items()}
    exit_codes = {n: p.exit_code for n, p in procs.items()}
    return summarise(obs, opts, ran_s, cut_short_s is not None, restarts, exit_codes, sets, console)
