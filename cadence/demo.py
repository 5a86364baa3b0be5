"""`cadence demo`: the whole closed loop on one machine, no robot and no strap (closed-loop issue).

A Zenoh router on loopback (this process), then every service as its own process, configured the way
systemd would configure it (environment variables over built-in defaults) and supervised the way systemd
would supervise it (a service that dies is restarted). The operator twin is the ECG source, in the ECG
gateway's place (no strap), and the executor runs the simulated UR16e; all of them share one data clock
running ``speed`` times faster than the wall clock. This process only watches the bus: the live view,
``summary.json`` and the figures come from what the services publish.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import math
import os
import signal
import socket
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table

from cadence.lab.marks import counted
from cadence.lab.report import event_row, from_demo, scale_row, thresholds, window_row, write_report
from cadence.lab.session import served_sets
from cadence.tools.gaps import Gaps
from common.hrv.calibration import CALIBRATION_FILE
from common.runtime.bus import Bus, BusConfig, Request
from common.runtime.clock import Clock
from common.runtime.errors import CadenceError, InputError
from common.runtime.lifetime import PARENT_ENV
from common.runtime.numeric import numeric_build
from common.runtime.resources import EXAMPLE_TASK
from common.runtime.storage import write_readable
from common.safety.states import routine_change
from common.sim.twin import TwinParams
from common.trajectory.shipped import digest_of_all
from common.trajectory.task import load_task
from schemas import (
    CellClock,
    CycleReport,
    HrvWindow,
    OperatorError,
    PlanProgress,
    Selection,
    ServiceStatus,
)
from schemas.pareto import ParetoSet
from schemas.topology import (
    CELL_CLOCK,
    DEFAULT_CELL,
    HEALTH,
    HRV_WINDOW,
    OPERATOR_ERROR,
    PLAN_PROGRESS,
    ROBOT_CYCLE,
    ROBOT_EVENT,
    ROBOT_STATE,
    SELECTION,
)
from services.decision_maker import STATE_FILE
from services.executor.persist import ExecutorStore
from services.registry import EXECUTOR, PLANNER, Need, cell, launch_order

STARTUP_TIMEOUT_S = 300.0  # wall time for every service to say it is up
DEMO_TOLERANCE = 0.7  # the twin's (common/sim/twin.py: 0.8 by default)
# from the registry and its graph: readers before writers, answerers before askers; the twin sends the
# ECG, no gateway runs
ORDER = tuple(s.name for s in launch_order() if s in cell(twin=True))
RESTART_DELAY_S = 0.5
STOP_TIMEOUT_S = 15.0


@dataclass(frozen=True, slots=True)
class DemoOptions:
    duration_s: float = 600.0  # data time
    speed: float = 8.0
    out: Path = Path("demo-out")
    seed: int = 1
    task: Path = EXAMPLE_TASK
    kill: tuple[tuple[str, float], ...] = ()  # (service, data time s): SIGKILL it then
    live: bool = True
    listen: str | None = None  # the router's endpoint; a free loopback port when None
    twin: tuple[tuple[str, bool | int | float], ...] = ()  # TwinParams fields over the demo's own
    decide: str = "paper"  # the decision maker's mode: "paper" (Alg. 1) or "personal" (DESIGN §7)
    processes: bool = False  # every service its own process on the wall clock (cadence/demo.py), not lockstep


TWIN_SOURCE = '[{ name = "twin", detects = "body", to_robot = true }]'


def twin_table(opts: DemoOptions) -> dict[str, bool | int | float]:
    """The twin's parameters in the demo: its seed, a co-worker less tolerant than the default, and what
    ``--twin`` asks."""
    return {"seed": opts.seed, "tolerance": DEMO_TOLERANCE, **dict(opts.twin)}


def inline_toml(table: dict[str, bool | int | float]) -> str:
    def value(v: bool | int | float) -> str:
        return ("true" if v else "false") if isinstance(v, bool) else repr(v)

    return "{ " + ", ".join(f"{k} = {value(v)}" for k, v in table.items()) + " }"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Supervised:
    """One service process, restarted when it dies (systemd's Restart=always, RestartSec=0.5)."""

    name: str
    env: dict[str, str]
    log: Path
    proc: asyncio.subprocess.Process | None = None
    restarts: int = 0
    exit_code: int | None = None  # at the end: after SIGTERM

    async def supervise(self, stopping: asyncio.Event, on_restart) -> None:
        """Until ``stopping``: never a start once it is set (a service that died just before the end was
        once started again after the stop had passed it, and ran alone until killed)."""
        with self.log.open("ab") as log:
            while not stopping.is_set():
                # from the loop's thread, and with PARENT_ENV: the service dies with the demo (SIGKILL too)
                # a session of its own: a terminal's Ctrl-C reaches the demo alone, which stops the services
                # in order with one SIGTERM each (a service's second signal forces its exit)
                self.proc = await asyncio.create_subprocess_exec(
                    sys.executable,
                    "-m",
                    f"services.{self.name}",
                    env=self.env | {PARENT_ENV: str(os.getpid())},
                    stdout=log,
                    stderr=log,
                    start_new_session=True,
                )
                if stopping.is_set():  # the stop came while it started: it passed this process by
                    await self.stop()
                rc = await self.proc.wait()
                if stopping.is_set():
                    self.exit_code = rc
                    return
                self.restarts += 1
                on_restart(self.name, rc)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stopping.wait(), RESTART_DELAY_S)

    def kill(self) -> None:
        if self.proc is not None and self.proc.returncode is None:
            self.proc.send_signal(signal.SIGKILL)

    async def stop(self) -> None:
        if self.proc is None or self.proc.returncode is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            await asyncio.wait_for(self.proc.wait(), STOP_TIMEOUT_S)
        except TimeoutError:
            self.proc.kill()


@dataclass
class Observed:
    """What the demo saw on the bus, on data time (seconds from the epoch)."""

    epoch_ns: int
    windows: list[dict] = field(default_factory=list)
    selections: list[dict] = field(default_factory=list)
    cycles: list[CycleReport] = field(default_factory=list)
    marked: list[OperatorError] = field(default_factory=list)  # operator/error as it came
    events: list[dict] = field(default_factory=list)
    scale: list[dict] = field(default_factory=list)  # report.scale_row
    gaps: Gaps = field(default_factory=Gaps)  # what the senders' numbers say this observer missed

    def watch(self, key: str, fn: Callable[[Any], None]) -> Callable[[str, Any], Awaitable[None]]:
        """A handler of one sender's key that also notes the message's number."""

        async def handler(_: str, msg: Any) -> None:
            self.gaps.note(key, msg.seq)
            fn(msg)

        return handler

    @property
    def n_cycles(self) -> int:
        """The cycles the executor reported, by its numbers: those seen and those it sent unseen."""
        return len(self.cycles) + sum(n for k, n in self.gaps.missed.items() if k.endswith("/robot/cycle"))

    @property
    def error_times_s(self) -> list[float]:
        """When each error that counts was marked (cadence/lab/marks.py: a withdrawn mark does not)."""
        return [self.t(e.t_ns) for e in counted(self.marked)]

    @property
    def errors(self) -> int:
        return len(self.error_times_s)

    def t(self, t_ns: int) -> float:
        return round((t_ns - self.epoch_ns) / 1e9, 3)

    def on_window(self, w: HrvWindow) -> None:
        self.windows.append(window_row(w, self.t(w.end_ns)))

    def on_selection(self, s: Selection) -> None:
        last = self.selections[-1] if self.selections else None
        key = self.t(s.window_end_ns) if s.window_end_ns else None
        if last is not None and (last["window_end_s"], last["k"]) == (key, s.k):
            return  # the periodic republication of the same decision
        self.selections.append(
            {
                "t_s": max(0.0, self.t(s.t_ns)),
                "k": s.k,
                "delta": s.delta,
                "reason": s.reason,
                "window_end_s": key,
                **thresholds(s),
            }
        )

    def on_event(
        self,
        source: str,
        kind: str,
        message: str,
        t_ns: int,
        change: tuple[str | None, str | None] = (None, None),
    ) -> None:
        """``change``: a state change's (from, to) states."""
        if kind == "state" and routine_change(*change):
            return
        self.events.append(event_row(self.t(t_ns), source, kind, message, change))

    def k_steps(self) -> tuple[int, int]:
        ks = [s["k"] for s in self.selections]
        down = sum(1 for a, b in itertools.pairwise(ks) if b < a)
        up = sum(1 for a, b in itertools.pairwise(ks) if b > a)
        return down, up


def service_env(name: str, opts: DemoOptions, endpoint: str, data: Path, epoch_ns: int) -> dict[str, str]:
    """What a systemd unit's EnvironmentFile would hold for this service in the demo."""
    env = {
        **os.environ,
        "CADENCE_BUS_CONNECT": f"['{endpoint}']",
        "CADENCE_DATA_DIR": str(data),
        "CADENCE_CADENCE_SPEED": repr(opts.speed),
        "CADENCE_CADENCE_EPOCH_NS": str(epoch_ns),
        "CADENCE_CADENCE_STATUS_PERIOD_S": "1.0",
        "CADENCE_CADENCE_LOG_FORMAT": "text",
    }
    for key, value in demo_settings(opts).get(name, {}).items():
        env[f"CADENCE_{name.upper()}_{key.upper()}"] = value
    return env


def demo_settings(opts: DemoOptions) -> dict[str, dict[str, str]]:
    """Each service's settings in the demo beyond its built-in defaults, as a deployment config's
    ``[service]`` tables would hold them (values in TOML; a bare word is a string): what it needs of the
    cell (services/registry.py), given as the demo's cell has it."""
    twin = twin_table(opts)
    given: dict[Need, dict[str, str]] = {
        "task": {"task": str(opts.task)},
        "resting_rr": {"rr_rest_s": repr(TwinParams().rr_rest_s)},
        "decide": {"decide": opts.decide},
        # a co-worker less tolerant than the twin's default: the example task's waits for the operator
        # (B2 clear, the parts) leave the arm idle part of each cycle, and the demo should show Alg. 1 at
        # work, stress first and relief after, within its first minutes
        "twin": {"twin": inline_toml(twin)},
        "strap": {},  # no strap: the twin is the cell's ECG source
        # no person stands at a pendant: a stop (the sim's watchdog on a loaded host) resumes by itself,
        # said in the events, rather than ending the demo's cycles until `cadence robot resume`
        "robot": {"backend": "sim", "start_selection": "last", "resume_policy": "auto"},
        # the twin walks into the shared area now and then: speed and separation monitoring, unless the
        # twin is told to publish no distance (then nothing would free the arm); the twin is the cell's
        # one source: a tracker that sees the body and measures to the arm
        "separation": {
            "separation": "true" if twin.get("separation", True) else "false",
            "separation_sources": TWIN_SOURCE,
        },
    }
    return {s.name: {k: v for need in s.needs for k, v in given[need].items()} for s in cell(twin=True)}


def live_view(obs: Observed, opts: DemoOptions, now_s: float, procs: dict[str, Supervised]) -> Group:
    shown = min(now_s, opts.duration_s)  # the run ends at its duration, whatever a late message says
    pace = (f"at {opts.speed:g}×" if opts.processes else f"lockstep, at most {opts.speed:g}×"
            if math.isfinite(opts.speed) else "lockstep, as fast as the host allows")  # fmt: skip
    t = Table(title=f"cadence demo — data time {shown:6.0f} / {opts.duration_s:.0f} s {pace}")
    for col in ("mean RR (last window)", "movement", "k", "cycles", "last cycle", "errors", "restarts"):
        t.add_column(col, justify="right")
    w = obs.windows[-1] if obs.windows else None
    rr = f"{w['mean_rr_s']:.3f} s ({w['quality']})" if w and w["mean_rr_s"] else "—"
    moved = f"{w['movement_mg']:.0f} mg" if w and w.get("movement_mg") is not None else "—"
    k = str(obs.selections[-1]["k"]) if obs.selections else "—"
    last = f"{obs.cycles[-1].cycle_time_s:.1f} s" if obs.cycles else "—"
    restarts = ", ".join(f"{n} {p.restarts}" for n, p in procs.items() if p.restarts) or "none"
    t.add_row(rr, moved, k, str(obs.n_cycles), last, str(obs.errors), restarts)
    ev = Table(show_header=False, box=None)
    for e in obs.events[-5:]:
        ev.add_row(f"{e['t_s']:7.1f} s", e["source"], e["kind"], e["message"][:90])
    stops = sum(e["kind"] == "protective_stop" for e in obs.events)
    if stops:  # what a person sees first and should not misread as the method's doing
        t.caption = (
            f"{stops} protective stop(s): the servo loop missed its deadlines, as a busy machine "
            f"does at {opts.speed:g}× (try a lower --speed); the demo resumes by itself, a real cell does not"
        )
    return Group(t, ev)


def fresh_start(data: Path) -> None:
    """A demo starts from a rested operator and a simulated arm no earlier demo left stopped or killed
    mid-path (a real executor's restart keeps both as a stop: services/executor/persist.py)."""
    for stale in (STATE_FILE, CALIBRATION_FILE):
        (data / stale).unlink(missing_ok=True)
    executor = ExecutorStore(data / EXECUTOR.name)
    executor.load()
    executor.forget_stop()  # an unchanged record is not written


async def run_demo(opts: DemoOptions, console: Console) -> dict:
    task = load_task(opts.task)
    opts.out.mkdir(parents=True, exist_ok=True)
    data, logs = opts.out / "data", opts.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    fresh_start(data)
    endpoint = opts.listen or f"tcp/127.0.0.1:{free_port()}"
    stopping = asyncio.Event()
    procs: dict[str, Supervised] = {}
    tasks: list[asyncio.Task] = []
    obs = Observed(epoch_ns=time.time_ns())
    cut_short_s: float | None = None  # data time run, when Ctrl-C ended it early

    def on_restart(name: str, rc: int) -> None:
        obs.on_event(
            "demo", "restart", f"{name} exited with {rc}; restarted", Clock(opts.speed, obs.epoch_ns).now_ns()
        )

    async def stop_all() -> None:
        """The robot first, the store last, each with SIGTERM; their exit codes are kept."""
        stopping.set()
        for name in reversed(list(procs)):
            await procs[name].stop()
        await asyncio.gather(*tasks, return_exceptions=True)

    def start(name: str, epoch_ns: int) -> None:
        p = Supervised(name, service_env(name, opts, endpoint, data, epoch_ns), logs / f"{name}.log")
        procs[name] = p
        tasks.append(asyncio.create_task(p.supervise(stopping, on_restart)))

    async with await Bus.open(BusConfig(mode="router", listen=[endpoint]), DEFAULT_CELL, role="demo") as bus:
        console.print(
            f"the demo cell's router: {endpoint}; join it with --connect {endpoint} "
            f"(`cadence record -o run.mcap --connect {endpoint}`, `cadence session --connect {endpoint} …`)"
        )
        try:
            # 1. the store first: it plans what it lacks, before the operator's clock starts
            health = aiter(bus.subscribe(HEALTH.at(PLANNER.name), maxsize=1))
            with console.status("planning the task's Pareto sets (once; they are stored) …") as status:

                def on_progress(pr: PlanProgress) -> None:
                    status.update(
                        f"Pareto sets: {pr.done_paths}/{pr.total_paths} ready ('{pr.path_id}' {pr.state})"
                    )

                bus.handle(PLAN_PROGRESS, _call(on_progress))
                start(PLANNER.name, obs.epoch_ns)
                async with asyncio.timeout(600):
                    while (await anext(health))[1].state != "serving":
                        pass
            # 2. the clock starts; everyone else joins
            epoch_ns = obs.epoch_ns = time.time_ns()
            clock = Clock(opts.speed, epoch_ns)

            async def tell_clock(_: Request) -> CellClock:  # a tool joining the cell stamps on its time
                return CellClock(t_ns=clock.now_ns(), seq=0, epoch_ns=epoch_ns, speed=opts.speed)

            bus.serve(CELL_CLOCK, tell_clock)
            watch(bus, obs)
            running: set[str] = set()
            all_up = asyncio.Event()

            def on_status(st: ServiceStatus) -> None:
                running.add(st.service)
                if running >= set(ORDER):
                    all_up.set()

            bus.handle(HEALTH, _call(on_status))
            for name in (n for n in ORDER if n != PLANNER.name):
                start(name, epoch_ns)
            # the run's duration counts from when every service is up: on a slow or loaded machine their start
            # (imports, sessions) can take longer than a short run, which would then end before it began
            with console.status("starting the services …"):
                try:
                    async with asyncio.timeout(STARTUP_TIMEOUT_S):
                        await all_up.wait()
                except TimeoutError:
                    await stop_all()
                    missing = ", ".join(sorted(set(ORDER) - running))
                    raise CadenceError(
                        f"{missing} did not start within {STARTUP_TIMEOUT_S:.0f} s; their logs are in {logs}"
                    ) from None
        except asyncio.CancelledError:  # Ctrl-C while planning or starting: no data time ran
            taking_the_interrupt(console)
            await stop_all()
            raise interrupted_before_data_time(opts) from None
        kills = sorted(opts.kill, key=lambda k: k[1])
        began_ns = clock.now_ns()
        end_ns = began_ns + round(opts.duration_s * 1e9)
        live = Live(console=console, refresh_per_second=4, transient=False) if opts.live else None
        try:
            if live is not None:
                live.start()
            while (now := clock.now_ns()) < end_ns:
                now_s = (now - epoch_ns) / 1e9
                while kills and kills[0][1] <= now_s:
                    name, _ = kills.pop(0)
                    obs.on_event("demo", "kill", f"SIGKILL {name}", now)
                    procs[name].kill()
                if live is not None:
                    live.update(live_view(obs, opts, now_s, procs))
                await asyncio.sleep(0.1)
        except asyncio.CancelledError:  # Ctrl-C: what ran is still summarised and reported, as cut short
            taking_the_interrupt(console)
            cut_short_s = (clock.now_ns() - began_ns) / 1e9
            console.print(f"interrupted after {cut_short_s:.0f} s of data time: stopping, then the summary")
        finally:
            if live is not None:
                live.stop()
        # 3. the sets the executor used, for the figures, while the store still answers
        sets = await served_sets(bus, task.paths, timeout=5.0)
        # 4. stop; exit codes are checked
        await stop_all()

    ran_s = cut_short_s if cut_short_s is not None else opts.duration_s
    restarts = {n: p.restarts for n, p in procs.items()}
    exit_codes = {n: p.exit_code for n, p in procs.items()}
    return summarise(obs, opts, ran_s, cut_short_s is not None, restarts, exit_codes, sets, console)


def watch(bus: Bus, obs: Observed) -> None:
    """The demo's observer on the cell's bus: what the summary and the report are made of."""
    # each of these has one sender, whose numbers say what this observer missed (cadence/tools/gaps.py)
    bus.handle(HRV_WINDOW, obs.watch(bus.key(HRV_WINDOW.suffix), obs.on_window))
    bus.handle(SELECTION, obs.watch(bus.key(SELECTION.suffix), obs.on_selection))
    bus.handle(ROBOT_CYCLE, obs.watch(bus.key(ROBOT_CYCLE.suffix), obs.cycles.append))
    bus.handle(
        ROBOT_EVENT,
        obs.watch(
            bus.key(ROBOT_EVENT.suffix),
            lambda e: obs.on_event(EXECUTOR.name, e.kind, e.message, e.t_ns, (e.from_state, e.to_state)),
        ),
    )

    bus.handle(OPERATOR_ERROR, _call(obs.marked.append))
    bus.handle(ROBOT_STATE, _call(lambda m: scale_row(obs.scale, m, obs.t(m.t_ns))))


def summarise(
    obs: Observed,
    opts: DemoOptions,
    ran_s: float,
    cut_short: bool,
    restarts: dict[str, int],
    exit_codes: dict[str, int | None],
    sets: dict[str, ParetoSet],
    console: Console,
) -> dict[str, Any]:
    """``summary.json`` and the report (index.html and its figures) of a run, in its folder."""
    if ran_s <= 0 or (cut_short and ran_s < 1.0):  # a second of data time or less: nothing to say
        raise interrupted_before_data_time(opts)
    down, up = obs.k_steps()
    minutes = ran_s / 60.0
    cycles = obs.n_cycles
    if said := obs.gaps.said():
        console.print(said, style="yellow")
    summary = {
        "duration_s": round(ran_s, 3),
        "cut_short": cut_short,
        "speed": opts.speed if math.isfinite(opts.speed) else "max",
        "cell": "processes" if opts.processes else "lockstep",
        "cycles": cycles,
        "productivity_per_min": round(cycles / minutes, 3),
        "errors": obs.errors,
        "error_rate": round(obs.errors / cycles, 4) if cycles else 0.0,
        "error_times_s": obs.error_times_s,
        "windows": obs.windows,
        "selections": [{k: v for k, v in s.items() if k != "window_end_s"} for s in obs.selections],
        "k_steps_down": down,
        "k_steps_up": up,
        "restarts": restarts,
        "exit_codes": exit_codes,
        "cycle_times_s": [round(c.cycle_time_s, 3) for c in obs.cycles],
        "cycle_ends_s": [obs.t(c.t_ns) for c in obs.cycles],
        "cycle_k": [dict(c.k_per_path) for c in obs.cycles],
        "events": obs.events,
        "scale": obs.scale,
        # by key, messages the cell sent that the observer did not see (their figures above are missing)
        "unseen": {k.split("/", 2)[-1]: n for k, n in obs.gaps.missed.items() if n},
        # what the run computed on: the planned sets, all of them or no digest (the same bytes on every
        # machine when shipped, common/trajectory/shipped.py), and numpy's kernels and BLAS here
        # (common/runtime/numeric.py)
        "sets_sha256": digest_of_all(sets, load_task(opts.task).paths),
        "build": numeric_build(),
    }
    kept = keep_summary(opts.out, json.dumps(summary, indent=1).encode(), console)
    reported = kept.parent == opts.out  # a folder that could not take the summary takes no report either
    if reported:
        try:
            run = from_demo(opts.out)  # the report of the run (cadence/lab/report.py), into the run's folder
            run.sets.update(sets)
            write_report(run, opts.out, TwinParams().rr_rest_s)
        except (OSError, InputError) as exc:
            why = exc.strerror or exc if isinstance(exc, OSError) else exc
            console.print(f"{opts.out}: the report could not be written ({why}); the summary holds the "
                          "run's figures", style="red")  # fmt: skip
            reported = False
    # where it all went, for the last line the command prints (not in the file)
    return {**summary, "written": {"summary": str(kept), "report": reported}}


LOCK_FILE = ".cadence-demo.lock"


def claim(folder: Path, force: bool = False) -> IO[str] | None:
    """The run's folder for this run alone: two demos into one folder both said "written", and one's log
    was lost. Held (an advisory lock) for as long as the returned file is open; ``force``: not taken."""
    import fcntl

    if force:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        f = (folder / LOCK_FILE).open("a+")
    except OSError as exc:
        raise InputError(f"{folder}: cannot be used for the run: {exc.strerror or exc}") from None
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.seek(0)
        who = f.read().strip() or "another process"
        f.close()
        raise InputError(f"{folder}: another demo writes there ({who}): give another --out, or --force "
                         "to share it") from None  # fmt: skip
    f.seek(0)
    f.truncate()
    f.write(f"pid {os.getpid()}\n")
    f.flush()
    return f


class NothingRan(CadenceError):
    """Interrupted before the cell's data time ran: there is nothing to summarise or report."""


def taking_the_interrupt(console: Console) -> None:
    """The first Ctrl-C (or SIGTERM), caught: the task goes on to stop the cell and write what ran (its
    cancellation taken back, so the waits that follow keep their own timeouts), and a second one says so
    rather than cutting the summary and the report off half-written."""
    if (me := asyncio.current_task()) is not None:
        me.uncancel()

    def again(*_: object) -> None:
        console.print("already stopping: the summary and the report follow", style="yellow")

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, again)


def interrupted_before_data_time(opts: DemoOptions) -> NothingRan:
    return NothingRan(f"interrupted before the cell's data time ran: nothing to summarise in {opts.out}")


def keep_summary(out: Path, data: bytes, console: Console) -> Path:
    """``summary.json`` in ``out``; where that folder cannot take it (a full disk, no permission), in a
    new folder under the system's temporary one, said in one line: an hour's run keeps its results."""
    try:
        write_readable(out / "summary.json", data)
        return out / "summary.json"
    except OSError as exc:
        why = exc.strerror or str(exc)
    elsewhere = Path(tempfile.mkdtemp(prefix="cadence-demo-")) / "summary.json"
    try:
        write_readable(elsewhere, data)
    except OSError as exc:
        console.print(f"{out}: cannot write summary.json ({why}), nor {elsewhere.parent} "
                      f"({exc.strerror or exc}): the summary is lost", style="red")  # fmt: skip
        return out / "summary.json"
    console.print(f"{out}: cannot write summary.json ({why}); it is in {elsewhere} instead", style="red")
    return elsewhere


def _call(fn):
    async def handler(_: str, msg) -> None:
        fn(msg)

    return handler


def summary_table(summary: dict[str, Any], wall_s: float) -> Table:
    """The demo's figures on the terminal: what ``summary.json`` holds, in one row."""
    cut = " (cut short)" if summary["cut_short"] else ""
    table = Table(title=f"cadence demo: {summary['duration_s']:g} s of data time in {wall_s:.0f} s{cut}")
    columns = (
        "cycles",
        "φ [cycles/min]",
        "errors",
        "ε [errors/cycle]",
        "windows",
        "k steps ↓ / ↑",
        "restarts",
    )
    for col in columns:
        table.add_column(col, justify="right")
    table.add_row(
        str(summary["cycles"]),
        f"{summary['productivity_per_min']:.2f}",
        str(summary["errors"]),
        f"{summary['error_rate']:.3f}",
        str(len(summary["windows"])),
        f"{summary['k_steps_down']} / {summary['k_steps_up']}",
        ", ".join(f"{k} {v}" for k, v in summary["restarts"].items() if v) or "none",
    )
    return table
