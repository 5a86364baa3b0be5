"""The window scorer of issue 19 on annotations made up here, where every figure is known."""

from __future__ import annotations

import numpy as np
import pytest

from cadence.bench.hrv_scoring import WindowScore, flutter_spans, has_arrhythmia_runs, truth, unreadable_spans
from common.hrv.records import Annotations


def beats(times: list[float], symbols: str, extra: list[tuple[float, str, str]] = ()) -> Annotations:
    rows = sorted([(t, s, "") for t, s in zip(times, symbols, strict=True)] + list(extra))
    return Annotations(np.array([r[0] for r in rows]), [r[1] for r in rows], [r[2] for r in rows])


def test_the_truth_is_the_mean_of_intervals_between_two_normal_beats() -> None:
    t = [i * 1.0 for i in range(31)]
    t[10] = 9.6  # a premature V beat: the intervals into and out of it are not NN
    sym = "N" * 10 + "V" + "N" * 20
    [w] = truth(beats(t, sym), [0.5], 30.0, 31.0)
    # NN intervals closing in [0.5, 30.5): 1..30 less those closing at 9.6 (into V) and 11 (out of it)
    assert w.mean_nn_s == pytest.approx(1.0)
    # no beat at 10 s but a rhythm mark: the mark is not a beat, the 2 s interval spans it (29 intervals)
    [w] = truth(beats(t[:10] + t[11:], "N" * 30, [(10.0, "+", "(N")]), [0.5], 30.0, 31.0)
    assert w.mean_nn_s == pytest.approx(30 / 29)


def test_too_few_nn_intervals_or_flutter_leave_a_window_unscored() -> None:
    t = [i * 1.0 for i in range(40)]
    few = truth(beats(t, "N" * 5 + "V" * 35), [0.0], 30.0, 40.0)
    assert few[0].mean_nn_s is None
    ann = beats(t, "N" * 40, [(12.0, "+", "(VFL"), (14.0, "+", "(N")])
    assert flutter_spans(ann, 40.0) == [(12.0, 14.0)]
    touched, clear = truth(ann, [0.0, 15.0], 10.0, 40.0)
    assert touched.mean_nn_s is None
    assert clear.mean_nn_s == pytest.approx(1.0)
    assert has_arrhythmia_runs(ann)
    assert not has_arrhythmia_runs(beats(t, "N" * 40, [(0.0, "+", "(N")]))


def test_an_interval_across_a_stretch_unreadable_in_every_lead_is_not_in_the_truth() -> None:
    t = [i * 1.0 for i in range(31) if i != 12]  # the beat at 12 s hidden in noise: an 11-13 s "NN interval"
    rows = [(ti, "N", "", 0) for ti in t] + [(11.5, "~", "", -1), (12.5, "~", "", 0), (20.0, "~", "", 1)]
    rows.sort()
    ann = Annotations(
        np.array([r[0] for r in rows]), [r[1] for r in rows], [r[2] for r in rows], tuple(r[3] for r in rows)
    )
    assert unreadable_spans(ann, 31.0) == [(11.5, 12.5)]  # one lead noisy (subtype 1) is still readable
    [w] = truth(ann, [0.5], 30.0, 31.0)
    assert w.mean_nn_s == pytest.approx(1.0)
    [w] = truth(beats(t, "N" * 30), [0.5], 30.0, 31.0)  # unmarked, the 2 s interval is the heart's
    assert w.mean_nn_s == pytest.approx(30 / 29)


def test_the_score_counts_good_and_held_windows_and_their_errors() -> None:
    t = [i * 1.0 for i in range(200)]
    tr = truth(beats(t, "N" * 200), [0.0, 30.0, 60.0, 90.0], 30.0, 200.0)
    sc = WindowScore("x")
    sc.add("r1", tr, [1.004, None, 1.025, 1.0], ["", "excluded", "", ""], sinus=True)
    f = sc.figures()
    assert (f["good"], f["held"], f["over_10_ms"], f["over_20_ms"]) == (3, 1, 1, 1)
    assert f["worst_ms"] == pytest.approx(25.0)
    assert f["worst_records"] == "r1"
    assert f["held_share_sinus"] == pytest.approx(0.25)
    assert sc.held_reasons == {"excluded": 1}


def test_each_window_carries_its_annotated_rhythm_and_the_score_counts_what_passed_inside_each() -> None:
    """Issue 55: a window of SVT read as good is read as if it were sinus rhythm; the score says how many."""
    t = [i * 1.0 for i in range(100)]
    marks = [(0.0, "+", "(N"), (25.0, "+", "(SVTA"), (28.0, "+", "(N"), (60.0, "+", "(AFIB")]
    ann = beats(t, "N" * 100, marks)
    w1, w2, w3 = truth(ann, [0.0, 30.0, 60.0], 30.0, 100.0)
    assert (w1.rhythm, w2.rhythm, w3.rhythm) == ("(SVTA", "(N", "(AFIB")  # 3 s of SVT make it not sinus
    sc = WindowScore("cadence")
    sc.add("r", [w1, w2, w3], [1.0, 1.0, None], ["", "", "irregular"])
    assert sc.by_rhythm == {"(SVTA": [1, 0, 1], "(N": [1, 0, 1], "(AFIB": [1, 1, 0]}
    assert sc.figures()["passed_not_sinus"] == 1
    other = WindowScore("cadence")
    other.add("s", [w1], [None], ["irregular"])
    sc.merge(other)
    assert sc.by_rhythm["(SVTA"] == [2, 1, 1]


def test_the_cross_validation_never_chooses_a_point_that_holds_a_healthy_persons_window() -> None:
    """Of two grid points, the one with the lesser loss holds a window of a GUDB subject (a healthy heart,
    in sinus rhythm whatever it does) on the units it is chosen on: the other is chosen. Left out, that
    subject does not count for its own fold's choice."""
    from cadence.bench.hrv_cv import CrossValidation, grid
    from cadence.bench.hrv_scoring import Truth

    def score(name: str, held_normal: int, over_10: int) -> WindowScore:
        sc = WindowScore(name)
        truths = [Truth(30.0 * i, 30.0 * (i + 1), 1.0) for i in range(10)]
        means = [None] * held_normal + [1.011] * over_10 + [1.0] * (10 - held_normal - over_10)
        sc.add("r", truths, means, ["rhythm"] * 10, sinus=True)
        return sc

    rules = grid({"step": (1.5, 1.6)})
    # point 0 holds one healthy window and erases an error elsewhere; point 1 holds none
    scores = {
        "100": [{("clean", "cadence"): score("cadence", 0, 0)},
                {("clean", "cadence"): score("cadence", 0, 1)}],
        "gudb/subject_00": [{("clean", "gudb-cs"): score("gudb-cs", 1, 0)},
                            {("clean", "gudb-cs"): score("gudb-cs", 0, 0)}],
    }  # fmt: skip
    cv = CrossValidation(rules, sorted(scores), scores)
    assert cv.losses()["100"][0] < cv.losses()["100"][1]
    assert list(cv.healthy_held()) == [1, 0]
    assert cv.chosen() == 1
    assert cv.chosen(leave_out="gudb/subject_00") == 0  # its own hold is not its fold's to see
