"""`cadence bench hrv`: the R-peak detector against the annotated beats and established detectors."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cadence.bench.pool import spawned_pool
from common.runtime.errors import InputError


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
