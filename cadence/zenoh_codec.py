"""Decoder for the `zenoh` command of zenoh-cli: `zenoh subscribe -k 'cadence/**' --decoder cadence`
prints every Cadence message as JSON. Registered as an entry point in group `zenoh_cli.codecs.decoders`
(zenoh-cli 0.5+: a function of the key and the payload bytes that returns text)."""

from __future__ import annotations

import msgspec

from schemas.topology import decode_any


def decode(key: str, payload: bytes) -> str:
    try:
        return msgspec.json.encode(decode_any(payload)).decode()
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        return msgspec.json.encode({"key": key, "error": str(exc), "bytes": len(payload)}).decode()
