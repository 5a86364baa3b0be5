"""Alg. 1, exact on decimal values: every branch, every boundary, and a property test against an
independent implementation written here in exact rationals (fractions.Fraction)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from decimal import Decimal
from fractions import Fraction

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.decision import Params, State, dec, k_for_path, step

P = Params.of("0.85")  # RR_r 0.85, RR_s 0.77, RR_s^max 0.69, k0 8


def run(values: list[str], p: Params = P) -> list[int]:
    s = State.initial(p)
    out = []
    for v in values:
        s = step(p, s, v).state
        out.append(s.k)
    return out


def test_the_initial_index_is_8_for_15_solutions_as_in_the_paper() -> None:
    assert P.k0 == 8
    assert State.initial(P).rr_prev == Decimal("0.85")
    assert P.rr_stress == Decimal("0.77")
    assert P.rr_stress_max == Decimal("0.69")


@pytest.mark.parametrize(
    ("prev", "rr", "delta", "reason"),
    [
        ("0.85", "0.81", -1, "stress"),  # ΔRR_r = -0.04 → floor(-1) = -1, exactly
        ("0.85", "0.79", -2, "stress"),  # ΔRR_r = -0.06 → floor(-2) = -2, exactly
        ("0.85", "0.83", 0, "hold"),  # ΔRR = -0.02: not below -Δ_rs
        ("0.85", "0.8299", -1, "stress"),  # just below the threshold
        ("0.80", "0.76", -1, "stress"),  # 0.76 - 0.80 is -0.04000000000000004 in binary floats
        ("0.80", "0.74", -2, "stress"),  # -0.06 → floor(-2) = -2, exactly
        ("0.80", "0.75", -2, "stress"),  # -0.05 → floor(-1.5) = -2
        # ΔRR = -0.06, but ΔRR_r = 0.84 - min(RR_r, RR_{i-1}) = -0.01 → floor(0.5) = 0
        ("0.90", "0.84", 0, "stress"),
        ("0.77", "0.78", 1, "rest"),  # ΔRR_s = +0.01 → ceil(1) = 1, exactly
        ("0.70", "0.77", 0, "rest"),  # RR_i = RR_s: ΔRR_s = 0.77 - max(0.77, 0.70) = 0
        ("0.70", "0.80", 3, "rest"),  # from max(RR_s, RR_{i-1}) = 0.77
        ("0.77", "0.785", 2, "rest"),  # +0.015 → ceil(1.5) = 2
        ("0.70", "0.76", 0, "hold"),  # rising but below RR_s, above RR_s^max
        ("0.70", "0.689", -1, "cumulative"),  # below RR_s^max
        ("0.70", "0.69", 0, "hold"),  # RR_i = RR_s^max is not below it
        ("0.86", "0.85", 0, "hold"),  # small drop
    ],
)
def test_branches_and_boundaries(prev: str, rr: str, delta: int, reason: str) -> None:
    r = step(P, State(8, Decimal(prev)), rr)
    assert (r.delta, r.reason) == (delta, reason)
    assert r.state.k == 8 + delta
    assert r.state.rr_prev == Decimal(rr)


def test_rr_equal_to_rr_rest_is_not_stress() -> None:
    # ΔRR = -0.05 < -Δ_rs, but RR_i = RR_r is not below RR_r
    assert step(P, State(8, Decimal("0.90")), "0.85").reason == "hold"


def test_k_is_clamped_at_1_and_n() -> None:
    assert step(P, State(1, Decimal("0.85")), "0.70").state.k == 1
    assert step(P, State(15, Decimal("0.77")), "0.95").state.k == 15
    assert step(P, State(2, Decimal("0.70")), "0.60").state.k == 1


def test_a_low_quality_window_holds_and_keeps_rr_prev() -> None:
    s = State(5, Decimal("0.80"))
    for r in (step(P, s, "0.60", good_quality=False), step(P, s, None)):
        assert r.state == s
        assert r.delta == 0
        assert r.reason == "low-quality"


def test_floats_are_taken_at_their_decimal_value() -> None:
    assert 0.76 - 0.80 < -0.04  # the binary trap this module avoids
    assert step(P, State(8, dec(0.80)), 0.76).delta == -1


def test_per_path_clamping() -> None:
    assert k_for_path(15, 12) == 12
    assert k_for_path(0, 12) == 1
    assert k_for_path(7, 12) == 7


# --- an independent implementation, in exact rationals ------------------------------------------


def reference(values: list[str], rr_r: str, n: int = 15) -> list[int]:
    q = Fraction
    d_rs, d_sr = q("0.02"), q("0.01")
    rr_rest = q(rr_r)
    rr_s = rr_rest - q("0.08")
    rr_s_max = rr_s - q("0.08")
    k = n - round(q("0.14") / d_rs)
    prev = rr_rest
    out = []
    for v in values:
        x = q(v)
        d = x - prev
        if d < -d_rs and x < rr_rest:
            delta = math.floor((x - min(rr_rest, prev) + d_rs) / d_rs)
        elif d > 0 and x >= rr_s:
            delta = math.ceil((x - max(rr_s, prev)) / d_sr)
        elif x < rr_s_max:
            delta = -1
        else:
            delta = 0
        k = max(1, min(n, k + delta))
        prev = x
        out.append(k)
    return out


# values on the 0.01 and 0.005 grids hit every threshold exactly; free values exercise the rest
grid = st.integers(min_value=100, max_value=240).map(lambda i: f"{i * 5 / 1000:.3f}")
free = st.decimals(min_value=Decimal("0.3"), max_value=Decimal("1.4"), places=4).map(str)


@settings(max_examples=400, deadline=None, derandomize=True)
@given(
    values=st.lists(st.one_of(grid, free), min_size=1, max_size=200),
    rr_r=st.sampled_from(["0.85", "0.7", "1.02"]),
)
def test_the_step_function_matches_an_exact_rational_implementation(values: list[str], rr_r: str) -> None:
    assert run(values, Params.of(rr_r)) == reference(values, rr_r)


def test_cadence_decide_prints_k_per_line_and_matches_the_reference() -> None:
    values = ["0.85", "0.81", "0.79", "0.75", "0.70", "0.62", "0.60", "0.70", "0.80", "0.85", "0.77", "0.78"]
    proc = subprocess.run(
        [sys.executable, "-m", "cadence", "decide", "--rr-rest", "0.85"],
        input="\n".join(values) + "\n",
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert [int(x) for x in proc.stdout.split()] == reference(values, "0.85")


@pytest.mark.parametrize("bad", ["abc", "-0.8", "0", "nan", "inf", "", "0.8 0.9", "850", "0.1"])
def test_cadence_decide_rejects_a_bad_line_naming_it(bad: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "cadence", "decide", "--rr-rest", "0.85"],
        input=f"0.8\n0.81\n{bad}\n",
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "<stdin>:3" in proc.stderr
    assert proc.stdout == ""


def test_cadence_decide_says_a_mean_rr_in_milliseconds_is_one() -> None:
    """850 (ms) read as seconds moved k 8 → 15 silently (issue 28)."""
    proc = subprocess.run(
        [sys.executable, "-m", "cadence", "decide", "--rr-rest", "0.85"],
        input="850\n",
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "milliseconds? 0.85 s" in proc.stderr


@pytest.mark.parametrize(
    ("flag", "said"), [("850", "--rr-rest: a mean RR of 850 s"), ("x", "--rr-rest: expected")]
)
def test_cadence_decide_checks_its_rr_rest_as_it_checks_the_lines(flag: str, said: str) -> None:
    """`--rr-rest 850` was taken as 850 s, and k went to 1 (issue 43)."""
    proc = subprocess.run(
        [sys.executable, "-m", "cadence", "decide", "--rr-rest", flag],
        input="0.8\n",
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert said in proc.stderr
    assert proc.stdout == ""


@pytest.mark.parametrize("minutes", ["0", "-1", "nan"])
def test_cadence_calibrate_refuses_minutes_that_record_nothing(minutes: str) -> None:
    proc = subprocess.run([sys.executable, "-m", "cadence", "calibrate", "--minutes", minutes],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2
    assert "--minutes" in proc.stderr


def test_cadence_calibrate_says_where_it_listens_when_nothing_answers() -> None:
    """Without a bus to join it waited in silence (issue 43): after 10 s it says where it listens."""
    proc = subprocess.Popen([sys.executable, "-m", "cadence", "calibrate", "--minutes", "1", "--cell",
                             f"lonely{os.getpid()}"], stderr=subprocess.PIPE, text=True)  # fmt: skip
    said = ""
    try:
        assert proc.stderr is not None
        while "Ctrl-C" not in said and (line := proc.stderr.readline()):  # blocks until it speaks
            said += line
    finally:
        proc.kill()
        proc.wait(10)
    said = " ".join(said.split())
    assert "no hrv/window on cell 'lonely" in said
    assert "listening through peers on this host" in said


def test_a_router_that_is_not_there_is_one_line_without_zenohs_source_file() -> None:
    from tests.support.cell import free_port

    cmd = [sys.executable, "-m", "cadence", "calibrate", "--connect", f"tcp/127.0.0.1:{free_port()}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0
    assert "cannot open a Zenoh session (client)" in proc.stderr
    assert ".rs:" not in proc.stderr
    assert "cargo" not in proc.stderr
    assert proc.stderr.count("\n") == 1


# --- the personal mode (issues 41, 54) --------------------------------------------------------------------


def test_the_personal_mode_follows_the_persons_recent_rr_within_bounds_and_holds_on_bad_windows() -> None:
    from common.decision import Personal, PersonalState, personal_step

    p, q = Params.of(0.85), Personal(step_s=0.02, keep=0.0, hysteresis=0.0)
    s = PersonalState.initial(p)
    assert (s.k, s.ref) == (8, 0.85)
    s, d, why = personal_step(p, q, s, 0.81, 30, True)  # 40 ms below its reference: two steps slower
    assert (s.k, d, why) == (6, -2, "stress")
    s, d, why = personal_step(p, q, s, 0.89, 30, True)
    assert (s.k, d, why) == (10, 4, "rest")
    assert personal_step(p, q, s, 0.50, 30, True)[0].k == 1  # never below 1 …
    assert personal_step(p, q, s, 1.50, 30, True)[0].k == 15  # … nor above N
    for rr, n, usable in ((None, 30, True), (0.5, 30, False), (0.5, 0, True)):  # held: k and state stay
        assert personal_step(p, q, s, rr, n, usable) == (s, 0, "low-quality")


def test_the_play_moves_k_only_past_the_hysteresis_and_only_that_far() -> None:
    from common.decision import Personal, PersonalState, personal_step

    p, q = Params.of(0.85), Personal(step_s=0.01, keep=0.0, hysteresis=0.5)
    s = PersonalState.initial(p)
    seq = ((0.841, 8), (0.839, 7), (0.845, 7), (0.851, 8), (0.82, 6), (0.829, 6), (0.808, 4), (0.82, 5))
    for rr, k in seq:
        s = personal_step(p, q, s, rr, 30, True)[0]
        assert s.k == k, (rr, s.k)


def test_the_personal_reference_follows_slowly_both_ways_and_not_at_all_under_stress() -> None:
    from common.decision import Personal, PersonalState, personal_step

    p, q = Params.of(0.85), Personal(keep=0.0)
    s = PersonalState.initial(p)
    for _ in range(120):  # an hour 60 ms below: stress, the reference stays
        s = personal_step(p, q, s, 0.79, 30, True)[0]
    assert s.ref == 0.85
    assert s.k <= p.k0 - 3
    for _ in range(120):  # an hour 30 ms below: within the freeze, followed with a time constant of 2 h
        s = personal_step(p, q, s, 0.82, 30, True)[0]
    assert s.ref == pytest.approx(0.82 + 0.03 * math.exp(-0.5), abs=1e-9)
    for _ in range(120):  # and up again, as slowly
        s = personal_step(p, q, s, 0.88, 30, True)[0]
    assert 0.83 < s.ref < 0.86
