"""Commands on a running cell: `cadence run`, `router`, `record`, `replay`, `get`, `robot resume`, and a
person's inputs: `signal`, `mark error`."""

from __future__ import annotations

import argparse
import contextlib
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO, TypeVar

import msgspec

from cadence.cli._common import (
    SERVICES,
    Commands,
    add_bus_flags,
    arg,
    bus_config,
    cell_clock,
    err,
    flags_from,
    joining,
    out,
    say_when_alone,
    stop_on_signals,
)
from common.runtime.errors import BusError, InputError
from schemas.base import Message
from schemas.operator import OperatorError, OperatorSignal, Separation
from schemas.topology import (
    DEFAULT_CELL,
    OPERATOR_ERROR,
    OPERATOR_SEPARATION,
    OPERATOR_SIGNAL,
    Topic,
    validated,
)

if TYPE_CHECKING:
    from common.runtime.bus import Bus

cli = Commands()


M = TypeVar("M", bound=Message)


@cli.command("run", help="run one service (production: one systemd unit each)")
@arg("service", choices=sorted(SERVICES))
@arg("args", nargs=argparse.REMAINDER, help="the service's options (--config, --data-dir, --cell)")
def cmd_run(args: argparse.Namespace) -> int:
    from services.registry import BY_NAME

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
@arg("-o", "--output", required=True, metavar="FILE.mcap")
@arg("--duration", type=float, help="stop after this many seconds")
@arg("--json", action="store_true", help="JSON channels (for Foxglove) instead of MessagePack")
@arg("--cell", default=DEFAULT_CELL, help=f"robot cell (default {DEFAULT_CELL})")
@arg("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
@arg("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
def cmd_record(args: argparse.Namespace) -> int:
    import asyncio

    from cadence.tools.recording import record
    from common.runtime.bus import Bus

    async def go() -> int:
        stop = stop_on_signals()
        if args.duration is not None:
            asyncio.get_running_loop().call_later(args.duration, stop.set)
        async with await Bus.open(bus_config(args, "peer"), args.cell, role="monitor") as bus:
            keys = args.keys or [bus.key("**")]
            err.print(f"recording {', '.join(keys)} to {args.output} (Ctrl-C to stop)")
            say_when_alone(bus, "record")
            rec = await record(
                bus,
                Path(args.output),
                keys,
                stop,
                json=args.json,
                on_first=lambda key: err.print(f"first message: {key}", markup=False, highlight=False),
            )
            alone = bus.isolation()
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

    import msgspec

    from common.runtime.bus import Bus
    from schemas.topology import AnyMessage

    until = time.monotonic() + args.wait

    async def ask() -> tuple[list, str | None]:
        async with await Bus.open(joining(args), DEFAULT_CELL, role="monitor") as bus:
            while True:
                replies = await bus.get(args.key, AnyMessage, timeout=args.timeout)
                if any(r.message is not None for r in replies) or time.monotonic() >= until:
                    return replies, bus.isolation()
                await asyncio.sleep(0.5)

    async def go() -> int:
        while True:  # with --wait, a router not up yet is asked again, as is a key nobody answers yet
            try:
                replies, alone = await ask()
                break
            except BusError:
                if time.monotonic() >= until:
                    raise
                await asyncio.sleep(0.5)
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


@cli.command(
    "top",
    help="the cell's keys (type, publishers, rate, last message) and services (alive, state, drops)",
    description="Watches every key under cadence/<cell>/: per key its message type, its publishers and "
    "readers from the graph, its rate over the last 10 s, the age of its last message, and what did not "
    "decode; per service whether its status still comes, its state, uptime, dropped messages "
    "(decode errors, rejections) and handler errors. Ctrl-C ends it.",
)
@flags_from(add_bus_flags, 5.0)
@arg("--once", type=float, metavar="S", help="print one view after S seconds and exit")
@arg("--status-period", type=float, default=5.0, metavar="S", help="services' status period (default 5)")
def cmd_top(args: argparse.Namespace) -> int:
    """The cell's keys and services, live; with --once S, one table after S seconds (for scripts)."""
    import asyncio

    from rich.live import Live

    from cadence.tools.top import Top
    from common.runtime.bus import Bus
    from common.runtime.service import first_of

    top = Top(args.cell)

    async def go() -> int:
        stop = stop_on_signals()
        cfg = joining(args)
        async with await Bus.open(cfg, args.cell, role="monitor") as bus:
            bus.subscribe_raw(bus.key("**"), top.on)
            say_when_alone(bus, "top")
            if args.once is not None:
                await first_of(stop.wait(), asyncio.sleep(args.once))
                out.print(top.view(args.status_period))
                return 0
            with Live(top.view(args.status_period), console=out, refresh_per_second=2) as live:
                while not stop.is_set():
                    await first_of(stop.wait(), asyncio.sleep(0.5))
                    live.update(top.view(args.status_period))
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


cli.group("robot", steps={"dest": "robot_command"}, help="the robot's executor: clear a latched stop")


@cli.command(
    "robot resume",
    help="clear a latched stop (protective stop, overruns, lost controller) once its cause is seen to",
    description="Ask the cell's executor to clear its latched stop. On a real UR16e this also unlocks "
    "the controller's protective stop (its dashboard refuses within 5 s of the stop). Prints the "
    "state it reached; exit 1 when the robot is still stopped after it.",
)
@arg("--by", help="who resumes, for the record (default: your user name)")
@flags_from(add_bus_flags, 15.0)
def cmd_robot_resume(args: argparse.Namespace) -> int:
    """Clear a latched stop: ask the executor of the cell on ``robot/resume`` and print what it did."""
    import asyncio
    import getpass

    from common.runtime.bus import Bus
    from schemas.topology import ROBOT_RESUME

    by = args.by or getpass.getuser()

    async def go() -> int:
        async with await Bus.open(joining(args), args.cell, role="operator") as bus:
            replies = await bus.get(ROBOT_RESUME, timeout=args.timeout, parameters=f"by={by}")
        for r in replies:
            if r.message is not None:
                print(r.message.message)
                return 1 if r.message.message.startswith("stopped") else 0
            err.print(f"cadence robot resume: {r.error}", markup=False, highlight=False)
            return 1
        err.print(
            f"cadence robot resume: no executor answered on cadence/{args.cell}/robot/resume within "
            f"{args.timeout:g} s (is it running, and is this host on its bus? --connect ENDPOINT)",
            markup=False,
        )
        return 1

    return asyncio.run(go())


async def tell(bus: Bus, topic: Topic[M], msg: M, timeout: float) -> str:
    """Put one message of a person's once something reads its key (Zenoh drops a put that nobody
    subscribes to): the key, or a BusError that says nobody listens."""
    out = bus.publisher(topic)
    try:
        await out.until_subscribed(timeout)
    except TimeoutError:
        raise BusError(
            f"nothing on the bus reads {out.key} within {timeout:g} s (is the cell running, and is this "
            "host on its bus? --connect ENDPOINT)"
        ) from None
    out.put(msg)
    return out.key


def _checked(msg: M) -> M:
    """What a receiver would accept: a message that fails the schema's bounds is an input error here."""
    try:
        return validated(msg)
    except msgspec.ValidationError as exc:
        raise InputError(str(exc)) from exc


def _tell_once(
    args: argparse.Namespace, topic: Topic[M], make: Callable[[int], M], role: str = "operator"
) -> int:
    """Publish ``make(t_ns)``, stamped on the cell's clock, once something reads ``topic``. A message the
    schema refuses is an input error before any bus is joined."""
    import asyncio

    from common.runtime.bus import Bus

    _checked(make(time.time_ns()))

    async def go() -> tuple[str, M]:
        async with await Bus.open(joining(args), args.cell, role=role) as bus:
            msg = _checked(make((await cell_clock(bus, min(1.0, args.timeout))).now_ns()))
            return await tell(bus, topic, msg, args.timeout), msg

    key, msg = asyncio.run(go())
    out.print(f"{msgspec.json.encode(msg).decode()} → {key}", markup=False, highlight=False)
    return 0


@cli.command(
    "signal",
    help="say what a task step waits for (a part placed): publish operator/signal NAME",
    description="Publishes NAME on operator/signal, as a push-button would: the executor's wait_for "
    "step of that name goes on. Waits until something reads the key (exit 1 if nothing does).",
)
@arg("name", metavar="NAME", help="the wait_for name in the task program, e.g. part_a2")
@arg("--source", default="cli", help="who says it, for the record (default cli)")
@flags_from(add_bus_flags, 10.0)
def cmd_signal(args: argparse.Namespace) -> int:
    """A part placed (or any step's signal), from a person at a terminal: what a button would send."""
    return _tell_once(
        args, OPERATOR_SIGNAL, lambda t: OperatorSignal(t_ns=t, seq=0, name=args.name, source=args.source)
    )


NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")  # no 1_0, inf or nan
MAX_LINE = 256  # bytes: a measurement is a few; a longer line is skipped, not read whole into memory


def separation_line(line: str, source: str, seq: int, t_ns: int) -> Separation:
    """``DISTANCE [AGE_S]`` (metres, seconds, plain decimal numbers) as a message; InputError says what is
    wrong with it."""
    fields = line.split()
    if not 1 <= len(fields) <= 2:
        raise InputError("expected DISTANCE_M [AGE_S]")
    if bad := [f for f in fields if not NUMBER.fullmatch(f)]:
        raise InputError(f"not a decimal number: {bad[0][:40]!r}")
    values = [float(f) for f in fields]
    age = values[1] if len(values) == 2 else 0.0
    return _checked(Separation(t_ns=t_ns, seq=seq, distance_m=values[0], source=source, age_s=age))


def read_line(stream: BinaryIO) -> bytes | None:
    """One line of at most ``MAX_LINE`` bytes, newline included; None at the end. A longer line is read
    to its end in bounded pieces and returned cut, so that it is reported, not held."""
    line = stream.readline(MAX_LINE + 1)
    if not line:
        return None
    if len(line) > MAX_LINE and not line.endswith(b"\n"):
        while (rest := stream.readline(1 << 16)) and not rest.endswith(b"\n"):
            pass
    return line


@cli.command(
    "separation",
    help="publish the nearest person's distance (operator/separation): a sensor's adapter",
    description="The interface of a cell's safety laser scanner or camera to the executor's speed and "
    "separation monitoring: DISTANCE in metres once, or - to read one measurement per line from stdin, "
    "'DISTANCE_M [AGE_S]' (AGE_S: how old it already is, the sensor's latency), each published at once. "
    "A bad line (not two decimal numbers, not UTF-8, over 256 bytes) is reported with its number and "
    "skipped. Pipe a driver into it: `scanner-driver | cadence separation - --source scanner:front`. On a "
    "deployed cell it joins as the separation_sensor account, the only one the router lets publish "
    "distances: --zenoh-config /etc/cadence/credentials/separation_sensor.json5.",
)
@arg("distance", metavar="DISTANCE|-", help="metres, or - for lines on stdin")
@arg(
    "--source",
    default="cli",
    help="the sensor, e.g. scanner:front (declare it in [executor] separation_sources)",
)
@flags_from(add_bus_flags, 10.0)
def cmd_separation(args: argparse.Namespace) -> int:
    """A sensor's distances onto the bus. Unheard, the executor holds the arm (stale separation)."""
    import asyncio
    import sys

    from common.runtime.bus import Bus

    if args.distance != "-":
        one = lambda t: separation_line(args.distance, args.source, 0, t)  # noqa: E731
        return _tell_once(args, OPERATOR_SEPARATION, one, role="separation_sensor")

    async def relay() -> int:
        bad = 0
        async with await Bus.open(joining(args), args.cell, role="separation_sensor") as bus:
            pub = bus.publisher(OPERATOR_SEPARATION)
            clock = await cell_clock(bus)  # a simulated cell's time runs at its own speed
            n = 0
            # the loop stays free meanwhile
            while (raw := await asyncio.to_thread(read_line, sys.stdin.buffer)) is not None:
                n += 1
                try:
                    if len(raw) > MAX_LINE:
                        raise InputError(f"over {MAX_LINE} bytes")
                    line = raw.decode("utf-8")
                    if not line.strip():
                        continue
                    pub.put(separation_line(line, args.source, n, clock.now_ns()))
                except UnicodeDecodeError as exc:
                    bad += 1
                    err.print(
                        f"stdin line {n}: not UTF-8 ({exc.reason} at byte {exc.start}); skipped", markup=False
                    )
                except InputError as exc:
                    bad += 1
                    shown = raw[:60].decode("utf-8", "replace").strip()
                    err.print(f"stdin line {n}: {shown!r}: {exc}; skipped", markup=False)
        return 1 if bad else 0

    return asyncio.run(relay())


cli.group(
    "mark", steps={"dest": "mark", "metavar": "MARK"}, help="the experimenter's marks on a running session"
)


@cli.command(
    "mark error",
    help="an error of the operator's (for ε): publish operator/error, source experimenter",
    description="Publishes an OperatorError with the kind and note given. Something must read "
    "operator/error (a recording or a session), or the mark would be lost: exit 1 if nothing does.",
)
@arg("--kind", choices=("wrong_object", "late", "other"), default="other")
@arg("--cycle", type=int, help="the robot's cycle it happened in, if known")
@arg("--note", default="", help="what happened")
@flags_from(add_bus_flags, 10.0)
def cmd_mark_error(args: argparse.Namespace) -> int:
    """The experimenter's mark: an error of the operator's, for the error rate ε."""
    return _tell_once(
        args,
        OPERATOR_ERROR,
        lambda t: OperatorError(
            t_ns=t, seq=0, cycle=args.cycle, description=args.note, kind=args.kind, source="experimenter"
        ),
    )


@cli.command(
    "mark undo",
    help="withdraw the experimenter's last mark (keyed by mistake): publish operator/error kind undo",
    description="Publishes an OperatorError of kind undo, source experimenter: the session and the "
    "analysis count the experimenter's last mark before it as withdrawn (an undo counts for nothing "
    "itself). Exit 1 if nothing reads operator/error.",
)
@arg("--note", default="", help="why (kept in the file)")
@flags_from(add_bus_flags, 10.0)
def cmd_mark_undo(args: argparse.Namespace) -> int:
    return _tell_once(
        args,
        OPERATOR_ERROR,
        lambda t: OperatorError(
            t_ns=t,
            seq=0,
            description=args.note or "withdraws the last mark",
            kind="undo",
            source="experimenter",
        ),
    )
