"""The shared memory between the servo process and its executor (common/runtime/mailbox.py): a ring that
keeps order across its wrap and refuses what it has no room for, and a latest-wins block whose reader
never sees half a write."""

from __future__ import annotations

import hashlib
import mmap
import multiprocessing
import os
import random

import numpy as np

from common.runtime.mailbox import RING_HEADER, Latest, Ring


def test_a_ring_keeps_the_order_across_its_wrap_and_refuses_what_does_not_fit() -> None:
    ring = Ring(memoryview(bytearray(RING_HEADER + 200)))
    got = []
    for i in range(100):  # each about 40 bytes: the ring wraps many times
        assert ring.put(("offer", i, np.full(2, float(i))))
        m = ring.get()
        got.append((m[1], float(m[2][0])))
        assert ring.get() is None
    assert got == [(i, float(i)) for i in range(100)]
    assert ring.put(b"x" * 100)
    assert not ring.put(b"y" * 100)  # no room: refused, nothing written
    assert ring.get() == b"x" * 100
    assert ring.get() is None
    assert ring.put(b"y" * 100)  # room again


def _writer(fd: int, n: int) -> None:
    block = Latest(memoryview(mmap.mmap(fd, Latest.nbytes(64, 16))), 64, 16)
    for i in range(n):
        block.view[:] = i
        block.write(str(i).encode())


def test_a_reader_of_the_latest_block_sees_one_whole_write_while_another_process_writes() -> None:
    fd = os.memfd_create("test-latest")
    os.ftruncate(fd, Latest.nbytes(64, 16))
    block = Latest(memoryview(mmap.mmap(fd, Latest.nbytes(64, 16))), 64, 16)
    writer = multiprocessing.get_context("fork").Process(target=_writer, args=(fd, 200_000))
    writer.start()
    reads = torn = 0
    while writer.is_alive() or reads == 0:
        got = block.read()
        if got is None:
            continue
        values, text = got
        reads += 1
        torn += int(values.min() != values.max() or (text != "" and float(text) != values[0]))
    writer.join()
    assert writer.exitcode == 0
    assert reads > 0
    assert torn == 0
    values, text = block.read() or (None, "")
    assert values is not None and values[0] == 199_999 and text == "199999"


def _consumer(fd: int, n: int, size: int) -> None:
    ring = Ring(memoryview(mmap.mmap(fd, size)))
    for i in range(n):
        while (m := ring.get()) is None:
            pass
        got, data, digest = m
        if got != i or hashlib.blake2b(data).digest() != digest:
            raise SystemExit(f"message {i}: got {got}, its bytes {'whole' if digest else 'damaged'}")


def test_a_full_ring_between_two_processes_never_overwrites_what_its_reader_has_not_read() -> None:
    # the producer finds the ring full again and again, so each of its free-room checks reads the tail
    # while the consumer moves it: half a tail read once overwrote unread messages (an EOFError in the servo)
    n, size = 200_000, RING_HEADER + (1 << 16)
    fd = os.memfd_create("test-ring")
    os.ftruncate(fd, size)
    ring = Ring(memoryview(mmap.mmap(fd, size)))
    consumer = multiprocessing.get_context("fork").Process(target=_consumer, args=(fd, n, size))
    consumer.start()
    rng = random.Random(7)
    for i in range(n):
        data = rng.randbytes(rng.randrange(0, 3000))
        m, tries = (i, data, hashlib.blake2b(data).digest()), 0
        while not ring.put(m):  # a tight loop on the tail, as the servo's executor never is, to find a tear
            tries += 1
            if tries % 10_000 == 0 and not consumer.is_alive():
                break
    consumer.join()
    assert consumer.exitcode == 0
