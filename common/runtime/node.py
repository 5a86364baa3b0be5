"""A service's logic as a node of the graph (DESIGN §3; dora's Python nodes, ros2's ``demo_nodes_py``).

The graph (``schemas/topology.py``, ``ROLES``) declares once what each role reads, publishes and answers.
A node implements that declaration: a method per input (``@on``), per query it answers (``@answers``)
and per timer (``@every``). Handlers take a typed message and return the messages to publish; they never
touch the bus, so a node's logic is tested by calling them, or served on a bus in memory
(common/runtime/memory.py), with nothing else to fake. Work that runs beside the handlers (the
executor's cycles) publishes through ``Node.publish``, routed the same way.

``node_main(Node)`` gives the ``main`` that ``service_main`` serves: it checks the class against its role's
declaration (a handler for a port the graph does not give the role, or a declared port with no handler,
stops the service at start), opens exactly the declared ports, publishes what handlers return on the
output that carries each message's type, and runs the timers and the node's ``work`` until the service
stops.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine, Sequence
from typing import Any, ClassVar, NamedTuple, TypeVar

import msgspec

from common.runtime.admission import Verdict
from common.runtime.bus import Request
from common.runtime.errors import BusError
from common.runtime.errors import Rejected as Rejected  # where handlers have always found it
from common.runtime.service import ServiceContext
from schemas.base import Message
from schemas.topology import ROLE, Topic

Out = Sequence[Message]  # what a handler returns: published in order, each on the output of its type
F = TypeVar("F", bound=Callable[..., Any])

_INPUT, _ANSWER, _TIMER = "_cadence_input", "_cadence_answer", "_cadence_timer"
_MAXSIZE, _ARRIVAL, _SCREEN = "_cadence_maxsize", "_cadence_arrival", "_cadence_screen"
_KEYED = "_cadence_keyed"


def on(
    topic: Topic[Any],
    maxsize: int = 256,
    arrival: bool = False,
    screen: str | None = None,
    keyed: bool = False,
) -> Callable[[F], F]:
    """Mark ``async def handler(self, msg) -> Out`` as the node's reader of ``topic``; ``maxsize``
    messages wait for it before the oldest is dropped (``Bus.handle``). With ``arrival``, a plain
    ``def handler(self, msg) -> None`` takes each message as it arrives, with no queue (``Bus.take``):
    for input judged and kept per sender at once, that no flood may push out of a queue. ``screen`` names
    a plain method ``(msg) -> None`` run on arrival, before the queue: what it refuses (``Rejected``)
    never takes a place in the queue (a window from the future, before any query it would make).
    ``keyed`` (arrival only): ``def handler(self, key, msg)``, for a family whose key says who sent it."""

    def mark(fn: F) -> F:
        if arrival == inspect.iscoroutinefunction(fn):
            raise TypeError(f"{fn.__name__}: an arrival handler is a plain function, a queued one async")
        if keyed and not arrival:
            raise TypeError(f"{fn.__name__}: only an arrival handler takes the key")
        setattr(fn, _KEYED, keyed)
        setattr(fn, _INPUT, topic)
        setattr(fn, _MAXSIZE, maxsize)
        setattr(fn, _ARRIVAL, arrival)
        setattr(fn, _SCREEN, screen)
        return fn

    return mark


class Answer(NamedTuple):
    """A reply that also changes what the node publishes: ``publish`` goes out before the reply does."""

    reply: Message
    publish: Out = ()


def answers(topic: Topic[Any]) -> Callable[[F], F]:
    """Mark ``async def handler(self, req: Request) -> message | Answer`` as the node's answer to
    ``topic``'s queries; raising ``QueryError`` replies with its text."""

    def mark(fn: F) -> F:
        setattr(fn, _ANSWER, topic)
        return fn

    return mark


def every(fn: F) -> F:
    """Mark ``async def timer(self) -> Out`` as one of the role's timers (``Role.timers`` in the graph,
    which holds its period): run at start and then every period."""
    setattr(fn, _TIMER, fn.__name__)
    return fn


def admitted(verdict: Verdict | None) -> Verdict | None:
    """A receiver's time line's verdict (common/runtime/admission.py) as a handler acts on it: a message
    the line drops is ``Rejected`` with the line's reason; else the verdict (None: nothing to judge)."""
    if verdict is not None and not verdict.acted_on:
        raise Rejected(verdict.code, verdict.detail)
    return verdict


class Node:
    """Base of a service's node: ``role`` names its declaration in the graph. ``setup`` runs before any
    port opens (state from disk); ``reads`` leaves out a declared input the settings do not use."""

    role: ClassVar[str]
    ends_with_work: ClassVar[bool] = False  # a replay that has ended, a task's last cycle: the service ends
    # At a stop, ``work`` gets this long to end by itself (the executor brings a moving arm to rest and
    # says so) before it is cancelled.
    stop_grace_s: ClassVar[float] = 0.0

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self._readers: dict[str, Callable[[float], Awaitable[None]]] = {}
        self.published: list[Message] = []  # what ``publish`` sent while no bus serves the node
        self._sink: Callable[[Out], None] = self.published.extend
        self._group: asyncio.TaskGroup | None = None  # the node's tasks, while it runs (``serve_node``)

    def publish(self, *msgs: Message) -> None:
        """Publish now, from work that is not a handler's return (the executor's cycles, its safety
        states): each message goes to the output of its type. Without a bus (a node's unit test) the
        messages are kept in ``published``."""
        self._sink(msgs)

    def start_soon(self, work: Coroutine[Any, Any, Any], name: str) -> asyncio.Task[Any] | None:
        """Work beside ``work``, in the node's own task group: cancelled when the service ends, and its
        failure the service's, as a handler's is not (a helper says its own errors first). None, the work
        dropped, when the node does not run (its setup, its end): the caller then does without."""
        if self._group is not None:
            with contextlib.suppress(RuntimeError):  # the group already shutting down (the service ends)
                return self._group.create_task(work, name=name)
        work.close()
        return None

    async def until_read(self, topic: Topic[Any], timeout_s: float) -> None:
        """Until a reader of one of the node's outputs is there (Zenoh drops a put nobody subscribes to
        yet); ``TimeoutError`` after ``timeout_s``. A recording is worth nothing to nobody."""
        await self._readers[topic.suffix](timeout_s)

    async def setup(self) -> None:
        """Load what the node resumes from; its ports open after this."""

    def reads(self, topic: Topic[Any]) -> bool:
        return True

    async def stream(self) -> AsyncIterator[Out]:
        """What a node sends at its own pace (the twin's ECG, the store's planning progress)."""
        return
        yield ()

    async def work(self) -> None:
        """The node's own work beside its handlers; by default, publishing its ``stream``. When it ends the
        service goes on serving, unless ``ends_with_work``."""
        async for out in self.stream():
            self._sink(out)
            if self.ctx.stop.is_set():
                break

    async def close(self) -> None:
        """Release what ``setup`` took (a process pool, a database), however the service stops."""


def handlers(cls: type[Node], mark: str) -> dict[str, tuple[Any, str]]:
    """The class's methods marked ``mark``: by their value's key (a topic's suffix, or the method name for
    a timer), the value and the method's name."""
    out: dict[str, tuple[Any, str]] = {}
    for name, fn in inspect.getmembers(cls, inspect.isfunction):
        if hasattr(fn, mark):
            value = getattr(fn, mark)
            key = value.suffix if isinstance(value, Topic) else name
            if key in out:
                raise BusError(f"{cls.__name__}: two handlers for {key} ({out[key][1]}, {name})")
            out[key] = (value, name)
    return out


def check(cls: type[Node]) -> None:
    """The class implements its role's declaration exactly: every declared input and query has its
    handler, no handler serves a port the graph does not give the role, and no two outputs share a type
    (a returned message goes to the output of its type)."""
    role = ROLE.get(getattr(cls, "role", ""))
    if role is None:
        raise BusError(f"{cls.__name__}: role {getattr(cls, 'role', None)!r} is not in the graph")
    missing = []
    for mark, declared, verb in (
        (_INPUT, role.inputs, "read"),
        (_ANSWER, role.answers, "answer"),
        (_TIMER, role.timers, "time"),
    ):
        have = set(handlers(cls, mark))
        want = {t.suffix if isinstance(t, Topic) else t.name for t in declared}
        if have - want:
            raise BusError(f"the graph does not let {role.name} {verb} {', '.join(sorted(have - want))}")
        if want - have:
            missing.append(f"{', '.join(sorted(want - have))}, which the graph has {role.name} {verb}")
    if missing:
        raise BusError(f"{cls.__name__} has no handler for {'; '.join(missing)} (schemas/topology.py)")
    types = [t.message for t in role.outputs]
    if len(set(types)) != len(types):
        raise BusError(f"{role.name}: two outputs carry the same message type")


def node_main(cls: type[Node]) -> Callable[[ServiceContext], Coroutine[Any, Any, None]]:
    """The service's ``main``: the node, served on the context's bus until the service stops."""
    check(cls)

    async def main(ctx: ServiceContext) -> None:
        node = cls(ctx)
        await node.setup()
        try:
            await serve_node(node)
        finally:
            await node.close()

    return main


async def serve_node(node: Node) -> None:
    ctx, bus = node.ctx, node.ctx.bus
    role = ROLE[node.role]
    outputs = {t.message: bus.publisher(t) for t in role.outputs if "*" not in t.suffix}
    node._readers = {p.topic.suffix: p.until_subscribed for p in outputs.values()}

    def publish(msgs: Out | None) -> None:
        for msg in msgs or ():
            port = outputs.get(type(msg))
            if port is None:
                raise TypeError(f"{node.role} has no output for {type(msg).__name__} (schemas/topology.py)")
            if port.topic.numbered == "port":  # the port numbers what it sends, per key (DESIGN §3)
                msg = msgspec.structs.replace(msg, seq=port.next_seq())
            port.put(msg)

    node._sink = publish

    def reader(fn: Callable[[Any], Awaitable[Out | None]]) -> Callable[[str, Any], Awaitable[None]]:
        async def handle(key: str, msg: Any) -> None:
            try:
                publish(await fn(msg))
            except Rejected as r:
                bus.reject(key, r.code, r.detail)

        return handle

    def judged(fn: Callable[..., None]) -> Callable[[str, Any], bool]:
        """A plain method run on arrival (an arrival handler, a screen): False, counted, when it refused."""
        keyed = getattr(fn, _KEYED, False)

        def judge(key: str, msg: Any) -> bool:
            try:
                fn(key, msg) if keyed else fn(msg)
            except Rejected as r:
                bus.reject(key, r.code, r.detail)
                return False
            return True

        return judge

    for topic, name in handlers(type(node), _INPUT).values():
        if node.reads(topic):
            fn = getattr(node, name)
            if getattr(fn, _ARRIVAL):
                bus.take(topic, judged(fn))
            else:
                screen = getattr(fn, _SCREEN)
                bus.handle(topic, reader(fn), maxsize=getattr(fn, _MAXSIZE),
                           screen=judged(getattr(node, screen)) if screen else None)  # fmt: skip

    def replier(fn: Callable[[Request], Awaitable[Any]]) -> Callable[[Request], Awaitable[Any]]:
        async def reply(req: Request) -> Any:
            out = await fn(req)
            if isinstance(out, Answer):
                publish(out.publish)
                return out.reply
            return out

        return reply

    for topic, name in handlers(type(node), _ANSWER).values():
        bus.serve(topic, replier(getattr(node, name)))

    async def tick(fn: Callable[[], Awaitable[Out | None]], period: str | float) -> None:
        seconds = float(getattr(ctx.settings, period) if isinstance(period, str) else period)
        while not ctx.stop.is_set():
            try:
                publish(await fn())
            except Exception as exc:  # a timer that fails is counted like a handler, and runs again
                bus.handler_failed(f"{node.role}/timer/{fn.__name__}", exc)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(ctx.stop.wait(), seconds)

    ended = asyncio.Event()  # the service ends: stopped, or its work ended and that ends it

    async def working() -> None:
        await node.work()
        if node.ends_with_work:
            ended.set()

    async def stopping(work: asyncio.Task[None]) -> None:
        await ctx.stop.wait()
        if node.stop_grace_s > 0:  # the executor brings a moving arm to rest before its work is cancelled
            await asyncio.wait([work], timeout=node.stop_grace_s)
        ended.set()

    # one group for the node's tasks: work that fails stops the service (its supervisor restarts it), and
    # however it ends, nothing of the node outlives it
    try:
        async with asyncio.TaskGroup() as group:
            node._group = group
            for timer in role.timers:
                group.create_task(tick(getattr(node, timer.name), timer.period), name=f"timer {timer.name}")
            work = group.create_task(working(), name="work")
            group.create_task(stopping(work), name="stop")
            await ended.wait()
            raise _Ended
    except BaseExceptionGroup as group_error:
        failures = [e for e in group_error.exceptions if not isinstance(e, _Ended)]
        if failures:
            raise failures[0] from None
    finally:
        node._group = None


class _Ended(Exception):
    """Raised in the node's task group when the service ends: the group cancels what still runs."""
