"""Reacting within a path (issue 31): the time scale for a person's distance and a switch of k mid-path,
driven through the servo loop's playback one controller step at a time, every commanded sample checked."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from common.robot.ur16e import forward_kinematics, link_points
from common.safety.geometry import Arm
from common.safety.separation import Ssm, stepped
from common.trajectory.planner import ParetoResult, plan_path
from common.trajectory.scaling import (
    DT,
    LIMIT_RTOL,
    Curve,
    Ramp,
    commanded,
    plan_ramp,
    ramp_ratio,
    resume_at,
    resume_ramp,
    stop_time,
    switch_curve,
)
from common.trajectory.task import PathPlan, load_task
from services.executor.playback import Playback, Switch
from tests.support.paths import EXAMPLE_TASK

TASK = load_task(EXAMPLE_TASK)
LIMITS = TASK.limits


@pytest.fixture(scope="module")
def planned() -> tuple[PathPlan, ParetoResult]:
    path = TASK.paths["b1_to_b2"]  # the longest path; its fastest solution rides the limits
    return path, plan_path(path, LIMITS, TASK.planner)


def finite_difference_ratios(q: np.ndarray) -> np.ndarray:
    """max |Δ^d q / DT^d| / limit for d = 1, 2, 3 over commanded samples: what the arm is sent."""
    lim = LIMITS.kinematic()
    return np.array([(np.abs(np.diff(q, n=d, axis=0)) / DT**d / lim[d - 1]).max() for d in (1, 2, 3)])


class Monitor:
    """Stands in for the executor's reaction task: every 10 steps it reads the scripted distance and asks
    for the σ of ISO/TS 15066 as a ramp, as services/executor/reaction.py does."""

    def __init__(self, pb: Playback, ssm: Ssm, top_speed: float) -> None:
        self.pb, self.ssm, self.top = pb, ssm, top_speed

    def wanted(self, distance: float | None, age: float) -> float:
        return stepped(self.ssm.scale(distance, age, self.top))

    def step(self, distance: float | None, age: float) -> None:
        pb = self.pb
        want = self.wanted(distance, age)
        if abs(want - pb.now.target) > 1e-9:
            ramp = plan_ramp(pb.curve, pb.ramp, pb.t + 0.02, want, LIMITS)
            assert ramp is not None, f"no ramp to {want} at t = {pb.t:.3f}"
            assert pb.offer(ramp=ramp)


def run(pb: Playback, each_step, max_steps: int = 20_000) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """Step the playback as the servo loop does; the commanded samples and (t, σ) of every step."""
    qs, trace = [], []
    for _ in range(max_steps):
        each_step(pb.t)
        q = pb.next()
        if q is None:
            break
        qs.append(np.array(q))
        trace.append((pb.t, pb.sigma))
    return np.array(qs), trace


def test_the_protective_distance_is_iso_ts_15066_eq_1_and_its_inverse() -> None:
    ssm = Ssm(human_speed_m_s=1.6, reaction_s=0.2, stop_time_s=0.8, intrusion_m=0.2, uncertainty_m=0.1)
    v_r = 1.2
    s_h, s_r, s_s = 1.6 * (0.2 + 0.8), v_r * 0.2, v_r * 0.8 / 2
    assert ssm.protective_distance(v_r) == pytest.approx(s_h + s_r + s_s + 0.2 + 0.1)
    assert ssm.allowed_speed(ssm.protective_distance(v_r)) == pytest.approx(v_r)
    assert ssm.allowed_speed(1.0) == 0.0  # inside v_h (T_r + T_s) + C + Z: not even at rest
    assert ssm.scale(5.0, 0.0, path_speed_m_s=1.0) == 1.0
    assert ssm.scale(ssm.protective_distance(0.6), 0.0, 1.2) == pytest.approx(0.5)
    assert ssm.scale(5.0, ssm.max_age_s + 0.01, 1.0) == 0.0  # stale: as if the person were at the robot
    assert ssm.scale(None, 0.0, 1.0) == 0.0
    # asked for in steps, rounded down (slower), where a step is meant exactly despite round-off
    assert [stepped(x) for x in (1.3, 1.0, 0.999, 3 * 0.05, 0.1499, 0.04, 0.0)] == pytest.approx(
        [1.0, 1.0, 0.95, 0.15, 0.1, 0.0, 0.0]
    )


def test_link_points_end_at_the_tcp_and_path_speed_is_the_fastest_point() -> None:
    q = np.radians([[10.0, -80, 100, -110, -90, 20], [-40, -95, 80, -70, -90, 60]])
    np.testing.assert_allclose(link_points(q)[:, -1], [forward_kinematics(x)[:3] for x in q], atol=1e-12)
    # the base turning alone: every point moves on a circle, the farthest fastest
    t = np.arange(0, 1.0, 0.001)
    spin = np.tile(np.radians([0.0, -90, 90, -90, -90, 0]), (len(t), 1))
    spin[:, 0] = t  # 1 rad/s
    body = Arm().body(spin[0])  # the farthest point of its capsules from the base's axis
    radius = max((np.hypot(*body.a[:, :2].T) + body.r).max(), (np.hypot(*body.b[:, :2].T) + body.r).max())
    assert Arm().top_speed(spin, 0.001) == pytest.approx(radius, rel=1e-3)


def test_a_ramp_joins_the_scale_state_in_force_continuously() -> None:
    first = Ramp.between(0.0, 0.0, (1.0, 0.0, 0.0), 0.3, 0.4)
    t = 0.2
    s, sig, sd, sdd = (float(x[0]) for x in first.state(np.array([t])))
    second = Ramp.between(t, s, (sig, sd, sdd), 0.8, 0.5)
    for a, b in zip(first.state(np.array([t])), second.state(np.array([t])), strict=True):
        assert float(a[0]) == pytest.approx(float(b[0]), abs=1e-12)
    _, sig_end, sd_end, sdd_end = (float(x[0]) for x in second.state(np.array([second.end + 1.0])))
    assert (sig_end, sd_end, sdd_end) == (pytest.approx(0.8), 0.0, 0.0)
    # s is the integral of σ
    grid = np.linspace(t, second.end, 20001)
    _, sigmas, _, _ = second.state(grid)
    assert float(second.state(np.array([second.end]))[0][0]) - s == pytest.approx(
        np.trapezoid(sigmas, grid), rel=1e-8
    )
    assert second.target == pytest.approx(0.8)


def test_separation_below_and_above_the_thresholds_during_a_path_keeps_every_sample_inside_the_limits(
    planned: tuple[PathPlan, ParetoResult],
) -> None:
    path, result = planned
    curve = Curve.of(result.solutions[-1].h, path)  # k = N: on the limits somewhere
    top = Arm().top_speed(curve.at(np.arange(0, curve.t_f, 0.01), order=0)[0], 0.01)
    stop = stop_time(curve, LIMITS)
    ssm = Ssm(stop_time_s=stop.time_s, stop_travel_s=stop.travel_s)
    near, middle, far = 0.9, ssm.protective_distance(0.45 * top), 4.0
    # (from t, distance or None for no message): far, half speed, far, the sensor silent, too near, far
    script = [(0.0, far), (0.2, middle), (1.2, far), (1.6, None), (3.6, near), (4.1, far)]
    pb = Playback(curve, Ramp.hold(0.0, 0.0, 1.0), lambda q: q.copy())
    monitor = Monitor(pb, ssm, top)
    last_heard = [0.0, far]
    ramps: dict[int, Ramp] = {}

    def each_step(t: float) -> None:
        ramps[round(t / DT)] = pb.ramp
        if round(t / DT) % 10:
            return
        distance = [d for t0, d in script if t0 <= t + 1e-9][-1]
        if distance is not None:
            last_heard[:] = [t, distance]
        monitor.step(last_heard[1], t - last_heard[0])

    q, trace = run(pb, each_step)
    assert pb.finished
    assert pb.missed == 0
    np.testing.assert_allclose(q[-1], path.waypoints[-1], atol=1e-9)
    # every commanded sample inside the limits: exactly (chain rule, the ramp in force at each step) …
    ticks = np.arange(len(q))
    t = ticks * DT
    state = np.array([[float(x[0]) for x in ramps[i].state(np.array([t[i]]))] for i in ticks])
    derivs = commanded(curve, state[:, 0], state[:, 1], state[:, 2], state[:, 3])
    np.testing.assert_allclose(derivs[0], q, atol=1e-12)
    lim = LIMITS.kinematic()
    exact = [float((np.abs(derivs[d]) / lim[d - 1]).max()) for d in (1, 2, 3)]
    assert max(exact) <= 1.0 + 1e-6, exact
    # … and as the arm sees them: finite differences of the samples, no jump anywhere
    fd = finite_difference_ratios(q)
    print(f"limit ratios, exact {np.round(exact, 4)}, finite differences {np.round(fd, 4)}")
    assert fd[0] <= 1.001
    assert fd[1] <= 1.01
    assert fd[2] <= 1.1
    # the scale follows the standard's distance: by the end of each phase, heading for (and where the
    # phase is long enough, at) the σ of its distance
    half = monitor.wanted(middle, 0.0)
    assert 0.3 < half < 0.6
    for at, want, reached in [(1.19, half, True), (1.59, 1.0, False), (3.59, 0.0, True), (4.09, 0.0, True)]:
        i = round(at / DT)
        assert ramps[i].target == pytest.approx(want), (at, ramps[i].target, want)
        if reached:
            assert trace[i - 1][1] == pytest.approx(want, abs=1e-9), (at, trace[i - 1][1], want)
    # silent sensor: within max_age + the stop, σ = 0 and the arm holds its place on the path
    held = [i for i, (ti, _) in enumerate(trace) if 1.6 + ssm.max_age_s + ssm.stop_time_s + 0.1 <= ti < 4.1]
    assert len(held) > 300
    assert np.ptp(q[held], axis=0).max() < 1e-12


def test_a_path_resumed_from_rest_within_it_goes_on_from_the_arms_point_inside_the_limits(
    planned: tuple[PathPlan, ParetoResult],
) -> None:
    """A stop cut the fastest solution short at its top speed: it goes on from the point of the curve
    nearest where the braking stop left the arm (past the last sample), from σ = 0, every commanded sample
    inside the limits, to the path's end."""
    path, result = planned
    curve = Curve.of(result.solutions[-1].h, path)
    s_last = float(curve.t_f * 0.4)
    q_at, qd_at = curve.at(np.array([s_last]), order=1)[:, 0]
    q_stopped = q_at + qd_at * 0.05  # a braking stop carries the arm on along its velocity for a while
    at = resume_at(curve, q_stopped, s_last)
    assert s_last < at < s_last + 0.5
    q_there = curve.at(np.array([at]), order=0)[0, 0]
    assert np.abs(q_there - q_stopped).max() < np.abs(q_at - q_stopped).max()  # nearer than the sample
    assert resume_ramp(curve, at, 0.0, LIMITS) == Ramp.hold(0.0, at, 0.0)  # nobody may move it: held
    ramp = resume_ramp(curve, at, 1.0, LIMITS)
    assert ramp is not None and ramp.target == 1.0
    pb = Playback(curve, ramp, lambda q: q.copy())
    q, trace = run(pb, lambda t: None)
    assert pb.finished and trace[0][1] == 0.0
    np.testing.assert_allclose(q[0], q_there, atol=1e-12)  # from the arm's point, at rest
    np.testing.assert_allclose(q[-1], path.waypoints[-1], atol=1e-9)
    fd = finite_difference_ratios(np.vstack([q_there, q_there, q_there, q]))  # from rest: no jump either
    assert fd[0] <= 1.001 and fd[1] <= 1.01 and fd[2] <= 1.1, fd
    assert ramp_ratio(curve, ramp, LIMITS) <= 1.0 + LIMIT_RTOL


@pytest.mark.parametrize(("k_from", "k_to"), [(3, 15), (15, 1), (8, 12)])
def test_a_switch_of_k_mid_path_is_continuous_to_the_jerk_and_inside_the_limits(
    planned: tuple[PathPlan, ParetoResult], k_from: int, k_to: int
) -> None:
    path, result = planned
    h_from, h_to = result.solutions[k_from - 1].h, result.solutions[k_to - 1].h
    curve = Curve.of(h_from, path)
    s_switch = 0.37 * curve.t_f
    sw = switch_curve(curve, path, h_to, s_switch, LIMITS)
    assert sw is not None
    before = curve.at(np.array([s_switch]))[:, 0]
    after = Curve.of(sw.h, sw.rest).at(np.array([0.0]))[:, 0]
    np.testing.assert_allclose(after, before, atol=1e-9)  # q, q', q'', q''' continuous at the switch
    # the rest passes the remaining waypoints of the executor's own copy, and ends as the path does
    joined = sw.curve
    np.testing.assert_allclose(joined.at(joined.sites, order=0)[0], path.waypoints, atol=1e-9)
    assert np.all(np.diff(joined.sites) > 0)
    # the new k's pace: the rest lasts as the new solution's rest would, stretched only if it must be
    rest_planned = np.sum(h_to) * (1 - s_switch / curve.t_f)
    print(f"k {k_from} → {k_to}: stretch {sw.stretch:.3f}, rest {joined.t_f - s_switch:.3f} s "
          f"(the new solution's share {rest_planned:.3f} s)")  # fmt: skip
    # driven through the playback: the loop takes it at s_switch, every sample inside the limits
    pb = Playback(curve, Ramp.hold(0.0, 0.0, 1.0), lambda q: q.copy())
    offered = []

    def each_step(t: float) -> None:
        if not offered and pb.s >= s_switch - 0.1:
            offered.append(pb.offer(switch=Switch(s_switch, joined)))

    q, _ = run(pb, each_step)
    assert offered == [True]
    assert pb.curve is joined
    assert pb.missed == 0
    assert len(q) * DT == pytest.approx(joined.t_f, abs=2 * DT)
    fd = finite_difference_ratios(q)
    assert fd[0] <= 1.001, fd
    assert fd[1] <= 1.01, fd
    assert fd[2] <= 1.1, fd


def test_a_switch_offered_after_its_point_is_refused_and_one_planned_on_another_curve_is_missed(
    planned: tuple[PathPlan, ParetoResult],
) -> None:
    path, result = planned
    curve = Curve.of(result.solutions[4].h, path)
    pb = Playback(curve, Ramp.hold(0.0, 0.0, 1.0), lambda q: q.copy())
    for _ in range(200):
        pb.next()
    sw = switch_curve(curve, path, result.solutions[9].h, pb.s - 0.01, LIMITS)
    assert sw is not None
    assert not pb.offer(switch=Switch(pb.s - 0.01, sw.curve))
    late = plan_ramp(curve, pb.ramp, pb.t - 0.1, 0.5, LIMITS)
    assert late is not None
    assert not pb.offer(ramp=late)
    # planned from a state no longer in force (the loop took a ramp meanwhile): refused
    stale = pb.now
    slower = plan_ramp(curve, pb.ramp, pb.t + 0.01, 0.5, LIMITS)
    assert slower is not None
    assert pb.offer(ramp=slower)
    while pb.now.pending_ramp is not None or pb.ramp is not slower:
        pb.next()
    ahead = switch_curve(curve, path, result.solutions[9].h, pb.s + 0.05, LIMITS)
    assert ahead is not None
    assert not pb.offer(switch=Switch(pb.s + 0.05, ahead.curve), base=stale)
    assert pb.adopted == 1
    assert pb.missed == 0


def test_a_ramp_from_a_hold_with_a_switch_pending_keeps_both_curves_inside_the_limits(
    planned: tuple[PathPlan, ParetoResult],
) -> None:
    """A selection that comes while the arm is held waits, joined, for the arm to move: the ramp that frees
    the arm is run on the joined curve from the switch on, so it is chosen inside the limits on both (the
    demo once kept an arm held for good when the first ramp fit the old curve only and was refused)."""
    path, result = planned
    slow = Curve.of(result.solutions[0].h, path)
    pb = Playback(slow, Ramp.hold(0.0, 0.0, 1.0), lambda q: q.copy())
    for _ in range(400):
        pb.next()
    stop = plan_ramp(slow, pb.ramp, pb.t + 0.02, 0.0, LIMITS)
    assert stop is not None
    assert pb.offer(ramp=stop)
    while pb.t < stop.end + 0.1:
        pb.next()
    assert pb.sigma == 0.0
    sw = switch_curve(slow, path, result.solutions[-1].h, pb.s + 0.005, LIMITS)  # to k = N, on the limits
    assert sw is not None
    assert pb.offer(switch=Switch(sw.s_switch, sw.curve))
    pb.next()  # the loop adopts it (held: the arm does not move)
    mine = plan_ramp(slow, pb.ramp, pb.t + 0.02, 1.0, LIMITS)  # fits the slow curve only
    assert mine is not None
    assert ramp_ratio(sw.curve, mine, LIMITS) > 1.1
    free = plan_ramp(slow, pb.ramp, pb.t + 0.02, 1.0, LIMITS, also=[sw.curve])
    assert free is not None
    assert ramp_ratio(slow, free, LIMITS) <= 1 + LIMIT_RTOL
    assert ramp_ratio(sw.curve, free, LIMITS) <= 1 + LIMIT_RTOL
    assert pb.offer(ramp=free)
    assert pb.now.pending_switch is not None
    q, _ = run(pb, lambda t: None)
    assert pb.curve is sw.curve
    assert pb.missed == 0
    assert pb.done
    fd = finite_difference_ratios(q)
    assert fd[0] <= 1.001, fd
    assert fd[1] <= 1.01, fd
    assert fd[2] <= 1.1, fd


def test_a_lease_that_runs_out_makes_the_loop_take_the_planned_stop_itself_inside_the_limits(
    planned: tuple[PathPlan, ParetoResult],
) -> None:
    """The owner's looks stop coming (a starved thread): when the lease on the scale runs out, the loop
    takes the checked stop planned ahead for it, from its own thread, and the arm comes to rest inside the
    limits; with no stop that fits the state, an unchecked one over the path's T_s, counted. A renewal
    clears the lapse."""
    from services.executor.playback import Offer

    path, result = planned
    curve = Curve.of(result.solutions[-1].h, path)
    clock = [0.0]  # the loop's clock, stepped with the samples
    for planned_stop in (True, False):
        pb = Playback(curve, Ramp.hold(0.0, 0.0, 1.0), lambda q: q.copy(), clock=lambda: clock[0])
        pb.stop_s = stop_time(curve, LIMITS).time_s
        pb.renew(0.05)
        sent = []
        for i in range(1500):  # 3 s: T_s of this path at k = N is 1.26 s
            clock[0] = i * DT
            if i == 10 and planned_stop:  # the owner's last look: a stop planned 75 ms ahead
                stop = plan_ramp(pb.curve, pb.ramp, pb.t + 0.075, 0.0, LIMITS)
                assert stop is not None
                pb.fallback = Offer(pb.now, ramp=stop)
            if (q := pb.next()) is not None:
                sent.append(q)
        assert pb.lapsed and pb.lapses == 1 and pb.unchecked == (0 if planned_stop else 1)
        assert pb.sigma == pytest.approx(0.0, abs=1e-9)  # at rest on its path
        assert pb.ramp.t0 <= 0.05 + 0.075 + DT  # the stop began within the lease and its lead
        if planned_stop:
            assert (finite_difference_ratios(np.array(sent)) <= 1.0 + 1e-6).all()
        pb.renew(clock[0] + 1.0)
        assert not pb.lapsed


def test_a_guards_cut_at_the_end_of_a_ramp_down_never_raises_the_scale_nor_sends_it_below_its_word(
    planned: tuple[PathPlan, ParetoResult],
) -> None:
    """The guard's cut (``Playback.cut``) joins the σ-state in force: at the end of a ramp down σ̈ is large
    and positive, and a quintic joined to it over the path's T_s rose from 0.51 past 1 before it fell
    (issue 74's walk-in). Cut at every few steps of a ramp down and of a ramp up, σ stays between where it
    was and the guard's word, and ends at the word."""
    path, result = planned
    curve = Curve.of(result.solutions[-1].h, path)
    stop_s = stop_time(curve, LIMITS).time_s
    cuts = 0
    for first, target, word in ((1.0, 0.5, 0.3), (0.2, 0.9, 0.6)):
        ramp = plan_ramp(curve, Ramp.hold(0.0, 0.0, first), 0.01, target, LIMITS)
        assert ramp is not None
        for cut_at in range(6, round(ramp.end / DT) + 6, 5):
            pb = Playback(curve, Ramp.hold(0.0, 0.0, first), lambda q: q.copy())
            pb.stop_s, pb.now = stop_s, replace(pb.now, pending_ramp=ramp)
            sigmas, at = [], None
            for i in range(cut_at + round(stop_s / DT) + 5):
                if i == cut_at:
                    at = pb.sigma
                    assert pb.cut(word)
                    cuts += 1
                assert pb.next() is not None
                if at is not None:
                    sigmas.append(pb.sigma)
            assert at is not None
            begun = sigmas[1:]  # the cut acts from the step after the one it came in
            lo, hi = min(begun[0], word), max(begun[0], word)
            assert lo - 1e-9 <= min(begun) and max(begun) <= hi + 1e-9, (first, cut_at, begun[0])
            assert sigmas[-1] == pytest.approx(word, abs=1e-9)
    assert cuts > 20


def test_an_arm_held_at_a_paths_start_is_sent_where_it_stands_until_the_path_advances(
    planned: tuple[PathPlan, ParetoResult],
) -> None:
    """A settled arm is off a path's first point by up to the settle tolerance. Held at σ = 0 before the
    path's first step (a person near), it is sent where it stands: pulled onto that point it crept at some
    mm/s beside the person holding it (loaded run 11 of 55add05). Once the scale frees it, the curve, and
    never where it stood again; at σ > 0 from the start, the curve from the first step."""
    path, result = planned
    curve = Curve.of(result.solutions[0].h, path)
    start = curve.at(np.array([0.0]), order=0)[0, 0]
    here = start + 2e-4
    pb = Playback(curve, Ramp.hold(0.0, 0.0, 0.0), lambda q: q.copy(), hold=here)
    assert all(np.array_equal(pb.next(), here) for _ in range(50))
    ramp = plan_ramp(curve, pb.now.ramp, pb.t + 0.01, 1.0, LIMITS, [])
    assert ramp is not None and pb.offer(ramp, None, pb.now)
    after = [pb.next() for _ in range(300)]
    first = next(i for i, q in enumerate(after) if not np.array_equal(q, here))
    assert first > 0 and all(not np.array_equal(q, here) for q in after[first:])
    assert pb.s > 0
    np.testing.assert_allclose(after[-1], curve.at(np.array([pb.s]), order=0)[0, 0])
    free = Playback(curve, Ramp.hold(0.0, 0.0, 1.0), lambda q: q.copy(), hold=here)
    np.testing.assert_array_equal(free.next(), start)
