"""Heart-rate variability: ``hrv/beats`` and ``hrv/window`` (paper §II-C; DESIGN §6)."""

from __future__ import annotations

from typing import Literal

from schemas.base import Message, NonNegInt, PositiveFloat

Quality = Literal["good", "low", "none"]


class Beats(Message, frozen=True, tag="hrv.beats.v1"):
    """Detected R peaks (data time, ns) and the RR interval ending at each; excluded ones are flagged."""

    peak_t_ns: list[int]
    rr_s: list[float]
    excluded: list[bool]


class HrvWindow(Message, frozen=True, tag="hrv.window.v1"):
    """One tumbling window; ``t_ns`` is its end. ``mean_rr_s`` is None when no clean beat was left."""

    start_ns: NonNegInt
    end_ns: NonNegInt
    mean_rr_s: PositiveFloat | None
    n_beats: NonNegInt
    excluded_fraction: float
    quality: Quality
    rmssd_s: float | None = None
    sdnn_s: float | None = None
