"""The receivers' rule for data time (common/runtime/admission.py): one message far from its stream is
dropped; a run of messages that agree with each other moves the stream there; duplicates never do."""

from __future__ import annotations

import pytest

from common.runtime.admission import TimeLine

S = 1_000_000_000
DAY = 86_400 * S


def windows(line: TimeLine, spans: list[tuple[int, int]]) -> list[str]:
    return [line.admit(a * S, b * S).action for a, b in spans]


def test_the_first_message_anchors_and_consecutive_ones_are_in_line() -> None:
    line = TimeLine(600)
    assert windows(line, [(0, 30), (30, 60), (60, 90)]) == ["accept"] * 3
    assert line.position_ns == 90 * S


def test_one_window_far_ahead_is_dropped_and_the_next_honest_one_is_answered() -> None:
    line = TimeLine(600)
    line.admit(0, 30 * S)
    v = line.admit(30 * DAY, 30 * DAY + 30 * S)
    assert (v.action, v.code) == (
        "drop",
        "ahead",
    )
    assert "2591970.000 s ahead" in v.detail  # from the stream's end, 30 s
    assert line.admit(30 * S, 60 * S).action == "accept"
    assert line.position_ns == 60 * S


def test_a_duplicate_is_dropped_and_never_moves_the_line_however_many_come() -> None:
    line = TimeLine(600, duplicate_s=600)
    line.admit(0, 30 * S)
    line.admit(30 * S, 60 * S)
    for _ in range(5):
        v = line.admit(30 * S, 60 * S)
        assert (v.action, v.code) == ("drop", "duplicate")
    assert line.position_ns == 60 * S


def test_a_run_that_agrees_with_itself_moves_the_line_after_confirm_messages() -> None:
    """A source restarted in time (a replay again from the start, a clock set right)."""
    line = TimeLine(120, tolerance_s=0.01, confirm=3)
    line.admit(5000 * S, 5001 * S)
    assert windows(line, [(0, 1), (1, 2)]) == ["drop", "drop"]
    assert line.admit(2 * S, 3 * S).action == "restart"
    assert line.position_ns == 3 * S
    assert line.admit(3 * S, 4 * S).action == "accept"


def test_a_position_persisted_far_in_the_future_cannot_lock_an_honest_stream_out() -> None:
    line = TimeLine(600, duplicate_s=600)
    line.anchor(3000 * DAY)
    assert windows(line, [(0, 30), (30, 60), (60, 90)]) == ["drop", "restart", "accept"]


def test_scattered_hostile_times_never_confirm_each_other() -> None:
    line = TimeLine(600, confirm=2)
    line.admit(0, 30 * S)
    assert (
        windows(line, [(10 * DAY, 10 * DAY + 30), (3 * DAY, 3 * DAY + 30), (50 * DAY, 50 * DAY + 30)])
        == ["drop"] * 3
    )
    assert line.position_ns == 30 * S


def test_a_change_of_kind_is_out_of_line_until_confirmed() -> None:
    line = TimeLine(120, tolerance_s=0.01, confirm=2)
    line.admit(0, S, 130.0)
    v = line.admit(S, 2 * S, 250.0)
    assert (v.action, v.code) == ("drop", "changed")
    assert line.admit(S, 2 * S, 130.0).action == "accept"
    assert [line.admit(t * S, (t + 1) * S, 250.0).action for t in (2, 3)] == ["drop", "restart"]


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError):
        TimeLine(0)
    with pytest.raises(ValueError):
        TimeLine(10, confirm=1)


NOW = 1_790_000_000 * S


def test_with_a_clock_the_first_message_is_believed_only_near_it() -> None:
    line = TimeLine(600, duplicate_s=600)
    v = line.admit(NOW - 30 * DAY, NOW - 30 * DAY + 30 * S, clock_ns=NOW)
    assert (v.action, v.code) == ("drop", "far_from_clock")
    assert line.admit(NOW - 30 * S, NOW, clock_ns=NOW).action == "accept"
    assert line.position_ns == NOW


def test_nothing_from_the_receivers_future_is_taken_however_many_agree() -> None:
    """A run of 20 contiguous windows up to 600 s ahead of the clock once moved the decision maker's time
    line, and the honest windows after it were dropped as duplicates for ten minutes."""
    line = TimeLine(600, duplicate_s=600, confirm=2, skew_s=0.05)
    assert line.admit(NOW - 30 * S, NOW, clock_ns=NOW).action == "accept"
    planted = [line.admit(NOW + i * 30 * S, NOW + (i + 1) * 30 * S, clock_ns=NOW + S) for i in range(20)]
    assert {(v.action, v.code) for v in planted} == {("drop", "ahead")}
    assert "ahead of the receiver's clock" in planted[0].detail
    honest = [
        line.admit(NOW + i * 30 * S, NOW + (i + 1) * 30 * S, clock_ns=NOW + (i + 1) * 30 * S)
        for i in range(6)
    ]
    assert [v.action for v in honest] == ["accept"] * 6
    # within the skew bound a stamp a little ahead is still taken
    assert line.admit(NOW + 180 * S, NOW + 210 * S, clock_ns=NOW + 210 * S - 40_000_000).action == "accept"


def test_with_a_clock_a_replay_far_from_it_is_taken_after_confirm() -> None:
    line = TimeLine(600, duplicate_s=600, confirm=2)
    old = NOW - 7 * DAY  # a recording from last week
    assert [line.admit(old + i * 30 * S, old + (i + 1) * 30 * S, clock_ns=NOW).action for i in range(3)] == [
        "drop",
        "restart",
        "accept",
    ]


def test_a_stale_line_gives_way_at_once_to_a_message_near_the_clock() -> None:
    line = TimeLine(600, duplicate_s=600)
    line.anchor(NOW - DAY)  # persisted yesterday
    v = line.admit(NOW - 30 * S, NOW, clock_ns=NOW)
    assert v.action == "restart"
    assert "clock" in v.detail
    # but near the clock a single message far from a live stream is still dropped
    assert line.admit(NOW - 3 * DAY, NOW - 3 * DAY + 30 * S, clock_ns=NOW).action == "drop"
