"""The streaming R-peak detector on the shared annotated recordings (MIT-BIH), resampled to 130 Hz."""

from __future__ import annotations

import numpy as np
import pytest

from common.hrv.records import read_record
from common.hrv.rpeaks import detect
from common.hrv.stream import match_beats
from tests.conftest import SHARED_DATA

ECG = SHARED_DATA / "ecg"
RECORDS = ["100", "101", "103", "105", "106", "119", "201", "208"]
needs_data = pytest.mark.skipif(not ECG.exists(), reason=f"the shared recordings are not at {ECG}")


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
