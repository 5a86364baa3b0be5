"""The synthetic cells of `cadence bench plant`, one worker process's share of them: each cell's traffic
(``PROFILE``) put by the accounts a deployed cell's services use, each on its own session to the cell's
own router, and read back in the cell by its monitor account, which times the arm's state and the
separation (`python -m cadence.bench.plant_cells SPEC.json`; the bench starts it).

Every message is stamped with the host's monotonic clock (``t_ns``), one clock for every process of the
bench: a reader's age of it is its latency across the cell's router. Cells are spread over each period
(each its own phase), as cells of a plant are: none waits on the others' burst.
"""

from __future__ import annotations

import asyncio
import heapq
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import msgspec

from cadence.deploy.cell import publishers
from schemas import (
    Beats,
    CycleReport,
    EcgChunk,
    HrvWindow,
    Message,
    RobotEvent,
    RobotState,
    RrIntervals,
    Selection,
    Separation,
    ServiceStatus,
)
from schemas.topology import ECG_SOURCES, Topic, cell_roster, decode_any, encode, topic_of

Make = Callable[[int, int], Message]  # (seq, t_ns) → a message


@dataclass(frozen=True, slots=True)
class Stream:
    """One key of a cell's traffic and how often it comes. Its account is its publisher in the graph
    (``account``): the one a deployed cell's router lets put it."""

    suffix: str
    hz: float
    make: Make

    @property
    def topic(self) -> Topic[Any]:
        topic = topic_of(f"cadence/any/{self.suffix}")
        assert topic is not None, self.suffix
        return topic

    @property
    def account(self) -> str:
        if self.suffix.startswith("health/"):
            return self.suffix.removeprefix("health/")
        # a cell with a strap: the twin has no account
        return min(publishers(self.topic) - set(ECG_SOURCES[1:]))


def _state(seq: int, t: int) -> Message:
    q = [0.1 * i + 1e-4 * (seq % 1000) for i in range(6)]
    return RobotState(t_ns=t, seq=seq, q=q, qd=[0.05] * 6, tcp=[0.4, 0.1, 0.3, 0.0, 3.14, 0.0],
                      path_id="pick", k=6, mode="path", state="running", separation_m=1.8)  # fmt: skip


def _status(service: str) -> Make:
    return lambda seq, t: ServiceStatus(t_ns=t, seq=seq, service=service, state="serving", uptime_s=seq,
                                        counters={"received": seq, "sent": seq})  # fmt: skip


# A cell at speed 1 (the process demo cell's keys and rates: the executor's state at 50 Hz, one scanner,
# the strap's ECG as the gateway forwards it, the analyser's beats and windows, the decision maker's
# republished selection, the executor's cycles and events, each service's status once a second)
PROFILE: tuple[Stream, ...] = (
    Stream("robot/state", 50.0, _state),
    Stream("operator/separation", 20.0,
           lambda seq, t: Separation(t_ns=t, seq=seq, distance_m=1.8, source="scanner:front")),
    Stream("ecg/samples", 130.0 / 73,
           lambda seq, t: EcgChunk(t_ns=t, seq=seq, fs_hz=130.0, samples_uv=[(seq * 7 + i) % 900 - 300
                                                                             for i in range(73)])),
    Stream("ecg/rr", 1.0, lambda seq, t: RrIntervals(t_ns=t, seq=seq, rr_s=[0.81])),
    Stream("hrv/beats", 1.2,
           lambda seq, t: Beats(t_ns=t, seq=seq, peak_t_ns=[t], rr_s=[0.81], excluded=[False])),
    Stream("hrv/window", 0.5,
           lambda seq, t: HrvWindow(t_ns=t, seq=seq, start_ns=max(0, t - 30_000_000_000), end_ns=t,
                                    mean_rr_s=0.81, n_beats=37, excluded_fraction=0.0, quality="good")),
    Stream("decision/selection", 1.0,
           lambda seq, t: Selection(t_ns=t, seq=seq // 30, k=6, n=15, delta=0, reason="hold")),
    Stream("robot/cycle", 0.2,
           lambda seq, t: CycleReport(t_ns=t, seq=seq, cycle=seq, cycle_time_s=5.0, k_per_path={"pick": 6})),
    Stream("robot/event", 0.2,
           lambda seq, t: RobotEvent(t_ns=t, seq=seq, kind="scale", message="scale 1.0 at 1.80 m")),
    *(Stream(f"health/{s}", 1.0, _status(s)) for s in cell_roster([ECG_SOURCES[0]])),
)  # fmt: skip
TIMED = ("robot/state", "operator/separation")  # read back in the cell and timed
EARLY_NS = 1_000_000  # a put due this soon goes now (stamped when it goes): fewer wake-ups of the putters
DERIVED = ("hrv/window", "robot/cycle", "robot/event")  # what a plant keeps of each one (none may be lost)
ACCOUNTS = tuple(sorted({s.account for s in PROFILE}))


class CellSpec(msgspec.Struct, frozen=True):
    name: str
    accounts: dict[str, str]  # account → its Zenoh config (a client of the cell's router)
    reader: str  # the cell's monitor account's config
    # a real cell: its services, each a process of its own (the bench starts them), not a profile put
    # by a worker; its messages are stamped on the data clock, which at speed 1 is the wall's
    services: list[str] = []


class WorkerSpec(msgspec.Struct, frozen=True):
    cells: list[CellSpec]
    first: int  # this worker's first cell's index among all (for its phase in each period)
    of: int  # all cells of the bench
    out: str  # where the results go (JSON)
    puts: bool = True  # this worker puts the cells' traffic
    reads: bool = True  # this worker reads it back in each cell (the readers' own process: their
    # callbacks wait on no putting of what the other cells send)


class WorkerResult(msgspec.Struct):
    """What one worker put and saw: how many of each key per cell, the stamps of the keys a plant keeps
    (to find each in what the plant got), and the timed keys' latencies (µs) with their stamps. Of a
    real cell, what its monitor session saw: the timed keys' latencies with when each came (monotonic),
    and the stamp of each derived message with when it came."""

    sent: dict[str, dict[str, int]]  # cell → suffix → how many
    derived: dict[str, dict[str, list[int]]]  # cell → a DERIVED suffix → the t_ns of each put
    timed: dict[str, list[tuple[int, int]]]  # suffix → [(t_ns, latency µs)]
    lost_puts: int = 0
    real_timed: dict[str, list[tuple[int, int]]] = {}  # suffix → [(came, monotonic ns; latency µs)]
    real_derived: dict[str, dict[str, list[tuple[int, int]]]] = {}  # cell → suffix → [(t_ns, came)]


def _schedule(spec: WorkerSpec, t0_ns: int) -> list[tuple[int, int, int]]:
    """The first put of each (cell, stream), its cell's phase in each stream's period: (t_ns, cell, s)."""
    first = []
    for c in range(len(spec.cells)):
        for s, stream in enumerate(PROFILE):
            period = 1e9 / stream.hz
            phase = ((spec.first + c) / spec.of + 0.37 * s) % 1.0
            first.append((t0_ns + int(phase * period), c, s))
    heapq.heapify(first)
    return first


async def drive(spec: WorkerSpec, start: asyncio.Future[tuple[int, int]]) -> WorkerResult:
    """Open every cell's sessions, wait until each cell's reader is subscribed, say ready, then put the
    profile from the start to the end the bench gives (``start``: (t0_ns, end_ns))."""
    from common.runtime.bus import Bus, BusConfig
    from common.runtime.transport import ZenohTransport

    buses: dict[tuple[int, str], Bus] = {}
    readers: list[Bus] = []
    subs: list[Any] = []  # Zenoh's subscribers, alive until the end
    timed: dict[str, list[tuple[int, int]]] = {k: [] for k in TIMED}
    decoders: dict[str, msgspec.msgpack.Decoder[RobotState] | msgspec.msgpack.Decoder[Separation]] = {
        "robot/state": msgspec.msgpack.Decoder(RobotState),
        "operator/separation": msgspec.msgpack.Decoder(Separation),
    }

    def arrived(suffix: str) -> Callable[[Any], None]:
        """Timed as the cell's session gets it, in Zenoh's own callback: the latency through the cell's
        router. (A service's loop adds its own hop; fifty cells' readers share this process's loop, a
        load no cell's service has.)"""
        decode, into = decoders[suffix].decode, timed[suffix]

        def on(sample: Any) -> None:
            now = time.monotonic_ns()
            t = decode(sample.payload.to_bytes()).t_ns
            into.append((t, (now - t) // 1000))

        return on

    real_timed: dict[str, list[tuple[int, int]]] = {k: [] for k in TIMED}
    real_derived: dict[str, dict[str, list[tuple[int, int]]]] = {}

    def real(cell: str, suffix: str) -> Callable[[Any], None]:
        """A real cell's message as its monitor session gets it: a timed key's latency on the wall clock
        (the data clock at speed 1), a derived one's stamp; each with when it came."""

        def on(sample: Any) -> None:
            came, wall = time.monotonic_ns(), time.time_ns()
            msg = decode_any(sample.payload.to_bytes())
            if suffix in TIMED:
                real_timed[suffix].append((came, (wall - msg.t_ns) // 1000))
            else:
                real_derived[cell][suffix].append((msg.t_ns, came))

        return on

    async def alive(session: Any, cell: CellSpec) -> None:
        """Until every service of a real cell has its presence on the bus (they start beside the bench:
        imports, sessions, the store's sets): the phases are timed from a cell that runs, and its monitor
        subscribes to a cell whose services are there."""
        get = session.liveliness().get
        async with asyncio.timeout(300):
            while True:
                replies = await asyncio.to_thread(
                    lambda: list(get(f"cadence/{cell.name}/health/*", timeout=2))
                )
                if {str(r.ok.key_expr).rsplit("/", 1)[1] for r in replies if r.ok} >= set(cell.services):
                    return
                await asyncio.sleep(0.5)

    try:
        for c, cell in enumerate(spec.cells):
            if spec.reads:
                reader = await Bus.open(BusConfig(config_file=cell.reader), cell.name)
                readers.append(reader)
                session = cast(ZenohTransport, reader.transport).session
                if cell.services:
                    await alive(session, cell)
                    real_derived[cell.name] = {k: [] for k in DERIVED}
                    for suffix in (*TIMED, *DERIVED):
                        subs.append(session.declare_subscriber(reader.key(suffix), real(cell.name, suffix)))
                else:
                    for suffix in TIMED:
                        subs.append(session.declare_subscriber(reader.key(suffix), arrived(suffix)))
            for account in ACCOUNTS if spec.puts else ():
                buses[c, account] = await Bus.open(BusConfig(config_file=cell.accounts[account]), cell.name)
        for c, cell in enumerate(spec.cells if spec.puts else ()):
            for stream in PROFILE:
                if stream.suffix in TIMED:
                    await buses[c, stream.account].until_subscribed(
                        f"cadence/{cell.name}/{stream.suffix}", 60
                    )
        print("ready", flush=True)
        t0, end = await start
        sent = {cell.name: {s.suffix: 0 for s in PROFILE} for cell in spec.cells if spec.puts}
        derived: dict[str, dict[str, list[int]]] = {cell: {k: [] for k in DERIVED} for cell in sent}
        keys = [[f"cadence/{cell.name}/{s.suffix}" for s in PROFILE] for cell in spec.cells]
        block = [s.topic.qos == "block" for s in PROFILE]  # as the services put them: the topic's QoS
        due = _schedule(spec, t0) if spec.puts else []
        if not due:
            await asyncio.sleep(max(0, end - time.monotonic_ns()) / 1e9)
        lost = 0
        while due:
            t, c, s = due[0]
            if t >= end:
                break
            now = time.monotonic_ns()
            if t > now + EARLY_NS:
                await asyncio.sleep((t - now) / 1e9)
                continue
            heapq.heappop(due)
            stream, name = PROFILE[s], spec.cells[c].name
            seq = sent[name][stream.suffix]
            stamp = time.monotonic_ns()
            try:
                buses[c, stream.account].put_raw(keys[c][s], encode(stream.make(seq, stamp)), block[s])
            except Exception:  # a put the session refused: counted, never a crash of the bench
                lost += 1
            sent[name][stream.suffix] = seq + 1
            if stream.suffix in DERIVED:
                derived[name][stream.suffix].append(stamp)
            heapq.heappush(due, (t + int(1e9 / stream.hz), c, s))
        await asyncio.sleep(0.5)  # the last puts' way through the cell's router
        return WorkerResult(sent=sent, derived=derived, timed=timed, lost_puts=lost, real_timed=real_timed,
                            real_derived=real_derived)  # fmt: skip
    finally:
        for sub in subs:
            sub.undeclare()
        for bus in [*buses.values(), *readers]:
            await bus.close()


async def _main(spec_path: str) -> None:
    spec = msgspec.json.decode(Path(spec_path).read_bytes(), type=WorkerSpec)
    loop = asyncio.get_running_loop()
    start: asyncio.Future[tuple[int, int]] = loop.create_future()

    async def listen() -> None:  # one line on stdin: "t0_ns end_ns"
        line = await asyncio.to_thread(sys.stdin.readline)
        t0, end = (int(x) for x in line.split())
        start.set_result((t0, end))

    listener = asyncio.create_task(listen())
    result = await drive(spec, start)
    listener.cancel()
    Path(spec.out).write_bytes(msgspec.json.encode(result))


if __name__ == "__main__":
    asyncio.run(_main(sys.argv[1]))
