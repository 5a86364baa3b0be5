"""Benchmark of R-peak detection at 130 Hz on the shared annotated records, against established
detectors in the same run (NeuroKit2, py-ecg-detectors). Prints every figure; asserts only quality."""

from __future__ import annotations

import pytest

from cadence.bench import bench_hrv
from tests.test_rpeaks import ECG, needs_data


@needs_data
def test_bench_hrv_against_established_detectors() -> None:
    scores, extra = bench_hrv(str(ECG))
    for s in sorted(scores, key=lambda x: -x.f1):
        print(f"{s.name:40s} Se {s.se:.4f} PPV {s.ppv:.4f} F1 {s.f1:.4f} {s.realtime:8.0f}x real time")
    print(extra)
    ours = next(s for s in scores if s.name == "cadence")
    others = [s for s in scores if s.name != "cadence"]
    if not others:
        pytest.skip("no established detector installed (uv sync --extra bench)")
    assert ours.f1 >= 0.99
    assert extra["window_err_median_ms"] <= 2.0
