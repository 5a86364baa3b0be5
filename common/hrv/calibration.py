"""The subject's resting level (paper §III-B; DESIGN §7): measured by `cadence calibrate` from the
windows of a few minutes at rest, stored in the data folder, published on ``operator/calibration``, and
loaded by the decision maker at start. The one place that knows the file and how RR_r is taken.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import msgspec
import numpy as np

from common.runtime.storage import Loaded, atomic_write, load_checked
from schemas.hrv import Quality
from schemas.operator import Calibration

CALIBRATION_FILE = "calibration.json"  # in the data folder
MIN_GOOD_SHARE = 0.6  # fewer good windows than this share at rest: the strap, not the subject


class GradedWindow(Protocol):
    """What a resting level needs of a window: ``HrvWindow`` on the bus, ``Window`` in a stream."""

    @property
    def mean_rr_s(self) -> float | None: ...
    @property
    def quality(self) -> Quality: ...
    @property
    def sdnn_s(self) -> float | None: ...


@dataclass(frozen=True, slots=True)
class RestingLevel:
    rr_rest_s: float  # mean of the good windows' mean RR
    sigma_s: float  # spread of RR at rest: the mean of the good windows' SDNN
    good: int
    total: int


def resting_level(wins: Sequence[GradedWindow], min_good_share: float = MIN_GOOD_SHARE) -> RestingLevel:
    """RR_r for the decision rule from a calibration's windows; ValueError when too few are good."""
    good = [w for w in wins if w.quality == "good" and w.mean_rr_s is not None]
    if not wins or len(good) < min_good_share * len(wins):
        raise ValueError(f"only {len(good)} of {len(wins)} windows are of good quality; check the strap")
    sdnn = [w.sdnn_s for w in good if w.sdnn_s is not None]
    return RestingLevel(
        float(np.mean([w.mean_rr_s for w in good])),
        float(np.mean(sdnn)) if sdnn else 0.0,
        len(good),
        len(wins),
    )


def calibration(
    wins: Sequence[GradedWindow], subject: str, t_ns: int, measured_sigma: bool
) -> tuple[Calibration, RestingLevel]:
    """The message for a subject's resting windows: σ_r stays the paper's (the message's default) unless
    ``measured_sigma`` asks for the good windows' mean SDNN."""
    level = resting_level(wins)
    sigma = {"sigma_rest_s": round(level.sigma_s, 6)} if measured_sigma and level.sigma_s > 0 else {}
    cal = Calibration(t_ns=t_ns, seq=0, subject=subject, rr_rest_s=round(level.rr_rest_s, 6), **sigma)
    return cal, level


def calibration_path(data_dir: Path) -> Path:
    return data_dir / CALIBRATION_FILE


def store_calibration(data_dir: Path, cal: Calibration) -> Path:
    path = calibration_path(data_dir)
    atomic_write(path, msgspec.json.encode(cal))
    return path


def load_calibration(data_dir: Path) -> Loaded[Calibration]:
    """The stored calibration; a damaged file is moved aside and ``problem`` says so."""
    return load_checked(calibration_path(data_dir), lambda b: msgspec.json.decode(b, type=Calibration))
