"""A person's and a sensor's messages onto the bus, as the operator's commands send them (`cadence
signal`, `mark`, `separation`): one message once something reads its key, checked as a receiver would
check it, and a scanner's lines of distances relayed as they come."""

from __future__ import annotations

import asyncio
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, BinaryIO, TypeVar

import msgspec
import numpy as np

from common.runtime.bus import Bus, BusConfig, Reply
from common.runtime.clock import Clock
from common.runtime.errors import BusError, InputError
from common.safety.geometry import Pose
from schemas.base import Message
from schemas.operator import Separation
from schemas.topology import (
    CELL_CLOCK,
    DEFAULT_CELL,
    OPERATOR_SEPARATION_OF,
    AnyMessage,
    Topic,
    source_chunk,
    validated,
)

M = TypeVar("M", bound=Message)


async def cell_clock(bus: Bus, timeout_s: float = 1.0) -> Clock:
    """The data clock of the cell ``bus`` joined: a simulated cell's (its demo answers ``clock``), else
    the wall clock, which a deployed cell runs on (DESIGN §4)."""
    for r in await bus.get(CELL_CLOCK, timeout=timeout_s):
        if r.message is not None:
            return Clock(r.message.speed, r.message.epoch_ns)
    return Clock()


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


def checked(msg: M) -> M:
    """What a receiver would accept: a message that fails the schema's bounds is an input error here."""
    try:
        return validated(msg)
    except msgspec.ValidationError as exc:
        raise InputError(str(exc)) from exc


NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")  # no 1_0, inf or nan
MAX_LINE = 256  # bytes: a measurement is a few; a longer line is skipped, not read whole into memory


@dataclass(frozen=True, slots=True)
class Form:
    """What a sensor's lines say (`cadence separation`): plain distances (ranges from the sensor, or
    ``to_robot``: measured to the arm), or ``points``, a person's nearest point per line in the sensor's
    frame, placed in the cell frame by ``pose`` when given (else by the executor, from the source's pose
    in its config; an undeclared source's frame is the cell's)."""

    points: bool = False
    pose: Pose | None = None
    to_robot: bool = False


def parse_pose(text: str) -> Pose:
    """``X,Y,YAW`` (metres, metres, degrees) in the cell frame; ValueError says what is wrong."""
    fields = text.split(",")
    if len(fields) != 3 or not all(NUMBER.fullmatch(f.strip()) for f in fields):
        raise ValueError(f"expected X,Y,YAW (metres, metres, degrees), got {text[:40]!r}")
    x, y, yaw = (float(f) for f in fields)
    return Pose(x, y, 0.0, yaw)


def separation_line(line: str, source: str, seq: int, t_ns: int, form: Form = Form()) -> Separation:
    """``DISTANCE [AGE_S]`` (metres, seconds), or with ``form.points`` ``X Y [Z]`` (metres), plain
    decimal numbers, as a message; InputError says what is wrong with it."""
    fields = line.split()
    shape = "X Y [Z]" if form.points else "DISTANCE_M [AGE_S]"
    if not 1 + form.points <= len(fields) <= 2 + form.points:
        raise InputError(f"expected {shape}")
    if bad := [f for f in fields if not NUMBER.fullmatch(f)]:
        raise InputError(f"not a decimal number: {bad[0][:40]!r}")
    values = [float(f) for f in fields]
    if not form.points:
        age = values[1] if len(values) == 2 else 0.0
        return checked(Separation(t_ns=t_ns, seq=seq, distance_m=values[0], source=source, age_s=age,
                                  to_robot=form.to_robot))  # fmt: skip
    point = np.array([values[0], values[1], values[2] if len(values) == 3 else 0.0])
    rng = min(100.0, float(np.linalg.norm(point)))  # the sensor's own range to it
    if form.pose is not None:
        point = form.pose.place(point[None])[0]
    p = (float(point[0]), float(point[1]), float(point[2]))
    return checked(Separation(t_ns=t_ns, seq=seq, distance_m=rng, source=source, points=(p,),
                              placed=form.pose is not None))  # fmt: skip


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


async def relay_separations(
    bus: Bus, source: str, stream: BinaryIO, say: Callable[[str], None], form: Form = Form()
) -> int:
    """Each line of ``stream`` (``DISTANCE_M [AGE_S]``, or ``X Y [Z]`` with ``form.points``) published at
    once, stamped on the cell's clock; a bad line is said with its number and skipped. The number of bad
    lines."""
    bad = 0
    pub = bus.publisher(OPERATOR_SEPARATION_OF.at(source_chunk(source)))  # its own key (its account's)
    clock = await cell_clock(bus)  # a simulated cell's time runs at its own speed
    n = 0
    # the loop stays free meanwhile
    while (raw := await asyncio.to_thread(read_line, stream)) is not None:
        n += 1
        try:
            if len(raw) > MAX_LINE:
                raise InputError(f"over {MAX_LINE} bytes")
            line = raw.decode("utf-8")
            if not line.strip():
                continue
            pub.put(separation_line(line, source, n, clock.now_ns(), form))
        except UnicodeDecodeError as exc:
            bad += 1
            say(f"stdin line {n}: not UTF-8 ({exc.reason} at byte {exc.start}); skipped")
        except InputError as exc:
            bad += 1
            shown = raw[:60].decode("utf-8", "replace").strip()
            say(f"stdin line {n}: {shown!r}: {exc}; skipped")
    return bad


Replies = tuple[list[Reply[Any]], str | None]


async def ask(cfg: BusConfig, key: str, timeout_s: float, wait_s: float) -> Replies:
    """``key``'s replies (`cadence get`), and why nothing could answer if this host is alone. With
    ``wait_s``, a router not up yet is asked again, as is a key nobody answers yet, until that has passed."""
    until = time.monotonic() + wait_s

    async def once() -> Replies:
        async with await Bus.open(cfg, DEFAULT_CELL, role="monitor") as bus:
            while True:
                replies = await bus.get(key, AnyMessage, timeout=timeout_s)
                if any(r.message is not None for r in replies) or time.monotonic() >= until:
                    return replies, bus.isolation()
                await asyncio.sleep(0.5)

    while True:
        try:
            return await once()
        except BusError:
            if time.monotonic() >= until:
                raise
            await asyncio.sleep(0.5)
