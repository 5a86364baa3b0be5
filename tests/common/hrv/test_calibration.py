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
from tests.support.paths import SHARED_DATA

GUDB = SHARED_DATA / "gudb"
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


def _window(end_s: float, mean_rr_s: float) -> bytes:
    import msgspec

    from schemas.hrv import HrvWindow

    end = round(end_s * 1e9)
    w = HrvWindow(t_ns=end, seq=0, start_ns=end - 10**10, end_ns=end, mean_rr_s=mean_rr_s, n_beats=12,
                  excluded_fraction=0.0, quality="good")  # fmt: skip
    return msgspec.msgpack.encode(w)


def _gate(settle_s: float, ready_s: float = 120.0):
    from cadence.lab.session import SessionOptions, Watch
    from common.runtime.resources import EXAMPLE_TASK

    opts = SessionOptions(subject="s", condition="b", minutes=1.0, out=Path("unused.mcap"),
                          data_dir=Path("."), task=EXAMPLE_TASK, settle_timeout_s=settle_s,
                          ready_timeout_s=ready_s)  # fmt: skip
    return Watch(), opts


def test_the_settle_gate_counts_the_persons_time_not_the_hosts() -> None:
    """A person who stays 100 ms above the baseline: the gate gives up after its timeout of *data* time,
    however fast the cell runs (here hours of windows in well under a second of wall time: a sped-up
    demo cell, where a wall-clock gate waited hours of heart and ran past a lab test's bound), and one
    who comes back to the baseline is let through the moment they do."""
    import asyncio

    from cadence.lab.session import Watch, until_settled
    from common.runtime.errors import CadenceError

    async def run(rr: list[float], settle_s: float) -> str:
        watch, opts = _gate(settle_s)
        shown = asyncio.Event()  # the gate looked and waits: the next window comes (in lockstep)
        looked: list[float] = []  # the data time at each look

        def show(_: str, w: Watch, __: object) -> None:
            looked.append(w.data_ns / 1e9)
            shown.set()

        async def feed() -> None:
            for i, r in enumerate(rr, start=1):
                await shown.wait()
                shown.clear()
                watch.on("cadence/c/hrv/window", _window(100.0 + 10 * i, r))

        watch.on("cadence/c/hrv/window", _window(100.0, 0.9))  # the data time the gate starts at
        feeder = asyncio.create_task(feed())
        try:
            await asyncio.wait_for(until_settled(watch, 0.8, opts, asyncio.Event(),
                                                 show), 10)  # fmt: skip
        except CadenceError as e:
            return f"{e} @ {looked[-1]:.0f}"
        finally:
            feeder.cancel()
        return f"through @ {watch.data_ns / 1e9:.0f}"

    # 100 ms above RR_r, windows for 200 s: refused at the first window past 60 s of data time
    why = asyncio.run(run([0.9] * 20, 60.0))
    assert "has not settled" in why and "after 60 s" in why, why
    assert why.endswith("@ 170"), why  # from 100 s: 60 s, and the window that passed it
    # the same person, back at the baseline after four windows: through at the second settled one
    assert asyncio.run(run([0.9] * 4 + [0.8] * 6, 60.0)) == "through @ 160"


def test_the_settle_gate_says_when_the_cells_data_stops() -> None:
    """No data time passes when nothing comes: the gate would wait for ever, so data that stops for the
    session's ready timeout (wall time: nothing else is there to count) is an error that says so."""
    import asyncio

    from cadence.lab.session import until_settled
    from common.runtime.errors import CadenceError

    watch, opts = _gate(600.0, ready_s=0.3)
    watch.on("cadence/c/hrv/window", _window(100.0, 0.9))
    with pytest.raises(CadenceError, match=r"no data from the cell for 0\.3 s"):
        asyncio.run(asyncio.wait_for(until_settled(watch, 0.8, opts, asyncio.Event(), lambda *_: None), 30))
