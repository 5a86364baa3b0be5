"""The wire contract: every message round-trips; wrong types, missing fields and unknown tags fail."""

from __future__ import annotations

import msgspec
import pytest

from schemas import (
    AccChunk,
    Beats,
    Calibration,
    CellClock,
    CycleReport,
    EcgChunk,
    HrvWindow,
    OperatorError,
    OperatorSignal,
    ParetoSet,
    ParetoSolution,
    ParetoSolutionReply,
    PlanProgress,
    RobotEvent,
    RobotState,
    RrIntervals,
    Selection,
    Separation,
    ServiceStatus,
)
from schemas.pareto import Limits, PathEnd
from schemas.topology import TOPICS, AnyMessage, decode_any, encode, topic_of

Z6 = [0.0] * 6
SOL = ParetoSolution(k=1, h=[0.5, 0.5, 1.0], t_f=2.0, f_time=12.0, f_jerk=3.0)
SAMPLES = [
    EcgChunk(t_ns=1, seq=0, fs_hz=130.0, samples_uv=[1, -2, 3], gap=True, source="polar"),
    RrIntervals(t_ns=1, seq=1, rr_s=[0.8, 0.81]),
    Beats(t_ns=1, seq=2, peak_t_ns=[10, 20], rr_s=[0.8, 0.9], excluded=[False, True]),
    HrvWindow(
        t_ns=30,
        seq=3,
        start_ns=0,
        end_ns=30,
        mean_rr_s=0.8,
        n_beats=37,
        excluded_fraction=0.05,
        quality="good",
    ),
    Calibration(t_ns=1, seq=4, subject="s01", rr_rest_s=0.85),
    Selection(t_ns=1, seq=5, k=8, n=15, delta=-1, reason="stress", window_end_ns=30),
    PlanProgress(t_ns=1, seq=6, path_id="p", state="running", done_paths=0, total_paths=2),
    ParetoSet(
        t_ns=1,
        seq=7,
        path_id="p",
        content_hash="abc",
        constraints="exact",
        waypoints=[Z6, Z6],
        limits=Limits(velocity=Z6, acceleration=Z6, jerk=Z6),
        start=PathEnd(velocity=Z6, acceleration=Z6, jerk=Z6),
        end=PathEnd(velocity=Z6, acceleration=Z6, jerk=Z6),
        front=[[1.0, 2.0]],
        solutions=[SOL],
    ),
    ParetoSolutionReply(t_ns=1, seq=8, path_id="p", content_hash="abc", n=1, solution=SOL),
    RobotState(t_ns=1, seq=9, q=Z6, qd=Z6, tcp=Z6, path_id="p", k=3, mode="moving"),
    CycleReport(t_ns=1, seq=10, cycle=3, cycle_time_s=21.5, k_per_path={"p": 3}),
    RobotEvent(t_ns=1, seq=11, kind="refused", message="over a limit", path_id="p"),
    ServiceStatus(t_ns=1, seq=12, service="x", state="running", uptime_s=3.0, counters={"decode_errors": 0}),
    CellClock(t_ns=1, seq=0, epoch_ns=1, speed=8.0),
    OperatorSignal(t_ns=1, seq=13, name="part_a2"),
    Separation(t_ns=1, seq=14, distance_m=1.8, source="scanner:front", age_s=0.03),
    OperatorError(t_ns=1, seq=14, cycle=3, description="wrong part"),
    AccChunk(t_ns=1, seq=0, fs_hz=25.0, x_mg=[-990, -985], y_mg=[30, 31], z_mg=[-237, -230], source="polar"),
]


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: type(m).__name__)
def test_every_message_round_trips_through_its_own_and_the_union_decoder(msg: object) -> None:
    payload = encode(msg)
    assert msgspec.msgpack.Decoder(type(msg)).decode(payload) == msg
    assert decode_any(payload) == msg


def test_every_message_type_has_a_topic_and_a_distinct_versioned_tag() -> None:
    types = {type(m) for m in SAMPLES}
    assert types == {t.message for t in TOPICS}
    tags = [t.__struct_config__.tag for t in types]
    assert len(set(tags)) == len(tags)
    assert all(tag.rsplit(".", 1)[1].startswith("v") for tag in tags)


def test_keys_map_to_their_topics() -> None:
    assert topic_of("cadence/cell1/pareto/progress").message is PlanProgress
    assert topic_of("cadence/cell7/pareto/b1_to_b2").message is ParetoSet
    assert topic_of("cadence/cell1/pareto/b1_to_b2/3").message is ParetoSolutionReply
    assert topic_of("cadence/cell1/health/executor").message is ServiceStatus
    assert topic_of("other/cell1/robot/state") is None


def as_dict(msg: object) -> dict:
    return msgspec.to_builtins(msg)


def test_a_wrong_type_is_rejected_not_coerced() -> None:
    d = as_dict(SAMPLES[5])
    d["k"] = "8"
    with pytest.raises(msgspec.ValidationError, match=r"Expected `int`, got `str` - at `\$.k`"):
        msgspec.msgpack.Decoder(Selection).decode(msgspec.msgpack.encode(d))


def test_a_missing_field_is_rejected() -> None:
    d = as_dict(SAMPLES[3])
    del d["quality"]
    with pytest.raises(msgspec.ValidationError, match="missing required field `quality`"):
        msgspec.msgpack.Decoder(HrvWindow).decode(msgspec.msgpack.encode(d))


def test_an_unknown_tag_is_rejected() -> None:
    d = as_dict(SAMPLES[5])
    d["type"] = "decision.selection.v9"
    with pytest.raises(msgspec.ValidationError, match=r"Invalid value .decision\.selection\.v9."):
        msgspec.msgpack.Decoder(AnyMessage).decode(msgspec.msgpack.encode(d))


@pytest.mark.parametrize(
    ("change", "where"),
    [
        ({"fs_hz": 400.0}, "not a rate the accelerometer has"),  # an impossible rate
        ({"x_mg": [-990, 40_000]}, r"\$.x_mg\[1\]"),  # beyond 16 g: no movement of a chest
        ({"y_mg": [30]}, "one entry per sample"),
        ({"x_mg": [0] * 300, "y_mg": [0] * 300, "z_mg": [0] * 300}, "over 10 s at 25 Hz"),
    ],
)
def test_an_impossible_accelerometer_chunk_does_not_decode(change: dict, where: str) -> None:
    d = {**as_dict(SAMPLES[-1]), **change}
    with pytest.raises(msgspec.ValidationError, match=where):
        msgspec.msgpack.Decoder(AccChunk).decode(msgspec.msgpack.encode(d))


def test_constraints_hold_at_the_edge() -> None:
    d = as_dict(SAMPLES[1])
    d["rr_s"] = [0.8, -0.1]
    with pytest.raises(msgspec.ValidationError, match=r"\$.rr_s\[1\]"):
        msgspec.msgpack.Decoder(RrIntervals).decode(msgspec.msgpack.encode(d))


def test_an_old_decoder_skips_a_field_it_does_not_know() -> None:
    d = as_dict(SAMPLES[5])
    d["added_later"] = 1
    assert msgspec.msgpack.Decoder(Selection).decode(msgspec.msgpack.encode(d)) == SAMPLES[5]
