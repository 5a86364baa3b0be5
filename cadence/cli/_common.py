"""What the command families share: the consoles, argument types, the planner's flags, the bus options, and
``Commands``, with which each family declares a command beside the function that runs it."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal, TypeVar

from msgspec import structs
from rich.console import Console

from common.runtime.resources import EXAMPLE_TASK
from schemas.topology import DEFAULT_CELL
from services.registry import SERVICES as REGISTRY

out = Console()
err = Console(stderr=True)

if TYPE_CHECKING:  # a command imports them when it runs: `cadence --version` needs none of them
    import asyncio

    from common.runtime.bus import Bus, BusConfig
    from common.trajectory.task import Task

# `cadence run NAME`: the services of the registry (those of the graph, and the UR emulator)
SERVICES = {s.name: s.module_name for s in REGISTRY}


Run = Callable[[argparse.Namespace], int]
R = TypeVar("R", bound=Run)
Setup = Callable[[argparse.ArgumentParser], None]
_ARGS = "_cadence_arguments"


def arg(*flags: str, **options: Any) -> Callable[[R], R]:
    """One argument of the command declared above it (``argparse``'s ``add_argument``)."""
    return flags_from(lambda p: p.add_argument(*flags, **options))


def flags_from(setup: Callable[..., None], *args: Any, **kwargs: Any) -> Callable[[R], R]:
    """Arguments several commands share (``add_bus_flags``, 15.0): ``setup(parser, *args, **kwargs)``."""

    def mark(fn: R) -> R:
        add: Setup = lambda p: setup(p, *args, **kwargs)  # noqa: E731
        setattr(fn, _ARGS, [add, *getattr(fn, _ARGS, [])])  # decorators apply upwards
        return fn

    return mark


@dataclass
class _Declared:
    path: tuple[str, ...]
    options: dict[str, Any]
    arguments: list[Setup] = field(default_factory=list)
    run: Run | None = None
    steps: dict[str, Any] | None = None  # a group's ``add_subparsers`` options


class Commands:
    """A family's commands, each declared where it is implemented: ``@cli.command("robot resume", help=…)``
    above its ``@arg``s and its function; ``cli.group("robot", …)`` for a command made of steps. The
    parsers are built in the order of declaration."""

    def __init__(self) -> None:
        self.declared: list[_Declared] = []

    def command(self, path: str, **options: Any) -> Callable[[R], R]:
        def declare(fn: R) -> R:
            self.declared.append(_Declared(tuple(path.split()), options, getattr(fn, _ARGS, []), fn))
            return fn

        return declare

    def group(self, path: str, steps: dict[str, Any], **options: Any) -> None:
        self.declared.append(_Declared(tuple(path.split()), options, steps=steps))

    def add(self, sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
        parents: dict[tuple[str, ...], argparse._SubParsersAction[argparse.ArgumentParser]] = {(): sub}
        for d in self.declared:
            parser = parents[d.path[:-1]].add_parser(d.path[-1], **d.options)
            for setup in d.arguments:
                setup(parser)
            if d.steps is not None:
                parents[d.path] = parser.add_subparsers(required=True, **d.steps)
            if d.run is not None:
                parser.set_defaults(func=d.run, command_parser=parser)


def positive_int(minimum: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from exc
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return parse


MAX_SPEED = 1000.0  # CommonSettings.speed's bound: every service refuses more


def speed(text: str) -> float:
    """A simulated cell's speed: every service refuses one above MAX_SPEED at its start, which a demo
    took for a crash and restarted for ever: refused here, once, with the range. ``max``: a lockstep
    cell, as fast as the host allows (infinity here)."""
    if text == "max":
        return math.inf
    value = positive_float(text)
    if value > MAX_SPEED:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_SPEED:g} (or max), got {text}")
    return value


def positive_float(text: str) -> float:
    """A number above 0 (a speed, a duration): a negative one would be accepted and then wait in silence."""
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from exc
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def task_with_overrides(args: argparse.Namespace) -> Task:
    from common.trajectory.task import load_task

    task = load_task(args.task)
    overrides = {
        "seed": args.seed,
        "n_solutions": args.n,
        "population": args.pop,
        "generations": args.generations,
        "constraints": args.constraints,
    }
    settings = structs.replace(task.planner, **{k: v for k, v in overrides.items() if v is not None})
    return replace(task, planner=settings)


def add_planner_flags(p: argparse.ArgumentParser, task_option: bool = False) -> None:
    if task_option:
        p.add_argument("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
    p.add_argument("--seed", type=int, help="NSGA-II seed (default: the task's, else 1)")
    p.add_argument("--n", type=positive_int(2), help="number of solutions N (default 15)")
    p.add_argument("--pop", type=positive_int(8), help="NSGA-II population (default 90)")
    p.add_argument(
        "--generations", type=positive_int(1), help="NSGA-II generations (default: tuned, see docs/design.md)"
    )
    p.add_argument(
        "--constraints",
        choices=("exact", "hull"),
        help="limits on the curve itself (exact, default) or on the control points (hull, the paper's)",
    )


def add_bus_flags(p: argparse.ArgumentParser, timeout_s: float) -> None:
    """The options of a command that joins a cell's bus for one exchange."""
    p.add_argument("--cell", default=DEFAULT_CELL, help=f"robot cell (default {DEFAULT_CELL})")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    p.add_argument("--zenoh-config", metavar="FILE.json5", help="Zenoh config file")
    p.add_argument("--timeout", type=float, default=timeout_s, help=f"seconds (default {timeout_s:g})")


def bus_config(args: argparse.Namespace, mode: Literal["peer", "client", "router"]) -> BusConfig:
    """The command's bus: its flags, over the ``CADENCE_BUS_*`` variables every service reads (a
    misspelled one is an error here as it is there, not ignored), over the defaults."""
    from common.runtime.bus import BusConfig
    from common.runtime.config import section

    env = section({}, "bus", BusConfig)
    flags: dict[str, Any] = {}
    if args.zenoh_config:
        flags.update(config_file=args.zenoh_config, mode=None)  # a config file says its own mode
    if args.connect:
        flags["connect"] = args.connect
    if listen := getattr(args, "listen", None):
        flags["listen"] = listen
    cfg = structs.replace(env, **flags)
    if cfg.mode is None and not cfg.config_file:
        cfg = structs.replace(cfg, mode="client" if cfg.connect and mode == "peer" else mode)
    return cfg


def joining(args: argparse.Namespace) -> BusConfig:
    """A command's bus: a peer on this host, or a client of the router ``--connect`` names."""
    return bus_config(args, "peer" if not args.connect else "client")


async def reaching(cfg: BusConfig, cell: str, role: str, timeout_s: float, command: str) -> Bus:
    """The bus, once the router a client connects to answers, within ``timeout_s``: a lab that starts
    the cell and its first session together would otherwise get "unable to connect" before the router
    listens. Said once while it waits; any other error at once."""
    import asyncio
    import time

    from common.runtime.bus import Bus
    from common.runtime.errors import BusError

    give_up, said = time.monotonic() + timeout_s, False
    while True:
        try:
            return await Bus.open(cfg, cell, role=role)
        except BusError as exc:
            if cfg.mode != "client" or "Unable to connect" not in str(exc) or time.monotonic() > give_up:
                raise
            if not said:
                err.print(f"cadence {command}: waiting up to {timeout_s:g} s for the router at "
                          f"{', '.join(cfg.connect)}", markup=False, soft_wrap=True)  # fmt: skip
                said = True
        await asyncio.sleep(1.0)


def say_when_alone(bus: Bus, command: str) -> None:
    """After a session's first moments, say on stderr if it reaches no router and no peer: Zenoh would
    leave the command waiting in silence."""
    import asyncio

    from common.runtime.service import ISOLATED_SAY_S

    def say() -> None:
        if (why := bus.isolation()) is not None:
            err.print(f"cadence {command}: {why}: nothing will come", markup=False, soft_wrap=True)

    asyncio.get_running_loop().call_later(ISOLATED_SAY_S, say)


def stop_on_signals() -> asyncio.Event:
    """An event set by SIGTERM or SIGINT (Ctrl-C), for the commands that run until stopped."""
    import asyncio

    from common.runtime.service import on_stop_signals

    stop = asyncio.Event()
    on_stop_signals(asyncio.get_running_loop(), stop.set)
    return stop
