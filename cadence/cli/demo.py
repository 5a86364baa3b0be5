"""`cadence demo`: the whole closed loop on this machine (the work: cadence/demo/)."""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import time
import tomllib
from collections.abc import Coroutine
from pathlib import Path
from typing import Any, TypeVar

import msgspec

from cadence.cli._common import Commands, arg, err, out, positive_float, speed
from common.runtime.errors import InputError
from common.runtime.resources import EXAMPLE_TASK

T = TypeVar("T")

cli = Commands()


async def ended_by_sigterm(main: Coroutine[Any, Any, T]) -> T:
    """``main``, which SIGTERM (a process manager, a closed terminal, `kill PID`) cancels as Ctrl-C does
    (asyncio's runner cancels the main task): what ran is kept. Whatever SIGINT's disposition: a background
    job of a non-interactive shell has SIGINT ignored, and a SIGTERM forwarded to that handler did nothing
    (the demo ran 72–156 s on to its end)."""
    import asyncio  # here: `cadence --help` need not import it (issue 76's start-up)

    loop, task = asyncio.get_running_loop(), asyncio.current_task()
    assert task is not None
    loop.add_signal_handler(signal.SIGTERM, task.cancel)
    try:
        return await main
    finally:
        with contextlib.suppress(RuntimeError, ValueError):  # the loop closing, or not the main thread
            loop.remove_signal_handler(signal.SIGTERM)


@cli.command(
    "demo",
    help="the whole closed loop on this machine: operator twin, every service, simulated UR16e",
    description="Plans the task if its sets are not stored, then runs every service (the operator twin as "
    "the ECG source, HRV analyser, Pareto store, decision maker, executor with the simulated UR16e) on one "
    "driven clock, in lockstep: the same run on every host, loaded or idle, at most --speed times real "
    "time. --processes runs each service as its own process on the wall clock instead, with a Zenoh "
    "router on loopback to join and a supervisor that restarts any that dies. Shows a live view and "
    "writes DIR/summary.json, DIR/rr_k.png (mean RR and k over time), DIR/cycles.png (joint positions of "
    "the first and last cycle), DIR/pareto.png (the sets) and DIR/index.html (the report that shows them).",
)
@arg("--duration", type=positive_float, default=600.0, help="data time to run, s (default 600)")
@arg(
    "--speed",
    type=speed,
    default=8.0,
    help="data time per wall time, above 0 and at most 1000 (default 8): a ceiling in lockstep, the "
    "processes' clock with --processes; max: as fast as the host allows (lockstep only)",
)
@arg(
    "--processes",
    action="store_true",
    help="every service its own process, on the wall clock times --speed, as systemd runs them (what "
    "--kill and --listen need): a busy host changes what such a run does",
)
@arg("--out", default="demo-out", metavar="DIR", help="output folder (default demo-out)")
@arg("--force", action="store_true", help="write into --out even while another demo writes there")
@arg("--seed", type=int, default=1, help="the operator twin's seed (default 1)")
@arg("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="default: box_filling")
@arg(
    "--kill",
    action="append",
    default=[],
    metavar="SERVICE@S",
    help="with --processes: SIGKILL a service at data time S (repeatable): shows the supervisor "
    "restarting it",
)
@arg("--no-live", action="store_true", help="no live view (for logs and CI)")
@arg(
    "--listen",
    metavar="ENDPOINT",
    help="with --processes: the router's endpoint (default: a free port on 127.0.0.1)",
)
@arg(
    "--twin",
    action="append",
    default=[],
    metavar="KEY=VALUE",
    help="a parameter of the operator twin (common/sim/twin.py; repeatable), e.g. heavy_from_s=120 "
    "heavy_until_s=300 (a stretch of heavier parts) or accelerometer=false (a strap without one)",
)
@arg(
    "--decide",
    choices=("paper", "personal"),
    default="paper",
    help="the decision maker's mode: paper (Alg. 1, default) or personal (k from this person's own "
    "scale; docs/decision.md, Decisions on real people)",
)
def cmd_demo(args: argparse.Namespace) -> int:
    from cadence.demo.folder import claim, keep_previous
    from cadence.demo.options import ORDER, DemoOptions, twin_table
    from cadence.demo.processes import run_demo
    from cadence.demo.summary import NothingRan, summary_table
    from common.sim.twin import TwinParams

    if not args.processes:
        needs = [flag for flag, given in (("--kill", args.kill), ("--listen", args.listen)) if given]
        if needs:
            raise InputError(f"{' and '.join(needs)} need --processes: the lockstep cell has no processes "
                             "to kill and no router to join")  # fmt: skip
    elif math.isinf(args.speed):
        raise InputError("--speed max runs the cell in lockstep: --processes run on the wall clock, "
                         "give them a number (at most 1000)")  # fmt: skip
    kills = []
    for spec in args.kill:
        name, _, at = spec.partition("@")
        if name not in ORDER or not at:
            raise InputError(
                f"--kill {spec}: expected SERVICE@SECONDS with SERVICE one of {', '.join(ORDER)}"
            )
        kills.append((name, float(at)))
    twin = []
    for spec in args.twin:
        key, _, text = spec.partition("=")
        try:
            twin.append((key.strip(), tomllib.loads(f"v = {text}")["v"]))
        except tomllib.TOMLDecodeError:
            raise InputError(f"--twin {spec}: expected KEY=VALUE, the value a number or true/false") from None
    opts = DemoOptions(
        duration_s=args.duration,
        speed=args.speed,
        out=Path(args.out),
        seed=args.seed,
        task=Path(args.task),
        kill=tuple(kills),
        live=not args.no_live,
        listen=args.listen,
        twin=tuple(twin),
        decide=args.decide,
        processes=args.processes,
    )
    try:  # a parameter the twin does not have, or out of its range: said now, not by a service at start
        msgspec.convert(twin_table(opts), TwinParams)
    except msgspec.ValidationError as exc:
        raise InputError(f"--twin: {exc}") from None
    # a task file that does not load is said now, in one line: the lockstep cell would wait an hour of
    # data time for a store that refused it
    from common.trajectory.task import load_task

    load_task(opts.task)
    t0 = time.monotonic()

    lock = claim(opts.out, args.force)
    if (kept := keep_previous(opts.out)) is not None:
        out.print(f"the last run's report and logs in {opts.out} are kept in {kept}", soft_wrap=True)
    before = signal.getsignal(signal.SIGTERM)
    try:
        if opts.processes:
            import asyncio

            summary = asyncio.run(ended_by_sigterm(run_demo(opts, out)))
        else:
            from cadence.demo.in_lockstep import run_lockstep
            from common.runtime import lockstep

            ceiling = opts.speed if math.isfinite(opts.speed) else None
            summary = lockstep.run(ended_by_sigterm(run_lockstep(opts, out)), ceiling)
    except NothingRan as exc:
        err.print(f"cadence: {exc}", markup=False, highlight=False, soft_wrap=True)
        return 130
    finally:
        signal.signal(signal.SIGTERM, before)
        if lock is not None:
            lock.close()
    wall = time.monotonic() - t0
    if opts.live:
        out.print()  # the live view's last frame stays above: a line between it and the summary
    out.print(summary_table(summary, wall))
    written = summary["written"]
    report = (" and a report (index.html and its figures)" if written["report"]
              else "; no report (see above)")  # fmt: skip
    # one line, not wrapped: a path broken across lines cannot be copied
    out.print(f"written: {written['summary']}{report}; service logs in {args.out}/logs", soft_wrap=True)
    bad = {n: c for n, c in summary["exit_codes"].items() if c != 0}
    if bad:
        err.print(f"services that did not exit cleanly: {bad}")
        return 1
    return 130 if summary["cut_short"] else 0  # as a shell reports an interrupted command
