"""ur_emulator: a UR e-Series controller on the wire, for the real ur-rtde client without a robot
(tests, and trying the executor's ur_rtde backend): ``cadence run ur_emulator --host 127.0.0.2``.

It prints ``ready <host>`` once its three ports listen, and, with ``--verbose``, what the client asked.
SIGUSR1 is a bump against the arm: a protective stop, as the real arm's force limit gives, which only the
dashboard's ``unlock protective stop`` clears (and not within 5 s of it). A line ``di N 1`` (``0``) on its
standard input sets (clears) standard digital input N, as a button wired to the controller would: what the
executor reads as an operator's signal (a task step's ``input = N``). A line ``estop`` presses and releases
the emergency stop: the program ends, the RTDE clients are dropped and none is taken for ``--restart-s``;
a line ``restarted`` ends that wait now (a test that must see the refusal sets a long one and ends it when
it has: the controller's restart then does not race the host's load).
An RTDE client that stops reading for ``--stall-s`` (10 s, as a real controller) is dropped.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

import numpy as np

from services.ur_emulator.controller import Controller
from services.ur_emulator.server import Emulator


def read_inputs(controller: Controller, emulator: Emulator) -> None:
    """``di N 0|1`` lines from standard input: the buttons on the controller's digital inputs; ``estop``,
    ``restarted``."""
    for line in sys.stdin:
        parts = line.split()
        if parts == ["estop"]:
            emulator.emergency_stop()
            print("emergency stop: RTDE restarting", flush=True)
            continue
        if parts == ["restarted"]:
            emulator.refuse_until = 0.0
            print("RTDE restarted", flush=True)
            continue
        if len(parts) == 3 and parts[0] == "di" and parts[1].isdecimal() and parts[2] in ("0", "1"):
            n = int(parts[1])
            if n <= 7:
                with controller.lock:
                    bits = controller.digital_in & ~(1 << n)
                    controller.digital_in = bits | (int(parts[2]) << n)
                print(f"digital input {n} {'on' if parts[2] == '1' else 'off'}", flush=True)
                continue
        print(f"ignored {line.strip()!r}: expected 'di N 0|1' with N 0–7, 'estop' or 'restarted'", flush=True)


def run(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="cadence run ur_emulator",
        description="Emulate a UR16e controller (RTDE 30004, dashboard 29999, script 30003) on HOST.",
    )
    parser.add_argument(
        "--host", default="127.0.0.2", help="loopback address to listen on (default 127.0.0.2)"
    )
    parser.add_argument(
        "--q0-deg",
        type=float,
        nargs=6,
        default=[0.0, -90.0, 90.0, -90.0, -90.0, 0.0],
        help="the arm's start pose",
    )
    parser.add_argument("--verbose", action="store_true", help="log the recipes the client asks for")
    parser.add_argument("--stall-s", type=float, default=10.0, help="drop an RTDE client not read this long")
    parser.add_argument(
        "--restart-s", type=float, default=3.0, help="RTDE takes no client this long after estop"
    )
    parser.add_argument(
        "--recipes-out", metavar="FILE.json", help="write every recipe the clients set up (the contract test)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    controller = Controller(np.radians(args.q0_deg))
    emulator = Emulator(controller, args.host, args.recipes_out, args.stall_s, args.restart_s)
    try:
        emulator.start()
    except OSError as exc:
        print(f"cadence ur_emulator: cannot listen on {args.host}: {exc.strerror}", file=sys.stderr)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    signal.signal(signal.SIGUSR1, lambda *_: controller.bump())
    threading.Thread(target=read_inputs, args=(controller, emulator), daemon=True).start()
    print(f"ready {args.host}", flush=True)
    seen_log = recipes_logged = 0
    while not stop.wait(0.2):
        with controller.lock:
            new, seen_log = controller.log[seen_log:], len(controller.log)
        for line in new:
            print(line, flush=True)
        if args.verbose:
            for kind, names in emulator.recipes_seen[recipes_logged:]:
                logging.info("%s %s", kind, ",".join(names))
            recipes_logged = len(emulator.recipes_seen)
    emulator.stop()
    return 0


if __name__ == "__main__":
    sys.exit(run())
