"""The cell a test runs: its services in the test's event loop as `cadence run` runs them, on Zenoh or on the
in-memory bus (``Cell``); data time near now; a test's raw put."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

from common.runtime.bus import Bus, BusConfig
from common.runtime.clock import Clock
from common.runtime.memory import MemoryNetwork
from schemas import ServiceStatus
from schemas.topology import DEFAULT_CELL

CELL = DEFAULT_CELL  # the cell every test runs in, unless it needs two


def now_ns() -> int:
    """Data time for a test's messages: now, to the second. Receivers believe a stream's first message
    when it is near their data clock (common/runtime/admission.py), as a live source's is."""
    import time

    return time.time_ns() // 1_000_000_000 * 1_000_000_000


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class InProcessService:
    """A service running in this test's event loop exactly as `cadence run <name>` runs it (its real
    ``main``, data on disk): on real Zenoh, connecting to the test's listening ``endpoint``, or on the
    in-memory bus of ``network`` (``Cell.service``); dora's MockNode."""

    def __init__(
        self,
        name: str,
        main,
        settings: object,
        data: Path,
        endpoint: str | None = None,
        speed: float = 1.0,
        cell: str = DEFAULT_CELL,
        epoch_ns: int | None = None,
        network: MemoryNetwork | None = None,
        lockstep: bool = False,
    ) -> None:
        import asyncio

        from common.runtime.config import CommonSettings
        from common.runtime.service import serve

        self.stop = asyncio.Event()
        self.cell = cell
        self.ctx = None  # the service's context once it runs (its bus, its counters)

        async def wrapped(ctx) -> None:
            self.ctx = ctx
            await main(ctx)

        # a faster clock needs an epoch, or its data time would be the wall's while its sleeps are shorter;
        # services of one cell share it (``epoch_ns``), as a demo's do
        epoch = epoch_ns if epoch_ns is not None else time.time_ns() if speed != 1.0 else None
        common = CommonSettings(
            cell=cell, data_dir=str(data), status_period_s=0.1, speed=speed, epoch_ns=epoch, lockstep=lockstep
        )
        self.task = asyncio.ensure_future(
            serve(
                name,
                wrapped,
                common,
                BusConfig(connect=[endpoint] if endpoint else []),
                settings,
                stop=self.stop,
                install_signals=False,
                bus=network.bus(cell, name) if network is not None else None,
            )
        )

    async def listening(self, bus, *suffixes: str, timeout: float = 30.0) -> None:
        """Wait until this service's subscriptions to ``cadence/<its cell>/<suffix>`` are known to the test's
        session, so what the test publishes next reaches them: Zenoh drops a put that has no known
        subscriber, and a service's first status can come before its subscriptions. The right way to
        wait before publishing; never wait on a status for that. (Matching counts every subscriber,
        the test's own too: call it before the test subscribes to the same keys.)"""
        import asyncio

        async with asyncio.timeout(timeout):
            for suffix in suffixes:
                while True:
                    if self.task.done():
                        self.task.result()  # the service died: say why
                        raise AssertionError(f"the service ended before subscribing to {suffix}")
                    try:
                        await bus.until_subscribed(f"cadence/{self.cell}/{suffix}", 0.5)
                        break
                    except TimeoutError:
                        continue

    async def reaches(self, *suffixes: str, timeout: float = 30.0) -> None:
        """Wait until this service's own session knows a subscriber of each key, so what it publishes
        next arrives (a service that feeds another: the analyser's windows, the decision maker)."""
        import asyncio

        async with asyncio.timeout(timeout):
            while self.ctx is None:
                if self.task.done():
                    self.task.result()
                await asyncio.sleep(0.01)  # polls a flag the service's first step sets; bounded above
            for suffix in suffixes:
                await self.ctx.bus.until_subscribed(self.ctx.bus.key(suffix), timeout)

    async def close(self) -> None:
        import asyncio

        self.stop.set()
        await asyncio.wait_for(self.task, 15)


def put(bus, key: str, msg, block: bool = False) -> None:
    """A message on any key from a session that speaks for nobody (a test's): the typed ports are the
    services' only way to publish, so a test's raw put lives here, not on the Bus."""
    from schemas.topology import encode

    bus.put_raw(key, encode(msg), block)


async def status_of(bus: Bus, name: str, pred, timeout: float = 20.0) -> ServiceStatus:
    sub = aiter(bus.subscribe(bus.key(f"health/{name}"), ServiceStatus, maxsize=1))
    async with asyncio.timeout(timeout):
        async for _, st in sub:
            if pred(st):
                return st
    raise AssertionError("unreachable")


@dataclass
class Cell:
    """The cell a test runs services in, and its name (one place, not "cell1" in every test): on the
    in-memory bus (``network``: the node-logic tests) or on Zenoh (``endpoint``, on which the test's own
    session listens: the tests of the bus itself and end to end)."""

    name: str = DEFAULT_CELL
    endpoint: str | None = None
    network: MemoryNetwork | None = None
    epoch_ns: int | None = None  # a lockstep cell's (in-memory only): its data time is epoch + loop time

    def now_ns(self) -> int:
        """Data time for the test's own messages: the cell's driven clock in lockstep, else the wall's."""
        if self.epoch_ns is not None:
            return Clock(epoch_ns=self.epoch_ns, driven=True).now_ns()
        return time.time_ns()

    @contextlib.asynccontextmanager
    async def session(self) -> AsyncIterator[Bus]:
        """The test's own session: it speaks for nobody, reads everything and puts raw (``put``)."""
        if self.network is not None:
            async with self.network.bus(self.name) as bus:
                yield bus
        else:
            async with await Bus.open(BusConfig(listen=[self.endpoint or ""]), self.name) as bus:
                yield bus

    def service(self, name: str, main, settings: object, data: Path, **options) -> InProcessService:
        """A service of this cell, started now in the test's event loop."""
        if self.epoch_ns is not None:
            options |= {"lockstep": True, "epoch_ns": self.epoch_ns}
        return InProcessService(name, main, settings, data, self.endpoint, cell=self.name,
                                network=self.network, **options)  # fmt: skip

    def key(self, suffix: str) -> str:
        return f"cadence/{self.name}/{suffix}"


def config_file(tmp: Path, name: str, cfg: dict) -> BusConfig:
    """A Zenoh config (a router's, an account's) as the file a deployed process reads."""
    p = tmp / f"{name}.json5"
    p.write_text(json.dumps(cfg))
    return BusConfig(config_file=str(p))


def account_file(tmp: Path, ca, cell: str, name: str, password: str, at: list[str]) -> BusConfig:
    """An account of ``cell`` as `cadence install` writes it: its certificate from the cell's CA (``ca``,
    a ``cadence.deploy.pki.Pem``), its password, the router's endpoints ``at``."""
    from cadence.deploy.cell import Tls, client_config, identity
    from cadence.deploy.pki import issue

    leaf = issue(ca, identity(cell, name), cell, [name])
    cfg = client_config(cell, name, password, at, Tls(ca.cert, leaf.cert, leaf.key))
    return config_file(tmp, identity(cell, name), cfg)
