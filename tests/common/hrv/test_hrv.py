"""RR cleaning and windows: against the annotations of the shared records, and across a data gap."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from common.hrv.records import read_record
from common.hrv.rpeaks import detect, detect_peaks
from common.hrv.stream import HrvStream, classify, intervals, peak_intervals, windows
from tests.support.cli import run_cli
from tests.support.data import ECG, device_rr, needs_data


def test_a_missed_beat_an_extra_beat_and_an_ectopic_pair_are_excluded() -> None:
    rr = np.full(30, 0.8)
    rr[5] = 1.6  # a missed beat
    rr[12], rr[13] = 0.3, 0.5  # an extra beat splits one interval
    rr[20], rr[21] = 0.55, 1.05  # a premature beat and its compensatory pause
    kinds = classify(rr)
    assert kinds[5] == "missed"
    assert kinds[12] == "extra"
    assert kinds[20] == "ectopic"
    assert kinds[21] == "ectopic"
    # which end of the fragment is the false beat cannot be told: the interval before it goes too
    assert kinds[11] == "extra"
    assert kinds[13] != "ok"
    assert sum(k != "ok" for k in kinds) == 6


def test_the_ecg_excludes_what_rr_cannot_tell_a_late_unlike_beat_and_a_burst_of_noise() -> None:
    rr = np.full(30, 0.8)  # regular to RR alone
    likeness, noise = np.ones(30), np.full(30, 1.0)  # noise: the person's own level between beats is 1
    likeness[10] = 0.4  # interval 10 has a beat unlike the template (a late PVC: RR cannot see it)
    noise[20] = 3.0  # a burst of noise, three times the usual, between the beats of interval 20
    kinds = classify(rr, likeness, noise)
    assert kinds[10] == "unlike"
    assert kinds[20] == "noise"
    assert sum(k != "ok" for k in kinds) == 2
    assert classify(rr) == ["ok"] * 30


def test_a_run_of_doubled_intervals_is_missed_beats_until_it_lasts_too_long_to_be_dropped_beats() -> None:
    """The H10's own RR in bigeminy: each premature beat left out, so every interval twice the rhythm's,
    regular to its neighbours. Against the level they are missed beats; a minute of them is a slow rhythm."""
    from common.hrv.stream import RELEVEL

    rr = np.concatenate([np.full(40, 0.8), np.full(20, 1.6), np.full(20, 0.8), np.full(RELEVEL + 20, 1.6)])
    kinds = classify(rr)
    # each step takes the two intervals on either side as a premature pair; between them:
    assert kinds[:38] == ["ok"] * 38
    assert kinds[42:58] == ["missed"] * 16
    assert kinds[62:78] == ["ok"] * 16
    run = kinds[82:]
    assert run[: RELEVEL - 2] == ["missed"] * (RELEVEL - 2)
    assert run[-10:] == ["ok"] * 10  # then relearnt
    assert classify(rr, segment_starts={80})[86:96] == ["ok"] * 10  # after a gap: no level to compare with


def test_a_mildly_early_beat_and_its_pause_are_excluded_but_not_the_beat_after_a_false_one() -> None:
    rr = np.full(30, 0.8)
    rr[8], rr[9] = 0.72, 0.86  # 10 % early, then a pause: within TOLERANCE each, a premature beat as a pair
    rr[20], rr[21] = 0.3, 0.5  # a false beat splits an interval: the beat closing 21 is a real one
    kinds = classify(rr)
    assert kinds[8] == kinds[9] == "ectopic"
    assert kinds[22] == "ok"
    assert kinds[7] == "ok"
    assert kinds[10] == "ok"
    assert kinds[19] == "extra"  # next to the fragment, which might have been the other piece
    assert sum(k != "ok" for k in kinds) == 5


def test_a_deep_breathing_rhythm_is_the_persons_own_but_a_premature_beat_in_it_is_not() -> None:
    """Respiratory sinus arrhythmia, ±18 % with each breath of 4.5 beats (GUDB's subject 11 sitting swings
    776-1200 ms): every interval is a normal beat's, and issue 19's fixed rules excluded its troughs and
    crests (a mean biased by up to 24 ms). The tolerance follows the person's own spread and a mildly
    early beat must drop sharper than a breath does; a premature beat and its pause still go."""
    beat = np.arange(200)
    rr = 0.95 * (1 + 0.18 * np.sin(2 * np.pi * beat / 4.5))
    kinds = classify(rr)
    assert kinds[5:] == ["ok"] * 195  # once the person's spread is learnt (5 intervals)
    assert kinds[:5].count("ok") >= 4
    pvc = rr.copy()
    pvc[100], pvc[101] = 0.55 * rr[100], rr[100] + 0.45 * rr[100]  # early by 45 %, full compensatory pause
    kinds = classify(pvc)
    assert kinds[100] != "ok"
    assert kinds[101] != "ok"
    assert sum(k != "ok" for k in kinds) <= 4  # the pair, and at most its neighbours


def test_a_lone_long_interval_stays_but_the_pause_after_a_premature_beat_goes() -> None:
    rr = np.full(40, 0.8) + np.tile([0.0, 0.02, -0.02], 14)[:40]  # the person's own small spread
    rr[20] = 1.05  # a pause of the person's own (a sigh, a sinus pause): 31 % long, after a normal beat
    rr[30], rr[31] = 0.5, 1.1  # a premature beat and its pause
    kinds = classify(rr)
    assert kinds[20] == "ok"
    assert kinds[30] != "ok"
    assert kinds[31] != "ok"


@needs_data
def test_good_windows_are_within_a_decision_step_of_the_annotated_nn_mean() -> None:
    """Issue 19's bar, by its scorer, on the shared records clean and with motion bursts, the variant
    that holds most (`cadence bench hrv --windows` runs all five; tests/bench runs white noise at 6 dB on
    the noisiest record): no window marked good is a decision step (20 ms) off the mean of the annotated
    NN intervals, and holding is not how."""
    from cadence.bench.hrv_windows import bench_hrv_windows

    scores = bench_hrv_windows(str(ECG), 130.0, ("clean", "motion"), peers=False)
    for variant, by_pipeline in scores.items():
        f = by_pipeline["cadence"].figures()
        print(variant, f)
        assert f["over_20_ms"] == 0, variant
        assert f["p95_ms"] <= 5.0, variant
        assert f["held_share_sinus"] <= 0.2, variant  # holding everything would be accurate and useless
    # Bundle branch block: 109 (left: wide QRS, T waves as tall as it) and 118 (right: a QRS of two peaks
    # of like height) held 95-100 % of their windows under issue 19's rules. The noise between beats now
    # counts against the person's own level, and a beat is aligned to the template before it is
    # compared: at least 80 % of their scored windows are good, none 10 ms off the annotations.
    clean = scores["clean"]["cadence"]
    for record in ("109", "118"):
        good = [w for w in clean.good if w.record == record]
        assert len(good) >= 0.8 * (len(good) + clean.held_by_record.get(record, 0)), record
        assert max(w.error_s for w in good) < 0.010, record
    # 101 at 300 s: the annotators marked a second unreadable and left out the beat in it, so their "NN"
    # interval is 1.9 s long; that interval is not in the truth (hrv_scoring.unreadable_spans), and the
    # window, good, is the heart's rhythm
    w101 = [w for w in clean.good if w.record == "101" and w.start_s == 300.0]
    assert w101
    assert w101[0].error_s < 0.002


@needs_data
def test_a_10_s_dropout_forms_no_interval_across_it_and_flags_its_window() -> None:
    rec = read_record(str(ECG / "100"), fs=130.0)
    x = rec.uv[: 130 * 120]
    gap = (45.0, 55.0)
    before, after = x[: int(gap[0] * 130)], x[int(gap[1] * 130) :]
    # the gateway reports the gap; the analyser starts its detector afresh after it
    peaks = np.concatenate([detect(before, 130.0) / 130.0, gap[1] + detect(after, 130.0) / 130.0])
    iv = intervals(peaks, gaps_s=[gap])
    assert not np.any((iv.t_s - iv.rr_s < gap[1]) & (iv.t_s > gap[0])), "an interval spans the gap"
    ws = {w.start_s: w for w in windows(iv, 30.0, end_s=120.0, gaps_s=[gap])}
    assert ws[30.0].quality == "low"  # a third of it is missing
    assert ws[30.0].mean_rr_s is not None  # still computed from what is there, for the record
    assert ws[0.0].quality == "good"
    assert ws[90.0].quality == "good"


@needs_data
@pytest.mark.parametrize("tool", ["peaks", "windows"])
def test_cadence_hrv_prints_json(tool: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "cadence", "hrv", tool, str(ECG / "103"), "--fs", "130"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    lines = [json.loads(line) for line in proc.stdout.splitlines()]
    if tool == "peaks":
        assert lines[0]["fs"] == 130.0
        assert len(lines[0]["peaks_s"]) > 2000
    else:
        assert len(lines) == 60
        assert {
            "start_s",
            "end_s",
            "mean_rr_s",
            "n_beats",
            "excluded",
            "quality",
            "reason",
        } <= set(lines[0])
        assert all((w["reason"] is None) == (w["quality"] == "good") for w in lines)


def test_a_broken_recording_is_one_line_and_exit_2(tmp_path) -> None:
    bad = tmp_path / "x.csv"
    bad.write_text("0,1\n0.1,2\n0.05,3\n")
    proc = subprocess.run(
        [sys.executable, "-m", "cadence", "hrv", "peaks", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "x.csv: row 3: time does not increase" in proc.stderr


@needs_data
@pytest.mark.parametrize("chunk", [73, 130 * 5])
def test_the_stream_gives_the_offline_windows_in_chunks(chunk: int) -> None:
    rec = read_record(str(ECG / "208"), fs=130.0)
    x = rec.uv[: 130 * 600]
    offline = windows(peak_intervals(detect_peaks(x, 130.0), 130.0), 30.0, end_s=len(x) / 130.0)
    stream, online = HrvStream(130.0), []
    for i in range(0, len(x), chunk):
        online += stream.feed(i / 130.0, x[i : i + chunk])[1]
    online += stream.flush()[1]
    assert online == offline


@needs_data
def test_the_stream_breaks_at_a_gap_and_flags_its_window() -> None:
    rec = read_record(str(ECG / "100"), fs=130.0)
    x = rec.uv[: 130 * 120]
    stream, online = HrvStream(130.0), []
    for i in range(0, len(x), 73):
        t = i / 130.0
        if 45.0 <= t < 55.0:
            continue  # ten seconds never arrive
        online += stream.feed(t, x[i : i + 73], gap=False)[1]  # the jump in data time is the gap
    online += stream.flush()[1]
    by_start = {w.start_s: w for w in online}
    assert by_start[30.0].quality == "low"
    assert by_start[0.0].quality == "good"
    assert by_start[90.0].quality == "good"
    assert len(stream.gaps) <= 1


@needs_data
def test_device_rr_gives_the_windows_of_the_same_beats() -> None:
    beats = read_record(str(ECG / "106"), fs=130.0).beats_s
    beats = beats[beats < 600.0]
    offline = windows(intervals(beats), 30.0, start_s=float(beats[0]), end_s=float(beats[-1]))
    stream, online = HrvStream(1024.0), []
    for t, rr in device_rr(beats):
        online += stream.feed_rr(t, rr)[1]
    online += stream.flush()[1]
    assert len(online) == len(offline) == 19
    for a, b in zip(online, offline, strict=True):
        assert (a.start_s, a.n_beats, a.quality) == pytest.approx((b.start_s, b.n_beats, b.quality))
        assert a.mean_rr_s == pytest.approx(b.mean_rr_s, abs=1e-9)
    assert {w.quality for w in online} >= {"good", "low"}  # record 106's runs of PVCs are seen in RR too


@needs_data
def test_lost_rr_notifications_form_no_interval_across_them() -> None:
    beats = read_record(str(ECG / "100"), fs=130.0).beats_s
    beats = beats[beats < 120.0]
    stream, online = HrvStream(1024.0), []
    for t, rr in device_rr(beats):
        if 45.0 <= t < 55.0:
            continue  # ten seconds of notifications never arrive, and nothing flags it
        online += stream.feed_rr(t, rr)[1]
    online += stream.flush()[1]
    assert stream.segments == 2
    assert len(stream.gaps) <= 1
    first = float(beats[0])
    by_start = {round(w.start_s - first): w for w in online}
    # an interval across the lost stretch would be ~10 s long, implausible, and excluded
    assert by_start[30].quality == "low"
    assert by_start[30].excluded == 0.0
    assert by_start[0].quality == "good"
    assert by_start[60].quality == "good"


@needs_data
def test_the_beats_the_stream_flags_are_the_intervals_its_windows_exclude() -> None:
    rec = read_record(str(ECG / "208"), fs=130.0)
    x = rec.uv[: 130 * 300]
    stream, beats, wins = HrvStream(130.0), [], []
    for i in range(0, len(x), 130):
        b, w = stream.feed(i / 130.0, x[i : i + 130])
        beats, wins = beats + b, wins + w
    b, w = stream.flush()
    beats, wins = beats + b, wins + w
    iv = peak_intervals(detect_peaks(x, 130.0), 130.0)
    assert [b.t_s for b in beats[1:]] == pytest.approx(list(iv.t_s))
    assert beats[0].kind == "start"
    assert beats[0].excluded
    assert [b.kind for b in beats[1:]] == iv.kind
    assert any(b.excluded for b in beats[1:])
    assert not all(b.excluded for b in beats[1:])  # 208: many PVCs
    for w in wins:
        inside = [b for b in beats[1:] if w.start_s <= b.t_s < w.end_s]
        assert w.excluded == pytest.approx(np.mean([b.excluded for b in inside]))
        assert (w.reason is None) == (w.quality == "good")


POLAR = ECG / "polar_h10"


def _windows_of(path: str) -> list[dict]:
    r = run_cli("hrv", "windows", path)
    assert r.returncode == 0, r.stderr
    return [json.loads(line) for line in r.stdout.splitlines()]


@needs_data
def test_the_polar_sensor_logger_exports_read_and_their_ecg_and_rr_agree(tmp_path) -> None:
    """The H10's most common saved form: the app's ECG export (µV, the sensor's clock) and its RR export
    of the same session; windows of each, with RMSSD and SDNN, agree where both are good."""
    ecg = _windows_of(str(POLAR / "Polar_H10_55354125_20210516_080846_ECG.txt"))
    rr = _windows_of(str(POLAR / "Polar_H10_55354125_20210516_080845_RR.txt"))
    assert len(ecg) >= 4
    assert len(rr) >= 4
    assert all({"rmssd_s", "sdnn_s"} <= w.keys() for w in ecg + rr)
    both = [(a, b) for a, b in zip(ecg, rr, strict=False) if a["quality"] == b["quality"] == "good"]
    assert len(both) >= 3
    # The RR export starts about 2.5 s before the ECG, so the same window holds other beats; this person's
    # RR swings 750-1100 ms within a few beats (a breathing rhythm, now kept as theirs), so windows 2.5 s
    # apart differ by up to some 35 ms. Over the whole session the two agree closely.
    assert all(abs(a["mean_rr_s"] - b["mean_rr_s"]) < 0.04 for a, b in both)
    assert abs(np.mean([a["mean_rr_s"] for a, _ in both]) - np.mean([b["mean_rr_s"] for _, b in both])) < 0.01
    assert read_record(str(POLAR / "Polar_H10_55354125_20210516_080846_ECG.txt")).fs == pytest.approx(
        130, rel=0.01
    )

    # a plain RR file, one interval per line in ms, is read the same way
    plain = tmp_path / "rr.txt"
    plain.write_text("".join(f"{800 + 10 * (i % 5)}\n" for i in range(120)))
    (w,) = [w for w in _windows_of(str(plain)) if w["end_s"] <= 90][:1]
    assert w["mean_rr_s"] == pytest.approx(0.82, abs=0.005)
    assert w["quality"] == "good"
    r = run_cli("hrv", "peaks", str(plain))
    assert r.returncode == 2
    assert "no ECG" in r.stderr


def test_a_run_of_tachycardia_and_a_2_to_1_block_are_held_as_rhythm_but_not_breathing_or_bigeminy() -> None:
    """Issue 55: a window whose rate jumps from one beat to the next (a run of supraventricular
    tachycardia starts, a 2:1 block halves the rate) is not sinus rhythm, however regular each side is:
    held with the reason ``rhythm``. A deep breath, a premature beat and its pause, and a run of bigeminy
    move a median of six intervals little, and keep their windows."""
    from dataclasses import replace

    from common.hrv.stream import RULES

    def held(rr: np.ndarray, quiet: bool = False) -> list[str | None]:
        """The windows' reasons; ``quiet``: an ECG that shows nothing between the beats (a blocked P
        wave is no QRS), so a doubled interval is the heart's pause, not a missed beat."""
        beats = np.concatenate([[0.0], np.cumsum(rr)])
        iv = intervals(beats, excursion=np.zeros(beats.size) if quiet else None)
        return [w.reason for w in windows(iv, 30.0, rules=replace(RULES, step=1.5))]

    n = 400
    breath = 0.9 * (1 + 0.1 * np.sin(2 * np.pi * np.arange(n) / 6.0))  # ±10 %, slow: 6 beats a breath
    assert held(breath) == [None] * len(held(breath))
    pvc = breath.copy()
    pvc[100], pvc[101] = 0.5 * breath[100], 1.5 * breath[100]
    assert "rhythm" not in held(pvc)
    bigeminy = breath.copy()
    bigeminy[200:260:2], bigeminy[201:260:2] = 0.55, 1.25  # a premature beat after every normal one
    assert "rhythm" not in held(bigeminy)
    svt = breath.copy()
    svt[150:190] = 0.4  # 150 beats a minute, from one beat to the next, for 40 beats
    assert "rhythm" in held(svt)
    for_ever = np.full(1200, 0.8)
    for_ever[100:] = 0.4  # at 80 s, a jump with no way back: held RHYTHM_HOLD_S (300 s), then believed
    reasons = held(for_ever)
    assert reasons[2:13] == ["rhythm"] * 11 and set(reasons[13:]) == {None}
    block = np.full(n, 0.8)
    block[150:190] = 1.6  # every other beat not conducted
    during = held(block, quiet=True)
    assert during[4:7] == ["rhythm"] * 3  # from the jump to the jump back (120-184 s), then sinus again
    assert "rhythm" not in during[:4] + during[7:]
    # a strap's RR cannot tell a blocked beat from a missed one: its windows are held all the same
    assert {held(block)[i] for i in (4, 5)} == {"no_clean_beats"}


def test_three_early_beats_in_a_row_are_a_run_of_tachycardia_held_as_rhythm_two_are_not() -> None:
    """Issue 55: a run of three ectopic beats or more (ventricular or supraventricular tachycardia, by the
    clinical definition) is too short to move the medians a jump in rate is read from, and the cleaning
    cuts it out as ectopic beats: its window was passed as if sinus. Held as ``rhythm`` now, at any rate
    of the run; a lone premature beat, a couplet and a run of bigeminy are not runs, nor a breath that
    shortens RR over several beats, nor an extra beat drawn among two intervals."""

    def reasons(rr: np.ndarray) -> list[str | None]:
        beats = np.concatenate([[0.0], np.cumsum(rr)])
        return [w.reason for w in windows(intervals(beats), 30.0)]

    breath = 0.9 * (1 + 0.1 * np.sin(2 * np.pi * np.arange(400) / 6.0))
    for rate in (0.35, 0.5, 0.6):  # 171, 120 and 100 beats a minute, against 67
        run = breath.copy()
        run[100:103], run[103] = rate, 1.5  # three early beats, then the pause
        assert reasons(run)[3] == "rhythm" and reasons(run)[:3] + reasons(run)[4:] == [None] * 10, rate
        longer = breath.copy()
        longer[100:108] = rate
        assert reasons(longer)[3] == "rhythm", rate
    couplet = breath.copy()
    couplet[100:102], couplet[102] = 0.5, 1.6
    pvc = breath.copy()
    pvc[100], pvc[101] = 0.5, 1.3
    bigeminy = breath.copy()
    bigeminy[100:160:2], bigeminy[101:160:2] = 0.55, 1.25
    # an annotator's (or a detector's) extra beat among two intervals: three pieces, unlike each other
    # (GUDB subject 05's hand bike, the cables' annotation at 41.5 s: 628, 500, 440, 364, 688 ms)
    extra = np.concatenate([breath[:100], [0.5, 0.44, 0.36], breath[102:]])
    for kept in (breath, couplet, pvc, bigeminy, extra):
        assert "rhythm" not in reasons(kept)
