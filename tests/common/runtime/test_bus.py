"""The bus with real Zenoh sessions on loopback (multicast scouting off), waiting on events only."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import threading

import pytest

from common.runtime.bus import Bus, BusConfig, QueryError, Request
from common.runtime.errors import BusError
from schemas import Selection, ServiceStatus
from schemas.topology import TOPICS
from tests.support.cell import CELL, free_port, put

pytestmark = pytest.mark.asyncio

SEL = Selection(t_ns=5, seq=1, k=8, n=15, delta=0, reason="initial")


async def pair(endpoint: str) -> tuple[Bus, Bus]:
    a = await Bus.open(BusConfig(listen=[endpoint]), CELL)
    b = await Bus.open(BusConfig(connect=[endpoint]), CELL)
    return a, b


async def test_a_published_message_arrives_decoded(endpoint: str) -> None:
    a, b = await pair(endpoint)
    async with a, b:
        sub = b.subscribe(b.key("decision/selection"), Selection)
        it = aiter(sub)
        received = asyncio.ensure_future(anext(it))
        # the subscriber's declaration reaches the publisher asynchronously: publish until it arrives
        async with asyncio.timeout(5):
            while not received.done():
                put(a, a.key("decision/selection"), SEL, block=True)
                await asyncio.wait({received}, timeout=0.05)
        key, msg = received.result()
        assert key == f"cadence/{CELL}/decision/selection"
        assert msg == SEL


async def test_malformed_payloads_on_every_key_are_counted_and_dropped(endpoint: str) -> None:
    a, b = await pair(endpoint)
    async with a, b:
        topics = [t for t in TOPICS if t.pattern == "topic"]
        keys = [b.key(t.suffix.replace("*", "x")) for t in topics]
        subs = [b.subscribe(k, t.message) for k, t in zip(keys, topics, strict=True)]
        good = asyncio.ensure_future(anext(aiter(subs[keys.index(b.key("decision/selection"))])))
        rng = os.urandom

        def counted() -> bool:
            return all(b.decode_errors[k] > 0 for k in keys)

        async with asyncio.timeout(10):
            while not counted():
                for k in keys:
                    a.put_raw(k, rng(37))
                await asyncio.sleep(0.05)
        # the subscriber still works after the garbage
        async with asyncio.timeout(5):
            while not good.done():
                put(a, a.key("decision/selection"), SEL)
                await asyncio.wait({good}, timeout=0.05)
        assert good.result()[1] == SEL


async def test_a_queryable_answers_and_an_error_reply_says_why(endpoint: str) -> None:
    a, b = await pair(endpoint)
    async with a, b:

        async def handler(req: Request) -> Selection:
            if req.key.endswith("/bad"):
                raise QueryError("no such thing")
            return SEL

        a.serve(a.key("decision/**"), handler)
        async with asyncio.timeout(5):
            while not (replies := await b.get(b.key("decision/selection"), Selection, timeout=1.0)):
                pass
        assert replies[0].message == SEL
        bad = await b.get(b.key("decision/bad"), Selection, timeout=2.0)
        assert bad[0].message is None
        assert bad[0].error == "no such thing"


@pytest.mark.parametrize("transport", ["zenoh", "memory"])
async def test_both_transports_keep_the_bus_s_contract(transport: str, endpoint: str) -> None:
    """What a ``Bus`` asks of a transport (common/runtime/transport.py), asked of Zenoh's and of the
    in-memory one alike: the lockstep cell and a node's tests run on the second, so where it answered
    otherwise, they would prove nothing of a service on the first."""
    from common.runtime.memory import MemoryNetwork

    if transport == "zenoh":
        a, b = await pair(endpoint)
    else:
        network = MemoryNetwork()
        a, b = network.bus(CELL), network.bus(CELL)
    key = a.key("decision/selection")
    async with a, b:
        assert a.isolation() is None and b.isolation() is None
        assert not a.matching(key)  # nobody listens yet: a put now would be dropped
        sub = b.subscribe(key, Selection)
        await a.until_subscribed(key, 10)
        assert a.matching(key)
        sent = [Selection(t_ns=5 + i, seq=i, k=1 + i, n=15, delta=0, reason="initial") for i in range(5)]
        for m in sent:
            put(a, key, m, block=True)
        got = [await sub.receive(10) for _ in sent]
        assert got == [(key, m) for m in sent]  # decoded, on their key, in order

        async def handler(req: Request) -> Selection:
            if req.params.get("k") == "0":
                raise QueryError("k counts from 1")
            return sent[int(req.params["k"]) - 1]

        b.serve(b.key("decision/**"), handler)
        async with asyncio.timeout(10):  # a queryable's declaration reaches the querier asynchronously
            while not (replies := await a.get(f"{key}?k=3", Selection, timeout=1.0)):
                pass
        assert [(r.key, r.message, r.error) for r in replies] == [(key, sent[2], None)]
        (bad,) = await a.get(f"{key}?k=0", Selection, timeout=2.0)
        assert (bad.message, bad.error) == (None, "k counts from 1")
        b.token(b.key("health/test"))
        put(a, key, SEL)
        assert (await sub.receive(10))[1] == SEL  # a bus that declared all of that still delivers
    with pytest.raises(BusError, match="closed"):
        a.matching(key)


async def test_a_closed_bus_refuses_use(endpoint: str) -> None:
    a = await Bus.open(BusConfig(listen=[endpoint]), CELL)
    await a.close()
    with pytest.raises(Exception, match="closed"):
        put(a, a.key("x"), SEL)


async def test_two_sessions_meet_through_cadence_router() -> None:
    port = free_port()
    router = subprocess.Popen(
        [sys.executable, "-m", "cadence", "router", "--listen", f"tcp/127.0.0.1:{port}"],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert "listening" in router.stderr.readline()
        ep = f"tcp/127.0.0.1:{port}"
        a = await Bus.open(BusConfig(mode="client", connect=[ep]), CELL)
        b = await Bus.open(BusConfig(mode="client", connect=[ep]), CELL)
        async with a, b:
            it = aiter(b.subscribe(b.key("health/x"), ServiceStatus))
            received = asyncio.ensure_future(anext(it))
            status = ServiceStatus(t_ns=1, seq=0, service="x", state="ok", uptime_s=1.0, counters={})
            async with asyncio.timeout(5):
                while not received.done():
                    put(a, a.key("health/x"), status)
                    await asyncio.wait({received}, timeout=0.05)
            assert received.result()[1] == status
    finally:
        router.send_signal(signal.SIGTERM)
        assert router.wait(timeout=10) == 0


async def test_zenoh_cli_prints_cadence_messages_as_json(endpoint: str) -> None:
    """The `zenoh` command of zenoh-cli loads Cadence's decoder from its entry point."""
    a = await Bus.open(BusConfig(listen=[endpoint]), CELL)
    zenoh_cli = os.path.join(os.path.dirname(sys.executable), "zenoh")
    proc = subprocess.Popen(
        [
            zenoh_cli,
            "--connect",
            endpoint,
            "--cfg",
            "scouting/multicast/enabled:false",
            "subscribe",
            "-k",
            "cadence/**",
            "--decoder",
            "cadence",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines: list[str] = []
    seen = threading.Event()

    def read() -> None:
        for line in proc.stdout:
            lines.append(line)
            if "decision.selection.v1" in line:
                seen.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        async with a:
            async with asyncio.timeout(20):
                while not seen.is_set():
                    put(a, a.key("decision/selection"), SEL)
                    await asyncio.sleep(0.1)
        line = next(x for x in lines if "decision.selection.v1" in x)
        assert '"k":8' in line
        assert '"reason":"initial"' in line
    finally:
        proc.terminate()
        proc.wait(timeout=10)


async def test_a_handler_coroutine_gets_messages_in_order_and_survives_its_own_errors(endpoint: str) -> None:
    a, b = await pair(endpoint)
    async with a, b:
        got: list[int] = []
        done = asyncio.Event()

        async def handler(key: str, msg: Selection) -> None:
            if msg.seq == 2:
                raise ValueError("a bug in the handler")
            got.append(msg.seq)
            if msg.seq == 3:
                done.set()

        b.handle(b.key("decision/selection"), Selection, handler)
        # wait until the subscription is known to the publisher: the first message handled
        async with asyncio.timeout(5):
            while not got:
                put(
                    a,
                    a.key("decision/selection"),
                    Selection(t_ns=0, seq=0, k=8, n=15, delta=0, reason="hold"),
                )
                await asyncio.sleep(0.05)
        got.clear()
        for seq in (1, 2, 3):
            put(
                a,
                a.key("decision/selection"),
                Selection(t_ns=seq, seq=seq, k=8, n=15, delta=0, reason="hold"),
                block=True,
            )
        await asyncio.wait_for(done.wait(), 5)
        assert got[-2:] == [1, 3]


async def test_a_session_opens_from_a_json5_zenoh_config_file(tmp_path, endpoint: str) -> None:
    conf = tmp_path / "peer.json5"
    conf.write_text(
        "{\n  // a Zenoh config file\n  mode: 'peer',\n  listen: { endpoints: ['" + endpoint + "'] },\n}\n"
    )
    a = await Bus.open(BusConfig(config_file=str(conf)), CELL)
    b = await Bus.open(BusConfig(connect=[endpoint]), CELL)
    async with a, b:
        a.serve(a.key("decision/selection"), lambda req: asyncio.sleep(0, SEL))
        async with asyncio.timeout(5):
            while not (replies := await b.get(b.key("decision/selection"), Selection, timeout=1.0)):
                pass
        assert replies[0].message == SEL


async def test_a_missing_zenoh_config_file_is_a_bus_error(tmp_path) -> None:
    with pytest.raises(BusError, match="bad Zenoh configuration"):
        await Bus.open(BusConfig(config_file=str(tmp_path / "none.json5")), CELL)


async def test_a_burst_past_a_handlers_queue_is_counted_not_lost_silently(endpoint: str) -> None:
    """Of a burst of 10,000 ecg/acc messages about 2,000 never reached the analyser's handler and were
    counted nowhere: what a full queue drops is counted (``rejected/<key>/queue_full``) and logged."""
    a, b = await pair(endpoint)
    async with a, b:
        release, handled = asyncio.Event(), []

        async def slow(key: str, msg: Selection) -> None:
            await release.wait()  # the handler is behind until the burst has come
            handled.append(msg.seq)

        b.handle(b.key("decision/selection"), Selection, slow, maxsize=16)
        await a.until_subscribed(a.key("decision/selection"), 10)
        for seq in range(1000):
            sel = Selection(t_ns=seq, seq=seq, k=8, n=15, delta=0, reason="hold")
            put(a, a.key("decision/selection"), sel, block=True)
        last = Selection(t_ns=1000, seq=1000, k=8, n=15, delta=0, reason="hold")
        put(a, a.key("decision/selection"), last, block=True)
        key = b.key("decision/selection")
        async with asyncio.timeout(10):  # every message arrived: handled, waiting, or counted
            while 1 + b.rejected[(key, "queue_full")] + 16 < 1001:
                await asyncio.sleep(0.01)  # polls a counter the bus's own callbacks raise; bounded above
        release.set()
        async with asyncio.timeout(10):
            while 1000 not in handled:
                await asyncio.sleep(0.01)
    dropped = b.rejected[(key, "queue_full")]
    assert dropped > 0
    assert len(handled) + dropped == 1001
    assert b.drop_counters()["rejected/decision/selection/queue_full"] == dropped
