"""A calibration that says whether a person can be read, a baseline in the posture of the work, the
paper's σ, and the gate that waits until the person has settled (issue 26)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common.hrv.calibration import SETTLED_S, calibration, resting_level, settled, verdict
from common.hrv.records import read_record
from common.hrv.stream import HrvStream, Window, intervals, windows
from schemas.operator import Calibration
from tests.support.data import ECG, needs_data

GUDB = Path(__file__).resolve().parents[2] / "shared" / "data" / "gudb"
needs_gudb = pytest.mark.skipif(not GUDB.is_dir(), reason=f"{GUDB} is absent (the shared GUDB beats)")


def streamed(record: str, minutes: float) -> list[Window]:
    """The windows the HRV analyser gives for the first ``minutes`` of a record, streamed in 0.1 s chunks."""
    rec = read_record(str(ECG / record), fs=130.0)
    x = rec.uv[: round(minutes * 60 * 130)]
    stream = HrvStream(130.0)
    out: list[Window] = []
    for i in range(0, len(x), 13):
        out += stream.feed(i / 130.0, x[i : i + 13])[1]
    return out + stream.flush()[1]


@needs_data
def test_an_ecg_that_cannot_be_read_gets_a_verdict_that_says_why_and_never_settles() -> None:
    """201 in atrial fibrillation: no window's mean RR says what load does, so the calibration refuses
    with the reason in words, and a session's gate would wait, saying what is wrong, never start."""
    wins = streamed("201", 5.0)
    v = verdict(wins)
    assert v.total == 10
    assert v.readable < 0.6
    assert v.problem is not None
    assert v.problem.startswith("this ECG cannot be read reliably")
    assert "irregular" in v.problem
    assert "atrial fibrillation" in v.problem
    with pytest.raises(ValueError, match="cannot be read reliably"):
        resting_level(wins)
    why = settled(wins, 0.7)
    assert why is not None
    assert "held" in why


@needs_data
@pytest.mark.parametrize("record", ["100", "109"])
def test_a_readable_ecg_calibrates_and_is_settled_at_its_own_level(record: str) -> None:
    """A normal rhythm, and a left bundle branch block (109: wide QRS, large T waves, every beat a normal
    one) that issue 19's rules held in every window: both are read, and settled at their baseline."""
    wins = streamed(record, 5.0)
    level = resting_level(wins)
    assert level.verdict.problem is None, level.verdict.lines()
    assert level.verdict.readable >= 0.9, level.verdict.lines()
    assert settled(wins, level.rr_rest_s) is None
    assert settled(wins, level.rr_rest_s + 2 * SETTLED_S) is not None  # far from it: not settled


def test_measured_sigma_is_the_spread_of_the_windows_means_not_the_beats_within_them() -> None:
    """The paper's σ_r is the standard deviation of mean RR between windows (Villani 2018), not SDNN."""
    means = [0.80, 0.82, 0.84, 0.78, 0.81]
    wins = [Window(30.0 * i, 30.0 * (i + 1), m, 37, 0.0, "good", 0.03, 0.05) for i, m in enumerate(means)]
    cal, level = calibration(wins, "s1", 1, measured_sigma=True)
    assert level.sigma_s == pytest.approx(float(np.std(means, ddof=1)))
    assert cal.sigma_rest_s == pytest.approx(float(np.std(means, ddof=1)), abs=1e-6)
    assert calibration(wins, "s1", 1, measured_sigma=False)[0].sigma_rest_s == 0.14  # the paper's default


def gudb_windows(subject: str, activity: str) -> list[Window]:
    beats = np.loadtxt(GUDB / subject / activity / "annotation_cs.tsv") / 250.0
    return windows(intervals(beats), 30.0, float(beats[0]), float(beats[-1]))


@needs_gudb
def test_a_baseline_taken_at_work_matches_the_work_where_one_taken_seated_does_not() -> None:
    """GUDB subject 08 sitting, then walking: against the seated baseline the walking windows are far below
    RR_r (read as stress by Alg. 1; the gate does not let a session start); against a baseline taken
    walking (--posture working) they are settled, and the level at rest is kept beside it."""
    sitting, walking = gudb_windows("subject_08", "sitting"), gudb_windows("subject_08", "walking")
    rest, _ = calibration(sitting, "s08", 1, measured_sigma=False)
    assert rest.posture == "rest"
    assert rest.rr_resting_s is None
    assert np.mean([w.mean_rr_s for w in walking]) < rest.rr_rest_s - 2 * SETTLED_S  # walking lowers RR
    assert settled(walking, rest.rr_rest_s) is not None
    work, _ = calibration(walking, "s08", 2, measured_sigma=False, posture="working", resting=rest)
    assert work.posture == "working"
    assert work.rr_resting_s == rest.rr_rest_s
    assert settled(walking, work.rr_rest_s) is None
    other = Calibration(t_ns=1, seq=0, subject="someone-else", rr_rest_s=0.9)
    assert calibration(walking, "s08", 2, False, "working", other)[0].rr_resting_s is None  # not theirs
