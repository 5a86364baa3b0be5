"""`cadence demo`: the whole cell in one process on a driven clock (common/runtime/lockstep.py).

Every service's own code runs as a node on the in-memory bus of one event loop whose clock is data time:
time moves on only when every node waits for a later instant. The run is a function of its options and
seed: the same windows, selections, cycles and errors on every host, loaded or idle. ``--speed X`` is a
ceiling (data time never runs ahead of X times the wall time), ``--speed max`` none: as fast as the host
allows.

The process cell (``cadence demo --processes``, cadence/demo/processes.py) runs every service as its own
process, at ``--speed`` times the wall clock, the way systemd runs them: a busy host changes what it does
(an arm whose samples come late moves later, a starved twin sees the robot later). It has what this one
does not: processes to kill (``--kill``) and a router to join (``--listen``). Here the services log into
``DIR/logs/cell.log``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live

from cadence.demo.folder import fresh_start
from cadence.demo.observe import Observed, watch
from cadence.demo.options import ORDER, DemoOptions, demo_settings
from cadence.demo.summary import interrupted_before_data_time, summarise
from cadence.demo.view import live_view, taking_the_interrupt
from cadence.lab.session import served_sets
from common.runtime.bus import BusConfig
from common.runtime.config import CommonSettings, section
from common.runtime.errors import CadenceError
from common.runtime.memory import MemoryNetwork
from common.runtime.service import serve
from schemas.health import ServiceStatus
from schemas.topology import DEFAULT_CELL, HEALTH
from services.registry import BY_NAME, PLANNER

TICK_S = 1.0  # data time between two looks at the services and the live view


def settings_of(name: str, opts: DemoOptions) -> Any:
    """The service's settings in the demo, as the wall-clock demo hands them over in its environment."""
    env = {f"CADENCE_{name.upper()}_{k.upper()}": v for k, v in demo_settings(opts).get(name, {}).items()}
    return section({}, name, BY_NAME[name].settings(), "<demo>", env)


async def run_lockstep(opts: DemoOptions, console: Console) -> dict[str, Any]:
    """The demo's run, in lockstep; its summary (written with the report, as the wall-clock demo's)."""
    if opts.kill:
        raise CadenceError("--kill SIGKILLs a service's process: the lockstep cell has none (--processes)")
    data, logs = opts.out / "data", opts.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    fresh_start(data)
    handler = logging.FileHandler(logs / "cell.log", mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s"))
    root, level = logging.getLogger(), logging.getLogger().level
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    try:
        return await _run(opts, console, data)
    finally:
        root.removeHandler(handler)
        root.setLevel(level)
        handler.close()


async def _run(opts: DemoOptions, console: Console, data: Path) -> dict[str, Any]:
    loop = asyncio.get_running_loop()
    epoch_ns = time.time_ns() // 1_000_000_000 * 1_000_000_000  # data time starts now, to the second
    common = CommonSettings(data_dir=str(data), epoch_ns=epoch_ns, lockstep=True, status_period_s=1.0)
    network, stop = MemoryNetwork(), asyncio.Event()
    obs = Observed(epoch_ns=epoch_ns)
    services: dict[str, asyncio.Task[None]] = {}

    def start(name: str) -> None:
        main, settings = BY_NAME[name].module().main, settings_of(name, opts)
        bus = network.bus(DEFAULT_CELL, name)
        served = serve(name, main, common, BusConfig(), settings, stop=stop, install_signals=False, bus=bus)
        services[name] = asyncio.ensure_future(served)

    async with network.bus(DEFAULT_CELL, "demo") as bus:  # no router: nobody joins a lockstep cell
        health = bus.subscribe(HEALTH.at(PLANNER.name), maxsize=1)
        try:
            with console.status("planning the task's Pareto sets (once; they are stored) …"):
                start(PLANNER.name)  # it plans what it lacks before the others start, as in the demo
                while (await health.receive(3600.0))[1].state != "serving":
                    if services[PLANNER.name].done():
                        services[PLANNER.name].result()
        except asyncio.CancelledError:  # Ctrl-C while planning: no data time ran
            taking_the_interrupt(console)
            stop.set()
            await asyncio.gather(*services.values(), return_exceptions=True)
            raise interrupted_before_data_time(opts) from None
        watch(bus, obs)
        running: set[str] = set()

        async def on_status(_: str, st: ServiceStatus) -> None:
            running.add(st.service)

        bus.handle(HEALTH, on_status)
        began = loop.time()
        obs.epoch_ns = epoch_ns + round(began * 1e9)
        for name in ORDER:
            if name != PLANNER.name:
                start(name)
        cut_short_s = await _until_done(opts, console, obs, services, began)
        sets = await served_sets(bus, {p for c in obs.cycles for p in c.k_per_path}, timeout=5.0)
        missing = set(ORDER) - running
        stop.set()
        results = await asyncio.gather(*services.values(), return_exceptions=True)
    exit_codes: dict[str, int | None] = {
        name: 0 if not isinstance(r, BaseException) else 1 for name, r in zip(services, results, strict=True)
    }
    for name, r in zip(services, results, strict=True):
        if isinstance(r, BaseException):
            console.print(f"{name} failed: {r!r}", style="red")
    if missing:
        console.print(f"no status came from {', '.join(sorted(missing))}", style="red")
    ran_s = cut_short_s if cut_short_s is not None else opts.duration_s
    restarts = dict.fromkeys(services, 0)
    return summarise(obs, opts, ran_s, cut_short_s is not None, restarts, exit_codes, sets, console)


async def _until_done(
    opts: DemoOptions, console: Console, obs: Observed, services: dict[str, asyncio.Task[None]], began: float
) -> float | None:
    """Data time passes until the run's duration, with the live view; the data time run when Ctrl-C
    ended it early (None when it did not)."""
    loop = asyncio.get_running_loop()
    live = Live(console=console, refresh_per_second=4, transient=False) if opts.live else None
    shown = -math.inf  # wall time the view was last drawn: at most 4 times a second, however fast the run
    try:
        if live is not None:
            live.start()
        while (now := loop.time() - began) < opts.duration_s - 1e-6:  # to the float's precision
            await asyncio.sleep(min(TICK_S, opts.duration_s - now))
            for name, task in services.items():
                if task.done():  # a service that ends in a lockstep cell is a fault of the run: said now
                    task.result()
                    raise CadenceError(f"{name} ended at {loop.time() - began:.0f} s of data time")
            if live is not None and time.monotonic() - shown >= 0.25:
                shown = time.monotonic()
                live.update(live_view(obs, opts, loop.time() - began, {}))
        return None
    except asyncio.CancelledError:  # Ctrl-C: what ran is still summarised and reported, as cut short
        taking_the_interrupt(console)
        ran_s = loop.time() - began
        console.print(f"interrupted after {ran_s:.0f} s of data time: stopping, then the summary")
        return ran_s
    finally:
        if live is not None:
            live.update(live_view(obs, opts, loop.time() - began, {}))
            live.stop()
