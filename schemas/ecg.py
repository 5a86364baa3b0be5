"""ECG from the strap (or a replay, or the operator twin): ``ecg/samples``, ``ecg/rr``, and the strap's
accelerometer, ``ecg/acc``."""

from __future__ import annotations

from typing import Annotated

import msgspec

from schemas.base import Message, Name, RrSeconds

# The sample rates an ECG source can have: the H10's 130 Hz (replays are resampled to it) and the
# usual rates of other chest straps and recorders.
ECG_RATES_HZ = (125.0, 128.0, 130.0, 200.0, 250.0, 256.0, 360.0, 500.0, 512.0, 1000.0)
MAX_CHUNK_S = 10.0  # an H10 frame is 73 samples (0.56 s); a chunk is never longer than this
# a strap's own clock runs off its nominal rate (the H10's 130 Hz by about 1 %): its measured rate is sent
RATE_TOLERANCE = 0.02
H10_FS_HZ = 130.0  # what the sources send: the H10's ECG rate, replays resampled to it, the twin's
H10_CHUNK = 73  # samples per H10 PMD notification at 130 Hz
MicroVolts = Annotated[int, msgspec.Meta(ge=-(2**23), le=2**23 - 1)]  # the H10's int24


class EcgChunk(Message, frozen=True, tag="ecg.chunk.v1"):
    """Consecutive samples in µV; ``t_ns`` is the data time of the first one. ``gap`` marks samples
    missing before this chunk (a BLE drop, a restart of the stream): never bridge it."""

    fs_hz: float
    samples_uv: Annotated[list[MicroVolts], msgspec.Meta(max_length=round(MAX_CHUNK_S * 1000))]
    gap: bool = False
    source: Name = ""

    def __post_init__(self) -> None:
        if not any(abs(self.fs_hz / r - 1.0) <= RATE_TOLERANCE for r in ECG_RATES_HZ):
            raise ValueError(
                f"fs_hz = {self.fs_hz} is not within 2 % of a rate an ECG source has {ECG_RATES_HZ}"
            )
        if len(self.samples_uv) > MAX_CHUNK_S * self.fs_hz:
            raise ValueError(f"{len(self.samples_uv)} samples is over {MAX_CHUNK_S:g} s at {self.fs_hz:g} Hz")


class RrIntervals(Message, frozen=True, tag="ecg.rr.v1"):
    """RR intervals as the device reports them (H10: 1/1024 s); ``t_ns`` is the notification time."""

    rr_s: Annotated[list[RrSeconds], msgspec.Meta(max_length=64)]
    gap: bool = False
    source: Name = ""


# The H10's accelerometer (PMD measurement type 2): 25, 50, 100 or 200 Hz, ±2, 4 or 8 g, in mg. A value
# beyond 16 g is no movement of a person's chest: a broken frame.
ACC_RATES_HZ = (25.0, 32.0, 50.0, 100.0, 200.0)  # and 32 Hz: an Empatica E4's (a wristband's replay)
MAX_ACC_MG = 16_000
Milligravity = Annotated[int, msgspec.Meta(ge=-MAX_ACC_MG, le=MAX_ACC_MG)]
_MAX_ACC = round(MAX_CHUNK_S * max(ACC_RATES_HZ))


class AccChunk(Message, frozen=True, tag="ecg.acc.v1"):
    """Consecutive 3-axis accelerometer samples from the strap, in mg; ``t_ns`` is the data time of the
    first one, on the clock of the ECG from the same strap. ``gap``: samples missing before this chunk."""

    fs_hz: float
    x_mg: Annotated[list[Milligravity], msgspec.Meta(max_length=_MAX_ACC)]
    y_mg: Annotated[list[Milligravity], msgspec.Meta(max_length=_MAX_ACC)]
    z_mg: Annotated[list[Milligravity], msgspec.Meta(max_length=_MAX_ACC)]
    gap: bool = False
    source: Name = ""

    def __post_init__(self) -> None:
        if self.fs_hz not in ACC_RATES_HZ:
            raise ValueError(f"fs_hz = {self.fs_hz} is not a rate the accelerometer has {ACC_RATES_HZ}")
        if not len(self.x_mg) == len(self.y_mg) == len(self.z_mg):
            raise ValueError("x_mg, y_mg and z_mg must have one entry per sample")
        if len(self.x_mg) > MAX_CHUNK_S * self.fs_hz:
            raise ValueError(f"{len(self.x_mg)} samples is over {MAX_CHUNK_S:g} s at {self.fs_hz:g} Hz")
