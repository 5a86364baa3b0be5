"""Heart-rate variability: ``hrv/beats`` and ``hrv/window`` (paper §II-C; DESIGN §6)."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.base import RR_MAX_S, Fraction, Message, RrSeconds, TimeNs

Quality = Literal["good", "low", "none"]
# why a window is not good: data missing in it, too many of its intervals excluded by the cleaning, too
# little of it covered by clean intervals, no clean interval at all, or a burst of noise in which beats
# were excluded (how many beats it hides cannot be told)
HoldReason = Literal["gap", "excluded", "coverage", "no_clean_beats", "noise", "irregular", "rhythm"]
MAX_WINDOW_S = 600.0  # a window is 30 s by default; none is longer than ten minutes
MAX_BEATS = 1000  # per Beats message, and far above what a window at 300 bpm can hold (x 3 for 600 s)
Spread = Annotated[float, msgspec.Meta(ge=0.0, le=RR_MAX_S)]


class Beats(Message, frozen=True, tag="hrv.beats.v1"):
    """Detected R peaks (data time, ns) and the RR interval ending at each (0 for the first peak of a
    segment); ``excluded`` flags the intervals the cleaning leaves out."""

    peak_t_ns: Annotated[list[TimeNs], msgspec.Meta(max_length=MAX_BEATS)]
    rr_s: Annotated[
        list[Annotated[float, msgspec.Meta(ge=0.0, le=MAX_WINDOW_S)]], msgspec.Meta(max_length=MAX_BEATS)
    ]
    excluded: Annotated[list[bool], msgspec.Meta(max_length=MAX_BEATS)]

    def __post_init__(self) -> None:
        if not len(self.peak_t_ns) == len(self.rr_s) == len(self.excluded):
            raise ValueError("peak_t_ns, rr_s and excluded must have one entry per beat")


class HrvWindow(Message, frozen=True, tag="hrv.window.v1"):
    """One tumbling window; ``t_ns`` is its end. ``mean_rr_s`` is None when no clean beat was left."""

    start_ns: TimeNs
    end_ns: TimeNs
    mean_rr_s: RrSeconds | None
    n_beats: Annotated[int, msgspec.Meta(ge=0, le=3 * MAX_BEATS)]
    excluded_fraction: Fraction
    quality: Quality
    rmssd_s: Spread | None = None
    sdnn_s: Spread | None = None
    reason: HoldReason | None = None  # why the window is not good (a new field: old decoders skip it)
    # the wearer's movement over the window, from the strap's accelerometer (None: no accelerometer data
    # for enough of it): the mean dynamic acceleration (gravity removed), and the share of its seconds
    # spent moving
    movement_mg: Annotated[float, msgspec.Meta(ge=0.0, le=32_000.0)] | None = None
    moving_fraction: Fraction | None = None

    def __post_init__(self) -> None:
        if not self.start_ns < self.end_ns:
            raise ValueError(f"the window starts ({self.start_ns}) at or after its end ({self.end_ns})")
        if self.end_ns - self.start_ns > MAX_WINDOW_S * 1e9:
            raise ValueError(f"the window is longer than {MAX_WINDOW_S:g} s")
        if self.quality == "good" and self.mean_rr_s is None:
            raise ValueError("a good window has a mean RR")
        if self.quality == "good" and self.reason is not None:
            raise ValueError(f"a good window has no reason to be held (got {self.reason!r})")
