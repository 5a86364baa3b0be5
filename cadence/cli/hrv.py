"""Heart-rate commands: `cadence hrv peaks|windows` on a recording, `cadence decide` (Alg. 1 on numbers),
`cadence calibrate` (a subject's resting level, from the bus)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from decimal import Decimal
from pathlib import Path
from typing import TYPE_CHECKING

from rich.progress import BarColumn, Progress, TextColumn

from cadence.cli._common import Commands, arg, bus_config, err, flags_from, out, positive_float, positive_int
from common.decision import Personal
from common.runtime.errors import InputError

if TYPE_CHECKING:
    from common.hrv.calibration import RestingLevel
    from schemas import Calibration


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


_MODE = Personal()


@cli.command(
    "decide",
    help="the decision rule (paper Alg. 1, or the personal mode) on mean RR values read from standard input",
    description="Reads one mean RR per line (seconds) from standard input and prints the selected k "
    "after each window, one per line. --mode paper (default): Alg. 1, RR_s = RR_r - offset, exact on "
    "decimal values. --mode personal: the decision maker's personal mode (DESIGN §7), each line a 30 s "
    "window weighed alike.",
)
@arg("--rr-rest", required=True, type=str, metavar="S", help="RR_r: the resting mean RR [s]")
@arg("--mode", choices=("paper", "personal"), default="paper", help="the decision rule (default paper)")
@arg("--n", type=positive_int(1), default=15, help="number of solutions N (default 15)")
@arg("--sigma-r", type=str, default="0.14", metavar="S", help="σ_r [s] (default 0.14)")
@arg("--rr-s-offset", type=str, default="0.08", metavar="S", help="RR_r − RR_s [s] (0.08)")
@arg("--sigma-s", type=str, default="0.08", metavar="S", help="σ_s [s] (default 0.08)")
@arg("--step", type=float, default=_MODE.step_s, metavar="S",
     help=f"personal: mean RR per step of k ({_MODE.step_s})")  # fmt: skip
@arg("--keep", type=float, default=_MODE.keep,
     help=f"personal: weight of the past a window, 0–0.95 ({_MODE.keep})")  # fmt: skip
@arg("--hysteresis", type=float, default=_MODE.hysteresis, metavar="STEPS",
     help=f"personal: how far past the middle between two k before k moves ({_MODE.hysteresis})")  # fmt: skip
@arg("--ref-tau", type=float, default=_MODE.ref_tau_s, metavar="S",
     help=f"personal: time constant of the reference, either way ({_MODE.ref_tau_s:g})")  # fmt: skip
@arg("--freeze", type=float, default=_MODE.freeze_s, metavar="S",
     help=f"personal: this far below the reference is stress; it stays ({_MODE.freeze_s})")  # fmt: skip
def cmd_decide(args: argparse.Namespace) -> int:
    from common.decision import Params, PersonalState, State, dec, personal_step, step

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
    lines = []
    if args.mode == "personal":
        mode = Personal(args.step, args.keep, args.hysteresis, args.ref_tau, args.freeze, _MODE.effort_tau_s)
        if not (mode.step_s > 0 and 0 <= mode.keep <= 0.95 and mode.hysteresis >= 0 and mode.ref_tau_s > 0
                and mode.freeze_s >= 0):  # fmt: skip
            raise InputError(f"decide: personal mode settings out of range: {mode}")
        now = PersonalState.initial(params)
        for value in values:
            now = personal_step(params, mode, now, float(value), 1, True)[0]
            lines.append(str(now.k))
    else:
        state = State.initial(params)
        for value in values:
            state = step(params, state, value).state
            lines.append(str(state.k))
    sys.stdout.write("".join(f"{x}\n" for x in lines))
    return 0


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

    from cadence.lab.calibrate import calibrate, calibration_screen
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
