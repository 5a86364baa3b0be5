"""The operator twin (common/sim/twin.py): its ECG is detectable, its heart answers the robot's pace."""

from __future__ import annotations

import numpy as np
import pytest

from common.hrv.stream import HrvStream, match_beats
from common.sim.twin import Operator, TwinParams

FS = 130.0
CHUNK = 73


def run(op: Operator, seconds: float, qd_norm: float = 0.0, t_start: float = 0.0) -> tuple[np.ndarray, list]:
    """Stream the twin's ECG through the real HRV stream while it watches a robot moving at qd_norm."""
    stream, wins, x_all = HrvStream(FS), [], []
    beats: set[float] = set()
    n0 = round(t_start * FS)
    for i in range(n0, n0 + round(seconds * FS), CHUNK):
        t = i / FS
        op.observe(t, np.full(6, qd_norm / np.sqrt(6)))
        x = op.ecg(t, CHUNK)
        beats.update(op.beats)
        x_all.append(x)
        wins += stream.feed(t, x)[1]
    wins += stream.flush()[1]
    return np.array(sorted(b for b in beats if t_start + 1 < b < t_start + seconds - 1)), wins


def test_the_real_detector_finds_the_twins_beats() -> None:
    from common.hrv.rpeaks import detect

    op, xs, beats = Operator(TwinParams(seed=3)), [], set()
    for i in range(0, round(300 * FS), CHUNK):
        xs.append(op.ecg(i / FS, CHUNK))
        beats.update(op.beats)  # it keeps only its last 64
    truth = np.array(sorted(b for b in beats if 1 < b < 299))
    found = detect(np.concatenate(xs), FS, chunk=CHUNK) / FS
    tp, fp, fn = match_beats(truth, found[(found > 1 - 0.1) & (found < 299 + 0.1)])
    assert fn == 0
    assert fp == 0
    assert tp == len(truth) > 300


def test_a_fast_robot_lowers_mean_rr_and_relief_raises_it_again() -> None:
    p = TwinParams(seed=1)
    op = Operator(p)
    _, rest = run(op, 120)
    _, fast = run(op, 300, qd_norm=2.0, t_start=120)
    _, relief = run(op, 400, qd_norm=0.0, t_start=420)
    good = [w.mean_rr_s for w in rest if w.quality == "good"]
    assert abs(np.mean(good) - p.rr_rest_s) < 0.02  # at rest the windows see the resting level
    assert fast[-1].mean_rr_s < np.mean(good) - 0.1  # stressed: RR fell by more than 100 ms
    assert relief[-1].mean_rr_s > fast[-1].mean_rr_s + 0.08  # eased again
    assert all(w.quality == "good" for w in rest + fast + relief)


def test_errors_are_likelier_under_stress_and_the_twin_is_seeded() -> None:
    calm, stressed = Operator(TwinParams()), Operator(TwinParams())
    for t in np.arange(0, 200, 0.1):
        stressed.observe(t, np.full(6, 1.0))
        stressed.advance(t)
    assert stressed.error_probability() > calm.error_probability() + 0.2
    a, b, c = Operator(TwinParams(seed=5)), Operator(TwinParams(seed=5)), Operator(TwinParams(seed=6))
    assert np.array_equal(a.ecg(0.0, 1000), b.ecg(0.0, 1000))
    assert not np.array_equal(a.ecg(0.0, 1000), c.ecg(0.0, 1000))


def test_the_twin_walks_into_the_shared_area_and_out_at_walking_speed() -> None:
    op = Operator(TwinParams(far_m=3.5, walk_near_m=1.5, walk_m_s=1.0, walk_every_s=45.0, walk_stay_s=4.0))
    t = np.arange(0.0, 100.0, 0.01)
    d = np.array([op.separation(x) for x in t])
    assert np.all(d[t < 45.0] == 3.5)
    assert d.min() == pytest.approx(1.5)
    assert d.max() == 3.5
    near = t[d <= 1.5 + 1e-9]
    # walks in for 2 s from 45 s, stays 4 s, walks out for 2 s; again from 90 s
    assert near.min() == pytest.approx(47.0, abs=0.011)
    assert near[near < 60].max() == pytest.approx(51.0, abs=0.011)
    assert op.separation(52.0) == pytest.approx(2.5)
    assert op.separation(54.0) == 3.5
    assert np.abs(np.diff(d)).max() <= 1.0 * 0.01 + 1e-9  # never faster than walking
    assert {op.separation(x) for x in (10.0, 60.0)} == {3.5}
    assert Operator(TwinParams(walk_every_s=0.0)).separation(500.0) == TwinParams().far_m


def test_exposure_is_the_held_states_time_weighted_mean_over_the_window_however_they_come() -> None:
    """The window's integrals are kept running (a study asks at every beat); they must equal the plain
    sum over the held states, whether the states come one by one or in blocks, and when asked for a
    time between states or before the newest one."""
    p = TwinParams(seed=3)
    one, many = Operator(p), Operator(p)
    rng = np.random.default_rng(0)
    ts = np.cumsum(rng.uniform(0.0, 0.4, 600))
    ts[100:103] = ts[100]  # three states at one instant: no acceleration from them
    qd = rng.normal(0.0, 1.0, (600, 6))
    for t, v in zip(ts, qd, strict=True):
        one.observe(float(t), v)
    for block in np.array_split(np.arange(600), 37):
        many.observe_all(ts[block], qd[block])

    def direct(t: float) -> float:  # the definition: a zero-order hold, summed over the window
        lo, speed, accel = t - p.window_s, 0.0, 0.0
        nxt = [*ts[1:], np.inf]
        for i, t0 in enumerate(ts):
            dt = max(0.0, min(nxt[i], t) - max(t0, lo))
            speed += float(np.linalg.norm(qd[i])) * dt
            if i and t0 > ts[i - 1] + 1e-3:
                accel += float(np.linalg.norm(qd[i] - qd[i - 1])) / (t0 - ts[i - 1]) * dt
        return (speed / p.pace_ref_rad_s + p.accel_weight * accel / p.accel_ref_rad_s2) / p.window_s

    for t in (5.0, 37.3, float(ts[300]), float(ts[300]) + 0.01, float(ts[-1]) - 3.0, float(ts[-1]) + 1.0):
        assert one.exposure(t) == pytest.approx(direct(t), rel=1e-9, abs=1e-12)
        assert many.exposure(t) == pytest.approx(direct(t), rel=1e-9, abs=1e-12)


def test_a_twin_away_until_calibrated_rests_beside_a_working_robot_and_works_once_it_arrives() -> None:
    """The demo cell's lab walk-through calibrates at rest (issue 56: the twin worked from the start, and
    its "at rest" baseline was its RR at work, 0.755 s against 0.85 s): away, the fast arm is no exposure,
    the heart stays at rest and the distance at the operator's own place; from its arrival the same arm
    stresses it as it does a twin that was there all along, counted from the arrival on."""
    fast = 1.6  # rad/s: the example task's minimum time
    away, there = Operator(TwinParams(seed=2, away_until_calibrated=True)), Operator(TwinParams(seed=2))
    _, rest = run(away, 240.0, fast)
    _, work = run(there, 240.0, fast)
    rr = lambda ws: np.mean([w.mean_rr_s for w in ws[-3:]])  # noqa: E731
    assert away.exposure(240.0) == 0.0 and there.exposure(240.0) > 1.0
    assert rr(rest) == pytest.approx(0.85, abs=0.02), rr(rest)
    assert rr(work) < rr(rest) - 0.08, (rr(work), rr(rest))
    assert away.separation(100.0) == away.p.far_m  # a walk would have come at 90 s
    away.arrive(240.0)
    away.arrive(300.0)  # a second calibration does not move the arrival
    assert away.arrived_s == 240.0
    away.observe(245.0, np.full(6, fast / np.sqrt(6)))
    assert 0.0 < away.exposure(245.0) < there.exposure(240.0)  # 5 s of it, not the 20 s window's
    _, later = run(away, 240.0, fast, t_start=245.0)
    assert rr(later) < rr(rest) - 0.08, rr(later)
