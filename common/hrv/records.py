"""Reading ECG recordings for replay and offline checks: WFDB records (with their reference beat
annotations), CSV files (time, µV), the Polar Sensor Logger app's exports (the most common way H10 data
is saved: ``…_ECG.txt``, ``;``-separated, µV, ``…_RR.txt``, RR in ms, and ``…_ACC.txt``, the
accelerometer in mg) and plain RR files (one interval per line, in s or ms), resampled to the strap's
rate. A broken file is an InputError naming it."""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.signal import resample_poly

from common.runtime.errors import InputError

# WFDB annotation symbols that mark beats (not rhythm, noise or comment annotations).
BEAT_SYMBOLS = frozenset("NLRBAaJSVrFejnE/fQ?")


@dataclass(frozen=True, slots=True)
class Annotations:
    """A record's reference annotations, all of them: beats, rhythm changes (``aux`` like ``(VFL``) and
    the flutter marks ``[`` ``!`` ``]``; ``subtype`` is WFDB's, which for a signal quality change ``~``
    says which leads are noisy from there on (-1: every lead unreadable)."""

    t_s: NDArray[np.float64]
    symbol: list[str]
    aux: list[str]
    subtype: tuple[int, ...] = ()


@dataclass(frozen=True, slots=True)
class Recording:
    fs: float
    uv: NDArray[np.float64]  # one lead, µV
    beats_s: NDArray[np.float64] | None  # reference beat times, if annotated
    sensor_start_ns: int | None = None  # a Polar export: its first sample on the strap's clock


@dataclass(frozen=True, slots=True)
class AccRecording:
    """A Polar Sensor Logger accelerometer export: each sample on the strap's clock (the ECG's), mg."""

    sensor_ns: NDArray[np.int64]
    xyz_mg: NDArray[np.int64]  # (n, 3)

    @property
    def fs(self) -> float:
        return float(1e9 / np.median(np.diff(self.sensor_ns)))


def resample(x: NDArray[np.float64], fs_in: float, fs_out: float) -> NDArray[np.float64]:
    if fs_in == fs_out:
        return x
    ratio = Fraction(fs_out / fs_in).limit_denominator(1000)
    out: NDArray[np.float64] = resample_poly(x, ratio.numerator, ratio.denominator)
    return out


def _header(p: Path) -> str:
    try:
        with p.open(encoding="utf-8", errors="replace") as f:
            return f.readline().strip()
    except OSError:
        return ""


def is_rr_file(path: str) -> bool:
    """An RR-only file: the Polar Sensor Logger's RR export, or numbers one per line."""
    p = Path(path)
    if not p.is_file():
        return False
    head = _header(p)
    if "RR-interval [ms]" in head:
        return True
    try:
        float(head)
        return True
    except ValueError:
        return False


def read_rr(path: str) -> NDArray[np.float64]:
    """RR intervals in seconds from an RR-only file; values above 10 are taken as milliseconds."""
    p = Path(path)
    polar = "RR-interval [ms]" in _header(p)
    try:
        if polar:
            rr = np.loadtxt(p, delimiter=";", skiprows=1, usecols=1, ndmin=1, dtype=float) / 1000.0
        else:
            rr = np.loadtxt(p, ndmin=1, dtype=float, comments="#")
            rr = rr / 1000.0 if np.median(rr) > 10 else rr
    except (OSError, ValueError) as exc:
        raise InputError(
            f"{p}: cannot read as RR intervals ({'Polar RR export' if polar else 'one per line'}): {exc}"
        ) from None
    if len(rr) < 2 or not np.all(np.isfinite(rr)) or np.any(rr <= 0):
        raise InputError(f"{p}: expected at least 2 positive RR intervals")
    return rr.astype(np.float64)


def read_record(path: str, fs: float | None = None, lead: int = 0) -> Recording:
    """A WFDB record path without extension, a CSV of (time [s], µV) or (time_ns, ecg_mV, …), or a Polar
    Sensor Logger ECG export; resampled to ``fs`` if given."""
    p = Path(path)
    head = _header(p) if p.is_file() else ""
    if "ecg [uV]" in head:
        rec = _read_polar_ecg(p)
    elif head.startswith("time_ns,ecg_mV"):
        rec = _read_ns_mv(p)
    elif p.suffix.lower() == ".csv":
        rec = _read_csv(p)
    elif p.with_suffix(".hea").exists():
        rec = _read_wfdb(p, lead)
    else:
        raise InputError(
            f"{path}: not a CSV file, a Polar Sensor Logger export, nor a WFDB record (no "
            f"{p.with_suffix('.hea').name} beside it)"
        )
    if fs is None or fs == rec.fs:
        return rec
    return Recording(fs, resample(rec.uv, rec.fs, fs), rec.beats_s, rec.sensor_start_ns)


def read_acc(path: str) -> AccRecording:
    """``Phone timestamp;sensor timestamp [ns];X [mg];Y [mg];Z [mg]``: times must increase, and no value
    may be beyond what a chest strap's accelerometer measures (16 g)."""
    from schemas.ecg import MAX_ACC_MG

    p = Path(path)
    if not p.is_file() or "X [mg]" not in _header(p):
        raise InputError(f"{path}: not a Polar Sensor Logger accelerometer export (…_ACC.txt, 'X [mg]')")
    try:
        data = np.loadtxt(p, delimiter=";", skiprows=1, usecols=(1, 2, 3, 4), ndmin=2, dtype=np.int64)
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: cannot read as a Polar Sensor Logger accelerometer export: {exc}") from None
    if len(data) < 3:
        raise InputError(f"{p}: expected at least 3 samples")
    if np.any(dt := np.diff(data[:, 0]) <= 0):
        raise InputError(f"{p}: row {int(np.argmax(dt)) + 3}: time does not increase")  # rows count from 1
    if np.any(big := np.abs(data[:, 1:]) > MAX_ACC_MG):
        raise InputError(f"{p}: row {int(np.argmax(big.any(axis=1))) + 2}: beyond ±{MAX_ACC_MG} mg")
    return AccRecording(data[:, 0], data[:, 1:])


def _read_wfdb(p: Path, lead: int) -> Recording:
    import wfdb

    try:
        r = wfdb.rdrecord(str(p), channels=[lead])
    except Exception as exc:  # wfdb raises many kinds; all mean the same to a user
        raise InputError(f"{p}: cannot read the WFDB record: {exc}") from exc
    units = (r.units or ["mV"])[0].lower()
    scale = 1000.0 if units == "mv" else 1.0
    uv = np.nan_to_num(r.p_signal[:, 0]) * scale
    beats = None
    if p.with_suffix(".atr").exists():
        try:
            a = wfdb.rdann(str(p), "atr")
        except Exception as exc:
            raise InputError(f"{p}.atr: cannot read the annotations: {exc}") from exc
        beats = np.array([s for s, sym in zip(a.sample, a.symbol, strict=True) if sym in BEAT_SYMBOLS]) / r.fs
    return Recording(float(r.fs), uv, beats)


def read_annotations(path: str) -> Annotations:
    """Every reference annotation of a WFDB record (beats, rhythm changes, noise marks), in seconds."""
    import wfdb

    p = Path(path)
    try:
        a = wfdb.rdann(str(p), "atr")
    except Exception as exc:
        raise InputError(f"{p}.atr: cannot read the annotations: {exc}") from exc
    aux = list(a.aux_note) if a.aux_note is not None else [""] * len(a.sample)
    sub = tuple(int(x) for x in a.subtype) if a.subtype is not None else ()
    return Annotations(np.asarray(a.sample, dtype=float) / float(a.fs), list(a.symbol), aux, sub)


def _from_times(p: Path, t_s: NDArray[np.float64], uv: NDArray[np.float64]) -> Recording:
    if len(t_s) < 3:
        raise InputError(f"{p}: expected at least 3 samples")
    dt = np.diff(t_s)
    if np.any(dt <= 0):
        raise InputError(f"{p}: row {int(np.argmax(dt <= 0)) + 2}: time does not increase")
    return Recording(float(1.0 / np.median(dt)), uv.astype(float), None)


def _read_polar_ecg(p: Path) -> Recording:
    """Phone timestamp;sensor timestamp [ns];timestamp [ms];ecg [uV]: the sensor's own clock."""
    try:
        data = np.loadtxt(p, delimiter=";", skiprows=1, usecols=(1, 3), ndmin=2, dtype=np.int64)
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: cannot read as a Polar Sensor Logger ECG export: {exc}") from None
    rec = _from_times(p, (data[:, 0] - data[0, 0]) / 1e9, data[:, 1].astype(float))
    return Recording(rec.fs, rec.uv, None, int(data[0, 0]))


def _read_ns_mv(p: Path) -> Recording:
    """time_ns,ecg_mV[,…]: rows without an ECG value (HR-only rows) are left out."""
    try:
        data = np.genfromtxt(p, delimiter=",", skip_header=1, usecols=(0, 1), dtype=float)
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: cannot read as a CSV of (time_ns, ecg_mV): {exc}") from None
    data = data[np.isfinite(data).all(axis=1)] if data.ndim == 2 else np.zeros((0, 2))
    if len(data) < 3:
        raise InputError(f"{p}: expected at least 3 rows of (time_ns, ecg_mV)")
    return _from_times(p, (data[:, 0] - data[0, 0]) / 1e9, data[:, 1] * 1000.0)


def _read_csv(p: Path) -> Recording:
    try:
        data = np.loadtxt(p, delimiter=",", ndmin=2, comments="#")
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: cannot read as CSV of (time s, µV): {exc}") from exc
    if data.shape[1] < 2 or len(data) < 3:
        raise InputError(f"{p}: expected at least 3 rows of (time s, µV)")
    dt = np.diff(data[:, 0])
    if np.any(dt <= 0):
        raise InputError(f"{p}: row {int(np.argmax(dt <= 0)) + 2}: time does not increase")
    return Recording(float(1.0 / np.median(dt)), data[:, 1].astype(float), None)
