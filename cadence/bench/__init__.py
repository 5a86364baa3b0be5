"""Benchmarks behind `cadence bench …`: each prints its figures and, where a baseline exists, the ratio
to it measured in the same run (the machines are shared and noisy; absolute times do not compare)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
from msgspec import structs
from numpy.typing import NDArray

from cadence.bench.ecg_noise import Variant
from cadence.bench.hrv_scoring import WindowScore
from cadence.bench.naive import evaluate_naive
from common.hrv.stream import RULES
from common.robot.ur16e import JointLimits
from common.runtime.errors import InputError
from common.runtime.resources import EXAMPLE_TASK
from common.trajectory.planner import (
    TrajectoryProblem,
    evaluate,
    hypervolume,
    plan_path,
)
from common.trajectory.task import PathPlan, PlannerSettings, Task, load_task
from schemas.topology import DEFAULT_CELL

T = TypeVar("T")


def longest_path(task: Task) -> PathPlan:
    """Most waypoints; ties broken by the longest lower-bound time."""

    def key(p: PathPlan) -> tuple[int, float]:
        lb = np.max(np.abs(np.diff(p.waypoints, axis=0)) / task.limits.velocity, axis=1).sum()
        return len(p.waypoints), float(lb)

    return max(task.paths.values(), key=key)


def ruckig_stop_at_every_waypoint(path: PathPlan, limits: JointLimits) -> float | None:
    """Time of the same motion as jerk-limited time-optimal moves that stop at every waypoint (Ruckig).

    None when the optional `ruckig` package is absent (`uv sync --extra bench`).
    """
    try:
        from ruckig import InputParameter, Result, Ruckig, Trajectory
    except ImportError:
        return None
    d = path.waypoints.shape[1]
    otg = Ruckig(d)
    total = 0.0
    for a, b in zip(path.waypoints[:-1], path.waypoints[1:], strict=True):
        inp = InputParameter(d)
        inp.current_position = a.tolist()
        inp.current_velocity = [0.0] * d
        inp.current_acceleration = [0.0] * d
        inp.target_position = b.tolist()
        inp.target_velocity = [0.0] * d
        inp.target_acceleration = [0.0] * d
        inp.max_velocity = limits.velocity.tolist()
        inp.max_acceleration = limits.acceleration.tolist()
        inp.max_jerk = limits.jerk.tolist()
        traj = Trajectory(d)
        if otg.calculate(inp, traj) not in (Result.Working, Result.Finished):
            raise RuntimeError("ruckig could not compute a segment")
        total += traj.duration
    return total


def _best_time(fn: Callable[[], T], repeat: int) -> tuple[float, T]:
    t0 = time.perf_counter()
    out = fn()
    best = time.perf_counter() - t0
    for _ in range(repeat - 1):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


@dataclass(frozen=True, slots=True)
class PlanBench:
    path_id: str
    n_waypoints: int
    generations: int
    population: int
    plan_s: float
    naive_plan_s: float
    eval_ms: float
    naive_eval_ms: float
    hv: float
    naive_hv: float
    tf_exact: float
    tf_hull: float
    tf_ruckig: float | None

    @property
    def plan_ratio(self) -> float:
        return self.naive_plan_s / self.plan_s

    @property
    def eval_ratio(self) -> float:
        return self.naive_eval_ms / self.eval_ms


def bench_plan(task: Task, settings: PlannerSettings, repeat: int = 3) -> PlanBench:
    """Planning time of the longest path against the straightforward evaluation, in the same run."""
    path = longest_path(task)
    exact = structs.replace(settings, constraints="exact")
    plan_s, fast = _best_time(lambda: plan_path(path, task.limits, exact), repeat)
    naive_s, slow = _best_time(lambda: plan_path(path, task.limits, exact, evaluator=evaluate_naive), 1)
    hull = plan_path(path, task.limits, structs.replace(settings, constraints="hull"))

    # One generation's evaluation, both ways, on the same population.
    problem = TrajectoryProblem(path, task.limits, "exact", settings.kappa)
    rng = np.random.default_rng(settings.seed)
    pop = np.exp(rng.uniform(np.log(problem.lb), np.log(problem.ub), (settings.population, len(problem.lb))))
    eval_s, _ = _best_time(lambda: evaluate(pop, path, task.limits, "exact"), 20)
    naive_eval_s, _ = _best_time(lambda: evaluate_naive(pop, path, task.limits, "exact"), 3)

    both = np.concatenate([fast.front, slow.front])
    ideal, nadir = both.min(axis=0), both.max(axis=0)
    return PlanBench(
        path_id=path.id,
        n_waypoints=len(path.waypoints),
        generations=fast.generations,
        population=settings.population,
        plan_s=plan_s,
        naive_plan_s=naive_s,
        eval_ms=eval_s * 1e3,
        naive_eval_ms=naive_eval_s * 1e3,
        hv=hypervolume(fast.front, ideal, nadir),
        naive_hv=hypervolume(slow.front, ideal, nadir),
        tf_exact=fast.solutions[-1].t_f,
        tf_hull=hull.solutions[-1].t_f,
        tf_ruckig=ruckig_stop_at_every_waypoint(path, task.limits),
    )


@dataclass(frozen=True, slots=True)
class Replanning:
    """Today's planner (pymoo's loop, one path after the other) beside the fast one, in the same run.

    Hypervolumes are shares of a long reference run's (``reference_generations``, another seed) under its
    normalisation, per path; the edit moves the middle waypoint of every path by ``edit_deg`` on every
    joint and plans it again warm (seeded by the last set) and cold.
    """

    path_id: str
    workers: int
    reference_generations: int
    path_s: float  # the longest path, fast engine
    pymoo_path_s: float
    task_s: float  # every path, fast engine, ``workers`` forked processes, pool start-up included
    pymoo_task_s: float  # every path, one after the other, pymoo's loop
    warm_s: float  # every edited path, warm, in the pool
    hv: dict[str, float]  # path → share, fast engine, cold
    pymoo_hv: dict[str, float]
    warm_hv: dict[str, float]
    edit_deg: float

    @property
    def path_ratio(self) -> float:
        return self.pymoo_path_s / self.path_s

    @property
    def task_ratio(self) -> float:
        return self.pymoo_task_s / self.task_s


def _edited(path: PathPlan, deg: float) -> PathPlan:
    wp = path.waypoints.copy()
    wp[len(wp) // 2] += np.radians(deg)
    return dataclasses.replace(path, waypoints=wp)


def bench_replanning(
    task: Task, settings: PlannerSettings, workers: int = 2, reference_generations: int = 600,
    edit_deg: float = 4.0, repeat: int = 2,
) -> Replanning:  # fmt: skip
    """Issue 31's figures: one path, the whole task, a warm replan after an edit, and their fronts."""
    from common.trajectory.pool import plan_paths

    paths = list(task.paths.values())
    longest = longest_path(task)
    path_s, _ = _best_time(lambda: plan_path(longest, task.limits, settings), repeat)
    pymoo_path_s, _ = _best_time(lambda: plan_path(longest, task.limits, settings, engine="pymoo"), repeat)
    task_s, fast = _best_time(lambda: plan_paths(paths, task.limits, settings, workers), repeat)
    pymoo_task_s, slow = _best_time(
        lambda: {p.id: plan_path(p, task.limits, settings, engine="pymoo") for p in paths}, 1
    )
    edited = [_edited(p, edit_deg) for p in paths]
    warm = {p.id: [s.h for s in fast[p.id].solutions] for p in paths}
    warm_s, warmed = _best_time(lambda: plan_paths(edited, task.limits, settings, workers, warm), repeat)
    long = structs.replace(settings, generations=reference_generations, seed=10_000)
    ref = plan_paths(paths, task.limits, long, workers)
    ref_edit = plan_paths(edited, task.limits, long, workers)

    def share(front: NDArray[np.float64], reference: NDArray[np.float64]) -> float:
        ideal, nadir = reference.min(axis=0), reference.max(axis=0)
        return hypervolume(front, ideal, nadir) / hypervolume(reference, ideal, nadir)

    return Replanning(
        path_id=longest.id,
        workers=workers,
        reference_generations=reference_generations,
        path_s=path_s,
        pymoo_path_s=pymoo_path_s,
        task_s=task_s,
        pymoo_task_s=pymoo_task_s,
        warm_s=warm_s,
        hv={p.id: share(fast[p.id].front, ref[p.id].front) for p in paths},
        pymoo_hv={p.id: share(slow[p.id].front, ref[p.id].front) for p in paths},
        warm_hv={p.id: share(warmed[p.id].front, ref_edit[p.id].front) for p in paths},
        edit_deg=edit_deg,
    )


@dataclass(frozen=True, slots=True)
class Convergence:
    """Hypervolume of default-setting runs after each checkpoint, as a share of a long run's."""

    path_id: str
    reference_generations: int
    checkpoints: list[int]
    shares: dict[int, list[float]]  # seed → share at each checkpoint (before the final polish)
    final: dict[int, float]  # seed → share of the finished run (after polishing its ends)


def convergence(
    task: Task,
    settings: PlannerSettings,
    seeds: list[int],
    reference_generations: int,
    checkpoints: list[int],
) -> Convergence:
    """How the default number of generations was chosen (docs/design.md, "The planner")."""
    path = longest_path(task)
    ref = plan_path(
        path, task.limits, structs.replace(settings, generations=reference_generations, seed=10_000)
    )
    ideal, nadir = ref.front.min(axis=0), ref.front.max(axis=0)
    hv_ref = hypervolume(ref.front, ideal, nadir)
    shares, final = {}, {}
    for seed in seeds:
        run = plan_path(
            path,
            task.limits,
            structs.replace(settings, generations=max(checkpoints), seed=seed),
            track_hypervolume=(ideal, nadir),
        )
        shares[seed] = [run.hypervolume_history[g - 1] / hv_ref for g in checkpoints]
        default = plan_path(path, task.limits, structs.replace(settings, seed=seed))
        final[seed] = hypervolume(default.front, ideal, nadir) / hv_ref
    return Convergence(path.id, reference_generations, checkpoints, shares, final)


@dataclass(frozen=True, slots=True)
class StoreBench:
    during_planning_ms: list[float]
    stored_ms: list[float]

    @staticmethod
    def pct(values: list[float], q: float) -> float:
        return float(np.percentile(values, q)) if values else float("nan")


async def bench_store(task_path: str, queries: int = 200) -> StoreBench:
    """Query latency on loopback against a store process: while it plans, and for a stored set."""
    import asyncio
    import socket
    import subprocess
    import sys
    import tempfile

    from common.runtime.bus import Bus, BusConfig
    from schemas.health import ServiceStatus
    from schemas.topology import AnyMessage

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    task = load_task(task_path)
    first = next(iter(task.paths))
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "c.toml"
        cfg.write_text(
            f"[cadence]\ndata_dir = '{tmp}'\nstatus_period_s = 0.05\n[bus]\nconnect = ['{endpoint}']\n"
            f"[pareto_store]\ntask = '{Path(task_path).resolve()}'\nshipped_sets = false\n"  # it plans
        )
        client = await Bus.open(BusConfig(listen=[endpoint]), DEFAULT_CELL)
        async with client:
            status = client.subscribe(client.key("health/pareto_store"), ServiceStatus, maxsize=1)
            proc = subprocess.Popen([sys.executable, "-m", "services.pareto_store", "--config", str(cfg)])
            try:
                latest: list[str] = [""]

                async def watch() -> None:
                    async for _, st in status:
                        latest[0] = st.state

                watcher = asyncio.create_task(watch())
                during: list[float] = []
                key = client.key(f"pareto/{first}")
                async with asyncio.timeout(300):
                    while latest[0] != "serving":
                        t0 = time.perf_counter()
                        replies = await client.get(key, AnyMessage, timeout=5.0)
                        if replies and latest[0].startswith("planning"):
                            during.append((time.perf_counter() - t0) * 1e3)
                stored = []
                for _ in range(queries):
                    t0 = time.perf_counter()
                    replies = await client.get(key, AnyMessage, timeout=5.0)
                    if not replies or replies[0].message is None:
                        raise RuntimeError(f"no stored set for {first}")
                    stored.append((time.perf_counter() - t0) * 1e3)
                watcher.cancel()
            finally:
                proc.terminate()
                proc.wait(timeout=20)
    return StoreBench(during, stored)


@dataclass(frozen=True, slots=True)
class DetectorScore:
    name: str
    tp: int
    fp: int
    fn: int
    seconds: float  # processing time, all records
    signal_s: float  # duration of all records

    @property
    def f1(self) -> float:
        return 2 * self.tp / (2 * self.tp + self.fp + self.fn)

    @property
    def se(self) -> float:
        return self.tp / (self.tp + self.fn)

    @property
    def ppv(self) -> float:
        return self.tp / (self.tp + self.fp)

    @property
    def realtime(self) -> float:
        return self.signal_s / self.seconds


def _established_detectors(fs: float) -> dict[str, Callable[[NDArray[np.float64]], object]]:
    """Established detectors, where the optional packages are installed (`uv sync --extra bench`)."""
    out: dict[str, Callable[[NDArray[np.float64]], object]] = {}
    try:
        import neurokit2 as nk

        def peaks(method: str) -> Callable[[NDArray[np.float64]], object]:
            return lambda x: nk.ecg_peaks(x, sampling_rate=fs, method=method)[1]["ECG_R_Peaks"]

        for method in ("neurokit", "pantompkins1985", "hamilton2002", "elgendi2010"):
            out[f"neurokit2:{method}"] = peaks(method)
    except ImportError:
        pass
    try:
        from ecgdetectors import Detectors

        d = Detectors(fs)
        for method in ("pan_tompkins_detector", "hamilton_detector", "two_average_detector", "swt_detector"):
            out[f"py-ecg-detectors:{method.removesuffix('_detector')}"] = getattr(d, method)
    except ImportError:
        pass
    return out


def spawned_pool(jobs: int | None, tasks: int) -> ProcessPoolExecutor:
    """A pool of ``jobs`` worker processes (default: one per core, never more than ``tasks``), spawned,
    not forked: the caller may hold threads (a bus session) whose locks a fork would copy held."""
    import multiprocessing
    import os

    n = max(1, min(jobs or os.cpu_count() or 1, tasks or 1))
    return ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"))


def bench_hrv(
    data_dir: str,
    fs: float = 130.0,
    chunk: int = 13,
    jobs: int | None = None,
    only: Sequence[str] | None = None,
) -> tuple[list[DetectorScore], dict[str, float]]:
    """Every annotated record of ``data_dir`` at ``fs``: each detector's Se, PPV, F1 and speed; for
    Cadence also the publication latency (data time from the peak to the end of the chunk that released
    it; chunks of 13 samples, 0.1 s) and the window mean-RR error. Records are scored in ``jobs`` spawned
    processes (default: one per core), each detector timed on its own record in its worker, so the
    speeds still compare with each other. ``only``: these records (names), not all."""
    records = sorted(p.with_suffix("") for p in Path(data_dir).glob("*.atr") if not only or p.stem in only)
    totals: dict[str, NDArray[np.float64]] = {}
    latency: list[float] = []
    errors: list[float] = []
    signal_s = 0.0
    with spawned_pool(jobs, len(records)) as pool:
        for part in pool.map(
            _detect_record, [str(r) for r in records], [fs] * len(records), [chunk] * len(records)
        ):
            for name, t in part.totals.items():
                totals[name] = totals.get(name, np.zeros(4)) + t
            latency += part.latency
            errors += part.errors
            signal_s += part.signal_s
    scores = [
        DetectorScore(n, int(t[0]), int(t[1]), int(t[2]), float(t[3]), signal_s) for n, t in totals.items()
    ]
    extra = {
        "records": float(len(records)),
        "latency_max_s": max(latency),
        "latency_p99_s": float(np.percentile(latency, 99)),
        "latency_over_0_5_s": float(np.mean(np.array(latency) > 0.5)),
        "window_err_median_ms": float(np.median(errors) * 1e3),
        "window_err_p95_ms": float(np.percentile(errors, 95) * 1e3),
        "good_windows": float(len(errors)),
    }
    return scores, extra


@dataclass(frozen=True, slots=True)
class _RecordDetection:
    totals: dict[str, NDArray[np.float64]]  # detector → (TP, FP, FN, seconds)
    latency: list[float]
    errors: list[float]
    signal_s: float


def _detect_record(path_str: str, fs: float, chunk: int) -> _RecordDetection:
    """One record for ``bench_hrv`` (a worker): every detector's matches and time, Cadence's latency and
    window errors."""
    from common.hrv.records import read_record
    from common.hrv.rpeaks import RPeakDetector
    from common.hrv.stream import intervals, match_beats, peak_intervals, windows

    path = Path(path_str)
    rec = read_record(str(path), fs=fs)
    if rec.beats_s is None:  # globbed by its annotation file: always annotated
        raise InputError(f"{path}: no beat annotations")
    beats_s = rec.beats_s
    totals: dict[str, NDArray[np.float64]] = {}
    latency: list[float] = []
    t0 = time.perf_counter()
    det, peaks = RPeakDetector(fs), []
    for i in range(0, len(rec.uv), chunk):
        new = det.feed_peaks(rec.uv[i : i + chunk])
        latency += [(min(i + chunk, len(rec.uv)) - p.sample) / fs for p in new]
        peaks += new
    peaks += det.flush_peaks()
    elapsed = time.perf_counter() - t0
    found = np.array(sorted(p.sample for p in peaks)) / fs
    totals["cadence"] = np.array([*match_beats(beats_s, found), elapsed], dtype=float)
    end = len(rec.uv) / fs
    ours = windows(peak_intervals(peaks, fs), 30.0, end_s=end)
    ref = windows(intervals(beats_s), 30.0, end_s=end)
    errors = [
        abs(a.mean_rr_s - b.mean_rr_s)
        for a, b in zip(ours, ref, strict=True)
        if a.quality == "good" and a.mean_rr_s is not None and b.mean_rr_s is not None
    ]
    for name, fn in _established_detectors(fs).items():
        t0 = time.perf_counter()
        idx = np.asarray(fn(rec.uv), dtype=np.float64)
        elapsed = time.perf_counter() - t0
        totals[name] = np.array([*match_beats(beats_s, np.sort(idx) / fs), elapsed], dtype=float)
    return _RecordDetection(totals, latency, errors, len(rec.uv) / fs)


def bench_hrv_windows(
    data_dir: str,
    fs: float = 130.0,
    variants: tuple[Variant, ...] = ("clean",),
    records: tuple[str, ...] = (),
    progress: Callable[[str], None] | None = None,
    peers: bool = True,
    jobs: int | None = None,
    gudb_dir: str | None = None,
) -> dict[str, dict[str, WindowScore]]:
    """Issue 19's table: per noise variant, how far the windows each pipeline marks good are from the
    annotated NN mean (``hrv_scoring``), for Cadence (its detector, cleaning and quality gate) and
    for NeuroKit2 (its default detector with its own artefact correction, Kubios' ``signal_fixpeaks``,
    and MeanNN over the corrected intervals of each window: it has no quality gate, so every window
    counts as good), in the same run. Noise is seeded by the record's name (``cadence.bench.ecg_noise``).

    With the clean variant, also ``cadence-rr``: the same cleaning and gate on a strap's own RR (``input =
    "rr"``), simulated as the H10 gives it: the annotated beats less every beat that is not normal (the
    strap leaves premature beats out, so one interval spans each). Records are scored in ``jobs``
    processes (default: one per core); the figures do not depend on it.

    With ``gudb_dir`` and the clean variant, also ``gudb-cs`` and ``gudb-cables``: healthy people's
    chest-strap beats as a strap's RR, against the strap's and the cables' annotated beats
    (``hrv_cv.gudb_unit``)."""
    from concurrent.futures import as_completed

    paths = sorted(p.with_suffix("") for p in Path(data_dir).glob("*.atr"))
    if records:
        paths = [p for p in paths if p.name in records]
    out: dict[str, dict[str, WindowScore]] = {v: {} for v in variants}  # in the order asked
    with spawned_pool(jobs, len(paths)) as pool:
        futures = {pool.submit(_score_record, str(p), fs, variants, peers): p.name for p in paths}
        for fut in as_completed(futures):
            if progress:
                progress(f"{futures[fut]} scored")
            for v, by_name in fut.result().items():
                for name, score in by_name.items():
                    out[v].setdefault(name, WindowScore(name)).merge(score)
    if gudb_dir and "clean" in variants and Path(gudb_dir).is_dir():
        from cadence.bench.hrv_cv import gudb_unit

        for subject in sorted(Path(gudb_dir).glob("subject_*")):
            for (_, name), score in gudb_unit(subject).score(RULES).items():
                out["clean"].setdefault(name, WindowScore(name)).merge(score)
        if progress:
            progress("GUDB scored")
    return {v: scores for v, scores in out.items() if scores}  # no records: nothing scored


def _score_record(
    path: str, fs: float, variants: tuple[Variant, ...], peers: bool
) -> dict[str, dict[str, WindowScore]]:
    """One record's windows in every variant, each pipeline's scored (a worker of bench_hrv_windows):
    Cadence's and the strap RR's as the cross-validation scores them (``hrv_cv.ecg_unit``), NeuroKit2's on
    the same noisy signal and windows."""
    from cadence.bench.hrv_cv import ecg_unit

    try:
        import neurokit2 as nk
    except ImportError:
        nk = None
    nk = nk if peers else None
    unit = ecg_unit(path, fs, variants)
    ours = unit.score(RULES)
    out: dict[str, dict[str, WindowScore]] = {}
    for series in unit.ecg:
        v, tr = series.variant, series.truths
        scores = out[v] = {"cadence": ours[(v, "cadence")]}
        if nk is not None:
            cleaned = nk.ecg_clean(series.signal, sampling_rate=fs)
            _, info = nk.ecg_peaks(cleaned, sampling_rate=fs, correct_artifacts=True)
            peaks = np.asarray(info["ECG_R_Peaks"], dtype=float) / fs
            rr, t_end = np.diff(peaks), peaks[1:]
            means = []
            for t in tr:
                sel = (t_end >= t.start_s) & (t_end < t.end_s)
                means.append(float(rr[sel].mean()) if sel.any() else None)
            scores["neurokit2"] = WindowScore("neurokit2")
            scores["neurokit2"].add(unit.name, tr, means, ["no beats"] * len(tr), series.sinus)
        if (v, "cadence-rr") in ours:
            scores["cadence-rr"] = ours[(v, "cadence-rr")]
    return out


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
