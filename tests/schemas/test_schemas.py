"""The wire contract: every message round-trips; wrong types, missing fields and unknown tags fail."""

from __future__ import annotations

import msgspec
import pytest

from schemas import (
    AccChunk,
    HrvWindow,
    ParetoSet,
    ParetoSolutionReply,
    PlanProgress,
    RrIntervals,
    Selection,
    ServiceStatus,
)
from schemas.topology import TOPICS, AnyMessage, decode_any, encode, topic_of
from tests.support.cell import CELL
from tests.support.messages import SAMPLES


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
    assert topic_of(f"cadence/{CELL}/pareto/progress").message is PlanProgress
    assert topic_of("cadence/cell7/pareto/b1_to_b2").message is ParetoSet
    assert topic_of(f"cadence/{CELL}/pareto/b1_to_b2/3").message is ParetoSolutionReply
    assert topic_of(f"cadence/{CELL}/health/executor").message is ServiceStatus
    assert topic_of(f"other/{CELL}/robot/state") is None


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
