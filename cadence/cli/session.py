"""`cadence session`: one subject's session in one condition, recorded (the work: cadence/lab/session.py,
and cadence/lab/live.py for the terminal)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from cadence.cli._common import Commands, add_bus_flags, arg, err, flags_from, out, reaching
from cadence.cli.hrv import add_posture
from common.runtime.errors import InputError
from common.runtime.resources import EXAMPLE_TASK

if TYPE_CHECKING:
    from cadence.lab.session import SessionOptions, Watch
    from schemas import Calibration
    from schemas.session import SessionEnd

cli = Commands()


@cli.command(
    "session",
    help="one subject's session in one condition on a running cell, recorded to one MCAP",
    description="Checks the cell first (a status from every service, the robot ready, a good HRV "
    "window), calibrates the subject at rest or at work if asked (--calibrate, --posture; stored and "
    "published as `cadence calibrate` does) or takes the stored calibration, waits until the person's "
    "windows are good and near the baseline (--settle-timeout), sets the condition on the decision maker "
    "((a) minimum time: k = N; (b) minimum jerk: k = 1; (c) tuned online: Alg. 1 from the initial k), "
    "and records the cell's traffic for MINUTES of data time, with a live view. The file carries the "
    "session's description (subject, condition, calibration, task hash, software, start and end in "
    "data time); Ctrl-C ends it early, complete and marked cut short (exit 1). For the study: "
    "`cadence study analyse`.",
)
@arg("--subject", required=True, help="the subject's ID (as in the calibration, and the study plan)")
@arg(
    "--study",
    metavar="PLAN.toml",
    help="the study plan (`cadence study plan`): refuses a subject not in it, runs the subject's next "
    "condition, records its place and the break before it, trains before their first session, and files "
    "the session in the plan's sessions folder",
)
@arg(
    "--condition",
    choices=("a", "b", "c", "y"),
    help="(a), (b), (c), or (y) yoked: k fixed at the subject's mean k of their (c) session; with "
    "--study, the plan's next one (another is refused)",
)
@arg("--minutes", type=float, help="data time to record (default: the plan's, else 10)")
@arg(
    "--training",
    type=float,
    metavar="MINUTES",
    help="familiarisation in the condition before it counts, recorded and not analysed (default: the "
    "plan's training_minutes before a subject's first session, else none)",
)
@arg(
    "--tlx",
    metavar="M,P,T,P,E,F",
    help="the subject's NASA-TLX, six scores 0-100 (mental, physical, temporal, performance, effort, "
    "frustration); without it a session of a study asks at the end when run in a terminal",
)
@arg("--yoked-to", metavar="C_SESSION.mcap", help="condition y without a plan: the subject's (c) session")
@arg(
    "--calibrate",
    type=float,
    metavar="MINUTES",
    help="calibrate first, for MINUTES (the paper: 5 at rest; not the 5-minute familiarisation)",
)
@flags_from(add_posture)
@arg(
    "--settle-timeout",
    type=float,
    default=600.0,
    metavar="S",
    help="before the condition starts, wait up to S seconds of the person's (data) time for two good "
    "windows within 40 ms of RR_r (the person settled where the calibration put them); 0: no wait "
    "(default 600)",
)
@arg("--measured-sigma", action="store_true", help="as `cadence calibrate`")
@arg("--out", metavar="FILE.mcap", help="default: SUBJECT_CONDITION.mcap")
@arg("--data-dir", help="where the calibration is stored (default CADENCE_DATA_DIR)")
@arg("--task", default=str(EXAMPLE_TASK), metavar="TASK.toml", help="the executor's task")
@arg("--note", default="", help="free text kept in the file (e.g. the experimenter)")
@flags_from(add_bus_flags, 120.0)
def cmd_session(args: argparse.Namespace) -> int:
    import asyncio

    from rich.live import Live

    from cadence.cli._common import joining, stop_on_signals
    from cadence.lab.calibrate import calibrate, calibration_screen
    from cadence.lab.live import (
        ask_tlx,
        fresh_path,
        parse_tlx,
        planned,
        session_view,
        sessions_folder,
        tty_keys,
        yoked_k,
    )
    from cadence.lab.session import SessionOptions, run_session
    from cadence.lab.session_file import load_session, task_digest
    from cadence.lab.tables import session_table
    from common.runtime.config import CommonSettings

    plan = planned(args)
    folder = sessions_folder(plan, args) if plan else Path(".")
    out_path = Path(args.out) if args.out else fresh_path(folder, args.subject, args.condition)
    if out_path.exists():
        raise InputError(f"{out_path}: exists; a session file is evidence and is never overwritten")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    data_dir = Path(args.data_dir or os.environ.get("CADENCE_DATA_DIR") or CommonSettings().data_dir)
    tlx = parse_tlx(args.tlx) if args.tlx else None
    opts = SessionOptions(
        subject=args.subject,
        condition=args.condition,
        minutes=args.minutes,
        out=out_path,
        data_dir=data_dir.expanduser(),
        task=Path(args.task),
        cell=args.cell,
        calibrate_minutes=args.calibrate,
        measured_sigma=args.measured_sigma,
        ready_timeout_s=args.timeout,
        notes=args.note,
        posture=args.posture,
        settle_timeout_s=None if args.settle_timeout == 0 else args.settle_timeout,
        training_minutes=args.training or 0.0,
        yoked_k=yoked_k(args, plan),
        study=plan.name if plan else "",
        period=args.period,
        previous_end_ns=args.previous_end_ns,
    )
    task_digest(opts.task)  # a task file that is not there is said before the session starts
    ask = None if tlx is None and not (plan and sys.stdin.isatty()) else ask_tlx(tlx)

    async def go() -> SessionEnd:
        stop = stop_on_signals()
        async with await reaching(joining(args), args.cell, "operator", args.timeout, "session") as bus:
            with Live(console=err, refresh_per_second=4, transient=False) as live:
                began = False

                def show(phase: str, w: Watch, o: SessionOptions) -> None:
                    nonlocal began
                    if phase == "running" and not began:  # a line that stays, above the live view
                        began = True
                        live.console.print(f"condition ({o.condition}) in force: recording {o.minutes:g} min")
                    live.update(session_view(phase, w, o))

                async def calib() -> Calibration:
                    minutes = args.calibrate
                    cal, level = await calibrate(
                        bus, minutes, args.subject, opts.data_dir, args.measured_sigma, posture=args.posture
                    )
                    for line in calibration_screen(cal, level, args.measured_sigma):
                        live.console.print(line)
                    return cal

                keys: asyncio.Queue[str] = asyncio.Queue()
                restore = tty_keys(keys)
                try:
                    return await run_session(bus, opts, stop, show, calib, keys, ask)
                finally:
                    if restore is not None:
                        restore()

    end = asyncio.run(go())
    if not out_path.exists():
        err.print("stopped before the condition took effect: no session file written")
        return 1
    s = load_session(out_path)
    out.print(session_table(s, end))
    if s.info.break_s is not None:
        least = f" (the plan asks at least {plan.break_minutes:g})" if plan else ""
        out.print(f"break before it: {s.info.break_s / 60:.1f} min of data time{least}")
    if s.end.tlx is not None:
        out.print(f"NASA-TLX raw: {s.end.tlx.raw:.1f}")
    return 0 if end.complete else 1
