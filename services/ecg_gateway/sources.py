"""ECG sources behind one interface (STYLE 4: the fake is chosen by argument, like bleak's backends).

A source yields chunks: the data time of their first sample (ns), µV samples at 130 Hz, and whether
samples are missing before this chunk; and, when it has an accelerometer, its samples (mg) on the same
clock. ``replay`` plays a recording; ``polar`` is the H10 over BLE (the
simulated operator is a node of its own, services/operator_twin, that sends its ECG in this one's place).
"""

from __future__ import annotations

import abc
from collections.abc import AsyncIterator
from dataclasses import dataclass

import numpy as np

from common.hrv.e4 import read_e4
from common.hrv.records import AccRecording, read_acc, read_record
from common.runtime.clock import pause, wall_monotonic, wall_ns
from schemas.ecg import ACC_RATES_HZ, H10_CHUNK, H10_FS_HZ, MAX_ACC_MG

FS_HZ, CHUNK = H10_FS_HZ, H10_CHUNK


@dataclass(frozen=True, slots=True)
class Chunk:
    t_ns: int
    samples_uv: list[int]
    gap: bool = False
    fs_hz: float = FS_HZ  # the source's own rate, measured where it can be (a strap's clock)


@dataclass(frozen=True, slots=True)
class RrChunk:
    """RR intervals as the device reports them (the H10's heart-rate notifications)."""

    t_ns: int
    rr_s: list[float]
    gap: bool = False  # intervals missing before these (a wrist that lost the pulse)


@dataclass(frozen=True, slots=True)
class AccSamples:
    """Accelerometer samples (x, y, z in mg) at ``fs_hz`` from data time ``t_ns``."""

    t_ns: int
    fs_hz: float
    xyz_mg: list[tuple[int, int, int]]
    gap: bool = False


Item = Chunk | RrChunk | AccSamples


class EcgSource(abc.ABC):
    name: str
    # A recording is worth nothing to nobody: a replay waits for a subscriber before its first chunk
    # (Zenoh drops a put that has no known subscriber). A live strap streams whoever listens.
    waits_for_listener: bool = False
    # whether it sends the accelerometer: a strap that refuses it, a recording without one, do not
    accelerometer: bool = False
    # whether it sends ECG samples; one that does not sends RR intervals, read with the analyser's
    # ``input = "rr"``
    ecg: bool = True

    @abc.abstractmethod
    def chunks(self) -> AsyncIterator[Item]: ...


class ReplaySource(EcgSource):
    """A WFDB record or CSV, resampled to 130 Hz, cut into H10-sized chunks with data times from
    ``start_ns``, paced at ``speed`` × real time (0: as fast as the consumer allows). By default a replay
    at real time starts now, as a strap would; a faster one ends by now (it starts a recording's length
    ago): receivers refuse data from their future (DESIGN §4), and a replay faster than the cell's
    clock would run into it. With ``acc``, a
    Polar accelerometer export, its samples go out beside the ECG: on the strap's clock when the ECG is
    a Polar export of the same session, else from the ECG's start."""

    name = "replay"
    waits_for_listener = True

    def __init__(
        self, record: str, speed: float = 1.0, start_ns: int | None = None, acc: str | None = None
    ) -> None:
        self.recording = read_record(record, fs=FS_HZ)  # InputError on a broken file, at start
        self.acc: AccRecording | None = read_acc(acc) if acc is not None else None
        self.accelerometer = self.acc is not None
        self.speed = speed
        length_ns = round(len(self.recording.uv) * 1e9 / FS_HZ) if speed != 1.0 else 0
        self.start_ns = wall_ns() - length_ns if start_ns is None else start_ns

    def _acc_items(self) -> list[AccSamples]:
        """The accelerometer in one-second chunks, each at its own data time (the strap's rate is
        nominal: 25 Hz measures as 25.3 on the export)."""
        if self.acc is None:
            return []
        origin = self.recording.sensor_start_ns or int(self.acc.sensor_ns[0])
        fs = min(ACC_RATES_HZ, key=lambda r: abs(r - self.acc.fs))  # type: ignore[union-attr]
        n = round(fs)
        return [
            AccSamples(self.start_ns + int(self.acc.sensor_ns[i]) - origin, fs,
                       [(int(a), int(b), int(c)) for a, b, c in self.acc.xyz_mg[i : i + n]])
            for i in range(0, len(self.acc.sensor_ns), n)
        ]  # fmt: skip

    async def chunks(self) -> AsyncIterator[Item]:
        x = np.rint(self.recording.uv).astype(int)
        acc = [a for a in self._acc_items() if a.t_ns >= self.start_ns]
        t_wall0 = wall_monotonic()
        for i in range(0, len(x), CHUNK):
            if self.speed > 0:
                due = t_wall0 + (i + CHUNK) / FS_HZ / self.speed  # a chunk exists once its last sample does
                await pause(max(0.0, due - wall_monotonic()))
            else:
                await pause(0)
            t_ns = self.start_ns + round(i * 1e9 / FS_HZ)
            yield Chunk(t_ns, x[i : i + CHUNK].tolist())
            end_ns = t_ns + round(CHUNK * 1e9 / FS_HZ)
            while acc and acc[0].t_ns + round(len(acc[0].xyz_mg) * 1e9 / acc[0].fs_hz) <= end_ns:
                yield acc.pop(0)  # sent once its last sample exists, as the strap does


class E4Source(EcgSource):
    """An Empatica E4 export (common/hrv/e4.py) as the wristband saw it: each interval as the device's RR
    at its closing beat, with ``gap`` where intervals are missing before it (the wrist lost the pulse), and
    with ``accelerometer`` its 32 Hz samples in one-second chunks. No ECG: the analyser reads it with
    ``input = "rr"``. Placed on the clock and paced as ``ReplaySource``.

    The accelerometer is off by default: the movement hold reads a chest strap's trunk (DESIGN §7), and a
    wrist's is the hands, which type and gesture through a Stroop test and an interview (`cadence bench
    decide --wrist-movement` measures what it would hold)."""

    name = "e4"
    waits_for_listener = True
    ecg = False

    def __init__(self, folder: str, speed: float = 1.0, start_ns: int | None = None,
                 accelerometer: bool = False) -> None:  # fmt: skip
        self.rec = read_e4(folder)  # InputError naming the file and line, at start
        self.accelerometer = accelerometer and self.rec.acc_hz is not None and len(self.rec.acc_mg) > 0
        self.speed = speed
        length_ns = self.rec.end_ns - self.rec.start_ns if speed != 1.0 else 0
        self.start_ns = wall_ns() - length_ns if start_ns is None else start_ns

    def items(self) -> list[tuple[int, Item]]:
        """Everything with the data time it exists at (an interval at its closing beat, an accelerometer
        second at its last sample), in that order."""
        rec, shift = self.rec, self.start_ns - self.rec.start_ns
        out: list[tuple[int, Item]] = []
        prev = None
        for beat, rr in zip(rec.beat_ns.tolist(), rec.ibi_s.tolist(), strict=True):
            gap = prev is not None and abs(beat - round(rr * 1e9) - prev) > 20_000_000  # not the last beat
            out.append((beat + shift, RrChunk(beat + shift, [round(rr, 6)], gap)))
            prev = beat
        if self.accelerometer:
            assert rec.acc_start_ns is not None and rec.acc_hz is not None
            n = round(rec.acc_hz)
            xyz = np.clip(np.rint(rec.acc_mg), -MAX_ACC_MG, MAX_ACC_MG).astype(int)
            for i in range(0, len(xyz) - n + 1, n):
                t = rec.acc_start_ns + shift + round(i * 1e9 / rec.acc_hz)
                rows = [(int(a), int(b), int(c)) for a, b, c in xyz[i : i + n]]
                out.append((t + round(n * 1e9 / rec.acc_hz), AccSamples(t, rec.acc_hz, rows)))
        out.sort(key=lambda x: x[0])
        return out

    async def chunks(self) -> AsyncIterator[Item]:
        t_wall0 = wall_monotonic()
        for exists_ns, item in self.items():
            if self.speed > 0:
                due = t_wall0 + (exists_ns - self.start_ns) / 1e9 / self.speed
                await pause(max(0.0, due - wall_monotonic()))
            else:
                await pause(0)
            yield item
