"""A subject's calibration from the cell's bus (`cadence calibrate`, and `cadence session --calibrate`):
minutes of windows at rest or at work, RR_r stored and published, and the screen that says what it is
worth. The arithmetic is common/hrv/calibration.py."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from common.runtime.errors import CadenceError, InputError

if TYPE_CHECKING:
    from common.hrv.calibration import RestingLevel
    from common.runtime.bus import Bus
    from schemas import Calibration, HrvWindow, RobotState
    from schemas.operator import Posture


SILENT_S = 10.0  # no window for this long: calibrate says where it listens


async def at_the_slowest(bus: Bus, by: str, what: str) -> None:
    """The robot at its slowest solution (k = 1), where it stays until a session sets its condition: a
    calibration at work is taken there, and a person settles there before a condition (a heart does not
    come back to its baseline beside a robot at minimum time). ``what`` names the step in the error."""
    from schemas.topology import DECISION_CONDITION

    replies = await bus.get(DECISION_CONDITION, timeout=10.0, parameters=f"mode=fixed;k=1;by={by}")
    if not replies or replies[0].message is None:
        why = replies[0].error if replies else "no decision maker answered"
        raise CadenceError(f"{what}: cannot set the slowest solution (k = 1): {why}")


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
    from schemas.topology import CALIBRATION, HRV_WINDOW, ROBOT_STATE

    calibrations = bus.publisher(CALIBRATION)
    if posture == "working":
        await at_the_slowest(bus, "calibrate", "calibrate --posture working")
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
