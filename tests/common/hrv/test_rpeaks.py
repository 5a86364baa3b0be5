"""The streaming R-peak detector on the shared annotated recordings (MIT-BIH), resampled to 130 Hz."""

from __future__ import annotations

import numpy as np
import pytest

from common.hrv.records import read_record
from common.hrv.rpeaks import detect
from common.hrv.stream import match_beats
from tests.support.data import ECG, needs_data

RECORDS = ["100", "101", "103", "105", "106", "119", "201", "208"]


@needs_data
@pytest.mark.parametrize("chunk", [1, 73, 130 * 7])
def test_chunked_and_whole_record_input_give_identical_peaks(chunk: int) -> None:
    rec = read_record(str(ECG / "208"), fs=130.0)
    x = rec.uv[: 130 * 180]
    np.testing.assert_array_equal(detect(x, 130.0, chunk=chunk), detect(x, 130.0))


@needs_data
def test_f1_at_130_hz_over_the_shared_records_is_at_least_99_percent() -> None:
    total = np.zeros(3, int)
    for name in RECORDS:
        rec = read_record(str(ECG / name), fs=130.0)
        tp, fp, fn = match_beats(rec.beats_s, detect(rec.uv, 130.0, chunk=73) / 130.0)
        print(
            f"{name}: Se {tp / (tp + fn):.4f} PPV {tp / (tp + fp):.4f} F1 {2 * tp / (2 * tp + fp + fn):.4f}"
        )
        total += (tp, fp, fn)
    tp, fp, fn = total
    f1 = 2 * tp / (2 * tp + fp + fn)
    print(f"all: F1 {f1:.4f}")
    assert f1 >= 0.99


@needs_data
def test_ventricular_beats_are_unlike_the_template_and_normal_beats_like_it() -> None:
    """What RR cannot tell (a PVC only mildly early), the QRS can: on 208, matched to the annotations."""
    from common.hrv.records import read_annotations
    from common.hrv.rpeaks import LIKE, detect_peaks

    rec, ann = read_record(str(ECG / "208"), fs=130.0), read_annotations(str(ECG / "208"))
    peaks = detect_peaks(rec.uv[: 130 * 300], 130.0, chunk=13)
    t = np.array([p.sample / 130.0 for p in peaks])
    like = np.array([p.likeness for p in peaks])

    def likeness_of(symbol: str) -> np.ndarray:
        at = [s for s, sym in zip(ann.t_s, ann.symbol, strict=True) if sym == symbol and s < 299.0]
        nearest = [int(np.argmin(np.abs(t - s))) for s in at]
        return np.array([like[i] for i, s in zip(nearest, at, strict=True) if abs(t[i] - s) < 0.15])

    normal, ventricular = likeness_of("N"), likeness_of("V")
    assert normal.size > 200
    assert ventricular.size > 100
    assert np.mean(normal >= LIKE) >= 0.99
    assert np.mean(ventricular < LIKE) >= 0.95


@needs_data
def test_a_burst_of_noise_is_noise_between_the_beats_around_it() -> None:
    from scipy import signal

    from common.hrv.rpeaks import detect_peaks

    rec = read_record(str(ECG / "100"), fs=130.0)
    x = rec.uv[: 130 * 120].copy()
    burst = signal.sosfilt(
        signal.butter(2, (5.0, 15.0), btype="band", fs=130.0, output="sos"),
        np.random.default_rng(1).normal(size=130),
    )
    qrs = np.percentile(np.abs(x - np.median(x)), 99.5)
    x[130 * 60 : 130 * 61] += 1.5 * qrs * burst / np.max(np.abs(burst))  # 1 s at 60 s, taller than a QRS
    peaks = detect_peaks(x, 130.0, chunk=13)
    hit = [p.noise for p in peaks if 60.0 < p.sample / 130.0 < 62.0]
    rest = [p.noise for p in peaks[1:] if not 59.5 < p.sample / 130.0 < 63.0]
    # relative to the person's own level between beats (about 1 on a clean ECG)
    assert max(hit) > 3.0
    assert max(rest) < 1.5
