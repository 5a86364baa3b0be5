"""`cadence bench plant --cells N`: a plant of N synthetic cells as deployed, on this host. Each cell has
its own router (`cadence router`, mTLS, its own CA, the cell's generated access control) and its services'
accounts, each on its own session, putting a cell's traffic at speed 1 (``plant_cells.PROFILE``: 81
messages and 20 kB a second); every line of ``per_line`` cells has a line router that reads its cells, and
the plant's router reads the lines, as `cadence plant-router` and `cadence install --plant` configure them.

It runs two phases of the same length: the cells alone, then with the plant monitor (`cadence plant`'s
view, here in the bench's own process) and the plant recorder (`cadence record --plant`, a process of its
own) reading every cell through the line and plant routers. Per phase: the arm's state and the separation
as each cell's monitor session gets them, p50/p99 (the in-cell figures a plant must not move), and each
group of processes' CPU; then how far behind the plant's view ever was, whether the plant got every
derived message (each cell's windows, cycles and events, by their stamps) and how many bytes a cell's
plant recording takes a day.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
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

PER_LINE = 10  # cells behind one line router
GROUPS = ("cell routers", "line routers", "plant router", "recorder", "monitor", "workers")  # CPU, by process
WORKERS = 2  # processes putting the cells' traffic (this host has 2 cores)
WARM_S, GAP_S = 2.0, 4.0  # before the first phase; between them (the plant's readers connect)


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

    def endpoint(self) -> str:
        while True:
            port, self.next = self.next, self.next + 1
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", port))
                except OSError:
                    continue
            return f"tls/127.0.0.1:{port}"


def layout(folder: Path, n_cells: int, per_line: int = PER_LINE) -> Layout:
    """Every router's and account's config for a plant of ``n_cells``, as a deployment writes them: each
    cell its own CA and its router built for a plant (``router_config(…, plant=True)``), the line and
    plant routers and the monitor as `cadence plant-router` writes them (``plant_files``)."""
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
        cas[name] = (endpoint, ca.cert)
        passwords = {a: f"pw-{name}-{a}" for a in ACCOUNTS}
        users = folder / f"{name}.users"
        users.write_text(users_of(name, passwords) + f"{PLANT}:{plant.password}\n")
        leaf = issue(ca, identity(name, "router"), name, here)
        tls = Tls(ca.cert + plant.ca.cert, leaf.cert, leaf.key)  # the plant's CA beside its own
        cfg = router_config(name, [endpoint], tls, str(users), plant=True)
        cell_routers.append(Router(name, write(f"{name}-router", cfg), endpoint))
        configs = {}
        for role in (*PUTTERS, "monitor"):
            leaf = issue(ca, identity(name, role), name, [role])
            cfg = client_config(name, role, passwords[role], [endpoint], Tls(ca.cert, leaf.cert, leaf.key))
            configs[role] = str(write(identity(name, role), cfg))
        reader = configs.pop("monitor")
        cells.append(CellSpec(name, configs, reader))
    plant_at = ports.endpoint()
    for name, (text, _) in plant_files(plant, cas, plant_at, here, folder, lines).items():
        (folder / name).parent.mkdir(exist_ok=True)
        (folder / name).write_text(text)
    line_routers = [Router(line, folder / line / "router.json5", at) for line, (at, _) in lines.items()]
    plant_router = Router("plant", folder / "router.json5", plant_at)
    return Layout(cells, cell_routers, line_routers, plant_router, folder / "plant-monitor.json5")


@dataclass
class Phase:
    """One phase's figures: in-cell latencies (ms) per timed key, and the routers' CPU (% of one core)."""

    latency_ms: dict[str, tuple[float, float]] = field(default_factory=dict)  # key → (p50, p99)
    cpu: dict[str, float] = field(default_factory=dict)  # "cell routers", "line routers", "plant router", …


@dataclass
class PlantFigures:
    cells: int
    lines: int
    seconds: float
    alone: Phase
    watched: Phase
    delivered: dict[str, float]  # in-cell, per timed key: received / put
    view_behind_s: float  # the stalest cell in the plant view, at any refresh of it
    transit_p99_ms: float  # a message to the plant monitor, cell to plant
    cells_seen: int  # cells in the plant view at the end
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


def _latencies(results: list[WorkerResult], since: int, until: int) -> dict[str, tuple[float, float]]:
    out = {}
    for key in TIMED:
        lat = [us for r in results for t, us in r.timed[key] if since <= t < until]
        out[key] = (float(np.percentile(lat, 50)) / 1000, float(np.percentile(lat, 99)) / 1000) if lat else (
            float("nan"), float("nan"))  # fmt: skip
    return out


async def _start_router(router: Router, logs: Path, procs: list[subprocess.Popen[bytes]]) -> int:
    """`cadence router` on the router's config, once it says it listens (its pid); what it says goes to a
    file (a pipe nobody reads would stop a router that logs). It joins ``procs`` as it starts, so that a
    router that fails beside it is not left running."""
    log = logs / f"{router.name}.log"
    with log.open("wb") as out:
        run = [sys.executable, "-m", "cadence", "router", "--zenoh-config", str(router.config)]
        proc = subprocess.Popen(run, stdout=subprocess.DEVNULL, stderr=out)
    procs.append(proc)
    async with asyncio.timeout(120):
        while b"listening" not in log.read_bytes():
            if proc.poll() is not None:
                said = log.read_text(errors="replace").strip().splitlines()[-1:]
                raise RuntimeError(f"the router {router.name} did not start: {' '.join(said)}")
            await asyncio.sleep(0.05)
    return proc.pid


async def bench_plant(n_cells: int, seconds: float = 10.0, per_line: int = PER_LINE,
                      progress: Console | None = None) -> PlantFigures:  # fmt: skip
    """The plant above, run on this host: see the module's words."""
    from cadence.tools.plant import Plant, plant_watch
    from common.runtime.bus import Bus, BusConfig
    from schemas.topology import decode_any

    say = progress.print if progress is not None else lambda *_: None
    procs: list[subprocess.Popen[bytes]] = []
    with tempfile.TemporaryDirectory(prefix="cadence-plant-") as tmp:
        folder = Path(tmp)
        say(f"{n_cells} cells: certificates and configs")
        lay = layout(folder, n_cells, per_line)
        try:
            say(f"{n_cells} cell routers, {len(lay.line_routers)} line routers, the plant's router")
            routers = {"cell routers": lay.cell_routers, "line routers": lay.line_routers,
                       "plant router": [lay.plant_router]}  # fmt: skip
            pids: dict[str, list[int]] = {}
            for group, members in routers.items():
                pids[group] = list(await asyncio.gather(*(_start_router(r, folder, procs) for r in members)))
            say("the cells' sessions")
            workers, outs = [], []
            share = -(-n_cells // WORKERS)
            # the readers first, in a process of their own (the putters wait until each is subscribed)
            specs = [WorkerSpec(lay.cells, 0, n_cells, str(folder / "readers.json"), puts=False)]
            for w in range(0, n_cells, share):
                result = str(folder / f"putter{w}.json")
                specs.append(WorkerSpec(lay.cells[w : w + share], w, n_cells, result, reads=False))
            for i, spec in enumerate(specs):
                path = folder / f"worker{i}.spec.json"
                path.write_bytes(msgspec.json.encode(spec))
                proc = subprocess.Popen([sys.executable, "-m", "cadence.bench.plant_cells", str(path)],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE)  # fmt: skip
                procs.append(proc)
                workers.append(proc)
                outs.append(Path(spec.out))
                assert proc.stdout is not None
                line = await asyncio.wait_for(asyncio.to_thread(proc.stdout.readline), 300)
                if line.strip() != b"ready":
                    raise RuntimeError("a worker of the cells did not start (its error is above)")
            pids["workers"] = [p.pid for p in workers]
            t0 = time.monotonic_ns() + 500_000_000
            a0 = t0 + int(WARM_S * 1e9)
            a1 = a0 + int(seconds * 1e9)
            b0 = a1 + int(GAP_S * 1e9)
            b1 = b0 + int(seconds * 1e9)
            for proc in workers:
                assert proc.stdin is not None
                proc.stdin.write(f"{t0} {b1}\n".encode())
                proc.stdin.flush()
            say(f"the cells alone, {seconds:g} s")
            await _until(a0)
            meter = Meter(pids)
            await _until(a1)
            alone_cpu = meter.read()
            say(f"with the plant monitor and recorder, {seconds:g} s")
            recording = folder / "plant.mcap"
            record = ["record", "--plant", "-o", str(recording), "--zenoh-config", str(lay.monitor)]
            recorder = subprocess.Popen([sys.executable, "-m", "cadence", *record], stdout=subprocess.DEVNULL,
                                        stderr=subprocess.PIPE)  # fmt: skip
            procs.append(recorder)
            plant, transit = Plant(), []
            windows: set[tuple[str, int]] = set()  # (cell, t_ns) of each window the monitor got
            behind = 0.0
            async with await Bus.open(BusConfig(config_file=str(lay.monitor)), "plant") as bus:

                def came(key: str, payload: bytes) -> None:
                    now = time.monotonic_ns()
                    plant.on(key, payload, now / 1e9)
                    with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
                        msg = decode_any(payload)
                        transit.append((msg.t_ns, now - msg.t_ns))
                        if key.endswith("/hrv/window"):
                            windows.add((key.split("/")[1], msg.t_ns))

                for key in plant_watch():
                    bus.subscribe_raw(key, came)
                await _until(b0)
                pids["recorder"], pids["monitor"] = [recorder.pid], [os.getpid()]
                meter = Meter(pids)
                grown = [(time.monotonic(), _size(recording))]  # the recording's growth, as it flushes
                while time.monotonic_ns() < b1:  # the view, refreshed as `cadence plant` does (2 Hz)
                    await asyncio.sleep(0.5)
                    now = time.monotonic()
                    Console(file=io.StringIO(), width=200).print(plant.view(now=now))
                    ages = [now - c.robot[0] for c in plant.cells.values() if c.robot is not None]
                    behind = max(behind, *ages)
                grown.append((time.monotonic(), _size(recording)))
                watched_cpu = meter.read()
            recorder.send_signal(signal.SIGTERM)
            _, err = await asyncio.to_thread(recorder.communicate, timeout=60)
            if recorder.returncode != 0:
                raise RuntimeError(f"cadence record --plant: {err.decode(errors='replace').strip()}")
            results = []
            for proc, done in zip(workers, outs, strict=True):
                await asyncio.to_thread(proc.wait, 60)
                results.append(msgspec.json.decode(done.read_bytes(), type=WorkerResult))
            phases = (a0, a1, b0, b1)
            return _figures(n_cells, len(lay.line_routers), seconds, results, phases, alone_cpu, watched_cpu,
                            len(plant.cells), transit, windows, behind, recording, grown)  # fmt: skip
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
    results: list[WorkerResult],
    phases: tuple[int, int, int, int],
    alone_cpu: dict[str, float],
    watched_cpu: dict[str, float],
    cells_seen: int,
    transit: list[tuple[int, int]],
    windows: set[tuple[str, int]],
    behind: float,
    recording: Path,
    grown: list[tuple[float, int]],
) -> PlantFigures:
    from cadence.tools.recording import HEALTH_EVERY_S, read
    from schemas.topology import decode_any

    a0, a1, b0, b1 = phases
    sent = {k: sum(r.sent[c][k] for r in results for c in r.sent) for k in TIMED}
    got = {k: sum(len(r.timed[k]) for r in results) for k in TIMED}
    put = {(cell, key, t) for r in results for cell, keys in r.derived.items() for key, ts in keys.items()
           for t in ts if b0 <= t < b1}  # fmt: skip
    recorded: set[tuple[str, str, int]] = set()
    health: dict[str, int] = {}  # a status key: its size (kept once every HEALTH_EVERY_S)
    for m in read(recording):
        cell, suffix = m.key.split("/", 2)[1:]
        recorded.add((cell, suffix, decode_any(m.data).t_ns))
        if suffix.startswith("health/"):
            health[m.key] = len(m.data)
    # a day: the file's growth while the cells ran (compressed chunks, one a second), and the statuses
    # at their thinned rate (their first, kept before that, says how big they are)
    (t0, size0), (t1, size1) = grown
    per_s = (size1 - size0) / (t1 - t0) + sum(health.values()) / HEALTH_EVERY_S
    per_day = per_s * 86400 / n_cells
    late = [dt for t, dt in transit if b0 <= t < b1]
    return PlantFigures(
        cells=n_cells,
        lines=n_lines,
        seconds=seconds,
        alone=Phase(_latencies(results, a0, a1), alone_cpu),
        watched=Phase(_latencies(results, b0, b1), watched_cpu),
        delivered={k: got[k] / sent[k] if sent[k] else float("nan") for k in TIMED},
        view_behind_s=behind,
        transit_p99_ms=float(np.percentile(late, 99)) / 1e6 if late else float("nan"),
        cells_seen=cells_seen,
        derived_lost={
            "monitor": sum(1 for c, k, t in put if k == "hrv/window" and (c, t) not in windows),
            "recorder": len(put - recorded),
        },
        derived_put=len(put),
        recorded_bytes_per_cell_day=per_day,
        lost_puts=sum(r.lost_puts for r in results),
    )


def plant_table(figures: list[PlantFigures]) -> tuple[Table, Table]:
    """In the cells, per phase (p50 / p99); and what the plant got: the share of the timed keys the cells'
    monitors got, the derived messages put while the plant read that its monitor (windows) and its
    recorder (windows, cycles, events) did not get, the stalest cell in its view, and its recording."""
    cells = Table(title="bench plant: in the cells (as each cell's monitor gets them); CPU in % of a core")
    for col in ("N", "plant readers", "robot/state ms", "separation ms", "cell routers", "lines", "plant",
                "recorder", "monitor", "cells' workers"):  # fmt: skip
        cells.add_column(col, justify="right")
    for f in figures:
        for name, phase in (("none", f.alone), ("monitor, recorder", f.watched)):
            lat = [f"{phase.latency_ms[k][0]:.2f} / {phase.latency_ms[k][1]:.2f}" for k in TIMED]
            cpu = [f"{phase.cpu[g]:.1f}" if g in phase.cpu else "" for g in GROUPS]
            cells.add_row(str(f.cells), name, *lat, *cpu)
        shift = [f"{f.watched.latency_ms[k][1] - f.alone.latency_ms[k][1]:+.2f}" for k in TIMED]
        cells.add_row("", "p99 shift", *shift, *[""] * 6, end_section=True)
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
