"""Heart-rate commands: `cadence hrv peaks|windows` on a recording, `cadence decide` (Alg. 1 on numbers),
`cadence calibrate` (a subject's resting level, from the bus)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from decimal import Decimal
from pathlib import Path
from typing import TYPE_CHECKING

from rich.progress import BarColumn, Progress, TextColumn

from cadence.cli._common import Commands, arg, bus_config, err, flags_from, out, positive_float, positive_int
from common.runtime.errors import CadenceError, InputError

if TYPE_CHECKING:
    from common.hrv.calibration import RestingLevel
    from common.runtime.bus import Bus
    from schemas import Calibration, HrvWindow, RobotState
    from schemas.operator import Posture


cli = Commands()


PEAKS = 'one JSON object {"fs", "peaks_s"}: R-peak times from the record start'


WINDOWS = "one JSON line per tumbling window: mean RR, RMSSD, SDNN, beats, excluded, quality"


def add_record(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "record",
        metavar="RECORD",
        help="WFDB record path without extension, a CSV (s, µV), a Polar Sensor Logger export "
        "(…_ECG.txt; for windows also …_RR.txt), RR intervals one per line (s or ms), or for windows an "
        "Empatica E4 export folder (IBI.csv, ACC.csv, …)",
    )
    p.add_argument("--fs", type=float, default=None, help="resample to this rate first (130: as the H10)")


def add_posture(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--posture",
        choices=("rest", "working"),
        default="rest",
        help="rest: seated at rest, as the paper; working: at the task with the robot at its slowest "
        "solution (k = 1), so moving and standing are in the baseline; the level at rest is kept beside it",
    )


def _record_peaks(args: argparse.Namespace):
    from common.hrv.records import read_record
    from common.hrv.rpeaks import detect_peaks

    rec = read_record(args.record, fs=args.fs)
    return rec, detect_peaks(rec.uv, rec.fs, chunk=round(rec.fs))


cli.group("hrv", steps={"dest": "hrv", "metavar": "TOOL"}, help="offline heart-rate tools on a recording")


@cli.command("hrv peaks", help=PEAKS, description=f"Prints {PEAKS}.")
@flags_from(add_record)
def cmd_hrv_peaks(args: argparse.Namespace) -> int:
    from common.hrv.records import is_rr_file

    if is_rr_file(args.record) or Path(args.record).is_dir():
        raise InputError(f"{args.record}: RR intervals only, no ECG to find peaks in (`cadence hrv windows`)")
    rec, peaks = _record_peaks(args)
    print(json.dumps({"fs": rec.fs, "peaks_s": [round(p.sample / rec.fs, 6) for p in sorted(peaks)]}))
    return 0


@cli.command("hrv windows", help=WINDOWS, description=f"Prints {WINDOWS}.")
@flags_from(add_record)
@arg("--window", type=float, default=30.0, help="window length [s] (default 30)")
def cmd_hrv_windows(args: argparse.Namespace) -> int:
    """Windows of an ECG (its detected beats), of an RR-only file (beats at the intervals' running sum,
    as the H10's own RR output is read with ``input = "rr"``), or of a wristband's export (its intervals
    have gaps: a window is judged by how many it holds, common/hrv/e4.py)."""
    import numpy as np

    from common.hrv.records import is_rr_file, read_rr
    from common.hrv.stream import intervals, peak_intervals, windows

    if Path(args.record).is_dir():  # an Empatica E4 export: windows over data time from its start
        from common.hrv.e4 import e4_windows, read_e4

        wins = [w for _, w in e4_windows(read_e4(args.record), args.window)]
    elif is_rr_file(args.record):
        rr = read_rr(args.record)
        beats_s = np.concatenate([[0.0], np.cumsum(rr)])
        wins = windows(intervals(beats_s), args.window, end_s=float(beats_s[-1]))
    else:
        rec, peaks = _record_peaks(args)
        wins = windows(peak_intervals(peaks, rec.fs), args.window, end_s=len(rec.uv) / rec.fs)
    for w in wins:
        print(
            json.dumps(
                {
                    "start_s": w.start_s,
                    "end_s": w.end_s,
                    "mean_rr_s": w.mean_rr_s,
                    "n_beats": w.n_beats,
                    "excluded": w.excluded,
                    "quality": w.quality,
                    "reason": w.reason,
                    "rmssd_s": w.rmssd_s,
                    "sdnn_s": w.sdnn_s,
                }
            )
        )
    return 0


DECIDE_MIN_S, DECIDE_MAX_S = 0.2, 3  # a window's mean RR that a heart can have (300 to 20 beats per minute)


@cli.command(
    "decide",
    help="the decision rule (paper Alg. 1) on mean RR values read from standard input",
    description="Reads one mean RR per line (seconds) from standard input and prints the selected k "
    "after each window, one per line. RR_s = RR_r - offset. Exact on decimal values.",
)
@arg("--rr-rest", required=True, type=str, metavar="S", help="RR_r: the resting mean RR [s]")
@arg("--n", type=positive_int(1), default=15, help="number of solutions N (default 15)")
@arg("--sigma-r", type=str, default="0.14", metavar="S", help="σ_r [s] (default 0.14)")
@arg("--rr-s-offset", type=str, default="0.08", metavar="S", help="RR_r − RR_s [s] (0.08)")
@arg("--sigma-s", type=str, default="0.08", metavar="S", help="σ_s [s] (default 0.08)")
def cmd_decide(args: argparse.Namespace) -> int:
    from common.decision import Params, State, dec, step

    def seconds(text: str, where: str) -> Decimal:
        """A mean RR as a heart can have it; the flag and the lines of stdin are checked alike (850 was
        once taken as 850 s for --rr-rest, and k went to 1)."""
        try:
            value = dec(text)
            ok = value.is_finite() and value > 0
        except ArithmeticError:
            ok = False
        if not ok:
            raise InputError(f"{where}: expected a positive number of seconds, got {text!r}")
        if not DECIDE_MIN_S <= value <= DECIDE_MAX_S:
            hint = f" (milliseconds? {value / 1000} s)" if value > DECIDE_MAX_S else ""
            span = f"{DECIDE_MIN_S}-{DECIDE_MAX_S} s"
            raise InputError(f"{where}: a mean RR of {text} s is outside {span}{hint}")
        return value

    seconds(args.rr_rest, "--rr-rest")
    try:
        params = Params.of(args.rr_rest, args.n, args.sigma_r, args.rr_s_offset, args.sigma_s)
    except (ValueError, ArithmeticError) as exc:
        raise InputError(f"decide: {exc}") from exc
    values = [seconds(line.strip(), f"<stdin>:{lineno}") for lineno, line in enumerate(sys.stdin, start=1)]
    state = State.initial(params)
    lines = []
    for value in values:
        state = step(params, state, value).state
        lines.append(str(state.k))
    sys.stdout.write("".join(f"{x}\n" for x in lines))
    return 0


SILENT_S = 10.0  # no window for this long: calibrate says where it listens


async def calibrate(
    bus: Bus,
    minutes: float,
    subject: str,
    data_dir: Path,
    measured_sigma: bool,
    progress: Callable[[float, float], object] | None = None,
    posture: Posture = "rest",
    silent: Callable[[float], object] | None = None,
    arm: list[bool] | None = None,
) -> tuple[Calibration, RestingLevel]:
    """Collect ``minutes`` of data time of windows from the bus; store and publish the calibration. At
    work (``posture`` working), the robot first runs its slowest solution (the decision maker's condition
    fixed at k = 1, where it stays until a session sets its own) and the stored calibration at rest of
    the same subject is kept beside the new baseline. An ECG that cannot be read is an InputError that
    says why (``calibration.Verdict``). ``silent(s)`` is called once when no window came for SILENT_S:
    nothing on the bus may be answering at all. ``arm`` gets, for each robot/state meanwhile, whether
    the arm moved: a person next to a working robot is not at rest."""

    from common.hrv.calibration import calibration, load_calibration, store_calibration
    from schemas.topology import CALIBRATION, DECISION_CONDITION, HRV_WINDOW, ROBOT_STATE

    calibrations = bus.publisher(CALIBRATION)
    if posture == "working":
        replies = await bus.get(DECISION_CONDITION, timeout=10.0, parameters="mode=fixed;k=1;by=calibrate")
        if not replies or replies[0].message is None:
            why = replies[0].error if replies else "no decision maker answered"
            raise CadenceError(f"calibrate --posture working: cannot set the slowest solution (k = 1): {why}")
    wins: list[HrvWindow] = []
    if arm is not None:

        async def watch(_: str, state: RobotState) -> None:
            arm.append(state.mode == "moving")

        bus.handle(ROBOT_STATE, watch, maxsize=1000)
    sub = bus.subscribe(HRV_WINDOW, maxsize=1000)
    waited = 0.0
    while True:
        try:
            _, w = await sub.receive(SILENT_S)
        except TimeoutError:
            waited += SILENT_S
            if silent is not None and waited == SILENT_S:
                silent(waited)
            continue
        wins.append(w)
        covered = (w.end_ns - wins[0].start_ns) / 60e9
        if progress is not None:
            progress(min(covered, minutes), minutes)
        if covered >= minutes - 1e-9:
            break
    resting = load_calibration(data_dir).value if posture == "working" else None
    try:  # the cell's data time
        cal, level = calibration(wins, subject, wins[-1].end_ns, measured_sigma, posture, resting)
    except ValueError as exc:
        raise InputError(f"calibrate: {exc}") from exc
    store_calibration(data_dir, cal)
    calibrations.put(cal)
    return cal, level


def calibration_screen(
    cal: Calibration, level: RestingLevel, measured_sigma: bool, arm: list[bool] | None = None
) -> list[str]:
    """What a calibration ends with: the person's verdict and which baseline the decision uses. At rest
    beside an arm that worked meanwhile it says the baseline is not one at rest (on the demo cell RR_r
    was 0.756 s after a fast session and 0.844 s after k = 1)."""
    where = "at work, at the slowest solution (k = 1)" if cal.posture == "working" else "at rest"
    lines = [
        f"subject {cal.subject}: RR_r = {cal.rr_rest_s:.3f} s {where}, over {level.good}/{level.total} good "
        f"windows: the baseline the decision uses",
    ]
    if cal.posture == "working":
        rest = cal.rr_resting_s
        lines.append(
            f"at rest: {rest:.3f} s (kept; {1e3 * (cal.rr_rest_s - rest):+.0f} ms at work)"
            if rest is not None
            else "at rest: none stored for this subject"
        )
    if cal.posture == "rest" and arm and any(arm):
        share = 100 * sum(arm) / len(arm)
        lines.append(f"NOT AT REST: the arm moved in {share:.0f} % of this calibration; a person beside a "
                     "working robot is not at rest, and the level depends on what it did. Stop the executor "
                     "for it, or calibrate at work (--posture working)")  # fmt: skip
    how = "measured: the spread of the windows' means" if measured_sigma else "the paper default"
    lines.append(f"σ_r = {cal.sigma_rest_s:.3f} s ({how}; measured {level.sigma_s:.3f} s)")
    if cal.movement_mg is None:
        lines.append("movement: no accelerometer; every window will be read as mental load")
    elif cal.posture == "working":
        lines.append(f"movement at work: {cal.movement_mg:.0f} ± {cal.movement_sd_mg or 0:.0f} mg; a window "
                     "well above it is not read as stress")  # fmt: skip
    else:
        lines.append(f"movement at rest: {cal.movement_mg:.0f} mg; the level at work is learnt from the "
                     "first windows of work")  # fmt: skip
    return lines + level.verdict.lines()


@cli.command(
    "calibrate",
    help="record windows at rest or at work, compute RR_r, store and publish the subject's calibration",
    description="Listens to hrv/window for MINUTES of data time (the ECG gateway and HRV analyser must "
    "run), averages the good windows' mean RR into RR_r, writes DATA_DIR/calibration.json and publishes "
    "it on operator/calibration. Ends with a verdict: the share of readable windows, why the others "
    "were held, and 'this ECG cannot be read reliably: …' (exit 2) when too few are good.",
)
@arg("--minutes", type=positive_float, default=5.0, help="time to record, above 0 (default 5)")
@flags_from(add_posture)
@arg("--subject", default="subject", help="who is calibrated")
@arg(
    "--measured-sigma",
    action="store_true",
    help="use the measured spread of the windows' mean RR as σ_r instead of the paper's 0.14 s. Not "
    "advised: the paper's σ are literature values, the spread between people, while one person's "
    "window-to-window spread is about 0.026 s, and a σ of 0.02 s moves the initial k from 8 to 14",
)
@arg("--config", metavar="FILE.toml", help="deployment config ([cadence], [bus])")
@arg("--data-dir", help="data folder (default from the config or CADENCE_DATA_DIR)")
@arg("--cell", help="robot cell name")
@arg("--connect", action="append", metavar="ENDPOINT", help="a router to join, e.g. tcp/127.0.0.1:7447")
@arg("--zenoh-config", metavar="FILE.json5", help="Zenoh config file (a deployed cell's operator account)")
def cmd_calibrate(args: argparse.Namespace) -> int:
    import asyncio

    from common.hrv.calibration import calibration_path
    from common.runtime.bus import Bus, BusConfig
    from common.runtime.config import CommonSettings, read_config, section

    raw = read_config(args.config)
    common = section(raw, "cadence", CommonSettings, args.config or "<defaults>")
    bus_cfg = section(raw, "bus", BusConfig, args.config or "<defaults>")
    if args.connect or args.zenoh_config:  # as every other cell command takes them
        bus_cfg = bus_config(args, "client" if args.connect else "peer")
    data_dir = Path(args.data_dir or os.environ.get("CADENCE_DATA_DIR") or common.data_path).expanduser()
    cell = args.cell or common.cell
    where = (
        f"the router at {', '.join(bus_cfg.connect)}" if bus_cfg.connect
        else f"the Zenoh config {bus_cfg.config_file}" if bus_cfg.config_file
        else "peers on this host (multicast scouting is off: --connect a router elsewhere)"
    )  # fmt: skip

    def silent(waited: float) -> None:
        err.print(f"no hrv/window on cell '{cell}' for {waited:.0f} s, listening through {where}: are the "
                  "ECG gateway and the HRV analyser running? Still listening (Ctrl-C to stop)")  # fmt: skip

    async def go() -> tuple[Calibration, RestingLevel]:
        async with await Bus.open(bus_cfg, cell, role="operator") as bus:
            with Progress(
                TextColumn(f"windows {'at work' if args.posture == 'working' else 'at rest'}"),
                BarColumn(),
                TextColumn("{task.completed:.1f}/{task.total:.1f} min"),
                console=err,
            ) as prog:
                bar = prog.add_task("", total=args.minutes)
                return await calibrate(
                    bus,
                    args.minutes,
                    args.subject,
                    data_dir,
                    args.measured_sigma,
                    lambda done, total: prog.update(bar, completed=done),
                    args.posture,
                    silent,
                    arm,
                )

    arm: list[bool] = []
    cal, level = asyncio.run(go())
    for line in calibration_screen(cal, level, args.measured_sigma, arm):
        out.print(line)
    out.print(f"stored in {calibration_path(data_dir)} and published on operator/calibration")
    return 0
