"""`cadence bench executor`: the servo loop on a backend, the executor's way."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from cadence.bench.planning import longest_path
from common.runtime.resources import EXAMPLE_TASK
from common.trajectory.task import load_task


@dataclass(frozen=True, slots=True)
class ExecutorBench:
    backend: str
    timing: dict[str, float | int]
    prepare_ms: float
    motions: int
    warnings: list[str]
    aborted: str | None = None  # why the run stopped early (the loop stopped the robot)

    def as_json(self) -> dict[str, float | int]:
        return {**self.timing, "prepare_ms": self.prepare_ms}


def bench_executor(
    backend_name: str,
    seconds: float,
    host: str = "127.0.0.1",
    core: int | None = None,
    fifo_priority: int = 80,
    task_file: str | None = None,
) -> ExecutorBench:
    """The servo loop on a backend for ``seconds``, the executor's way: the longest path of the task at
    the limits, forward and back, while the main thread reads and encodes the robot's state at 50 Hz as
    the state publisher does. And the time to turn h into validated 500 Hz samples for that path."""
    import os

    from common.trajectory.planner import boundary_stretch, interval_bounds
    from common.trajectory.validate import validated_samples
    from schemas.robot import RobotState
    from schemas.topology import encode
    from services.executor import ServoLoop, SimBackend, UrRtdeBackend

    task = load_task(task_file or EXAMPLE_TASK)
    path = longest_path(task)
    lb, _ = interval_bounds(path.waypoints, task.limits, task.planner.kappa)
    h_fast = lb * boundary_stretch(lb[None], path, task.limits, "exact")[0]
    h_slow = 3.0 * h_fast  # the slow end of a set: the most samples to prepare
    times = []
    for _ in range(7):
        t0 = time.perf_counter()
        validated_samples(h_slow, path, task.limits, path.waypoints)
        times.append(time.perf_counter() - t0)
    prepare_ms = float(np.median(times)) * 1e3
    q = validated_samples(h_fast, path, task.limits, path.waypoints)
    backend = SimBackend(q[0], limits=task.limits) if backend_name == "sim" else UrRtdeBackend(host)
    backend.connect()
    try:
        if float(np.max(np.abs(backend.actual_q() - q[0]))) > 1e-3:
            backend.move_j(q[0], 0.5, 1.0)
        loop = ServoLoop(
            backend,
            core=core if core is not None else max(os.sched_getaffinity(0)),
            fifo_priority=fifo_priority,
        )
        loop.start()
        motions, seq, aborted = [backend.prepare(q), backend.prepare(q[::-1])], 0, None
        end = time.monotonic() + seconds
        n = 0
        while time.monotonic() < end:
            fut = loop.run(motions[n % 2], settle_ticks=250)
            while not fut.done():
                encode(
                    RobotState(
                        t_ns=time.time_ns(),
                        seq=seq,
                        q=backend.actual_q().tolist(),
                        qd=backend.actual_qd().tolist(),
                        tcp=backend.tcp_pose().tolist(),
                        path_id=path.id,
                        k=1,
                        mode="moving",
                    )
                )
                seq += 1
                time.sleep(0.02)
            n += 1
            outcome = fut.result().outcome
            if outcome != "done":
                aborted = f"the servo loop ended a motion early: {outcome} {backend.fault()}".strip()
                break
        loop.close()
    finally:
        backend.close()
    return ExecutorBench(
        backend_name, loop.summary().as_dict(), round(prepare_ms, 2), n, loop.warnings, aborted
    )
