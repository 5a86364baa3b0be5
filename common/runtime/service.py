"""What every service shares (DESIGN §9, §10; uvicorn's server.py for the shutdown).

- Configuration (common/runtime/config.py): an unknown or mistyped key stops the service at start with
  one line naming the file (or variable) and the key, exit code 2.
- Logging: human-readable on a terminal, JSON lines under systemd (``JOURNAL_STREAM`` set).
- SIGTERM/SIGINT set the stop event; the service's main coroutine gets a bounded time to finish its
  step, then is cancelled; the bus undeclares everything and closes; exit 0. A second signal a second or
  more after the first exits at once; one that comes with it (the kernel's parent-death signal beside a
  supervisor's SIGTERM) is the same request.
- Presence and health: a liveliness token on ``health/<service>`` and a periodic ``ServiceStatus``.
- systemd: READY=1 once running, WATCHDOG=1 at half of ``WATCHDOG_USEC`` from the event loop itself,
  so a stalled loop stops pinging.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import signal
import socket
import sys
from collections import Counter
from collections.abc import Callable, Coroutine, Mapping
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import msgspec

from common.runtime.bus import Bus, BusConfig
from common.runtime.clock import monotonic, pause, wall_monotonic
from common.runtime.config import CommonSettings, read_config, section
from common.runtime.errors import BusError, ConfigError, InputError
from common.runtime.lifetime import die_with_supervisor
from schemas.health import ServiceStatus
from schemas.topology import HEALTH

log = logging.getLogger("cadence.service")

DRAIN_S = 5.0
SECOND_SIGNAL_AFTER_S = 1.0  # a signal this soon after the first is the same stop, asked twice
MAX_STATE_CHARS = 4000  # what ServiceStatus.state may hold (schemas.base.Text)


@dataclass
class ServiceContext:
    """What a service's main coroutine gets: the bus, its settings, a stop event and its counters."""

    name: str
    bus: Bus
    common: CommonSettings
    settings: Any
    stop: asyncio.Event
    counters: Counter[str] = field(default_factory=Counter)
    state: str = "starting"
    detail: str = ""  # what an operator should know beyond the state (a damaged file moved aside)
    link: str = ""  # set while the bus reaches no router and no peer (``Bus.isolation``)
    started: float = field(default_factory=wall_monotonic)
    notes: dict[str, str] = field(default_factory=dict)  # each part's own say beside ``detail``, by part

    def said(self) -> str:
        """The status's detail: the link's word, the service's, each part's."""
        return "; ".join(x for x in (self.link, self.detail, *self.notes.values()) if x)

    def note(self, part: str) -> Callable[[str], None]:
        """A part's own say in the status's detail ("" when it has nothing to say): each writes its own,
        and no part's word overwrites another's."""
        self.notes.setdefault(part, "")
        return partial(self.notes.__setitem__, part)

    def status(self, seq: int) -> ServiceStatus:
        counters = {k: v for k, v in self.counters.items() if v >= 0}
        counters.update(self.bus.drop_counters())
        return ServiceStatus(
            t_ns=self.common.clock.now_ns(),  # data time, as every other key: a recording lines it up
            seq=seq,
            service=self.name,
            state=self.state[:MAX_STATE_CHARS],
            uptime_s=wall_monotonic() - self.started,
            counters=counters,
            detail=self.said()[:MAX_STATE_CHARS],
        )


# --- systemd --------------------------------------------------------------------------------------


def sd_notify(message: str, env: Mapping[str, str] | None = None) -> bool:
    """Send one datagram to systemd's notification socket; False when not under systemd."""
    env = os.environ if env is None else env
    addr = env.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):
        addr = "\0" + addr[1:]  # abstract namespace
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.connect(addr)
        s.sendall(message.encode())
    return True


def watchdog_period_s(env: Mapping[str, str] | None = None) -> float | None:
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid and int(pid) != os.getpid():
        return None
    return int(usec) / 2e6


# --- logging --------------------------------------------------------------------------------------


class _JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {
            "t": record.created,
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


def setup_logging(fmt: str) -> None:
    use_json = fmt == "json" or (fmt == "auto" and "JOURNAL_STREAM" in os.environ and not sys.stderr.isatty())
    handler = logging.StreamHandler()
    handler.setFormatter(
        _JsonFormatter()
        if use_json
        else logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s")
    )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(os.environ.get("CADENCE_LOG_LEVEL", "INFO"))


# --- running a service ----------------------------------------------------------------------------


ISOLATED_SAY_S = 3.0  # a session needs a moment to find its router; after this, alone is said


async def _periodic(ctx: ServiceContext) -> None:
    health = ctx.bus.publisher(HEALTH.at(ctx.name))
    wd = watchdog_period_s()
    next_status = 0.0
    alone_since: float | None = None
    while True:
        now = monotonic()  # the loop's clock: a lockstep cell's statuses come on its data time
        problem = ctx.bus.isolation()
        if problem is None:
            if ctx.link:
                log.info("the bus reaches a router or a peer again")
            alone_since, ctx.link = None, ""
        else:
            alone_since = alone_since if alone_since is not None else now
            if now - alone_since >= ISOLATED_SAY_S and not ctx.link:
                log.warning("%s: nothing this service publishes reaches anyone", problem)
                ctx.link = problem
        if now >= next_status:
            health.put(ctx.status(health.next_seq()))
            next_status = now + ctx.common.status_period_s
        if wd is not None:
            sd_notify("WATCHDOG=1")
        await pause(min(ctx.common.status_period_s, wd or ctx.common.status_period_s, 1.0))


def on_stop_signals(loop: asyncio.AbstractEventLoop, callback: Callable[[], None]) -> None:
    """Call ``callback`` in the loop on SIGTERM, SIGINT and SIGHUP (a closed terminal, or systemd's
    ``kill -HUP``: a service that reloads nothing stops cleanly rather than dying of it).

    Not ``loop.add_signal_handler``: asyncio learns of such a signal from a byte in its self-pipe, the
    pipe that ``call_soon_threadsafe`` also writes to, and a burst of Zenoh samples can fill it just when
    the signal comes; the byte is then dropped and the signal lost (a recorder under load ignored its
    SIGTERM that way). A Python-level handler always runs, and hands the callback to the loop.
    """
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, lambda *_: loop.call_soon_threadsafe(callback))


async def serve(
    name: str,
    main: Callable[[ServiceContext], Coroutine[Any, Any, None]],
    common: CommonSettings,
    bus_cfg: BusConfig,
    settings: Any,
    stop: asyncio.Event | None = None,
    install_signals: bool = True,
    bus: Bus | None = None,
) -> None:
    """Run ``main`` until it returns or the stop event is set, then shut down in order. ``bus``: one
    opened already (on a ``MemoryNetwork``: the lockstep cell, a test) instead of Zenoh's from ``bus_cfg``."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    if install_signals:
        first_at: float | None = None

        def on_signal() -> None:
            """One stop, however it is asked for: a second signal forces the exit only when it comes a
            while after the first. The kernel's parent-death signal and a supervisor's SIGTERM, or a
            terminal's SIGINT and a SIGTERM, arrive together, and once cut the executor's decelerating
            stop 40 ms after it began."""
            nonlocal first_at
            now = wall_monotonic()
            if first_at is not None:
                if now - first_at >= SECOND_SIGNAL_AFTER_S:
                    log.warning("second signal: exiting now")
                    os._exit(1)
                return
            first_at = now
            log.info("stopping %s", name)
            stop.set()

        on_stop_signals(loop, on_signal)
    async with bus if bus is not None else await Bus.open(bus_cfg, common.cell, role=name) as bus:
        ctx = ServiceContext(name, bus, common, settings, stop)
        bus.token(bus.key(HEALTH.at(name).suffix))
        ctx.state = "running"  # before main starts, so that main's own word on its state stands
        speed = f", {common.speed:g}x" if common.speed != 1.0 else ""
        log.info("%s running: cell %s, data %s%s", name, common.cell, common.data_path, speed)
        periodic = asyncio.create_task(_periodic(ctx))
        work = asyncio.create_task(main(ctx))
        sd_notify("READY=1")
        stopper = asyncio.create_task(stop.wait())
        await asyncio.wait({work, stopper}, return_when=asyncio.FIRST_COMPLETED)
        ctx.state = "stopping"
        stop.set()
        sd_notify("STOPPING=1")
        try:
            await asyncio.wait_for(asyncio.shield(work), DRAIN_S)
        except TimeoutError:
            log.warning("%s did not finish within %.0f s; cancelling", name, DRAIN_S)
            work.cancel()
        for task in (periodic, stopper, work):
            task.cancel()
        results = await asyncio.gather(periodic, stopper, work, return_exceptions=True)
        if isinstance(results[2], BaseException) and not isinstance(results[2], asyncio.CancelledError):
            raise results[2]


def service_main(
    name: str,
    settings_type: type[Any],
    main: Callable[[ServiceContext], Coroutine[Any, Any, None]],
    argv: list[str] | None = None,
    prepare: Callable[[Any, CommonSettings], None] | None = None,
) -> int:
    """``python -m services.<name>`` and ``cadence run <name>``: parse, configure, serve; exit code."""
    parser = argparse.ArgumentParser(prog=f"cadence run {name}", description=f"Run the {name} service.")
    parser.add_argument(
        "--config", metavar="FILE.toml", help="deployment config (default: built-in defaults)"
    )
    parser.add_argument("--data-dir", help="data folder (default ~/.local/share/cadence or CADENCE_DATA_DIR)")
    parser.add_argument("--cell", help="robot cell name (key prefix cadence/<cell>/…)")
    parser.add_argument(
        "--speed", type=float, help="simulation: data time runs this many times faster than the wall clock"
    )
    args = parser.parse_args(argv)
    die_with_supervisor()
    try:
        raw = read_config(args.config)
        source = args.config or "<defaults>"
        common = section(raw, "cadence", CommonSettings, source)
        if args.data_dir or os.environ.get("CADENCE_DATA_DIR"):
            common = msgspec.structs.replace(common, data_dir=args.data_dir or os.environ["CADENCE_DATA_DIR"])
        if args.cell:
            common = msgspec.structs.replace(common, cell=args.cell)
        if args.speed is not None:
            if not 0 < args.speed <= 1000:
                raise ConfigError(f"--speed: must be above 0 and at most 1000, got {args.speed}")
            common = msgspec.structs.replace(common, speed=args.speed)
        # the command line's values are held to the same rules as the file's
        common = section(
            {"cadence": msgspec.structs.asdict(common)}, "cadence", CommonSettings, "(command line)", {}
        )
        bus_cfg = section(raw, "bus", BusConfig, source)
        settings = section(raw, name, settings_type, source)
        setup_logging(common.log_format)
        if prepare is not None:
            prepare(settings, common)  # checks that need no bus (task files, data folder)
        asyncio.run(serve(name, main, common, bus_cfg, settings))
    except InputError as exc:
        print(f"cadence {name}: error: {exc}", file=sys.stderr)
        return 2
    except BusError as exc:
        print(f"cadence {name}: bus error: {exc}", file=sys.stderr)
        return 1
    return 0
