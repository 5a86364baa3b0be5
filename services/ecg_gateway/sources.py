"""ECG sources behind one interface (STYLE 4: the fake is chosen by argument, like bleak's backends).

A source yields chunks: the data time of their first sample (ns), µV samples at 130 Hz, and whether
samples are missing before this chunk. ``replay`` plays a recording; ``polar`` is the H10 over BLE (the
simulated operator is a node of its own, services/operator_twin, that sends its ECG in this one's place).
"""

from __future__ import annotations

import abc
import asyncio
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass

import numpy as np

from common.hrv.records import read_record
from schemas.ecg import H10_CHUNK, H10_FS_HZ

FS_HZ, CHUNK = H10_FS_HZ, H10_CHUNK


@dataclass(frozen=True, slots=True)
class Chunk:
    t_ns: int
    samples_uv: list[int]
    gap: bool = False


@dataclass(frozen=True, slots=True)
class RrChunk:
    """RR intervals as the device reports them (the H10's heart-rate notifications)."""

    t_ns: int
    rr_s: list[float]


class EcgSource(abc.ABC):
    name: str
    # A recording is worth nothing to nobody: a replay waits for a subscriber before its first chunk
    # (Zenoh drops a put that has no known subscriber). A live strap streams whoever listens.
    waits_for_listener: bool = False

    @abc.abstractmethod
    def chunks(self) -> AsyncIterator[Chunk | RrChunk]: ...


class ReplaySource(EcgSource):
    """A WFDB record or CSV, resampled to 130 Hz, cut into H10-sized chunks with data times from
    ``start_ns``, paced at ``speed`` × real time (0: as fast as the consumer allows)."""

    name = "replay"
    waits_for_listener = True

    def __init__(self, record: str, speed: float = 1.0, start_ns: int | None = None) -> None:
        self.recording = read_record(record, fs=FS_HZ)  # InputError on a broken file, at start
        self.speed = speed
        self.start_ns = time.time_ns() if start_ns is None else start_ns

    async def chunks(self) -> AsyncIterator[Chunk]:
        x = np.rint(self.recording.uv).astype(int)
        t_wall0 = time.monotonic()
        for i in range(0, len(x), CHUNK):
            if self.speed > 0:
                due = t_wall0 + (i + CHUNK) / FS_HZ / self.speed  # a chunk exists once its last sample does
                await asyncio.sleep(max(0.0, due - time.monotonic()))
            else:
                await asyncio.sleep(0)
            yield Chunk(self.start_ns + round(i * 1e9 / FS_HZ), x[i : i + CHUNK].tolist())
