"""One message of every type the bus carries, each at the edge of its bounds."""

from __future__ import annotations

from schemas import (
    AccChunk,
    Beats,
    Calibration,
    CellClock,
    CycleReport,
    EcgChunk,
    HrvWindow,
    OperatorError,
    OperatorSignal,
    ParetoSet,
    ParetoSolution,
    ParetoSolutionReply,
    PlanProgress,
    RobotEvent,
    RobotState,
    RrIntervals,
    Selection,
    Separation,
    ServiceStatus,
)
from schemas.pareto import Limits, PathEnd

Z6 = [0.0] * 6
SOL = ParetoSolution(k=1, h=[0.5, 0.5, 1.0], t_f=2.0, f_time=12.0, f_jerk=3.0)

SAMPLES = [
    EcgChunk(t_ns=1, seq=0, fs_hz=130.0, samples_uv=[1, -2, 3], gap=True, source="polar"),
    RrIntervals(t_ns=1, seq=1, rr_s=[0.8, 0.81]),
    Beats(t_ns=1, seq=2, peak_t_ns=[10, 20], rr_s=[0.8, 0.9], excluded=[False, True]),
    HrvWindow(
        t_ns=30,
        seq=3,
        start_ns=0,
        end_ns=30,
        mean_rr_s=0.8,
        n_beats=37,
        excluded_fraction=0.05,
        quality="good",
    ),
    Calibration(t_ns=1, seq=4, subject="s01", rr_rest_s=0.85),
    Selection(t_ns=1, seq=5, k=8, n=15, delta=-1, reason="stress", window_end_ns=30),
    PlanProgress(t_ns=1, seq=6, path_id="p", state="running", done_paths=0, total_paths=2),
    ParetoSet(
        t_ns=1,
        seq=7,
        path_id="p",
        content_hash="abc",
        constraints="exact",
        waypoints=[Z6, Z6],
        limits=Limits(velocity=Z6, acceleration=Z6, jerk=Z6),
        start=PathEnd(velocity=Z6, acceleration=Z6, jerk=Z6),
        end=PathEnd(velocity=Z6, acceleration=Z6, jerk=Z6),
        front=[[1.0, 2.0]],
        solutions=[SOL],
    ),
    ParetoSolutionReply(t_ns=1, seq=8, path_id="p", content_hash="abc", n=1, solution=SOL),
    RobotState(t_ns=1, seq=9, q=Z6, qd=Z6, tcp=Z6, path_id="p", k=3, mode="moving"),
    CycleReport(t_ns=1, seq=10, cycle=3, cycle_time_s=21.5, k_per_path={"p": 3}),
    RobotEvent(t_ns=1, seq=11, kind="refused", message="over a limit", path_id="p"),
    ServiceStatus(t_ns=1, seq=12, service="x", state="running", uptime_s=3.0, counters={"decode_errors": 0}),
    CellClock(t_ns=1, seq=0, epoch_ns=1, speed=8.0),
    OperatorSignal(t_ns=1, seq=13, name="part_a2"),
    Separation(t_ns=1, seq=14, distance_m=1.8, source="scanner:front", age_s=0.03),
    OperatorError(t_ns=1, seq=14, cycle=3, description="wrong part"),
    AccChunk(t_ns=1, seq=0, fs_hz=25.0, x_mg=[-990, -985], y_mg=[30, 31], z_mg=[-237, -230], source="polar"),
]
