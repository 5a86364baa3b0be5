"""A flood of separation readings as fast as one process can put them (issue 74: 200–316k a second made a
near person forgotten), run as its own process (``python -m tests.support.flood ENDPOINT KEY SOURCE
SECONDS AGE``) so that its puts take no turn from the test's own tracker. Each reading says a person far
off, ``AGE`` s old when stamped (a flood that saturates its receiver reaches it that old whatever it says;
saying so makes it arrive stale on any host); the stamp is renewed every ``RESTAMP`` readings (encoding
each one would halve the rate).
Its last line is JSON: how many it put, and its first and last put on the wall clock (s)."""

from __future__ import annotations

import json
import sys
import time

import zenoh

from common.runtime.bus import BusConfig, zenoh_config
from schemas import Separation
from schemas.topology import encode

RESTAMP = 256


def main(endpoint: str, key: str, source: str, seconds: float, age_s: float) -> None:
    session = zenoh.open(zenoh_config(BusConfig(mode="client", connect=[endpoint])))
    pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
    n, start = 0, time.time()
    end = start + seconds
    while time.time() < end:
        sep = Separation(
            t_ns=time.time_ns(), seq=n, distance_m=100.0, source=source, to_robot=True, age_s=age_s
        )
        payload = encode(sep)
        for _ in range(RESTAMP):
            pub.put(payload)
        n += RESTAMP
    last = time.time()
    pub.undeclare()
    session.close()
    print(
        json.dumps({"readings": n, "start": start, "end": last, "per_s": round(n / (last - start))}),
        flush=True,
    )


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]), float(sys.argv[5]))
