"""`cadence bench plant --cells N`: a plant of N cells as deployed, on this host. Each cell has its own
router (`cadence router`, mTLS, its own CA, the cell's generated access control, the plant's link on the
host's network interface where it has one: the uplink). The first cell is a real one, its services as
`cadence demo --processes` runs them at speed 1, each on its own account; the others are synthetic, their
services' accounts each on its own session putting a cell's traffic at speed 1 (``plant_cells.PROFILE``:
81 messages and 20 kB a second). Every line of ``per_line`` cells has a line router that reads its cells,
and the plant's router reads the lines, as `cadence plant-router` and `cadence install --plant` configure
them; the plant's processes run at its priority (``PLANT_NICE``).

It runs rounds of two phases of the same length: the cells alone, then with the plant monitor (`cadence
plant`'s view, ``plant_monitor``) and the plant recorder (`cadence record --plant`), each a process of
its own, reading every cell through the line and plant routers. Per kind of phase: the arm's state and
the separation as each cell's monitor session gets them, p50/p99 pooled and each phase's p99 (the
in-cell figures a plant must not move; the real cell's apart), and each group of processes' CPU; then
how far behind the plant's view ever was, whether the plant got every derived message (each cell's
windows, cycles and events, by their stamps) and how many bytes a cell's plant recording takes a day.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np
from rich.console import Console
from rich.table import Table

from cadence.bench.plant_cells import TIMED, CellSpec, WorkerResult, WorkerSpec
from cadence.bench.plant_monitor import MonitorResult, MonitorSpec

PER_LINE = 10  # cells behind one line router
# CPU, by group of processes
GROUPS = ("cell routers", "line routers", "plant router", "recorder", "monitor", "workers", "real cell")
WORKERS = 2  # processes putting the cells' traffic (this host has 2 cores)
WARM_S, GAP_S = 2.0, 4.0  # before the first phase; between them (the plant's readers connect)
LINGER_S = 1.0  # the plant's readers after a phase: what was put in it is on its way through two hops
ROUNDS = 3  # pairs of phases: the cells alone, then with the plant reading
WAKE = "host wake"  # a phase's figures of ``wake_probe``, beside the timed keys'


@dataclass(frozen=True, slots=True)
class Router:
    name: str
    config: Path
    endpoint: str


@dataclass(frozen=True, slots=True)
class Layout:
    cells: list[CellSpec]
    cell_routers: list[Router]
    line_routers: list[Router]
    plant_router: Router
    monitor: Path  # the plant monitor's account (`cadence plant`, `cadence record --plant`)


class _Ports:
    """Free ports for the routers, below the ephemeral range (32768 and up on Linux): a port found free
    there can be taken by another router's outgoing connection before its own router listens on it."""

    def __init__(self) -> None:
        import random

        self.next = random.randrange(20_000, 28_000)

    def endpoint(self, host: str = "127.0.0.1") -> str:
        while True:
            port, self.next = self.next, self.next + 1
            with socket.socket() as s:
                try:
                    s.bind((host, port))
                except OSError:
                    continue
            return f"tls/{host}:{port}"


def host_interface() -> tuple[str, str] | None:
    """A network interface of this host other than loopback, with its IPv4 address, if it has one: the
    cells' routers take the plant's links there, their uplink (``router_config``'s ``uplink``)."""
    import fcntl
    import struct

    for _, name in socket.if_nameindex():
        if name == "lo":
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:  # SIOCGIFADDR: fails for an interface without an IPv4 address (down, or none given)
                packed = fcntl.ioctl(s.fileno(), 0x8915, struct.pack("256s", name.encode()[:15]))
            except OSError:
                continue
        return name, socket.inet_ntoa(packed[20:24])
    return None


def layout(
    folder: Path,
    n_cells: int,
    per_line: int = PER_LINE,
    uplink: tuple[str, str] | None = None,
    real: tuple[str, ...] = (),
) -> Layout:
    """Every router's and account's config for a plant of ``n_cells``, as a deployment writes them: each
    cell its own CA and its router built for a plant (``router_config(…, plant=True)``), the line and
    plant routers and the monitor as `cadence plant-router` writes them (``plant_files``). ``uplink``
    (an interface and its address): each cell's router takes the plant's link there and sends the arm's
    state on it at the plant's rate (`cadence install --uplink-interface`); the cell's own sessions come
    over loopback. ``real``: the first cell is a real one, these services' accounts its own."""
    from cadence.bench.plant_cells import ACCOUNTS as PUTTERS
    from cadence.deploy.cell import ACCOUNTS, PLANT, Tls, client_config, identity, router_config, to_json5
    from cadence.deploy.cell import users_file as users_of
    from cadence.deploy.pki import issue, make_ca
    from cadence.deploy.plant import new_secret, plant_files

    plant = new_secret()
    here = ["127.0.0.1"]
    ports = _Ports()

    def write(name: str, cfg: dict[str, object]) -> Path:
        path = folder / f"{name}.json5"
        path.write_text(to_json5(cfg, f"cadence bench plant: {name}"))
        return path

    cells, cell_routers, cas = [], [], {}
    lines: dict[str, tuple[str, list[str]]] = {}
    for i in range(n_cells):
        line = f"line{i // per_line + 1}"
        name = f"{line}-cell{i % per_line + 1}"
        lines.setdefault(line, (ports.endpoint(), []))[1].append(name)
        ca = make_ca(name)
        endpoint = ports.endpoint()
        up = ports.endpoint(uplink[1]) if uplink else endpoint
        cas[name] = (up, ca.cert)
        passwords = {a: f"pw-{name}-{a}" for a in ACCOUNTS}
        users = folder / f"{name}.users"
        users.write_text(users_of(name, passwords) + f"{PLANT}:{plant.password}\n")
        leaf = issue(ca, identity(name, "router"), name, [*here, *uplink[1:]] if uplink else here)
        tls = Tls(ca.cert + plant.ca.cert, leaf.cert, leaf.key)  # the plant's CA beside its own
        listen = sorted({endpoint, up})
        cfg = router_config(name, listen, tls, str(users), plant=True, uplink=uplink[0] if uplink else None)
        cell_routers.append(Router(name, write(f"{name}-router", cfg), endpoint))
        configs = {}
        services = list(real) if real and i == 0 else []
        for role in (*(services or PUTTERS), "monitor"):
            leaf = issue(ca, identity(name, role), name, [role])
            cfg = client_config(name, role, passwords[role], [endpoint], Tls(ca.cert, leaf.cert, leaf.key))
            configs[role] = str(write(identity(name, role), cfg))
        reader = configs.pop("monitor")
        cells.append(CellSpec(name, configs, reader, services))
    plant_at = ports.endpoint()
    for name, (text, _) in plant_files(plant, cas, plant_at, here, folder, lines).items():
        (folder / name).parent.mkdir(exist_ok=True)
        (folder / name).write_text(text)
    line_routers = [Router(line, folder / line / "router.json5", at) for line, (at, _) in lines.items()]
    plant_router = Router("plant", folder / "router.json5", plant_at)
    return Layout(cells, cell_routers, line_routers, plant_router, folder / "plant-monitor.json5")


@dataclass
class Phase:
    """The phases of one kind, pooled: in-cell latencies (ms) per timed key, and the host's own delay in
    waking a thread (``WAKE``: how late ``wake_probe`` woke, where it ran), each phase's p99, and each
    group of processes' CPU (% of one core, the phases' mean)."""

    latency_ms: dict[str, tuple[float, float]] = field(default_factory=dict)  # key → (p50, p99)
    p99_by_phase: dict[str, list[float]] = field(default_factory=dict)  # key → each phase's p99, in order
    cpu: dict[str, float] = field(default_factory=dict)  # "cell routers", "line routers", "plant router", …


@dataclass
class PlantFigures:
    cells: int
    lines: int
    seconds: float
    rounds: int  # pairs of phases, the cells alone then with the plant reading
    uplink: str | None  # the interface the cells' routers sent the plant's share on (None: loopback)
    alone: Phase
    watched: Phase
    real_cell: str | None  # the real cell among them, if one ran: its own figures, as its monitor gets them
    real_alone: Phase | None
    real_watched: Phase | None
    delivered: dict[str, float]  # in-cell, per timed key: received / put
    view_behind_s: float  # the stalest cell in the plant view, at any refresh of it
    transit_p99_ms: float  # a message to the plant monitor, cell to plant
    cells_seen: int  # cells in the plant view, the fewest at the end of a phase
    derived_lost: dict[str, int]  # "monitor" / "recorder": derived messages put while it ran, not got
    derived_put: int
    recorded_bytes_per_cell_day: float
    lost_puts: int

    def to_dict(self) -> dict[str, object]:
        import dataclasses

        return dataclasses.asdict(self)


def _cpu_ticks(pids: list[int]) -> int:
    total = 0
    for pid in pids:
        with contextlib.suppress(OSError):
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])  # utime, stime
    return total


class Meter:
    """CPU of groups of processes between two readings, in % of one core."""

    def __init__(self, groups: dict[str, list[int]]) -> None:
        self.groups = groups
        self.at = (time.monotonic(), {g: _cpu_ticks(p) for g, p in groups.items()})

    def read(self) -> dict[str, float]:
        t0, before = self.at
        now, ticks = time.monotonic(), {g: _cpu_ticks(p) for g, p in self.groups.items()}
        per_s = os.sysconf("SC_CLK_TCK") * (now - t0)
        return {g: 100.0 * (ticks[g] - before[g]) / per_s for g in self.groups}


def _phase(
    timed: list[dict[str, list[tuple[int, int]]]],
    spans: list[tuple[int, int]],
    cpu: list[dict[str, float]],
    keys: tuple[str, ...] = TIMED,
) -> Phase:
    """The phases of one kind (``spans``, monotonic ns) pooled, and each one's p99; ``cpu``, each phase's
    reading (none for the real cell: its services' CPU is a group of the plant's)."""

    def within(key: str, since: int, until: int) -> list[int]:
        return [us for each in timed for t, us in each.get(key, ()) if since <= t < until]

    def ms(lat: list[int], q: float) -> float:
        return float(np.percentile(lat, q)) / 1000 if lat else float("nan")

    phase = Phase(cpu={g: float(np.mean([c[g] for c in cpu])) for g in cpu[0]} if cpu else {})
    for key in keys:
        each = [within(key, *span) for span in spans]
        pooled = [us for lat in each for us in lat]
        phase.latency_ms[key] = (ms(pooled, 50), ms(pooled, 99))
        phase.p99_by_phase[key] = [ms(lat, 99) for lat in each]
    return phase


def _start(name: str, run: list[str], logs: Path, procs: list[subprocess.Popen[bytes]], plant: bool = False,
           talks: bool = False, env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:  # fmt: skip
    """A process of the bench, its errors to a file (a pipe nobody reads would stop one that logs); it
    joins ``procs`` as it starts, so that one that fails beside it is not left running. ``plant``: at the
    plant's priority, as docs/operations.md runs the plant's routers (`nice -n 10`) and as `cadence
    plant` and `cadence record --plant` take it themselves. ``talks``: a worker, told when to start on
    its input, saying it is ready on its output."""
    from cadence.tools.plant import yield_to_cells

    pipe = subprocess.PIPE if talks else subprocess.DEVNULL
    with (logs / f"{name}.log").open("wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", *run], stdin=pipe, stdout=pipe, stderr=out, env=env,
                                preexec_fn=yield_to_cells if plant else None)  # fmt: skip
    procs.append(proc)
    return proc


def _real_env(service: str, cell: CellSpec, folder: Path, epoch_ns: int) -> dict[str, str]:
    """A real cell's service as `cadence demo --processes` configures it at speed 1 (the operator twin
    its ECG and its separation, the simulated UR16e, the shipped sets), on its own account of the cell's
    router as a deployed cell's units give it (``CADENCE_BUS_CONFIG_FILE``)."""
    from cadence.demo.options import DemoOptions
    from cadence.demo.processes import service_env
    from cadence.demo.supervise import PARENT_ENV

    data = folder / f"{cell.name}-data"
    data.mkdir(exist_ok=True)
    env = service_env(service, DemoOptions(speed=1.0), "", data, epoch_ns)
    del env["CADENCE_BUS_CONNECT"]
    own = {"CADENCE_CADENCE_CELL": cell.name, "CADENCE_BUS_CONFIG_FILE": cell.accounts[service]}
    return env | own | {PARENT_ENV: str(os.getpid())}


async def _said(proc: subprocess.Popen[bytes], what: bytes, log: Path, timeout: float = 120) -> None:
    """Until a router says ``what`` in its log; its last words if it ends first."""
    async with asyncio.timeout(timeout):
        while True:
            if what in log.read_bytes():
                return
            if proc.poll() is not None:
                said = log.read_text(errors="replace").strip().splitlines()[-1:]
                raise RuntimeError(f"{log.stem} did not start: {' '.join(said)}")
            await asyncio.sleep(0.05)


async def _ready(proc: subprocess.Popen[bytes], log: Path) -> None:
    """Until a worker (the cells', the monitor) says it is ready on a line of its own."""
    assert proc.stdout is not None
    line = await asyncio.wait_for(asyncio.to_thread(proc.stdout.readline), 300)
    if line.strip() != b"ready":
        said = log.read_text(errors="replace").strip().splitlines()[-3:]
        raise RuntimeError(f"{log.stem} did not start: {' '.join(said)}")


async def bench_plant(n_cells: int, seconds: float = 10.0, per_line: int = PER_LINE, rounds: int = ROUNDS,
                      real: bool = True, progress: Console | None = None) -> PlantFigures:  # fmt: skip
    """The plant above, run on this host: see the module's words."""
    from cadence.demo.options import ORDER

    say = progress.print if progress is not None else lambda *_: None
    procs: list[subprocess.Popen[bytes]] = []
    uplink = host_interface()
    with tempfile.TemporaryDirectory(prefix="cadence-plant-") as tmp:
        folder = Path(tmp)
        say(f"{n_cells} cells: certificates and configs")
        lay = layout(folder, n_cells, per_line, uplink, ORDER if real else ())
        try:
            on = uplink[0] if uplink else "loopback"
            say(f"{n_cells} cell routers, {len(lay.line_routers)} line routers, the plant's; uplinks on {on}")
            pids: dict[str, list[int]] = {}
            groups = {"cell routers": lay.cell_routers, "line routers": lay.line_routers,
                      "plant router": [lay.plant_router]}  # fmt: skip
            for group, members in groups.items():
                started = [_start(r.name, ["cadence", "router", "--zenoh-config", str(r.config)], folder,
                                        procs, plant=group != "cell routers") for r in members]  # fmt: skip
                await asyncio.gather(*(_said(p, b"listening", folder / f"{r.name}.log")
                                       for p, r in zip(started, members, strict=True)))  # fmt: skip
                pids[group] = [p.pid for p in started]
            if real:
                say(f"the real cell {lay.cells[0].name}: {', '.join(ORDER)}")
                cell, epoch = lay.cells[0], time.time_ns()
                envs = {s: _real_env(s, cell, folder, epoch) for s in ORDER}
                started = [
                    _start(f"{cell.name}-{s}", [f"services.{s}"], folder, procs, env=envs[s]) for s in ORDER
                ]
                pids["real cell"] = [p.pid for p in started]
            say("the cells' sessions")
            workers, outs = [], []
            synthetic = [c for c in lay.cells if not c.services]
            share = -(-len(synthetic) // WORKERS)
            # the readers first, in a process of their own (the putters wait until each is subscribed;
            # the readers, until every service of the real cell is on the bus)
            specs = [WorkerSpec(lay.cells, 0, n_cells, str(folder / "readers.json"), puts=False)]
            for w in range(0, len(synthetic), share):
                out = str(folder / f"putter{w}.json")
                specs.append(WorkerSpec(synthetic[w : w + share], w, len(synthetic), out, reads=False))
            for i, spec in enumerate(specs):
                path = folder / f"worker{i}.spec.json"
                path.write_bytes(msgspec.json.encode(spec))
                run = ["cadence.bench.plant_cells", str(path)]
                proc = _start(f"worker{i}", run, folder, procs, talks=True)
                await _ready(proc, folder / f"worker{i}.log")
                workers.append(proc)
                outs.append(Path(spec.out))
            pids["workers"] = [p.pid for p in workers]
            # rounds of two phases, the cells alone then with the plant reading, a gap before each (the
            # plant's readers start or stop in it): a host that slows down for a while slows both kinds
            t0 = time.monotonic_ns() + 500_000_000
            spans, at = [], t0 + int(WARM_S * 1e9)
            for _ in range(2 * rounds):
                spans.append((at, at + int(seconds * 1e9)))
                at = spans[-1][1] + int(GAP_S * 1e9)
            end = spans[-1][1]
            woke = folder / "wake.json"
            probe = _start("wake_probe", ["cadence.bench.wake_probe", str(end), str(woke)], folder, procs)
            for proc in workers:
                assert proc.stdin is not None
                proc.stdin.write(f"{t0} {end}\n".encode())
                proc.stdin.flush()
            cpu: dict[str, list[dict[str, float]]] = {"alone": [], "watched": []}
            seen: list[MonitorResult] = []
            recordings: list[tuple[Path, int, int]] = []  # a phase's recording, its size at its start, end
            for i, (since, until) in enumerate(spans):
                kind = ("alone", "watched")[i % 2]
                say(f"round {i // 2 + 1} of {rounds}: "
                    + ("the cells alone" if kind == "alone" else "with the plant monitor and recorder")
                    + f", {seconds:g} s")  # fmt: skip
                if kind == "alone":
                    await _until(since)
                    meter = Meter(pids)
                    await _until(until)
                    cpu[kind].append(meter.read())
                    continue
                recording = folder / f"plant{i // 2}.mcap"
                record = ["cadence", "record", "--plant", "-o", str(recording)]
                record += ["--zenoh-config", str(lay.monitor)]
                recorder = _start(f"recorder{i // 2}", record, folder, procs)
                spec_path, result = folder / f"monitor{i // 2}.spec.json", folder / f"monitor{i // 2}.json"
                linger = until + int(LINGER_S * 1e9)
                watch = MonitorSpec(str(lay.monitor), until, linger, str(result))
                spec_path.write_bytes(msgspec.json.encode(watch))
                monitor = _start(f"monitor{i // 2}", ["cadence.bench.plant_monitor", str(spec_path)], folder,
                                 procs, talks=True)  # fmt: skip
                await _ready(monitor, folder / f"monitor{i // 2}.log")
                await _until(since)
                meter = Meter({**pids, "recorder": [recorder.pid], "monitor": [monitor.pid]})
                size0 = _size(recording)
                await _until(until)
                cpu[kind].append(meter.read())
                recordings.append((recording, size0, _size(recording)))
                await _until(linger)
                recorder.send_signal(signal.SIGTERM)
                for proc in (recorder, monitor):
                    await asyncio.to_thread(proc.wait, 60)
                if recorder.returncode != 0:
                    said = (folder / f"recorder{i // 2}.log").read_text(errors="replace").strip()
                    raise RuntimeError(f"cadence record --plant: {said}")
                seen.append(msgspec.json.decode(result.read_bytes(), type=MonitorResult))
            results = []
            for proc, done in zip(workers, outs, strict=True):
                await asyncio.to_thread(proc.wait, 60)
                results.append(msgspec.json.decode(done.read_bytes(), type=WorkerResult))
            await asyncio.to_thread(probe.wait, 60)
            wake = msgspec.json.decode(woke.read_bytes(), type=list[tuple[int, int]])
            return _figures(n_cells, len(lay.line_routers), seconds, uplink[0] if uplink else None, results,
                            spans, cpu, seen, recordings, wake)  # fmt: skip
        finally:
            for proc in procs:
                if proc.poll() is None:
                    proc.terminate()
            for proc in procs:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(10)
                if proc.poll() is None:
                    proc.kill()


def _size(path: Path) -> int:
    with contextlib.suppress(OSError):
        return path.stat().st_size
    return 0


async def _until(t_ns: int) -> None:
    wait = (t_ns - time.monotonic_ns()) / 1e9
    if wait > 0:
        await asyncio.sleep(wait)


def _figures(
    n_cells: int,
    n_lines: int,
    seconds: float,
    uplink: str | None,
    results: list[WorkerResult],
    spans: list[tuple[int, int]],
    cpu: dict[str, list[dict[str, float]]],
    seen: list[MonitorResult],
    recordings: list[tuple[Path, int, int]],
    wake: list[tuple[int, int]],
) -> PlantFigures:
    from cadence.tools.recording import HEALTH_EVERY_S, read
    from schemas.topology import decode_any

    alone, watched = spans[0::2], spans[1::2]

    def while_read(t: int) -> bool:
        return any(since <= t < until for since, until in watched)

    sent = {k: sum(r.sent[c][k] for r in results for c in r.sent) for k in TIMED}
    got = {k: sum(len(r.timed[k]) for r in results) for k in TIMED}
    put = {(cell, key, t) for r in results for cell, keys in r.derived.items() for key, ts in keys.items()
           for t in ts if while_read(t)}  # fmt: skip
    # a real cell's: what its monitor session got while the plant read (its stamps are the data clock's)
    put |= {(cell, key, t) for r in results for cell, keys in r.real_derived.items()
            for key, pairs in keys.items() for t, came in pairs if while_read(came)}  # fmt: skip
    real_cell = next((cell for r in results for cell in r.real_derived), None)
    timed = [r.timed for r in results]
    real_timed = [r.real_timed for r in results if r.real_derived]
    recorded: set[tuple[str, str, int]] = set()
    per_s = []
    for recording, size0, size1 in recordings:
        health: dict[str, int] = {}  # a status key: its size (kept once every HEALTH_EVERY_S)
        for m in read(recording):
            cell, suffix = m.key.split("/", 2)[1:]
            recorded.add((cell, suffix, decode_any(m.data).t_ns))
            if suffix.startswith("health/"):
                health[m.key] = len(m.data)
        # a day: the file's growth while the cells ran (compressed chunks, one a second), and the
        # statuses at their thinned rate (their first, kept before that, says how big they are)
        per_s.append((size1 - size0) / seconds + sum(health.values()) / HEALTH_EVERY_S)
    windows = {(cell, t) for s in seen for cell, t in s.windows}
    late = [dt for s in seen for t, dt in s.transit if while_read(t)]
    return PlantFigures(
        cells=n_cells,
        lines=n_lines,
        seconds=seconds,
        rounds=len(watched),
        uplink=uplink,
        alone=_phase([*timed, {WAKE: wake}], alone, cpu["alone"], (*TIMED, WAKE)),
        watched=_phase([*timed, {WAKE: wake}], watched, cpu["watched"], (*TIMED, WAKE)),
        real_cell=real_cell,
        real_alone=_phase(real_timed, alone, []) if real_cell else None,
        real_watched=_phase(real_timed, watched, []) if real_cell else None,
        delivered={k: got[k] / sent[k] if sent[k] else float("nan") for k in TIMED},
        view_behind_s=max(s.behind_s for s in seen),
        transit_p99_ms=float(np.percentile(late, 99)) / 1e6 if late else float("nan"),
        cells_seen=min(s.cells_seen for s in seen),
        derived_lost={
            "monitor": sum(1 for c, k, t in put if k == "hrv/window" and (c, t) not in windows),
            "recorder": len(put - recorded),
        },
        derived_put=len(put),
        recorded_bytes_per_cell_day=float(np.mean(per_s)) * 86400 / n_cells,
        lost_puts=sum(r.lost_puts for r in results),
    )


def plant_table(figures: list[PlantFigures]) -> tuple[Table, Table]:
    """In the cells, per kind of phase (p50 / p99 pooled, and the arm's state's p99 in each phase, to see
    how much a phase's own p99 wanders), beside how late a thread of the host woke in the same phases (each
    phase's p99 after the arm's state's); and what the plant got: the share of the timed keys the cells'
    monitors got, the derived messages put while the plant read that its monitor (windows) and its
    recorder (windows, cycles, events) did not get, the stalest cell in its view, and its recording."""
    cells = Table(title="bench plant: in the cells (as each cell's monitor gets them); CPU in % of a core")
    for col in ("N", "plant readers", "robot/state ms", "separation ms", "host wake ms",
                "p99 by phase: robot/state; host wake",
                "cell routers", "lines", "plant", "recorder", "monitor", "cells' workers",
                "real cell"):  # fmt: skip
        cells.add_column(col, justify="right")
    for f in figures:
        pairs = [("", f.alone, f.watched)]
        if f.real_alone is not None and f.real_watched is not None:
            pairs.append(("real cell: ", f.real_alone, f.real_watched))  # its CPU: a column of the above
        for who, alone, watched in pairs:
            for name, phase in ((f"{who}none", alone), (f"{who}monitor, recorder", watched)):
                lat = [f"{phase.latency_ms[k][0]:.2f} / {phase.latency_ms[k][1]:.2f}" if k in phase.latency_ms
                       else "" for k in (*TIMED, WAKE)]  # fmt: skip
                each = "; ".join(", ".join(f"{p99:.1f}" for p99 in phase.p99_by_phase[k])
                                 for k in (TIMED[0], WAKE) if k in phase.p99_by_phase)  # fmt: skip
                cpu = [f"{phase.cpu[g]:.1f}" if g in phase.cpu else "" for g in GROUPS]
                cells.add_row(str(f.cells), name, *lat, each, *cpu)
            shift = [f"{watched.latency_ms[k][1] - alone.latency_ms[k][1]:+.2f}" if k in alone.latency_ms
                     else "" for k in (*TIMED, WAKE)]  # fmt: skip
            cells.add_row("", f"{who}p99 shift", *shift, *[""] * 8, end_section=True)
    plant = Table(title="bench plant: what the plant got")
    for col in ("N", "lines", "delivered in cells", "derived lost", "view behind s", "to plant p99 ms",
                "MB / cell-day"):  # fmt: skip
        plant.add_column(col, justify="right")
    for f in figures:
        plant.add_row(
            str(f.cells),
            str(f.lines),
            " / ".join(f"{100 * f.delivered[k]:.2f} %" for k in TIMED),
            f"{f.derived_lost['monitor']}, {f.derived_lost['recorder']} of {f.derived_put}",
            f"{f.view_behind_s:.2f}",
            f"{f.transit_p99_ms:.2f}",
            f"{f.recorded_bytes_per_cell_day / 1e6:.1f}",
        )
    return cells, plant
