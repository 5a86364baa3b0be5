"""The bus from asyncio: typed ports on the graph, over a transport (DESIGN §3; STYLE "Zenoh 1.x").

A ``Bus`` checks every port against the graph, decodes at arrival, counts and runs handlers in its event
loop; its ``Transport`` (common/runtime/transport.py) only moves bytes by key: Zenoh for a service, a tool
and end to end, memory for the lockstep cell and a node's tests (common/runtime/memory.py). Everything
declared is undeclared before the transport closes. What is dropped is counted and logged at most once
per key and kind every 10 s (docs/operations.md): a payload that does not decode (``decode_errors``), a
message its receiver rejects (``reject``, the rules of ``common/runtime/admission.py``), a handler that
raises (``handler_errors``). None of them stops a service.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections import Counter
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Annotated, Any, Generic, Literal, TypeVar, overload

import msgspec
import zenoh

from common.runtime.clock import wall_monotonic
from common.runtime.errors import BusError
from common.runtime.transport import Declared, Transport, ZenohTransport, zenoh_words
from schemas.base import Message
from schemas.topology import ROLE, Topic, encode, key_for, may_ask, may_publish, may_subscribe, topic_of
from schemas.topology import key as topology_key

M = TypeVar("M", bound=Message)

log = logging.getLogger("cadence.bus")

_LOG_EVERY_S = 10.0
_MAX_COUNTERS = 200  # of each kind in a status: a wildcard subscription may see any number of keys


# Where a session listens unless told: loopback only. A cell's services are clients of its router, and
# the router listens on the network only where its config says (``cadence install`` writes one).
LOOPBACK_LISTEN = {"router": ["tcp/127.0.0.1:7447"], "peer": ["tcp/127.0.0.1:0"], "client": []}


class BusConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """How a service joins the bus. ``config_file`` (JSON5, Zenoh's own format) is read first; the
    other fields override it. Multicast scouting is off unless asked for: cells share networks."""

    mode: Literal["peer", "client", "router"] | None = None  # default: the config file's, else peer
    listen: list[str] = []  # default: the config file's, else loopback only (LOOPBACK_LISTEN)
    connect: list[str] = []
    multicast_scouting: bool = False
    lease_ms: Annotated[int, msgspec.Meta(ge=100, le=600_000)] = 1000
    config_file: str | None = None


def zenoh_config(cfg: BusConfig) -> zenoh.Config:
    try:
        conf = zenoh.Config.from_file(cfg.config_file) if cfg.config_file else zenoh.Config()
        if cfg.mode is not None or not cfg.config_file:
            conf.insert_json5("mode", json.dumps(cfg.mode or "peer"))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
        if cfg.listen:
            conf.insert_json5("listen/endpoints", json.dumps(cfg.listen))
        elif not isinstance(json.loads(conf.get_json("listen/endpoints")), list):
            # Zenoh's own default listens on every interface, with no authentication
            conf.insert_json5("listen/endpoints", json.dumps(LOOPBACK_LISTEN))
        if cfg.connect:
            conf.insert_json5("connect/endpoints", json.dumps(cfg.connect))
        # A killed peer's token vanishes at once; a frozen one only when its lease runs out (DESIGN §11).
        conf.insert_json5("transport/link/tx/lease", json.dumps(cfg.lease_ms))
    except zenoh.ZError as exc:
        raise BusError(f"bad Zenoh configuration {cfg.config_file or ''}: {zenoh_words(exc)}") from exc
    return conf


@dataclass(frozen=True, slots=True)
class Request:
    """A query as the handler sees it: the concrete key and the selector's parameters."""

    key: str
    parameters: str

    @property
    def params(self) -> dict[str, str]:
        """The selector's ``a=1;b=2`` as a mapping (a part without ``=`` is ignored)."""
        return dict(p.split("=", 1) for p in self.parameters.split(";") if "=" in p)


@dataclass(frozen=True, slots=True)
class Reply(Generic[M]):
    key: str
    message: M | None
    error: str | None


class QueryError(Exception):
    """Raised by a queryable handler: its text goes back to the querier with ``reply_err``."""


async def answer(
    answers: type[M] | None, handler: Callable[[Request], Awaitable[M]], req: Request
) -> tuple[bool, bytes]:
    """A queryable handler's reply: (True, the encoded message) or (False, the error's text)."""
    try:
        msg = await handler(req)
        if answers is not None and not isinstance(msg, answers):
            raise TypeError(f"{req.key} answers {answers.__name__}, not {type(msg).__name__}")
        return True, encode(msg)
    except QueryError as exc:
        return False, str(exc).encode()
    except Exception:
        log.exception("query handler failed on %s", req.key)
        return False, b"internal error"


class Subscription(Generic[M]):
    """Decoded messages of one key expression, as an async iterator of (key, message).

    The queue is bounded and drops the oldest sample when full (telemetry); ``maxsize=1`` keeps only the
    latest (a selection is state, not an event: DESIGN §11).
    """

    def __init__(
        self,
        bus: Bus,
        key_expr: str,
        msg_type: type[M],
        maxsize: int,
        arrival: Callable[[str, M], object] | None = None,
        screen: Callable[[str, M], bool] | None = None,
    ) -> None:
        self._bus = bus
        self._decoder = msgspec.msgpack.Decoder(msg_type)
        self._queue: asyncio.Queue[tuple[str, M]] = asyncio.Queue(maxsize)
        self._arrival, self._screen = arrival, screen
        self.dropped = 0
        self._sub: Declared | None = bus.transport.declare_subscriber(key_expr, self._put)

    def _put(self, key: str, payload: bytes) -> None:
        """On the loop thread: decode at arrival, so bad input is counted whether or not anyone reads. With
        ``arrival``, each message is taken there and then, and never queued: what one sender floods
        cannot push another's message out of a queue (the executor's separation readings). ``screen``
        says at arrival whether a message may wait in the queue at all (what is from the future never
        takes an honest message's place)."""
        msg = self._bus.decode(key, payload, self._decoder)
        if msg is None or (self._screen is not None and not self._screen(key, msg)):
            return
        if self._arrival is not None:
            try:
                self._arrival(key, msg)
            except Exception as exc:
                self._bus.handler_failed(key, exc)
            return
        if self._queue.full():
            self._queue.get_nowait()
            self.dropped += 1
            if self._queue.maxsize > 1:  # a ring of one keeps the latest by design (state, not events)
                behind = f"the reader is {self._queue.maxsize} messages behind: the oldest dropped"
                self._bus.reject(key, "queue_full", behind)
        self._queue.put_nowait((key, msg))

    @property
    def pending(self) -> int:
        """Messages received and not yet read."""
        return self._queue.qsize()

    def __aiter__(self) -> AsyncIterator[tuple[str, M]]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[tuple[str, M]]:
        while True:
            yield await self._queue.get()

    async def receive(self, timeout: float) -> tuple[str, M]:
        """The next message, or ``TimeoutError``; unlike a cancelled ``anext``, the subscription goes on."""
        async with asyncio.timeout(timeout):
            return await self._queue.get()

    def undeclare(self) -> None:
        """Idempotent: the bus undeclares what is left at close."""
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None


class Publisher(Generic[M]):
    """One key that the graph gives this process's role: the message type, the QoS and the sequence
    counter of that key travel together, so a put can be neither of another type nor another QoS."""

    def __init__(self, bus: Bus, topic: Topic[M], key: str) -> None:
        self._bus = bus
        self.topic = topic
        self.key = key
        self.seq = 0  # what next_seq gives next

    def next_seq(self) -> int:
        """This key's sequence number for the next message (DESIGN §3: each sender counts per key)."""
        self.seq += 1
        return self.seq - 1

    def put(self, msg: M) -> None:
        """Publish from the loop thread."""
        if not isinstance(msg, self.topic.message):
            raise TypeError(f"{self.key} carries {self.topic.message.__name__}, not {type(msg).__name__}")
        self._bus._check_open()
        self._bus.transport.send(self.key, encode(msg), block=self.topic.qos == "block")

    async def until_subscribed(self, timeout: float) -> None:
        await self._bus.until_subscribed(self.key, timeout)


class RawSubscription:
    """Something declared on the transport (a raw subscriber, a queryable); ``undeclare`` is idempotent."""

    def __init__(self, sub: Declared) -> None:
        self._sub: Declared | None = sub

    def undeclare(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None


class Bus:
    """The typed ports of one process (or of a test) on one transport, used from one event loop; an async
    context manager (httpx's habit)."""

    def __init__(
        self, transport: Transport, cell: str, role: str | None = None, cfg: BusConfig | None = None
    ) -> None:
        self.transport = transport
        self.cfg = cfg or BusConfig()
        self.cell = cell
        # Who this process is on the graph (schemas/topology.py); None for a test's or a replay's
        # session, which speak for nobody and are held to nothing (the router's ACL still is).
        self.role = role
        self.ports: list[tuple[str, str, Topic[Any]]] = []  # (kind, role, topic): what was opened
        self.decode_errors: Counter[str] = Counter()
        self.rejected: Counter[tuple[str, str]] = Counter()  # (key, reason)
        self.handler_errors: Counter[tuple[str, str]] = Counter()  # (key, exception type)
        self._last_log: dict[tuple[str, str], float] = {}
        self._declared: list[Subscription[Any] | RawSubscription] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._handled: list[Subscription[Any]] = []  # the handlers' queues
        self._handling = 0  # handlers running now
        self._closed = False

    @classmethod
    async def open(cls, cfg: BusConfig, cell: str, role: str | None = None) -> Bus:
        """On a Zenoh session configured by ``cfg``."""
        if role is not None and role not in ROLE:  # before a session exists that would need closing
            raise BusError(f"unknown role {role!r}; the graph has {', '.join(ROLE)}")
        conf = zenoh_config(cfg)
        try:
            session = await asyncio.to_thread(zenoh.open, conf)
        except zenoh.ZError as exc:
            raise BusError(
                f"cannot open a Zenoh session ({cfg.mode or cfg.config_file or 'peer'}): {zenoh_words(exc)}"
            ) from exc
        transport = ZenohTransport(session, asyncio.get_running_loop(), cfg.mode == "router", cfg.connect)
        return cls(transport, cell, role, cfg)

    async def __aenter__(self) -> Bus:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def key(self, suffix: str) -> str:
        return topology_key(self.cell, suffix)

    def isolation(self) -> str | None:
        """Why nothing can reach this bus: None while it has a router or a peer (or is a router, which
        others come to); else what it tried, for a person to act on."""
        return self.transport.isolation()

    def idle(self) -> bool:
        """No handler running and none with a message waiting: what an in-memory network waits for
        before it calls itself settled (common/runtime/memory.py)."""
        return self._handling == 0 and not any(sub.pending for sub in self._handled)

    # --- the graph ----------------------------------------------------------------------------------

    def _port(self, kind: Literal["publish", "subscribe", "ask"], topic: Topic[Any]) -> None:
        """Check a port against the graph and remember it (the graph test reads ``ports``)."""
        if self.role is None:
            return
        allowed = {"publish": may_publish, "subscribe": may_subscribe, "ask": may_ask}[kind]
        if not allowed(self.role, topic):
            raise BusError(f"the graph does not let {self.role} {kind} {topic.suffix} (schemas/topology.py)")
        self.ports.append((kind, self.role, topic_of(self.key(topic.suffix)) or topic))  # the family

    def _resolve(
        self,
        kind: Literal["publish", "subscribe", "ask"],
        what: Topic[Any] | str,
        msg_type: Any,
    ) -> tuple[str, Any]:
        """(key expression, message type) of a port on a topic of the graph, or on a key expression for a
        tool or a test (``msg_type`` then says how to decode; a queryable's replies go unchecked). Checked
        against the graph either way when this process has a role."""
        self._check_open()
        if not isinstance(what, str):
            self._port(kind, what)
            return key_for(what, self.cell), what.message
        if msg_type is None and kind != "publish":
            raise TypeError(f"{kind} by key expression needs msg_type")
        if self.role is not None:
            topic = topic_of(what.split("?", 1)[0])
            if topic is None:
                raise BusError(f"{what} is not a key of the graph (schemas/topology.py)")
            self._port(kind, topic)
        return what, msg_type

    def publisher(self, topic: Topic[M]) -> Publisher[M]:
        """The port for one key (a family's member: ``HEALTH.at(name)``)."""
        self._check_open()
        if "*" in topic.suffix.split("/"):
            raise ValueError(f"{topic.suffix}: a publisher needs one key; name it with .at()")
        self._port("publish", topic)
        return Publisher(self, topic, key_for(topic, self.cell))

    def asks(self, topic: Topic[Any]) -> None:
        """Declare a query the process may send (checked against the graph now, as a publisher is), for a
        port it asks only now and then (the decision maker asks for windows it missed)."""
        self._check_open()
        self._port("ask", topic)

    def _check_open(self) -> None:
        if self._closed:
            raise BusError("the bus is closed")

    # --- decoding -----------------------------------------------------------------------------------

    def _log_limited(self, key: str, kind: str, text: str, count: int) -> None:
        """One line per key and kind every 10 s at most, with the count so far: a flood of bad input
        must not become a flood of log."""
        now = wall_monotonic()
        if now - self._last_log.get((key, kind), -_LOG_EVERY_S) >= _LOG_EVERY_S:
            self._last_log[(key, kind)] = now
            log.warning("%s on %s: %s (%d so far)", kind, key, text, count)

    def decode(self, key: str, payload: bytes, decoder: msgspec.msgpack.Decoder[Any]) -> Any:
        """The message, or None for one that does not decode, whatever the decoder raised: a payload
        nested 50,000 maps deep raises ``RecursionError``, not a ``DecodeError``, and 2,000 of them must
        be 2,000 counted decode errors and one log line, not 24,000 lines of traceback."""
        try:
            return decoder.decode(payload)
        except (msgspec.ValidationError, msgspec.DecodeError) as exc:
            text = str(exc)
        except Exception as exc:  # RecursionError, MemoryError's cousins: any payload that breaks decoding
            text = f"{type(exc).__name__}: {exc}"
        self.decode_errors[key] += 1
        self._log_limited(key, "dropped a malformed message", text, self.decode_errors[key])
        return None

    def reject(self, key: str, reason: str, detail: str = "") -> None:
        """A message that decoded but that the receiver must not act on (common/runtime/admission.py)."""
        self.rejected[(key, reason)] += 1
        self._log_limited(
            key,
            f"dropped a message ({reason})",
            detail or reason,
            sum(n for (k, _), n in self.rejected.items() if k == key),
        )

    def handler_failed(self, key: str, exc: Exception) -> None:
        name = type(exc).__name__
        self.handler_errors[(key, name)] += 1
        tb = exc.__traceback__
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        where = f" at {tb.tb_frame.f_code.co_filename}:{tb.tb_lineno}" if tb is not None else ""
        self._log_limited(key, "a handler failed", f"{name}: {exc}{where}", self.handler_errors[(key, name)])

    def drop_counters(self) -> dict[str, int]:
        """What was dropped, for ``ServiceStatus.counters``: keys relative to ``cadence/<cell>/``."""
        prefix = self.key("")
        out = {"decode_errors": sum(self.decode_errors.values())}
        for name, counter in (("rejected", self.rejected), ("handler_errors", self.handler_errors)):
            for (key, why), n in counter.most_common(_MAX_COUNTERS):
                out[f"{name}/{key.removeprefix(prefix)}/{why}"] = n
        return out

    # --- topics -------------------------------------------------------------------------------------

    def put_raw(self, key: str, payload: bytes, block: bool = False) -> None:
        """Bytes as they are, on any key: a replay's, or a test's (``tests.conftest.put``); a session that
        speaks for nobody. A process with a role publishes through its ``publisher`` ports."""
        self._check_open()
        if self.role is not None:
            raise BusError(f"{self.role}: publish {key} through Bus.publisher (schemas/topology.py)")
        self.transport.send(key, payload, block)

    def matching(self, key: str) -> bool:
        """Whether a subscriber somewhere matches ``key`` now (Zenoh's matching status): a put to a key
        nobody subscribes to is dropped silently, so a replay says so rather than count it as sent."""
        self._check_open()
        return self.transport.matching(key)

    async def until_subscribed(self, key: str, timeout: float) -> None:
        """Wait until a subscriber somewhere matches ``key`` (Zenoh's matching status), so that what is
        published next reaches it: a replay, a test. TimeoutError when none appears."""
        self._check_open()
        await self.transport.until_subscribed(key, timeout)

    def subscribe_raw(self, key_expr: str, callback: Callable[[str, bytes], None]) -> RawSubscription:
        """Payloads as they travel, undecoded (recording): ``callback(key, bytes)`` on the loop thread."""
        self._check_open()
        sub = RawSubscription(self.transport.declare_subscriber(key_expr, callback))
        self._declared.append(sub)
        return sub

    def subscribe(
        self,
        what: Topic[M] | str,
        msg_type: type[M] | None = None,
        maxsize: int = 256,
    ) -> Subscription[M]:
        """The messages of a topic of the graph (``HEALTH.at("executor")`` for one key of a family); or of
        a key expression, decoded as ``msg_type``, for a tool or a test."""
        return self._subscription(what, msg_type, maxsize)

    def _subscription(
        self,
        what: Topic[Any] | str,
        msg_type: Any,
        maxsize: int,
        arrival: Callable[[str, Any], object] | None = None,
        screen: Callable[[str, Any], bool] | None = None,
    ) -> Subscription[Any]:
        key_expr, msg_type = self._resolve("subscribe", what, msg_type)
        sub = Subscription(self, key_expr, msg_type, maxsize, arrival, screen)
        self._declared.append(sub)
        return sub

    def take(self, what: Topic[M], callback: Callable[[str, M], object]) -> Subscription[M]:
        """Each message of a topic of the graph handed to ``callback`` on the loop thread as it arrives,
        decoded, with no queue between: for input that must be judged on arrival and kept per sender
        (DESIGN §8: one source's flood cannot displace another's reading). The callback must be quick;
        one that raises is counted like a handler."""
        return self._subscription(what, None, 1, arrival=callback)

    @overload
    def handle(
        self,
        what: Topic[M],
        handler: Callable[[str, M], Awaitable[None]],
        /,
        *,
        maxsize: int = 256,
        screen: Callable[[str, M], bool] | None = None,
    ) -> Subscription[M]: ...

    @overload
    def handle(
        self,
        what: str,
        msg_type: type[M],
        handler: Callable[[str, M], Awaitable[None]],
        /,
        *,
        maxsize: int = 256,
        screen: Callable[[str, M], bool] | None = None,
    ) -> Subscription[M]: ...

    def handle(
        self,
        what: Topic[Any] | str,
        /,
        *args: Any,
        maxsize: int = 256,
        screen: Callable[[str, Any], bool] | None = None,
    ) -> Any:
        """Subscribe with a handler coroutine, run for each message in order in a task the bus owns.
        A handler that raises is counted and logged (rate-limited) and the next message is handled: bad
        input never stops a service. ``screen``: whether a message may be queued (``Subscription``)."""
        msg_type, handler = args if isinstance(what, str) else (None, *args)
        sub = self._subscription(what, msg_type, maxsize, screen=screen)
        self._handled.append(sub)

        async def pump() -> None:
            async for key, msg in sub:
                self._handling += 1
                try:
                    await handler(key, msg)
                except Exception as exc:
                    self.handler_failed(key, exc)
                finally:
                    self._handling -= 1

        self._spawn(pump())
        return sub

    # --- queries ------------------------------------------------------------------------------------

    def serve(self, what: Topic[M] | str, handler: Callable[[Request], Awaitable[M]]) -> RawSubscription:
        """Answer queries on a topic of the graph (a key expression, for a test): the handler returns
        the topic's message or raises ``QueryError``. The returned handle undeclares the queryable (the
        bus does at close)."""
        key_expr, answers = self._resolve("publish", what, None)

        async def respond(key: str, parameters: str) -> tuple[bool, bytes]:
            return await answer(answers, handler, Request(key, parameters))

        served = RawSubscription(self.transport.declare_queryable(key_expr, respond))
        self._declared.append(served)
        return served

    def _spawn(self, coro: Awaitable[None]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    @overload
    async def get(
        self, what: Topic[M], /, *, timeout: float = 2.0, parameters: str = ""
    ) -> list[Reply[M]]: ...

    @overload
    async def get(self, what: str, msg_type: Any, /, timeout: float = 2.0) -> list[Reply[Any]]: ...

    async def get(
        self,
        what: Topic[Any] | str,
        msg_type: Any = None,
        timeout: float = 2.0,
        *,
        parameters: str = "",
    ) -> list[Reply[Any]]:
        """Query a topic of the graph (``PARETO_SET.at(path_id)``) and decode every reply; an error reply
        keeps its text. Never blocks the loop. A selector and ``msg_type`` instead (any type, a union
        too), for a tool that asks any key (``cadence get``) or a test."""
        selector, msg_type = self._resolve("ask", what, msg_type)
        if parameters:
            selector += f"?{parameters}"
        decoder = msgspec.msgpack.Decoder(msg_type)
        out: list[Reply[Any]] = []
        for key, ok, payload in await self.transport.query(selector, timeout):
            if ok:
                msg = self.decode(key, payload, decoder)
                out.append(Reply(key, msg, None if msg is not None else "reply does not decode"))
            else:
                out.append(Reply(selector, None, payload.decode(errors="replace")))
        return out

    # --- presence -----------------------------------------------------------------------------------

    def token(self, key: str) -> None:
        self._check_open()
        self._declared.append(RawSubscription(self.transport.token(key)))

    # --- shutdown -----------------------------------------------------------------------------------

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for d in reversed(self._declared):
            d.undeclare()
        self._declared.clear()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.transport.close()
