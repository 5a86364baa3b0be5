"""The Empatica E4 wristband's export, as labs record with it (``shared/data/stress_predict``): a folder
with ``IBI.csv``, ``ACC.csv``, ``HR.csv`` and ``tags_*.csv``.

- ``IBI.csv``: the session's start (Unix s) and the word IBI; then ``t_s, ibi_s``: the time of the beat
  that closes each interval, from the start, and the interval. The wristband finds beats in its pulse
  (PPG), and where it cannot read the pulse (movement, poor contact) intervals are missing: an interval
  after a gap is still a true one between two beats, but a window may hold a third of its beats, or
  none. Windows of such intervals are judged by how many they hold (``e4_windows``), not by how much
  of the window they cover, as a chest strap's are.
- ``ACC.csv``: the start (×3), the rate (32 Hz, ×3), then x, y, z in 1/64 g (±2 g) of the wrist.
- ``HR.csv``: the start, the rate (1 Hz), then the wristband's average heart rate (bpm).
- ``tags_*.csv``: Unix times of the wristband's button (the experimenter's marks between blocks).

A file that is not what it should be is an ``InputError`` naming the file and the line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from common.hrv.stream import Window
from common.runtime.errors import InputError
from schemas.base import RR_MAX_S
from schemas.hrv import HoldReason, Quality

Array = NDArray[np.float64]
MG_PER_UNIT = 1000.0 / 64.0  # ACC.csv counts 1/64 g
CONTIGUOUS_S = 0.01  # an interval follows the one before when its beat closed that one, within this
MIN_INTERVALS = 10  # a window of wrist intervals with fewer is held: too few beats to say what the heart did


@dataclass(frozen=True, slots=True)
class E4:
    """One session's export. Times are Unix ns."""

    folder: Path
    start_ns: int
    beat_ns: NDArray[np.int64]  # the beat that closes each interval
    ibi_s: Array
    acc_start_ns: int | None
    acc_hz: float | None
    acc_mg: Array  # (n, 3), mg
    tags_ns: NDArray[np.int64]

    @property
    def end_ns(self) -> int:
        """The last beat's time, or the start where there is none."""
        return int(self.beat_ns[-1]) if self.beat_ns.size else self.start_ns


def _rows(path: Path, header: int) -> tuple[list[str], list[list[float]]]:
    """The first ``header`` lines as text, the rest as numbers; InputError naming file and line."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file (an Empatica E4 export folder has it)") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not text (byte {exc.start})") from None
    if len(lines) < header:
        raise InputError(f"{path}: expected {header} header line(s), the file has {len(lines)}")
    rows = []
    for n, line in enumerate(lines[header:], start=header + 1):
        if not line.strip():
            continue
        try:
            rows.append([float(x) for x in line.split(",")])
        except ValueError:
            raise InputError(f"{path}:{n}: expected numbers separated by commas, got {line[:60]!r}") from None
    return lines[:header], rows


def _start(path: Path, text: str) -> float:
    try:
        start = float(text.split(",")[0])
    except ValueError:
        raise InputError(
            f"{path}:1: expected the session's start in Unix seconds, got {text[:60]!r}"
        ) from None
    if not 1e9 < start < 4.1e9:  # 2001 … 2100
        raise InputError(f"{path}:1: a start of {start} is not a Unix time in seconds")
    return start


def read_e4(folder: str | Path) -> E4:
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder (an Empatica E4 export: IBI.csv, ACC.csv, …)")
    ibi_path = folder / "IBI.csv"
    head, rows = _rows(ibi_path, 1)
    start = _start(ibi_path, head[0])
    ibi = np.array(rows, dtype=float).reshape(-1, 2) if rows else np.empty((0, 2))
    if ibi.size and (np.any(np.diff(ibi[:, 0]) <= 0) or np.any(ibi[:, 1] <= 0) or np.any(ibi[:, 1] > 3.0)):
        raise InputError(f"{ibi_path}: beat times must rise and intervals lie in (0, 3] s")
    acc_path = folder / "ACC.csv"
    acc_start, acc_hz, acc = None, None, np.empty((0, 3))
    if acc_path.exists():
        head, rows = _rows(acc_path, 2)
        acc_start = _start(acc_path, head[0])
        try:
            acc_hz = float(head[1].split(",")[0])
        except ValueError:
            raise InputError(f"{acc_path}:2: expected the rate in Hz, got {head[1][:60]!r}") from None
        if not 1.0 <= acc_hz <= 1000.0:
            raise InputError(f"{acc_path}:2: a rate of {acc_hz} Hz is not an accelerometer's")
        acc = np.array(rows, dtype=float).reshape(-1, 3) * MG_PER_UNIT if rows else acc
    tags = []
    for tag_path in sorted(folder.glob("tags*.csv")):
        _, rows = _rows(tag_path, 0)
        tags += [r[0] for r in rows]
    return E4(
        folder,
        round(start * 1e9),
        np.round((start + ibi[:, 0]) * 1e9).astype(np.int64),
        ibi[:, 1].copy(),
        None if acc_start is None else round(acc_start * 1e9),
        acc_hz,
        acc,
        np.round(np.array(tags, dtype=float) * 1e9).astype(np.int64),
    )


def e4_windows(rec: E4, length_s: float = 30.0, start_ns: int | None = None, end_ns: int | None = None,
               min_intervals: int = MIN_INTERVALS) -> list[tuple[int, Window]]:  # fmt: skip
    """Tumbling windows over data time, from ``start_ns`` (the session's start), with the intervals
    whose closing beat falls in each: (start ns, window). Fewer than ``min_intervals`` is held
    ("coverage": too few beats were read); the mean of those there is kept beside, for a person to see."""
    t0 = rec.start_ns if start_ns is None else start_ns
    end = rec.end_ns if end_ns is None else end_ns
    step = round(length_s * 1e9)
    out = []
    for a in range(t0, end - step + 1, step):
        sel = (rec.beat_ns >= a) & (rec.beat_ns < a + step)
        rr = rec.ibi_s[sel]
        n = int(rr.size)
        mean = float(rr.mean()) if n else None
        good = n >= min_intervals
        sd = float(rr.std(ddof=1)) if n > 1 else None
        # RMSSD over intervals that follow one another (the wristband drops the beats it cannot read:
        # an interval whose beat does not close the one before is the start of another run)
        t = rec.beat_ns[sel]
        joined = np.abs(np.diff(t) / 1e9 - rr[1:]) < CONTIGUOUS_S
        diffs = np.diff(rr)[joined]
        rmssd = min(float(np.sqrt(np.mean(diffs**2))), RR_MAX_S) if diffs.size >= 2 else None
        quality: Quality = "good" if good else "low" if n else "none"
        reason: HoldReason | None = None if good else "coverage" if n else "no_clean_beats"
        w = Window((a - t0) / 1e9, (a - t0 + step) / 1e9, mean, n, 0.0, quality, rmssd, sd, reason)
        out.append((a, w))
    return out
