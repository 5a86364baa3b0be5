"""The bus in memory: the lockstep cell's transport, and a node's logic tested without Zenoh (dora's
``MockNode``).

A ``MemoryNetwork`` is what the buses of one process share in place of a network: ``network.bus(cell,
role)`` is a real ``Bus`` on a ``MemoryTransport``, so every typed port, every graph check of a role's
ports, every decode (the schema's bounds), every drop counter and every rejection is the ``Bus``'s own
code. Only delivery differs: a put reaches the matching subscribers of every bus of the same network (key
expressions matched as Zenoh matches them), later on the loop and in order, and a query the matching
queryables. The Zenoh tier of the tests stays for the bus itself and for end to end.

``serving(Node, settings)`` serves one node on it beside a test's own session, and ``run_node`` feeds it
inputs and gives back what it published: a node's logic tested with its ports, its decoding and its
graph checks, in milliseconds and with no network. ``MemoryNetwork.settle`` waits until every put has been
delivered and every handler has returned, so a test asserts on what the node did, not on a delay.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections import deque
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import zenoh

from common.runtime.bus import Bus, M
from common.runtime.clock import pause
from common.runtime.config import CommonSettings
from common.runtime.node import Node, serve_node
from common.runtime.service import ServiceContext
from common.runtime.transport import Declared, Respond
from schemas.base import Message
from schemas.topology import DEFAULT_CELL, Topic, decode_any, encode, topic_of


@dataclass
class _Entry:
    key_expr: str
    callback: Any  # (key, payload) for a subscriber; a queryable's ``Respond``
    network: MemoryNetwork
    kind: str

    def undeclare(self) -> None:
        entries = self.network.subscribers if self.kind == "sub" else self.network.queryables
        if self in entries:
            entries.remove(self)


class _Token:
    def undeclare(self) -> None:
        pass


TEST_HISTORY = 100_000  # the puts ``serving`` keeps for a test to read (``NodeRun.outputs``)


@dataclass
class MemoryNetwork:
    """What the buses of one process share: who subscribes and who answers, and, for a test that asks for
    it (``history``: how many), the latest puts in order (``sent``). None by default: the lockstep demo
    runs on this network for hours, and it once kept every message it carried (126 MB per data hour)."""

    history: int = 0
    subscribers: list[_Entry] = field(default_factory=list)
    queryables: list[_Entry] = field(default_factory=list)
    changed: asyncio.Event = field(default_factory=asyncio.Event)  # set at each declaration and put
    in_flight: int = 0  # deliveries scheduled and not yet made
    buses: list[Bus] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.sent: deque[tuple[str, bytes]] = deque(maxlen=self.history)
        self.senders: deque[str | None] = deque(maxlen=self.history)  # the role that sent each of ``sent``

    def bus(self, cell: str = DEFAULT_CELL, role: str | None = None) -> Bus:
        """A bus on this network, for ``role`` (None: a session that speaks for nobody, a test's)."""
        bus = Bus(MemoryTransport(self, asyncio.get_running_loop(), role), cell, role)
        self.buses.append(bus)
        return bus

    def settled(self) -> bool:
        """Nothing on its way: every put delivered, every handler's queue empty, no handler running."""
        return self.in_flight == 0 and all(b.idle() for b in self.buses)

    async def settle(self, timeout: float = 10.0) -> None:
        """Until ``settled`` holds across a few turns of the loop (a handler's reply is delivered a turn
        after it returns); TimeoutError after ``timeout``, with what was still on its way."""
        try:
            async with asyncio.timeout(timeout):
                quiet = 0
                while quiet < 3:
                    await pause(0 if self.settled() else 0.001)  # a handler may wait on a thread
                    quiet = quiet + 1 if self.settled() else 0
        except TimeoutError:
            busy = [b.role or "a test's session" for b in self.buses if not b.idle()]
            raise TimeoutError(
                f"the in-memory bus did not settle in {timeout:g} s: {self.in_flight} deliveries, "
                f"handlers busy or queued on {', '.join(busy) or 'none'}"
            ) from None

    async def until(self, condition: Callable[[], bool], timeout: float) -> None:
        """Until ``condition()`` holds, re-checked at each declaration and put; TimeoutError after."""
        async with asyncio.timeout(timeout):
            while not condition():
                self.changed.clear()
                await self.changed.wait()


def _intersects(a: str, b: str) -> bool:
    return bool(zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b)))


class MemoryTransport:
    """One bus's end of a ``MemoryNetwork``; ``role``: whose puts these are (``MemoryNetwork.senders``)."""

    def __init__(self, network: MemoryNetwork, loop: asyncio.AbstractEventLoop, role: str | None) -> None:
        self.network, self.loop, self.role = network, loop, role

    def declare_subscriber(self, key_expr: str, callback: Callable[[str, bytes], None]) -> Declared:
        entry = _Entry(key_expr, callback, self.network, "sub")
        self.network.subscribers.append(entry)
        self.network.changed.set()
        return entry

    def send(self, key: str, payload: bytes, block: bool) -> None:
        network = self.network
        network.sent.append((key, payload))
        network.senders.append(self.role)
        network.changed.set()

        def deliver(callback: Callable[[str, bytes], None]) -> None:
            network.in_flight -= 1
            callback(key, payload)

        for entry in list(network.subscribers):
            if _intersects(entry.key_expr, key):
                network.in_flight += 1
                self.loop.call_soon(deliver, entry.callback)  # as from Zenoh's thread: later, in order

    def declare_queryable(self, key_expr: str, respond: Respond) -> Declared:
        entry = _Entry(key_expr, respond, self.network, "query")
        self.network.queryables.append(entry)
        self.network.changed.set()
        return entry

    async def query(self, selector: str, timeout: float) -> list[tuple[str, bool, bytes]]:
        key_expr, _, parameters = selector.partition("?")
        out = []
        for entry in list(self.network.queryables):
            if _intersects(entry.key_expr, key_expr):  # replied on the query's key, as a Zenoh queryable does
                ok, payload = await asyncio.wait_for(entry.callback(key_expr, parameters), timeout)
                out.append((key_expr if ok else selector, ok, payload))
        return out

    def matching(self, key: str) -> bool:
        return any(_intersects(e.key_expr, key) for e in self.network.subscribers)

    async def until_subscribed(self, key: str, timeout: float) -> None:
        await self.network.until(lambda: self.matching(key), timeout)

    def token(self, key: str) -> Declared:
        return _Token()

    def isolation(self) -> str | None:
        return None

    async def close(self) -> None:
        pass


@dataclass
class NodeRun:
    """One node served on a ``MemoryNetwork``, and the test's own session on it (``test``: a session that
    speaks for nobody, as a test's on Zenoh does)."""

    node: Node
    network: MemoryNetwork
    test: Bus

    def _sent_by_node(self) -> list[tuple[str, bytes]]:
        return [
            s for s, who in zip(self.network.sent, self.network.senders, strict=True) if who == self.node.role
        ]

    @property
    def outputs(self) -> list[Message]:
        """Everything the node has published on its outputs, in order, decoded as a receiver would (its
        health statuses left out)."""
        return [
            decode_any(p) for k, p in self._sent_by_node() if (t := topic_of(k)) and t.family != "health/*"
        ]

    def published(self, topic: Topic[M]) -> list[M]:
        """What the node published on ``topic``."""
        key = self.test.key(topic.suffix)
        return [cast(M, decode_any(p)) for k, p in self._sent_by_node() if k == key]

    async def put(self, topic: Topic[Any], msg: Message, timeout: float = 10.0) -> None:
        """``msg`` on ``topic`` once the node reads it, then until the node has handled it."""
        key = self.test.key(topic.suffix)
        await self.test.until_subscribed(key, timeout)
        self.test.put_raw(key, encode(msg))
        await self.network.settle(timeout)


@contextlib.asynccontextmanager
async def serving(
    cls: type[Node], settings: Any, data_dir: Path, cell: str = DEFAULT_CELL, **common: Any
) -> AsyncIterator[NodeRun]:
    """``cls`` served as its service serves it (``serve_node``: the declared ports, the timers, the work),
    on the in-memory bus; stopped, its work ended and ``close`` run at the end."""
    network = MemoryNetwork(history=TEST_HISTORY)
    bus = network.bus(cell, cls.role)
    ctx = ServiceContext(cls.role, bus, CommonSettings(cell=cell, data_dir=str(data_dir), **common),
                         settings, asyncio.Event())  # fmt: skip
    node = cls(ctx)
    await node.setup()
    served = asyncio.ensure_future(serve_node(node))
    test = network.bus(cell)
    try:
        yield NodeRun(node, network, test)
        if served.done():
            served.result()  # the node's work failed: say why
    finally:
        ctx.stop.set()
        try:
            await asyncio.wait_for(served, 15)
        finally:
            await node.close()
            await test.close()
            await bus.close()


async def run_node(
    cls: type[Node],
    settings: Any,
    inputs: Iterable[tuple[Topic[Any], Message]],
    data_dir: Path,
    **common: Any,
) -> list[Message]:
    """What ``cls`` publishes when fed ``inputs`` in order, each handled before the next is sent."""
    async with serving(cls, settings, data_dir, **common) as run:
        for topic, msg in inputs:
            await run.put(topic, msg)
        return run.outputs
