"""Session files and runs written by a test: a session's description, its windows, selections and
cycles, as `cadence session` and the demo write them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cadence.lab.session_file import SessionWriter
from cadence.tools.recording import Recorder
from common.trajectory.planner import content_hash
from common.trajectory.task import parse_task
from schemas import Calibration, CycleReport, HrvWindow, OperatorError, RobotEvent, RobotState, Selection
from schemas.session import SessionEnd, SessionInfo
from schemas.topology import encode
from services.pareto_store.jobs import plan_job
from tests.support.cell import CELL
from tests.support.executor import TASK

T0 = 1_800_000_000 * 10**9
S = 10**9
CAL = Calibration(t_ns=T0, seq=0, subject="s1", rr_rest_s=0.9)


def info(subject: str = "s1", condition: str = "a", cal: Calibration | None = CAL, cell: str = CELL):
    return SessionInfo(
        subject=subject, condition=condition, cell=cell, calibration=cal, start_ns=T0, minutes=2.0,
        task="box_filling.toml", task_sha256="0" * 64, software="cadence test",
    )  # fmt: skip


def write(path: Path, i: SessionInfo, *, end_s: float = 120.0, rr: float = 0.8, cycles: int = 10,
          errors: int = 3) -> Path:  # fmt: skip
    """A two-minute session: cycles spread over it, one before its start and one after its end (neither
    counts), windows every 30 s (one held), the robot's state every second."""
    w = writer(path, i)
    for t in range(0, int(end_s) + 1):
        w.put("robot/state", state(t), T0 + t * S)
    for n, t in enumerate([-5.0, *np.linspace(10, end_s - 1, cycles), end_s + 5]):
        w.put("robot/cycle", CycleReport(t_ns=T0 + round(t * S), seq=n, cycle=n, cycle_time_s=5.0,
                                         k_per_path={"p": 3}), T0 + round(t * S))  # fmt: skip
    for n in range(errors):
        t_ns = T0 + (20 + n) * S
        w.put("operator/error", OperatorError(t_ns=t_ns, seq=n, source="twin"), t_ns)
    for end in (30.0, 60.0, 90.0, 120.0):
        w.put("hrv/window", window(end, rr if end != 60.0 else 0.5, "good" if end != 60.0 else "low"),
              T0 + round(end * S))  # fmt: skip
    w.put("decision/selection", Selection(t_ns=T0, seq=0, k=15, n=15, delta=0, reason="fixed"), T0)
    w.close(SessionEnd(end_ns=T0 + round(end_s * S), complete=True, reason="on time"))
    return path


def write_run(tmp_path: Path) -> Path:
    """A recording of a short run: sets, four windows and selections, three cycles, an error, an event."""
    task = parse_task(TASK, "shuttle.toml")
    sets = {
        pid: plan_job(p, task, task.planner, content_hash(p, task.limits, task.planner))
        for pid, p in task.paths.items()
    }
    path = tmp_path / "run.mcap"
    rec = Recorder(path)
    key = f"cadence/{CELL}/"
    for s in sets.values():
        rec.write(key + f"pareto/{s.path_id}", encode(s))
    for i, (rr, k) in enumerate([(0.85, 5), (0.80, 3), (0.82, 4), (0.84, 5)]):
        end = T0 + (i + 1) * 30 * 10**9
        rec.write(key + "hrv/window", encode(HrvWindow(
            t_ns=end, seq=i, start_ns=end - 30 * 10**9, end_ns=end, mean_rr_s=rr, n_beats=35,
            excluded_fraction=0.0, quality="good")))  # fmt: skip
        rec.write(key + "decision/selection", encode(Selection(
            t_ns=end, seq=i, k=k, n=5, delta=0, reason="hold", window_end_ns=end)))  # fmt: skip
    for c in range(3):
        ks = {"there": 5 - c, "back": 5 - c}
        report = CycleReport(t_ns=T0 + (c + 1) * 40 * 10**9, seq=c, cycle=c, cycle_time_s=40.0, k_per_path=ks)
        rec.write(key + "robot/cycle", encode(report))
    rec.write(key + "operator/error", encode(OperatorError(t_ns=T0 + 50 * 10**9, seq=0, cycle=1)))
    rec.write(
        key + "robot/event",
        encode(RobotEvent(t_ns=T0 + 60 * 10**9, seq=0, kind="overrun", message="1 <overrun>")),
    )
    rec.close()
    return path


def window(end_s: float, rr: float | None, quality: str = "good") -> HrvWindow:
    return HrvWindow(
        t_ns=T0 + round(end_s * S), seq=0, start_ns=T0 + round((end_s - 30) * S),
        end_ns=T0 + round(end_s * S), mean_rr_s=rr, n_beats=30, excluded_fraction=0.0, quality=quality,  # type: ignore[arg-type]
        reason=None if quality == "good" else "excluded",
    )  # fmt: skip


def writer(path: Path, i: SessionInfo) -> SessionWriter:
    w = SessionWriter(path, i.cell)
    w.begin(i)
    return w


def state(t_s: float) -> RobotState:
    return RobotState(t_ns=T0 + round(t_s * S), seq=0, q=[0.0] * 6, qd=[0.0] * 6, tcp=[0.0] * 6)
