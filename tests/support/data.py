"""The recordings the tests read (the shared annotated ECG, skipped with the reason when absent) and the
ECG the tests make: synthetic beats in the H10's chunks, a strap's RR notifications, a record cut short."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common.hrv.records import read_record
from schemas import EcgChunk
from tests.support.paths import SHARED_DATA

ECG = SHARED_DATA / "ecg"
FS = 130.0  # the H10's rate
CHUNK = 73  # samples in one of its notifications


needs_data = pytest.mark.skipif(not ECG.exists(), reason=f"the shared recordings are not at {ECG}")


def device_rr(beats: np.ndarray, every_s: float = 1.0) -> list[tuple[float, list[float]]]:
    """The strap's notifications for these beats: about once a second, the intervals ended since the last
    one, sent at the time of the last beat (the H10's RR stream)."""
    out: list[tuple[float, list[float]]] = []
    j = 1
    for k in range(2, len(beats) + 1):
        if k == len(beats) or beats[k] - beats[j - 1] > every_s:
            out.append((float(beats[k - 1]), np.diff(beats[j - 1 : k]).tolist()))
            j = k
    return out


def record_cut(tmp_path: Path, name: str, seconds: float) -> tuple[Path, np.ndarray]:
    """The first seconds of a shared record as a CSV (what the gateway replays), and those seconds
    resampled to 130 Hz (what the offline reference analyses)."""
    rec = read_record(str(ECG / name))
    n = int(seconds * rec.fs)
    csv = tmp_path / f"{name}.csv"
    np.savetxt(csv, np.c_[np.arange(n) / rec.fs, rec.uv[:n]], delimiter=",", fmt="%.6f")
    return csv, read_record(str(csv), fs=130.0).uv


S = 1_000_000_000


DAY = 86_400 * S


def synthetic_ecg(seconds: float) -> np.ndarray:
    """R waves every 0.8 s (75 bpm), µV."""
    t = np.arange(0, seconds, 1 / FS)
    return np.rint(1000 * np.exp(-(((t % 0.8) - 0.4) ** 2) / 2e-4)).astype(int)


def chunks(x: np.ndarray, t0_ns: int) -> list[EcgChunk]:
    return [
        EcgChunk(t_ns=t0_ns + round(i * 1e9 / FS), seq=n, fs_hz=FS, samples_uv=x[i : i + CHUNK].tolist())
        for n, i in enumerate(range(0, len(x), CHUNK))
    ]
