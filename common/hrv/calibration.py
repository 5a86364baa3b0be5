"""The subject's baseline (paper §III-B; DESIGN §7): measured by `cadence calibrate` from the windows of
a few minutes at rest or at work, stored in the data folder, published on ``operator/calibration``, and
loaded by the decision maker at start. The one place that knows the file and how RR_r is taken; and
what a person at the strap is told: whether their ECG can be read (``verdict``), and whether they have
settled before a session starts (``settled``).
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
from schemas.operator import Calibration, Posture

CALIBRATION_FILE = "calibration.json"  # in the data folder
MIN_GOOD_SHARE = 0.6  # fewer good windows than this share at rest: the strap, not the subject


SETTLED_S = 0.04  # a window this near the baseline (two decision steps): the person has settled
SETTLED_WINDOWS = 2  # in a row, and good, before a session starts

# why a window was held, in words a person at the strap can act on
HOLD_WORDS: dict[str, str] = {
    "noise": "the signal is noisy between beats (electrode contact: wet the strap, tighten it)",
    "excluded": "too many beats are unlike the person's own or out of rhythm (frequent ectopic beats?)",
    "irregular": "the rhythm is irregular beat to beat (atrial fibrillation?): its mean RR does not follow "
    "load",
    "rhythm": "the heart rate jumped from one beat to the next (a run of fast beats, or a beat in two not "
    "conducted?): its mean RR does not follow load until the rate comes back",
    "gap": "the signal dropped out (the strap lost contact or the link)",
    "coverage": "too few clean beats cover the window",
    "no_clean_beats": "no clean beat at all (is the strap on?)",
}


class GradedWindow(Protocol):
    """What a calibration needs of a window: ``HrvWindow`` on the bus, ``Window`` in a stream."""

    @property
    def mean_rr_s(self) -> float | None: ...
    @property
    def quality(self) -> Quality: ...
    @property
    def reason(self) -> str | None: ...
    @property
    def excluded_fraction(self) -> float: ...


@dataclass(frozen=True, slots=True)
class Verdict:
    """Whether this person's ECG can be read: the one screen after a calibration. A strap
    that gives no good window is never a silent 100 % hold: ``problem`` says why, in words."""

    good: int
    total: int
    excluded: float  # the mean share of beats the cleaning left out, over all windows
    reasons: dict[str, int]  # why the others were held

    @property
    def readable(self) -> float:
        return self.good / self.total if self.total else 0.0

    @property
    def problem(self) -> str | None:
        if self.total and self.readable >= MIN_GOOD_SHARE:
            return None
        if not self.reasons:
            return "this ECG cannot be read reliably: no window yet"
        why = max(self.reasons, key=lambda r: self.reasons[r])
        return (
            f"this ECG cannot be read reliably: {self.total - self.good} of {self.total} windows held, most "
            f"({self.reasons[why]}) because {HOLD_WORDS.get(why, why)}"
        )

    def lines(self) -> list[str]:
        held = ", ".join(f"{r} {n}" for r, n in sorted(self.reasons.items(), key=lambda kv: -kv[1]))
        return [
            f"readable windows: {self.good} of {self.total} ({self.readable * 100:.0f} %)"
            + (f"; held: {held}" if held else ""),
            f"beats left out by the cleaning: {self.excluded * 100:.1f} % (the beat template and the noise "
            "level are learnt for this person as it reads)",
            self.problem or "this ECG can be read: the decision will follow this person's windows",
        ]


def verdict(wins: Sequence[GradedWindow]) -> Verdict:
    reasons: dict[str, int] = {}
    for w in wins:
        if w.quality != "good":
            why = w.reason or "no_clean_beats"
            reasons[why] = reasons.get(why, 0) + 1
    good = sum(1 for w in wins if w.quality == "good" and w.mean_rr_s is not None)
    excluded = float(np.mean([w.excluded_fraction for w in wins])) if wins else 1.0
    return Verdict(good, len(wins), excluded, reasons)


@dataclass(frozen=True, slots=True)
class RestingLevel:
    rr_rest_s: float  # mean of the good windows' mean RR
    sigma_s: float  # the paper's σ: the spread (sd) of the good windows' mean RR; 0 with fewer than two
    good: int
    total: int
    verdict: Verdict


def resting_level(wins: Sequence[GradedWindow]) -> RestingLevel:
    """RR_r for the decision rule from a calibration's windows; ValueError (the verdict's words) when too
    few are good to trust it.

    σ is the paper's: the standard deviation of the mean RR between windows (§III-B, from Villani 2018),
    which Alg. 1's range RR_r + σ_r is about, not the spread of beats within a window (SDNN, some 50 ms
    at rest, which would move k₀ to 12)."""
    v = verdict(wins)
    if v.problem is not None:
        raise ValueError(v.problem)
    means = [w.mean_rr_s for w in wins if w.quality == "good" and w.mean_rr_s is not None]
    sigma = float(np.std(means, ddof=1)) if len(means) >= 2 else 0.0
    return RestingLevel(float(np.mean(means)), sigma, len(means), len(wins), v)


def calibration(
    wins: Sequence[GradedWindow],
    subject: str,
    t_ns: int,
    measured_sigma: bool,
    posture: Posture = "rest",
    resting: Calibration | None = None,
) -> tuple[Calibration, RestingLevel]:
    """The message for a subject's calibration windows: σ_r stays the paper's (the message's default)
    unless ``measured_sigma`` asks for the spread of the good windows' means. A working calibration keeps
    ``resting``'s level (the same subject's stored calibration at rest), when there is one. Windows with a
    movement figure (a strap with its accelerometer) give the level of movement the calibration saw: the
    median, robust to a person settling the strap, and the spread."""
    level = resting_level(wins)
    moves = [m for w in wins if (m := getattr(w, "movement_mg", None)) is not None]
    movement = (
        {"movement_mg": round(float(np.median(moves)), 1), "movement_sd_mg": round(float(np.std(moves)), 1)}
        if len(moves) >= 2
        else {}
    )
    sigma = {"sigma_rest_s": round(level.sigma_s, 6)} if measured_sigma and level.sigma_s > 0 else {}
    kept = None
    if posture == "working" and resting is not None and resting.subject == subject:
        kept = resting.rr_rest_s if resting.posture == "rest" else resting.rr_resting_s
    cal = Calibration(
        t_ns=t_ns,
        seq=0,
        subject=subject,
        rr_rest_s=round(level.rr_rest_s, 6),
        posture=posture,
        rr_resting_s=kept,
        **sigma,
        **movement,
    )
    return cal, level


def settled(wins: Sequence[GradedWindow], baseline_s: float) -> str | None:
    """None when the last SETTLED_WINDOWS windows are good and within SETTLED_S of the baseline: the
    person's rhythm has settled where the calibration put it, so Alg. 1's first step (from RR_{-1} =
    RR_r) reads load, not the walk to the cell. Else what is still wrong."""
    last = list(wins)[-SETTLED_WINDOWS:]
    if len(last) < SETTLED_WINDOWS:
        return f"{len(last)} of {SETTLED_WINDOWS} windows seen"
    for w in last:
        if w.quality != "good" or w.mean_rr_s is None:
            return f"a window is held ({HOLD_WORDS.get(w.reason or '', w.reason or 'no beats')})"
        off = w.mean_rr_s - baseline_s
        if abs(off) > SETTLED_S:
            return (
                f"mean RR {w.mean_rr_s:.3f} s is {abs(off) * 1e3:.0f} ms {'below' if off < 0 else 'above'} "
                f"the baseline {baseline_s:.3f} s (settled: within {SETTLED_S * 1e3:.0f} ms)"
            )
    return None


def calibration_path(data_dir: Path) -> Path:
    return data_dir / CALIBRATION_FILE


def store_calibration(data_dir: Path, cal: Calibration) -> Path:
    path = calibration_path(data_dir)
    atomic_write(path, msgspec.json.encode(cal))
    return path


def load_calibration(data_dir: Path) -> Loaded[Calibration]:
    """The stored calibration; a damaged file is moved aside and ``problem`` says so."""
    return load_checked(calibration_path(data_dir), lambda b: msgspec.json.decode(b, type=Calibration))
