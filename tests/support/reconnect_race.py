"""A servo thread calling servoJ without pause while the main thread reconnects, again and again, through
the real client: run as its own process (``python -m tests.support.reconnect_race HOST N``), so that a
crash of the client is the process's exit status, not the end of the test runner."""

from __future__ import annotations

import sys
import threading

from services.executor.backends import UrRtdeBackend
from tests.support.emulator import WATCHDOG_HZ


def main(host: str, reconnects: int) -> None:
    b = UrRtdeBackend(host, watchdog_hz=WATCHDOG_HZ)
    b.connect()
    target = b.target(b.actual_q())  # holding where it stands: servoJ to its own position
    done = threading.Event()
    calls = refused = 0

    def servo() -> None:
        nonlocal calls, refused
        while not done.is_set():
            calls += 1
            refused += not b.servo(target)
            done.wait(0.0005)

    thread = threading.Thread(target=servo, daemon=True)
    thread.start()
    for _ in range(reconnects):
        b.reconnect()
        done.wait(0.05)
    done.set()
    thread.join()
    b.close()
    print(f"{reconnects} reconnects, {calls} servo calls, {refused} refused", flush=True)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]))
