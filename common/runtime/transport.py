"""What a ``Bus`` needs of a network, and Zenoh's answer to it (python-can's ``BusABC``, httpx's transports).

The ``Bus`` (common/runtime/bus.py) holds the graph's checks, decoding, counting and the tasks it runs; a
transport only moves bytes by key: it declares subscribers and queryables, puts, queries, says whether
anyone listens, holds liveliness tokens, and closes. It speaks strings and bytes, never messages, so every
check a receiver makes is the bus's, whichever transport carries it. Two implement it: ``ZenohTransport``
here (a service, a tool, the tests of the bus and end to end) and ``MemoryTransport``
(common/runtime/memory.py: the lockstep cell and a node's tests).

Zenoh has no asyncio API. Its callbacks run on Zenoh's own threads and only hand the sample to the event
loop (``call_soon_threadsafe``, tolerant of a closed loop); a query runs in a worker thread with a timeout;
a queryable's answer always drops the query (``with query``), or the querier would wait for its timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

import zenoh

from common.runtime.errors import BusError

# A queryable's answer to (the query's key, its selector's parameters): (True, the encoded message) or
# (False, the error's text), as ``common.runtime.bus.answer`` gives it
Respond = Callable[[str, str], Awaitable[tuple[bool, bytes]]]


class Declared(Protocol):
    """Something declared on a transport: a subscriber, a queryable, a token."""

    def undeclare(self) -> None: ...


class Transport(Protocol):
    """The network under one ``Bus``, used from its event loop's thread."""

    def declare_subscriber(self, key_expr: str, callback: Callable[[str, bytes], None]) -> Declared:
        """``callback(key, payload)`` on the loop's thread for each put matching ``key_expr``, later than
        the put and in its order."""
        ...

    def send(self, key: str, payload: bytes, block: bool) -> None:
        """Put ``payload`` on ``key``; ``block``: wait for room rather than drop under congestion."""
        ...

    def declare_queryable(self, key_expr: str, respond: Respond) -> Declared:
        """Answer each query matching ``key_expr`` with what ``respond`` gives, on the query's key."""
        ...

    async def query(self, selector: str, timeout: float) -> list[tuple[str, bool, bytes]]:
        """(key, ok, payload) per reply; an error reply's key is the selector's."""
        ...

    def matching(self, key: str) -> bool:
        """Whether a subscriber somewhere matches ``key`` now."""
        ...

    async def until_subscribed(self, key: str, timeout: float) -> None:
        """Until a subscriber somewhere matches ``key``; TimeoutError when none appears."""
        ...

    def token(self, key: str) -> Declared:
        """A liveliness token on ``key``: present while declared (DESIGN §11)."""
        ...

    def isolation(self) -> str | None:
        """Why nothing can reach this transport, for a person to act on; None while something can."""
        ...

    async def close(self) -> None:
        """After everything declared has been undeclared; answers still running are cancelled."""
        ...


def zenoh_words(exc: Exception) -> str:
    """Zenoh's message without the Rust source file it was raised in (``… at /root/.cargo/…/x.rs:447.``),
    which says nothing to a user."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc)).strip()


def _call_soon(loop: asyncio.AbstractEventLoop, fn: Callable[..., object], *args: object) -> None:
    """From a Zenoh thread into the loop; a closed loop (shutdown) drops the call (bleak's habit)."""
    with contextlib.suppress(RuntimeError):
        loop.call_soon_threadsafe(fn, *args)


class ZenohTransport:
    """One Zenoh session. ``router``: this session is a router, which others come to; ``connect``: the
    endpoints it was told to reach, for the words of ``isolation``."""

    def __init__(
        self, session: zenoh.Session, loop: asyncio.AbstractEventLoop, router: bool, connect: list[str]
    ) -> None:
        self.session = session
        self.loop = loop
        self.router, self.connect = router, connect
        self._answers: set[asyncio.Task[None]] = set()

    def declare_subscriber(self, key_expr: str, callback: Callable[[str, bytes], None]) -> Declared:
        loop = self.loop
        sub: Declared = self.session.declare_subscriber(
            key_expr, lambda s: _call_soon(loop, callback, str(s.key_expr), s.payload.to_bytes())
        )
        return sub

    def send(self, key: str, payload: bytes, block: bool) -> None:
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self.session.put(key, payload, congestion_control=cc)

    def declare_queryable(self, key_expr: str, respond: Respond) -> Declared:
        def on_query(query: zenoh.Query) -> None:
            _call_soon(self.loop, self._spawn, respond, query)

        queryable: Declared = self.session.declare_queryable(key_expr, on_query)
        return queryable

    def _spawn(self, respond: Respond, query: zenoh.Query) -> None:
        task = asyncio.ensure_future(self._answer(respond, query))
        self._answers.add(task)
        task.add_done_callback(self._answers.discard)

    @staticmethod
    async def _answer(respond: Respond, query: zenoh.Query) -> None:
        with query:  # dropping the query tells the querier that no more replies come
            ok, payload = await respond(str(query.key_expr), str(query.parameters))
            if ok:
                query.reply(query.key_expr, payload)
            else:
                query.reply_err(payload)

    async def query(self, selector: str, timeout: float) -> list[tuple[str, bool, bytes]]:
        def run() -> list[Any]:
            return list(self.session.get(selector, timeout=timeout))

        try:
            replies = await asyncio.to_thread(run)
        except zenoh.ZError as exc:
            raise BusError(f"query {selector} failed: {zenoh_words(exc)}") from exc
        return [
            (str(r.ok.key_expr), True, r.ok.payload.to_bytes())
            if r.ok is not None
            else (selector, False, r.err.payload.to_bytes())
            for r in replies
        ]

    def matching(self, key: str) -> bool:
        pub: Any = self.session.declare_publisher(key)
        try:
            return bool(pub.matching_status.matching)
        finally:
            pub.undeclare()

    async def until_subscribed(self, key: str, timeout: float) -> None:
        pub: Any = self.session.declare_publisher(key)  # zenoh's stubs type matching_status as a bool
        matched = asyncio.Event()
        loop = self.loop
        listener: Any = pub.declare_matching_listener(
            lambda status: _call_soon(loop, matched.set) if status.matching else None
        )
        try:
            if not pub.matching_status.matching:
                await asyncio.wait_for(matched.wait(), timeout)
        finally:
            listener.undeclare()
            pub.undeclare()

    def token(self, key: str) -> Declared:
        token: Declared = self.session.liveliness().declare_token(key)
        return token

    def isolation(self) -> str | None:
        """Zenoh itself says nothing when a client reaches no router."""
        if self.router:
            return None
        info = self.session.info
        if any(True for _ in info.routers_zid()) or any(True for _ in info.peers_zid()):
            return None
        tried = ", ".join(self.connect) or "no endpoint to connect to, and multicast scouting is off"
        return f"connected to no router and no peer (connect: {tried})"

    async def close(self) -> None:
        for task in list(self._answers):
            task.cancel()
        await asyncio.gather(*self._answers, return_exceptions=True)
        await asyncio.to_thread(self.session.close)
