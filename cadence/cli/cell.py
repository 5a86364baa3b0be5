"""Commands on a running cell: `cadence run`, `router`, `record`, `replay`, `get`, `robot resume`, and a
person's inputs: `signal`, `mark error`."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import msgspec

from cadence.cli._common import (
    SERVICES,
    Commands,
    add_bus_flags,
    arg,
    bus_config,
    err,
    flags_from,
    joining,
    out,
    say_when_alone,
    stop_on_signals,
)
from common.runtime.errors import InputError
from schemas.base import Message
from schemas.topology import (
    DEFAULT_CELL,
)
from schemas.topology import key as key_of

if TYPE_CHECKING:
    from rich.console import RenderableType

cli = Commands()


M = TypeVar("M", bound=Message)


@cli.command("run", help="run one service (production: one systemd unit each)")
@arg("service", choices=sorted(SERVICES))
@arg("args", nargs=argparse.REMAINDER, help="the service's options (--config, --data-dir, --cell)")
def cmd_run(args: argparse.Namespace) -> int:
    from common.runtime.lifetime import name_this_thread
    from services.registry import BY_NAME

    name_this_thread(args.service)  # its process's main thread, as `top -H` shows it (the servo's: servo)
    return BY_NAME[args.service].run(args.args)


@cli.command("router", help="run a Zenoh router (no zenohd binary needed)")
@arg(
    "--listen",
    action="append",
    default=None,
    metavar="ENDPOINT",
    help="default: the config file's, else tcp/127.0.0.1:7447 (loopback only)",
)
@arg("--connect", action="append", metavar="ENDPOINT", help="other routers")
@arg("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
def cmd_router(args: argparse.Namespace) -> int:
    import asyncio

    from common.runtime.bus import Bus
    from common.runtime.service import sd_notify, watchdog_period_s

    async def go() -> None:
        stop = stop_on_signals()
        async with await Bus.open(bus_config(args, "router"), DEFAULT_CELL):
            err.print(f"Zenoh router listening on {', '.join(args.listen or ['its config file'])}")
            sd_notify("READY=1")  # under systemd (Type=notify); a no-op elsewhere
            period = watchdog_period_s()
            while not stop.is_set():
                if period is not None:
                    sd_notify("WATCHDOG=1")
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), period or 3600.0)

    asyncio.run(go())
    return 0


@cli.command(
    "record",
    help="record bus traffic into an MCAP file",
    description="Records every message under the key expressions (default cadence/<cell>/**) into "
    "FILE.mcap, one channel per key with the message type's JSON schema. Stops on Ctrl-C, SIGTERM or "
    "after --duration; the file is complete in every case.",
)
@arg("keys", nargs="*", metavar="KEYEXPR", help="key expressions (default cadence/<cell>/**)")
@arg(
    "--plant",
    action="store_true",
    help="what a plant keeps of every cell: windows, calibrations, new selections, cycles, events, errors, "
    "signals, and each service's status once a minute; no raw ECG, accelerometer, beats or RR (health "
    "data), no arm state or separation readings; at the plant's priority (nice 10), below a cell's",
)
@arg("-o", "--output", required=True, metavar="FILE.mcap")
@arg("--force", action="store_true", help="overwrite FILE.mcap if it is there (by default: refused)")
@arg("--duration", type=float, help="stop after this many seconds")
@arg("--json", action="store_true", help="JSON channels (for Foxglove) instead of MessagePack")
@arg("--cell", default=DEFAULT_CELL, help=f"robot cell (default {DEFAULT_CELL})")
@arg("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
@arg("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
def cmd_record(args: argparse.Namespace) -> int:
    import asyncio

    from cadence.tools.recording import PlantThinning, plant_keys, record
    from common.runtime.bus import Bus

    if args.plant and args.keys:
        raise InputError("--plant records its own keys (every cell's derived ones): give no KEYEXPR with it")
    if args.plant:
        from cadence.tools.plant import yield_to_cells

        yield_to_cells()
    taken = f"{args.output}: exists (a recording is evidence): give another -o, or --force to overwrite it"
    if not args.force and Path(args.output).exists():
        raise InputError(taken)  # before the bus: said at once

    async def go() -> int:
        stop = stop_on_signals()
        if args.duration is not None:
            asyncio.get_running_loop().call_later(args.duration, stop.set)
        async with await Bus.open(bus_config(args, "peer"), args.cell, role="monitor") as bus:
            keys = plant_keys() if args.plant else args.keys or [bus.key("**")]
            shown = "every cell's derived keys (--plant)" if args.plant else ", ".join(keys)
            err.print(f"recording {shown} to {args.output} (Ctrl-C to stop)")
            say_when_alone(bus, "record")
            try:
                rec = await record(
                    bus,
                    Path(args.output),
                    keys,
                    stop,
                    json=args.json,
                    on_first=lambda key: err.print(f"first message: {key}", markup=False, highlight=False),
                    keep=PlantThinning() if args.plant else None,
                    replace=args.force,
                )
            except FileExistsError:  # another recording took the name since the check
                raise InputError(taken) from None
            alone = bus.isolation()
        if rec.failed is not None:  # what a flush put in the file is readable; the rest was lost
            err.print(f"{rec.failed}: the recording stopped; {rec.on_disk} messages are in {args.output}",
                      markup=False, highlight=False, soft_wrap=True)  # fmt: skip
            return 1
        err.print(f"{rec.count} messages written to {args.output}")
        if rec.count == 0:
            why = alone or "nothing was published on these keys"
            err.print(f"nothing came: {why}", markup=False, soft_wrap=True)
        return 0

    return asyncio.run(go())


@cli.command(
    "replay",
    help="republish a recording with its original data time",
    description="Republishes the recorded payloads on their keys, paced by the recorded arrival times "
    "divided by --speed. Services work on data time, so they give what they gave live.",
)
@arg("recording", metavar="FILE.mcap")
@arg("--speed", type=float, default=1.0, help="× the recorded pace; 0 as fast as possible")
@arg("--keys", nargs="+", metavar="KEYEXPR", help="replay only these key expressions")
@arg("--wait", type=float, help="seconds to wait after joining the bus before replaying")
@arg("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
@arg("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
def cmd_replay(args: argparse.Namespace) -> int:
    import asyncio

    from cadence.tools.recording import replay
    from common.runtime.bus import Bus

    async def go() -> int:
        async with await Bus.open(bus_config(args, "peer"), DEFAULT_CELL) as bus:
            if args.wait is not None:
                await asyncio.sleep(args.wait)  # let subscribers on other hosts discover this session
            heard: set[str] = set()
            n = await replay(bus, Path(args.recording), args.speed, args.keys, heard)
        if n and not heard:
            err.print(
                f"cadence replay: {n} messages of {args.recording} sent, but no subscriber matched any of "
                "their keys: nothing received them (is the cell running, on this --connect, this cell?)"
            )
            return 1
        err.print(f"{n} messages replayed from {args.recording}")
        return 0

    return asyncio.run(go())


@cli.command("get", help="query a key (e.g. cadence/cell1/pareto/b1_to_b2) and print JSON")
@arg("key", help="key expression or selector")
@arg("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
@arg("--timeout", type=float, default=5.0, help="seconds (default 5)")
@arg(
    "--wait",
    type=float,
    default=0.0,
    metavar="S",
    help="ask again until a reply comes or S seconds have passed (a router or a service still starting)",
)
@arg("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
def cmd_get(args: argparse.Namespace) -> int:
    import asyncio

    from cadence.tools.say import ask

    async def go() -> int:
        replies, alone = await ask(joining(args), args.key, args.timeout, args.wait)
        ok = 0
        for r in replies:
            if r.message is not None:
                ok += 1
                print(msgspec.json.encode(r.message).decode())
            else:
                err.print(f"{r.key}: error: {r.error}", markup=False, highlight=False)
        if not replies:
            why = alone or "nothing that answers it is on this bus (is the cell running? --connect ENDPOINT)"
            err.print(f"no reply for {args.key} within {args.timeout} s: {why}", markup=False, soft_wrap=True)
        return 0 if ok else 1

    return asyncio.run(go())


def add_watch_flags(p: argparse.ArgumentParser) -> None:
    """A live view's options: the bus's, and one view after S seconds for scripts."""
    add_bus_flags(p, 5.0)
    p.add_argument("--once", type=float, metavar="S", help="print one view after S seconds and exit")
    p.add_argument(
        "--status-period", type=float, default=5.0, metavar="S", help="services' status period (default 5)"
    )


@cli.command(
    "plant",
    help="every cell on the mesh in one table: services, robot, k, the operator's window, their ages",
    description="Watches cadence/*/ (statuses, the arm's state, selections and windows; never the raw "
    "ECG): per cell how many services still send their status and any that is not serving, the robot's "
    "safety state and why, the selection in force, the operator's last window, and the age of each. "
    "It runs at the plant's priority (nice 10), below a cell's. Ctrl-C ends it.",
)
@flags_from(add_watch_flags)
def cmd_plant(args: argparse.Namespace) -> int:
    from cadence.tools.plant import Plant, plant_watch, yield_to_cells

    yield_to_cells()
    plant = Plant()
    return watching(args, "plant", plant_watch(), plant.on, plant.view)


@cli.command(
    "top",
    help="the cell's keys (type, publishers, rate, last message) and services (alive, state, drops)",
    description="Watches every key under cadence/<cell>/: per key its message type, its publishers and "
    "readers from the graph, its rate over the last 10 s, the age of its last message, and what did not "
    "decode; per service whether its status still comes, its state, uptime, dropped messages "
    "(decode errors, rejections) and handler errors. Ctrl-C ends it.",
)
@flags_from(add_watch_flags)
def cmd_top(args: argparse.Namespace) -> int:
    """The cell's keys and services, live; with --once S, one table after S seconds (for scripts)."""
    from cadence.tools.top import Top

    top = Top(args.cell)
    return watching(args, "top", [key_of(args.cell, "**")], top.on, top.view)


def watching(
    args: argparse.Namespace,
    command: str,
    keys: list[str],
    on: Callable[[str, bytes], None],
    view: Callable[[float], RenderableType],
) -> int:
    """A live view of what ``keys`` carry, as the monitor account; with --once S, one view after S
    seconds (for scripts)."""
    import asyncio

    from rich.live import Live

    from common.runtime.bus import Bus
    from common.runtime.clock import first_of

    async def go() -> int:
        stop = stop_on_signals()
        async with await Bus.open(joining(args), args.cell, role="monitor") as bus:
            for key in keys:
                bus.subscribe_raw(key, on)
            say_when_alone(bus, command)
            if args.once is not None:
                await first_of(stop.wait(), asyncio.sleep(args.once))
                out.print(view(args.status_period))
                return 0
            with Live(view(args.status_period), console=out, refresh_per_second=2) as live:
                while not stop.is_set():
                    await first_of(stop.wait(), asyncio.sleep(0.5))
                    live.update(view(args.status_period))
        return 0

    return asyncio.run(go())


@cli.command(
    "view",
    help="the cell in Foxglove: every key as a channel, the arm in 3D (WebSocket server)",
    description="Runs the Foxglove SDK's WebSocket server: every key of the graph is a channel (JSON, "
    "with its message type's JSON schema), robot/state also as /robot/joint_states "
    "(foxglove.JointStates) and /tf (foxglove.FrameTransforms of the UR16e's links, from its DH "
    "table). Open ws://HOST:PORT in Foxglove and import the layout deploy/foxglove/cadence.layout.json.",
)
@flags_from(add_bus_flags, 5.0)
@arg("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
@arg("--port", type=int, default=8765, help="port (default 8765; 0: any free one)")
def cmd_view(args: argparse.Namespace) -> int:
    """The cell in Foxglove: a WebSocket server that bridges every key (cadence/tools/view.py)."""
    import asyncio

    import foxglove

    from cadence.tools.view import Bridge
    from common.runtime.bus import Bus
    from common.runtime.resources import FOXGLOVE_LAYOUT

    async def go() -> int:
        stop = stop_on_signals()
        bridge = Bridge(args.cell)
        try:
            server = foxglove.start_server(name=f"cadence {args.cell}", host=args.host, port=args.port,
                                           context=bridge.context)  # fmt: skip
        except Exception as exc:  # the SDK raises its own kinds for a port in use
            raise InputError(f"cannot serve Foxglove on {args.host}:{args.port}: {exc}") from None
        try:
            cfg = joining(args)
            async with await Bus.open(cfg, args.cell, role="monitor") as bus:
                bus.subscribe_raw(bus.key("**"), bridge.on)
                out.print(
                    f"Foxglove: open a connection to ws://{args.host}:{server.port} "
                    f"({len(bridge.channels) + 2} channels so far); layout: {FOXGLOVE_LAYOUT}; Ctrl-C ends",
                    markup=False, soft_wrap=True,
                )  # fmt: skip
                say_when_alone(bus, "view")
                await stop.wait()
        finally:
            server.stop()
        return 0

    return asyncio.run(go())
