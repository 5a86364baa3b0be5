"""Decoder for the `zenoh` command of zenoh-cli: `zenoh subscribe -k 'cadence/**' --decoder cadence`
prints every Cadence message as JSON. Registered as an entry point in group `zenoh_cli.codecs.decoders`
(zenoh-cli 0.5+: a function of the key and the payload bytes that returns text).

Each key is decoded as the type the graph gives it (schemas/topology.py), so a message of another type on
a key says so; a key outside the graph is decoded by its tag alone."""

from __future__ import annotations

import msgspec

from schemas.base import Message
from schemas.topology import decode_any, topic_of

_DECODERS: dict[type[Message], msgspec.msgpack.Decoder[Message]] = {}


def _decode(key: str, payload: bytes) -> Message:
    topic = topic_of(key)
    if topic is None:
        return decode_any(payload)
    decoder = _DECODERS.get(topic.message)
    if decoder is None:
        decoder = _DECODERS[topic.message] = msgspec.msgpack.Decoder(topic.message)
    return decoder.decode(payload)


def decode(key: object, payload: bytes) -> str:
    """``key`` is zenoh's ``KeyExpr`` from zenoh-cli (a ``str`` from a test)."""
    text = str(key)
    try:
        return msgspec.json.encode(_decode(text, payload)).decode()
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        return msgspec.json.encode({"key": text, "error": str(exc), "bytes": len(payload)}).decode()
