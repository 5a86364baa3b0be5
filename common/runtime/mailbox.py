"""Shared memory between two processes, neither of which ever waits for the other (DESIGN §8: the servo
process and its executor; ros2_control's ``RealtimeBuffer`` and the UR driver's realtime buffers are the
same idea).

``Ring``: a single-producer, single-consumer ring of messages. The producer writes a message's bytes
beyond what the consumer has read, then moves its ``head`` past them: that one aligned 8-byte store is
the commit, so the consumer never reads half a message. A full ring refuses a message (``put`` is False):
the producer learns at once, and nobody blocks.

``Latest``: a fixed block of numbers (and a short text) that one side rewrites and the other reads,
latest wins, under a sequence lock: the writer makes the count odd, writes, makes it even; a reader that
saw the count change or odd while it copied tries again. A reader waits at most for one write (a few µs).

Both lay over any writable buffer (an ``mmap`` of a ``memfd`` both processes hold). Ordering rests on the
stores reaching memory in program order (x86-64's TSO, where the cells' PCs run); each index is written by
one side only.
"""

from __future__ import annotations

import pickle
import struct
from typing import Any

import numpy as np
from numpy.typing import NDArray

_LEN = struct.Struct("<I")
RING_HEADER = 16  # head (the producer's), tail (the consumer's): bytes written and read, ever


class Ring:
    """Messages (any picklable object) from one producer to one consumer through ``buf``."""

    def __init__(self, buf: memoryview) -> None:
        self.buf = buf
        self.size = len(buf) - RING_HEADER
        if self.size <= _LEN.size:
            raise ValueError(f"a ring needs more than {RING_HEADER + _LEN.size} bytes, got {len(buf)}")
        # head and tail through numpy: one aligned 8-byte load or store each (``struct`` moves a ``Q`` a
        # byte at a time, and a reader that saw half a tail overwrote messages not yet read)
        self._ends: NDArray[np.uint64] = np.frombuffer(buf, dtype=np.uint64, count=2)
        if not self._ends.flags.aligned:
            raise ValueError("a ring's buffer must start on an 8-byte boundary")

    def _head(self) -> int:
        return int(self._ends[0])

    def _tail(self) -> int:
        return int(self._ends[1])

    def _copy_in(self, at: int, data: bytes) -> None:
        i = RING_HEADER + at % self.size
        first = min(len(data), RING_HEADER + self.size - i)
        self.buf[i : i + first] = data[:first]
        if first < len(data):
            self.buf[RING_HEADER : RING_HEADER + len(data) - first] = data[first:]

    def _copy_out(self, at: int, n: int) -> bytes:
        i = RING_HEADER + at % self.size
        first = min(n, RING_HEADER + self.size - i)
        out = bytes(self.buf[i : i + first])
        if first < n:
            out += bytes(self.buf[RING_HEADER : RING_HEADER + n - first])
        return out

    def put(self, message: object) -> bool:
        """The producer's: False, nothing written, when the ring has no room for it."""
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        head = self._head()
        if head + _LEN.size + len(data) - self._tail() > self.size:
            return False
        self._copy_in(head, _LEN.pack(len(data)))
        self._copy_in(head + _LEN.size, data)
        self._ends[0] = head + _LEN.size + len(data)  # the commit
        return True

    def get(self) -> Any:
        """The consumer's: the oldest message, or None when there is none."""
        tail = self._tail()
        if tail == self._head():
            return None
        (n,) = _LEN.unpack(self._copy_out(tail, _LEN.size))
        message = pickle.loads(self._copy_out(tail + _LEN.size, n))
        self._ends[1] = tail + _LEN.size + n
        return message

    def pending(self) -> bool:
        return self._tail() != self._head()


class Latest:
    """``n`` float64 values and a text of at most ``text_bytes`` (UTF-8), latest wins (sequence lock)."""

    def __init__(self, buf: memoryview, n: int, text_bytes: int = 0) -> None:
        need = Latest.nbytes(n, text_bytes)
        if len(buf) < need:
            raise ValueError(f"{n} values and {text_bytes} bytes of text need {need} bytes, got {len(buf)}")
        self.seq: NDArray[np.uint64] = np.frombuffer(buf, dtype=np.uint64, count=1)
        self.values: NDArray[np.float64] = np.frombuffer(buf, dtype=np.float64, count=n, offset=8)
        self._text_at, self._text_bytes = 8 + 8 * n, text_bytes
        self._buf = buf
        self.view = np.empty(n)  # the writer's draft: filled freely, published by ``write``

    @staticmethod
    def nbytes(n: int, text_bytes: int = 0) -> int:
        return 8 + 8 * n + 4 + text_bytes

    def write(self, text: bytes | None = None) -> None:
        """Publish ``view`` (and ``text`` when given: else the text stays)."""
        self.seq[0] += np.uint64(1)  # odd: being written
        self.values[:] = self.view
        if text is not None:
            text = text[: self._text_bytes]
            at = self._text_at
            _LEN.pack_into(self._buf, at, len(text))
            self._buf[at + 4 : at + 4 + len(text)] = text
        self.seq[0] += np.uint64(1)

    def read(self, tries: int = 1000) -> tuple[NDArray[np.float64], str] | None:
        """A consistent copy of the values and the text; None when every try met a write (the writer
        stopped mid-write: it died there)."""
        for _ in range(tries):
            before = int(self.seq[0])
            if before & 1:
                continue
            values = self.values.copy()
            at = self._text_at
            (n,) = _LEN.unpack_from(self._buf, at)
            raw = bytes(self._buf[at + 4 : at + 4 + min(n, self._text_bytes)])
            if int(self.seq[0]) == before:
                return values, raw.decode("utf-8", "replace")
        return None
