"""Session files (cadence/lab/session_file.py) and their analysis (cadence/lab/analysis.py): the measures are
taken between the session's start and end, a file that cannot stand for its session is refused with the
reason, and each pair of conditions gets the Wilcoxon test scipy can give, with its method said."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cadence.lab.analysis import analyse, paired_test
from cadence.lab.session_file import load_session
from cadence.tools.recording import Recorder
from common.runtime.errors import InputError
from schemas import Calibration, OperatorError
from schemas.session import SessionEnd
from schemas.topology import encode
from tests.support.cell import CELL
from tests.support.sessions import T0, S, info, state, window, write, writer


def test_a_session_counts_what_happened_between_its_start_and_end(tmp_path: Path) -> None:
    s = load_session(write(tmp_path / "s.mcap", info()))
    assert s.minutes == pytest.approx(2.0)
    assert s.n_cycles == 10
    assert s.n_errors == 3
    assert s.productivity_per_min == pytest.approx(5.0)
    assert s.error_rate == pytest.approx(0.3)
    assert s.mean_rr_s == pytest.approx(0.8)  # the held window (0.5 s) does not count
    assert s.mean_rr_norm == pytest.approx(0.8 / 0.9)


def test_a_file_that_cannot_stand_for_its_session_is_refused_with_the_reason(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no calibration"):
        load_session(write(tmp_path / "nocal.mcap", info(cal=None)))

    # killed mid-session: the writer never finished the file
    w = writer(tmp_path / "killed.mcap", info())
    w.put("robot/state", state(1.0), T0 + S)
    w.recorder._file.flush()
    with pytest.raises(InputError, match="incomplete or damaged"):
        load_session(tmp_path / "killed.mcap")

    plain = Recorder(tmp_path / "plain.mcap")  # `cadence record`, not a session
    plain.write(f"cadence/{CELL}/robot/state", encode(state(1.0)))
    plain.close()
    with pytest.raises(InputError, match="not a session file"):
        load_session(tmp_path / "plain.mcap")

    w = writer(tmp_path / "cells.mcap", info())
    w.put("robot/state", state(1.0), T0 + S)
    w.recorder.write("cadence/cell2/robot/state", encode(state(2.0)), T0 + 2 * S)
    w.close(SessionEnd(end_ns=T0 + 60 * S, complete=True))
    with pytest.raises(InputError, match=f"mixes cells: keys of {CELL}, cell2"):
        load_session(tmp_path / "cells.mcap")


def test_publishers_on_different_clocks_are_a_mixed_clock_error(tmp_path: Path) -> None:
    # a 10× replay of the strap beside a live executor at 1×: log time is the wall clock here
    w = writer(tmp_path / "rates.mcap", info())
    for t in range(0, 40):
        w.put("robot/state", state(t), T0 + t * S)
        w.put("hrv/window", window(30 + 10 * t, 0.8), T0 + t * S)
    w.close(SessionEnd(end_ns=T0 + 40 * S, complete=True))
    with pytest.raises(InputError, match=r"mixes clocks: data time runs at 10× .* but 1× on robot"):
        load_session(tmp_path / "rates.mcap")

    # the same rate, but an old recording replayed: its data time is a day behind the executor's
    w = writer(tmp_path / "offset.mcap", info())
    for t in range(0, 40):
        w.put("robot/state", state(t), T0 + t * S)
        w.put("hrv/window", window(t - 86_400, 0.8), T0 + t * S)
    w.close(SessionEnd(end_ns=T0 + 40 * S, complete=True))
    with pytest.raises(InputError, match="mixes clocks: robot/state's data time is 86400 s ahead of hrv/"):
        load_session(tmp_path / "offset.mcap")


def test_calibrated_at_work_the_study_shows_mean_rr_over_the_level_at_rest_too(tmp_path: Path) -> None:
    """At work (k = 1) RR_r is the working level: mean RR / RR_r is about 1 in (b) by construction. The
    level at rest the calibration kept gives the measure the conditions compare on."""
    from cadence.lab.analysis import RESTING

    working = Calibration(t_ns=T0, seq=0, subject="s1", rr_rest_s=0.75, posture="working", rr_resting_s=0.9)
    s = load_session(write(tmp_path / "w.mcap", info(cal=working)))
    assert s.mean_rr_norm == pytest.approx(0.8 / 0.75)
    assert s.mean_rr_resting_norm == pytest.approx(0.8 / 0.9)
    files = [
        write(tmp_path / f"{c}.mcap", info(condition=c, cal=working), rr=rr)
        for c, rr in (("a", 0.7), ("b", 0.8))
    ]
    study = analyse([load_session(f) for f in files])
    assert RESTING in study.metrics
    assert study.table["b"][RESTING][0] == pytest.approx(0.8 / 0.9)
    assert any("calibrated at work" in n for n in study.notes)
    at_rest = analyse([load_session(write(tmp_path / "r.mcap", info()))])
    assert RESTING not in at_rest.metrics  # at rest it is mean RR / RR_r itself


def test_analysis_pairs_by_subject_and_refuses_two_sessions_of_one_condition(tmp_path: Path) -> None:
    files = []
    for i, subject in enumerate(("s1", "s2", "s3")):
        a, b = info(subject, "a"), info(subject, "b")
        files.append(write(tmp_path / f"{subject}_a.mcap", a, rr=0.7 + 0.01 * i, cycles=10 + i))
        files.append(write(tmp_path / f"{subject}_b.mcap", b, rr=0.85 + 0.02 * i, cycles=3))
    study = analyse([load_session(f) for f in files])
    assert study.conditions == ["a", "b"]
    assert not study.simulated
    mean, sd, n = study.table["a"]["productivity_per_min"]
    assert (mean, n) == (pytest.approx(5.5), 3)
    assert sd == pytest.approx(0.5)
    t = study.tests["a-b"]["mean_rr_s"]
    assert t.n == 3
    assert t.method == "exact"
    assert t.p == pytest.approx(0.25)  # 2 / 2³, all three go up
    assert t.median_difference == pytest.approx(0.16)
    with pytest.raises(InputError, match="two sessions of subject s1 in condition a"):
        analyse([load_session(f) for f in files] + [load_session(files[0])])


def test_the_wilcoxon_method_is_the_one_scipy_can_give() -> None:
    x = np.arange(12.0)
    exact = paired_test(x, x + np.linspace(0.1, 1.2, 12))
    assert exact.method == "exact"
    assert exact.p == pytest.approx(2 / 2**12)
    tied = paired_test(x, x + 0.5)  # every difference the same: ties, so no exact distribution
    assert tied.method == "normal approximation"
    assert tied.p < 0.01
    zero = paired_test(x, x.copy())
    assert zero.p == 1.0
    assert zero.method.startswith("none")
    assert paired_test(np.array([]), np.array([])).n == 0


def test_the_live_views_keys_mark_errors_and_signal_parts() -> None:
    from cadence.lab.session import key_message
    from schemas import OperatorSignal

    names = ["b2_clear", "part_a2", "part_c2"]
    late = key_message("l", names, T0)
    assert isinstance(late, OperatorError)
    assert (late.kind, late.source, late.t_ns) == ("late", "experimenter", T0)
    part = key_message("2", names, T0)
    assert isinstance(part, OperatorSignal)
    assert (part.name, part.source) == ("part_a2", "keyboard")
    assert key_message("4", names, T0) is None
    assert key_message("q", names, T0) is None
