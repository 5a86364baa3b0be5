"""ECG from the strap (or a replay, or the operator twin): ``ecg/samples`` and ``ecg/rr``."""

from __future__ import annotations

from typing import Annotated

import msgspec

from schemas.base import Message, PositiveFloat


class EcgChunk(Message, frozen=True, tag="ecg.chunk.v1"):
    """Consecutive samples in µV; ``t_ns`` is the data time of the first one. ``gap`` marks samples
    missing before this chunk (a BLE drop, a restart of the stream): never bridge it."""

    fs_hz: PositiveFloat
    samples_uv: list[int]
    gap: bool = False
    source: str = ""


class RrIntervals(Message, frozen=True, tag="ecg.rr.v1"):
    """RR intervals as the device reports them (H10: 1/1024 s); ``t_ns`` is the notification time."""

    rr_s: list[Annotated[float, msgspec.Meta(gt=0, lt=5)]]
    gap: bool = False
    source: str = ""
