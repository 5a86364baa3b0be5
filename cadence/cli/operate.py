"""A person's inputs to a running cell: `cadence robot resume`, `signal`, `separation` (a sensor's
adapter) and the experimenter's `mark error|undo` (the work: cadence/tools/say.py)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import TypeVar

import msgspec

from cadence.cli._common import Commands, add_bus_flags, arg, err, flags_from, joining, out
from common.runtime.errors import InputError
from schemas.base import Message
from schemas.operator import OperatorError, OperatorSignal
from schemas.topology import OPERATOR_ERROR, OPERATOR_SEPARATION_OF, OPERATOR_SIGNAL, Topic, source_chunk

cli = Commands()
M = TypeVar("M", bound=Message)


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


def _tell_once(
    args: argparse.Namespace, topic: Topic[M], make: Callable[[int], M], role: str = "operator"
) -> int:
    """Publish ``make(t_ns)``, stamped on the cell's clock, once something reads ``topic``. A message the
    schema refuses is an input error before any bus is joined."""
    import asyncio

    from cadence.tools.say import cell_clock, checked, tell
    from common.runtime.bus import Bus

    checked(make(time.time_ns()))

    async def go() -> tuple[str, M]:
        async with await Bus.open(joining(args), args.cell, role=role) as bus:
            msg = checked(make((await cell_clock(bus, min(1.0, args.timeout))).now_ns()))
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


@cli.command(
    "separation",
    help="publish where the nearest person is (operator/separation): a sensor's adapter",
    description="The interface of a cell's safety laser scanner or camera to the executor's speed and "
    "separation monitoring: DISTANCE in metres once, or - to read one measurement per line from stdin, "
    "'DISTANCE_M [AGE_S]' (AGE_S: how old it already is, the sensor's latency), each published at once. "
    "A plain distance is a range from the sensor, which the executor reads on the safe side (the person "
    "may stand anywhere at that range: the arm's extent is taken off); --to-robot says it was measured to "
    "the arm already. With --points each line is the person's nearest point, 'X Y [Z]' in metres in the "
    "sensor's frame (a value once: 'X,Y[,Z]'), placed in the cell by --pose X,Y,YAW, or else by the "
    "executor from the source's pose in its config (an undeclared source's frame is the cell's: its "
    "origin is the robot's base unless the config moves it). A bad line (not decimal numbers, not UTF-8, "
    "over 256 bytes) is reported with its number and skipped. Pipe a driver into it: `scanner-driver | "
    "cadence separation - --source scanner:front`. It publishes on the source's own key, "
    "operator/separation/<source> (scanner:front → scanner_front). On a deployed cell it joins as that "
    "scanner's account, the only one the router lets publish there: --zenoh-config "
    "/etc/cadence/credentials/sensor_scanner_front.json5.",
)
@arg("distance", metavar="DISTANCE|X,Y[,Z]|-", help="metres (a point with --points), or - for stdin lines")
@arg(
    "--source",
    default="cli",
    help="the sensor, e.g. scanner:front (declare it in [executor] separation_sources)",
)
@arg("--points", action="store_true", help="the person's nearest points, 'X Y [Z]' a line (metres)")
@arg("--pose", metavar="X,Y,YAW", help="with --points: the sensor's pose in the cell frame (m, m, degrees)")
@arg("--to-robot", action="store_true", help="plain distances are measured to the arm, not from the sensor")
@flags_from(add_bus_flags, 10.0)
def cmd_separation(args: argparse.Namespace) -> int:
    """A sensor's readings onto the bus. Unheard, the executor holds the arm (stale separation)."""
    import asyncio
    import sys

    from cadence.tools.say import Form, parse_pose, relay_separations, separation_line
    from common.runtime.bus import Bus

    if args.pose and not args.points:
        raise InputError("--pose places points: it goes with --points")
    if args.to_robot and args.points:
        raise InputError("--to-robot says what a plain distance means: points need no such word")
    try:
        pose = parse_pose(args.pose) if args.pose else None
    except ValueError as exc:
        raise InputError(f"--pose: {exc}") from None
    form = Form(args.points, pose, args.to_robot)
    if args.distance != "-":
        value = args.distance.replace(",", " ") if args.points else args.distance
        one = lambda t: separation_line(value, args.source, 0, t, form)  # noqa: E731
        own = OPERATOR_SEPARATION_OF.at(source_chunk(args.source))  # the source's own key (its account's)
        return _tell_once(args, own, one, role="separation_sensor")

    async def relay() -> int:
        async with await Bus.open(joining(args), args.cell, role="separation_sensor") as bus:
            bad = await relay_separations(
                bus, args.source, sys.stdin.buffer, lambda line: err.print(line, markup=False), form
            )
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
