"""The bus in memory, for a node's logic tested without Zenoh (dora's ``MockNode``).

A ``MockBus`` is a ``Bus`` whose transport is a list: every typed port, every graph check of a role's
ports, every decode (the schema's bounds), every drop counter and every rejection is the real ``Bus``'s
code. Only delivery differs: a put reaches the matching subscribers of every ``MockBus`` of the same
``MockNetwork`` (key expressions matched as Zenoh matches them), and a query the matching queryables.
The Zenoh tier of the tests stays for the bus itself and for end to end.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from common.runtime.bus import Bus, BusConfig, M, Request, answer
from schemas.topology import DEFAULT_CELL


@dataclass
class _Entry:
    key_expr: str
    callback: Any  # (key, payload) for a subscriber; (answers type, handler) for a queryable
    network: MockNetwork
    kind: str

    def undeclare(self) -> None:
        entries = self.network.subscribers if self.kind == "sub" else self.network.queryables
        if self in entries:
            entries.remove(self)


@dataclass
class MockNetwork:
    """What the MockBuses of one test share: who subscribes and who answers, and every put, in order."""

    subscribers: list[_Entry] = field(default_factory=list)
    queryables: list[_Entry] = field(default_factory=list)
    sent: list[tuple[str, bytes]] = field(default_factory=list)
    changed: asyncio.Event = field(default_factory=asyncio.Event)  # set at each declaration and put

    async def until(self, condition: Callable[[], bool], timeout: float) -> None:
        """Until ``condition()`` holds, re-checked at each declaration and put; TimeoutError after."""
        async with asyncio.timeout(timeout):
            while not condition():
                self.changed.clear()
                await self.changed.wait()


def _intersects(a: str, b: str) -> bool:
    return bool(zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b)))


class MockBus(Bus):
    def __init__(
        self, cell: str = DEFAULT_CELL, role: str | None = None, network: MockNetwork | None = None
    ) -> None:
        super().__init__(None, asyncio.get_running_loop(), cell, role, BusConfig())  # type: ignore[arg-type]
        self.network = network or MockNetwork()

    def _declare_subscriber(self, key_expr: str, callback: Callable[[str, bytes], None]) -> Any:
        entry = _Entry(key_expr, callback, self.network, "sub")
        self.network.subscribers.append(entry)
        self.network.changed.set()
        return entry

    def _send(self, key: str, payload: bytes, block: bool) -> None:
        self.network.sent.append((key, payload))
        self.network.changed.set()
        for entry in list(self.network.subscribers):
            if _intersects(entry.key_expr, key):
                self.loop.call_soon(entry.callback, key, payload)  # as from Zenoh's thread: later, in order

    def _declare_queryable(
        self, key_expr: str, answers: type[M] | None, handler: Callable[[Request], Awaitable[M]]
    ) -> Any:
        entry = _Entry(key_expr, (answers, handler), self.network, "query")
        self.network.queryables.append(entry)
        self.network.changed.set()
        return entry

    async def _query(self, selector: str, timeout: float) -> list[tuple[str, bool, bytes]]:
        key_expr, _, parameters = selector.partition("?")
        out = []
        for entry in list(self.network.queryables):
            if _intersects(entry.key_expr, key_expr):
                answers, handler = entry.callback  # replied on the query's key, as a Zenoh queryable does
                ok, payload = await asyncio.wait_for(
                    answer(answers, handler, Request(key_expr, parameters)), timeout
                )
                out.append((key_expr if ok else selector, ok, payload))
        return out

    def matching(self, key: str) -> bool:
        return any(_intersects(e.key_expr, key) for e in self.network.subscribers)

    async def until_subscribed(self, key: str, timeout: float) -> None:
        await self.network.until(lambda: self.matching(key), timeout)

    def token(self, key: str) -> None:
        self._check_open()

    def isolation(self) -> str | None:
        return None

    async def _close_transport(self) -> None:
        pass
