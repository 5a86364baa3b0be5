"""`cadence record` and `cadence replay`: bus traffic to and from MCAP files (DESIGN §1, §3, §11).

A recording keeps every payload as it travelled (MessagePack), one channel per key, with the message
type's JSON schema attached (msgspec's), so the file opens in MCAP tools; ``json=True`` writes JSON
channels instead, which Foxglove's viewer can decode, and which report and replay read as well. Log
time is the wall clock at arrival, publish time the message's own data time. A replay republishes the
payloads unchanged (so with their original data time) on their keys, paced by the recorded log times
divided by ``speed``; services on data time then give exactly what they gave live.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import msgspec
import zenoh
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from common.runtime.bus import Bus
from common.runtime.errors import InputError
from schemas.topology import AnyMessage, decode_any, encode, topic_of

PROFILE = "cadence"


@dataclass
class Recorder:
    """Writes samples as they arrive; ``close`` finishes the file (its summary and index)."""

    path: Path
    json: bool = False

    def __post_init__(self) -> None:
        self._file = self.path.open("wb")
        self._writer = Writer(self._file, chunk_size=256 * 1024, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="cadence")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self.count = 0
        self.undecodable = 0
        self.closed = False

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
            self._writer.add_metadata(name, data)

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
        self._writer.add_message(
            self._channel(key),
            log_time=time.time_ns() if log_time_ns is None else log_time_ns,
            data=data,
            publish_time=msg.t_ns if msg is not None else 0,
            sequence=seq,
        )
        self.count += 1

    def close(self) -> None:
        self.closed = True
        self._writer.finish()
        self._file.close()


async def record(
    bus: Bus,
    path: Path,
    keys: list[str],
    stop: asyncio.Event,
    json: bool = False,
    on_first: Callable[[str], None] | None = None,
) -> Recorder:
    """Record until ``stop``; the file is complete even when the stop is a signal. ``on_first(key)`` is
    called once, when the first message is written (a person wants to know that anything comes)."""
    rec = Recorder(path, json)

    def write(key: str, payload: bytes) -> None:
        rec.write(key, payload)
        if on_first is not None and rec.count == 1:
            on_first(key)

    subs = [bus.subscribe_raw(k, write) for k in keys]
    try:
        await stop.wait()
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


def read(path: Path, keys: list[str] | None = None) -> Iterator[Recorded]:
    """A recording's messages in log-time order, those under ``keys`` (key expressions) only; JSON
    channels' messages come as MessagePack, as on the bus."""
    exprs = [zenoh.KeyExpr(k) for k in keys or []]
    try:
        with path.open("rb") as f:
            for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
                if exprs and not any(e.includes(zenoh.KeyExpr(channel.topic)) for e in exprs):
                    continue
                encoding, data = as_msgpack(channel.message_encoding, message.data)
                yield Recorded(channel.topic, message.log_time, data, encoding)
    except FileNotFoundError:
        raise InputError(f"{path}: no such recording") from None
    except Exception as exc:  # the mcap package raises many kinds on a damaged file
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path}: not a readable MCAP recording ({type(exc).__name__}: {exc})") from None


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
