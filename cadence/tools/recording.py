"""`cadence record` and `cadence replay`: bus traffic to and from MCAP files (DESIGN §1, §3, §11).

A recording keeps every payload as it travelled (MessagePack), one channel per key, with the message
type's JSON schema attached (msgspec's), so the file opens in MCAP tools. What it holds reaches the disk
every second (a chunk each), so a recorder killed loses at most that; a file left without its footer (a
kill, a disk that filled) is read up to its last whole chunk, and said so. A disk that cannot take more
ends the recording at once, with one line naming the file; ``json=True`` writes JSON
channels instead, which Foxglove's viewer can decode, and which report and replay read as well. Log
time is the wall clock at arrival, publish time the message's own data time. A replay republishes the
payloads unchanged (so with their original data time) on their keys, paced by the recorded log times
divided by ``speed``; services on data time then give exactly what they gave live.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import zenoh
from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from common.runtime.bus import Bus
from common.runtime.errors import CadenceError, InputError
from schemas.topology import AnyMessage, decode_any, encode, topic_of

PROFILE = "cadence"
FLUSH_S = 1.0  # what a recorder holds reaches the disk this often (wall s): a kill loses at most this
# What a plant keeps of every cell (`cadence record --plant`): what each cell decided and did, and how its
# services are. Not the worker's raw signals (ECG, accelerometer, beats, device RR: health data, a third
# of a cell's bytes), nor the arm's state at its servo's rate or each separation reading (the rest: the
# events say when the arm held).
PLANT_SUFFIXES = (
    "hrv/window",
    "operator/calibration",
    "decision/selection",
    "robot/cycle",
    "robot/event",
    "operator/error",
    "operator/signal",
    "health/*",
)
HEALTH_EVERY_S = 60.0  # a plant keeps a service's status once a minute (wall s)


def plant_keys(root: str = "cadence") -> list[str]:
    return [f"{root}/*/{suffix}" for suffix in PLANT_SUFFIXES]


class PlantThinning:
    """A filter for a plant recording: every message but the repeats. A service's status is kept once
    every ``every_s`` (wall time, as statuses come): five services' statuses every few seconds were a
    third of a plant recording, and the executor's says what the robot is doing, which its events already
    say (measured on the demo cell: 0.4 executor statuses a second kept on a change of state); a
    selection only when it is a new one (the decision maker republishes the one in force)."""

    def __init__(self, every_s: float = HEALTH_EVERY_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.every_s, self.clock = every_s, clock
        self.kept_at: dict[str, float] = {}  # a status key: when one was last kept
        self.seq: dict[str, int] = {}  # a selection key: the last one kept

    def __call__(self, key: str, payload: bytes) -> bool:
        if "/health/" in key:
            now = self.clock()
            if now - self.kept_at.get(key, -math.inf) < self.every_s:
                return False
            self.kept_at[key] = now
            return True
        if not key.endswith("/decision/selection"):
            return True
        try:
            seq = decode_any(payload).seq
        except msgspec.DecodeError:
            return True  # kept as it came: a recording is evidence
        if self.seq.get(key) == seq:
            return False
        self.seq[key] = seq
        return True


@dataclass
class Recorder:
    """Writes samples as they arrive; ``flush`` puts what it holds on disk (a chunk); ``close`` finishes
    the file (its summary and index). A write the disk refuses ends it: ``failed`` says why."""

    path: Path
    json: bool = False
    replace: bool = True  # False: a file already there is never overwritten (FileExistsError)

    def __post_init__(self) -> None:
        self._file = self.path.open("wb" if self.replace else "xb")
        self._writer = Writer(self._file, chunk_size=256 * 1024, compression=CompressionType.ZSTD)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self.count = 0
        self.on_disk = 0  # of ``count``, those in the file (after a refused write, counted by reading it)
        self.undecodable = 0
        self.closed = False
        self.failed: str | None = None
        self._guard(lambda: self._writer.start(profile=PROFILE, library="cadence"))

    def _guard(self, write: Callable[[], object]) -> None:
        """A write to the file; a disk that refuses it (full, gone) ends the recording, said in ``failed``."""
        if self.failed is not None:
            return
        try:
            write()
        except OSError as exc:
            self.failed = f"cannot write {self.path}: {exc.strerror or exc}"
            self.closed = True

    def _channel(self, key: str) -> int:
        if key in self._channels:
            return self._channels[key]
        topic = topic_of(key)
        schema_id = 0
        if topic is not None:
            name = topic.message.__struct_config__.tag
            if name not in self._schemas:
                schema = msgspec.json.encode(msgspec.json.schema(topic.message))
                self._schemas[name] = self._writer.register_schema(name, "jsonschema", schema)
            schema_id = self._schemas[name]
        enc = "json" if self.json else "msgpack"
        self._channels[key] = self._writer.register_channel(key, enc, schema_id, {"cadence": "v1"})
        return self._channels[key]

    def metadata(self, name: str, data: dict[str, str]) -> None:
        """An MCAP metadata record (a session's description): MCAP tools list them beside the channels."""
        if not self.closed:
            self._guard(lambda: self._writer.add_metadata(name, data))

    def write(self, key: str, payload: bytes, log_time_ns: int | None = None) -> None:
        """``log_time_ns``: when it arrived; the wall clock now unless a simulation gives its own."""
        if self.closed:
            return
        try:
            msg = decode_any(payload)
        except msgspec.DecodeError:
            self.undecodable += 1  # kept as it came: a recording is evidence
            msg = None
        data = msgspec.json.encode(msg) if self.json and msg is not None else payload
        seq = self._seq.get(key, 0)
        self._seq[key] = seq + 1
        log_time = time.time_ns() if log_time_ns is None else log_time_ns
        publish = msg.t_ns if msg is not None else 0
        self._guard(lambda: self._writer.add_message(self._channel(key), log_time=log_time, data=data,
                                                     publish_time=publish, sequence=seq))  # fmt: skip
        self.count += self.failed is None

    def flush(self) -> None:
        """What it holds, to disk, as a whole chunk: a recorder killed now loses nothing before it."""
        if not self.closed:
            self._guard(self._writer.flush)

    def _finish(self) -> None:
        self._writer.finish()
        self._file.flush()
        try:
            os.fsync(self._file.fileno())
        except OSError as exc:
            if exc.errno != errno.EINVAL:  # a pipe or a terminal has nothing to sync; a disk may refuse it
                raise

    def close(self) -> None:
        if self.failed is None:  # the footer and what the file object holds, on the disk: a disk that fills
            # at the close refuses this flush, not the close after it (once: "written", rc 0, no footer)
            self._guard(self._finish)
        self.closed = True
        with contextlib.suppress(OSError):  # a full disk: what was flushed stays readable
            self._file.close()
        if self.failed is None:
            self.on_disk = self.count
        else:  # the writer put whole chunks out as they filled, and a flush some: the file says which
            try:
                self.on_disk = sum(1 for _ in read(self.path, notes=[]))
            except (CadenceError, OSError):  # not even its header reached the disk
                self.on_disk = 0


async def record(
    bus: Bus,
    path: Path,
    keys: list[str],
    stop: asyncio.Event,
    json: bool = False,
    on_first: Callable[[str], None] | None = None,
    keep: Callable[[str, bytes], bool] | None = None,
    replace: bool = True,
) -> Recorder:
    """Record until ``stop``; the file is complete even when the stop is a signal. ``on_first(key)`` is
    called once, when the first message is written (a person wants to know that anything comes);
    ``keep(key, payload)`` False leaves a message out (``PlantThinning``); ``replace`` False: a file already
    at ``path`` is left as it is (FileExistsError), another recording's evidence."""
    rec = Recorder(path, json, replace)

    def write(key: str, payload: bytes) -> None:
        if keep is not None and not keep(key, payload):
            return
        rec.write(key, payload)
        if rec.failed is not None:
            stop.set()
        elif on_first is not None and rec.count == 1:
            on_first(key)

    subs = [bus.subscribe_raw(k, write) for k in keys]
    try:
        while not stop.is_set() and rec.failed is None:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), FLUSH_S)
            rec.flush()
    finally:
        for s in subs:
            s.undeclare()
        # samples Zenoh handed over before the undeclare wait in the loop's ready queue: one pass of
        # the loop writes them, then the file is finished
        await asyncio.sleep(0)
        rec.close()
    return rec


@dataclass(frozen=True, slots=True)
class Recorded:
    key: str
    log_time: int
    data: bytes
    encoding: str


_JSON_ANY = msgspec.json.Decoder(AnyMessage)


def as_msgpack(encoding: str, data: bytes) -> tuple[str, bytes]:
    """A JSON channel's message (``record --json``, for Foxglove) as the bus carries it, so that report
    and replay read both forms; what does not decode as a Cadence message stays as it was."""
    if encoding != "json":
        return encoding, data
    try:
        return "msgpack", encode(_JSON_ANY.decode(data))
    except msgspec.DecodeError:
        return encoding, data


def read(path: Path, keys: list[str] | None = None, notes: list[str] | None = None) -> Iterator[Recorded]:
    """A recording's messages in log-time order, those under ``keys`` (key expressions) only; JSON
    channels' messages come as MessagePack, as on the bus. A file without its footer (a recorder killed,
    a disk that filled) is read from the start up to its last whole chunk, and ``notes`` says so."""
    exprs = [zenoh.KeyExpr(k) for k in keys or []]

    def wanted(topic: str) -> bool:
        return not exprs or any(e.includes(zenoh.KeyExpr(topic)) for e in exprs)

    try:
        with path.open("rb") as f:
            try:
                found = list(make_reader(f).iter_messages(log_time_order=True))
            except Exception as exc:  # no footer, no index: read it as a stream, as far as it goes
                found = _as_far_as_it_goes(path, exc, notes)
    except FileNotFoundError:
        raise InputError(f"{path}: no such recording") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    for _, channel, message in found:
        if wanted(channel.topic):
            encoding, data = as_msgpack(channel.message_encoding, message.data)
            yield Recorded(channel.topic, message.log_time, data, encoding)


def _as_far_as_it_goes(path: Path, why: Exception, notes: list[str] | None) -> list[Any]:
    """The file's records in order, as far as they go: its channels and the messages of every whole
    chunk (the stream reader opens the chunks as they come; the cut ends it)."""
    channels: dict[int, Channel] = {}
    found: list[Any] = []
    with path.open("rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False, emit_chunks=False).records:
                if isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message) and record.channel_id in channels:
                    found.append((None, channels[record.channel_id], record))
        except Exception as exc:  # the cut: a record the file ends within
            if not found:
                kind = type(why).__name__
                raise InputError(f"{path}: not a readable MCAP recording ({kind}: {why})") from exc
    if notes is not None:
        notes.append(f"{path}: ends without its footer (a recorder killed, or a disk that filled): "
                     f"{len(found)} messages read up to the last whole chunk")  # fmt: skip
    found.sort(key=lambda m: m[2].log_time)
    return found


async def replay(
    bus: Bus, path: Path, speed: float, keys: list[str] | None = None, heard: set[str] | None = None
) -> int:
    """Republish a recording; ``speed`` 0 is as fast as the bus takes it. Returns the messages sent;
    ``heard`` gets each key that a subscriber matched when its first message, or the last, was sent."""
    t0_wall, t0_log, n = time.monotonic(), None, 0
    seen: set[str] = set()
    for m in read(path, keys):
        if m.encoding != "msgpack":
            raise InputError(f"{path}: a message on {m.key} ({m.encoding}) is not a Cadence message")
        if t0_log is None:
            t0_log = m.log_time
        if speed > 0:
            due = t0_wall + (m.log_time - t0_log) / 1e9 / speed
            await asyncio.sleep(max(0.0, due - time.monotonic()))
        if heard is not None and m.key not in seen:
            seen.add(m.key)
            if bus.matching(m.key):
                heard.add(m.key)
        bus.put_raw(m.key, m.data, block=True)
        n += 1
    if heard is not None:
        heard.update(k for k in seen - heard if bus.matching(k))
    return n
