"""The load of `cadence bench executor --load` that the executor must decode: about 5,000 operator signals
every 50 ms, each stamped an hour ago, so that the executor decodes every one on arrival and refuses it
(its admission window), and none holds or moves the arm. Run as its own process
(``python -m cadence.bench.signal_flood ENDPOINT KEY SECONDS``); its last line is JSON: how many it put.
"""

from __future__ import annotations

import json
import sys
import time

import zenoh

from common.runtime.bus import BusConfig, zenoh_config
from schemas import OperatorSignal
from schemas.topology import encode

BURST, EVERY_S = 5000, 0.05
HOUR_NS = 3600 * 10**9


def main(endpoint: str, key: str, seconds: float) -> None:
    session = zenoh.open(zenoh_config(BusConfig(mode="client", connect=[endpoint])))
    pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
    n, start = 0, time.monotonic()
    due = start
    while (now := time.monotonic()) < start + seconds:
        if now < due:
            time.sleep(due - now)
        payload = encode(OperatorSignal(t_ns=time.time_ns() - HOUR_NS, seq=n, name="part", source="bench"))
        for _ in range(BURST):
            pub.put(payload)
        n += BURST
        due += EVERY_S
    took = time.monotonic() - start
    pub.undeclare()
    session.close()
    print(json.dumps({"signals": n, "per_s": round(n / took)}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], float(sys.argv[3]))
