"""The plant monitor of `cadence bench plant`: `cadence plant`'s view of every cell, in a process of its own
at the plant's priority, as `cadence plant` runs (`python -m cadence.bench.plant_monitor SPEC.json`; the
bench starts one for each phase the plant reads in). It redraws the view as `cadence plant` does and
notes how far behind it ever was, each message's way from its cell, and which windows came.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import sys
import time
from pathlib import Path

import msgspec
from rich.console import Console

REFRESH_S = 0.5  # `cadence plant`'s redraw


class MonitorSpec(msgspec.Struct, frozen=True):
    config: str  # the plant monitor's account (a client of the plant's router)
    phase_end_ns: int  # monotonic: the end of the phase it watches (the cells may stop putting there)
    until_ns: int  # monotonic: when it stops (after the phase: what was put in it is still on its way)
    out: str  # where its result goes (JSON)


class MonitorResult(msgspec.Struct):
    transit: list[tuple[int, int]]  # (t_ns of a message, ns from its stamp to the monitor)
    windows: list[tuple[str, int]]  # (cell, t_ns) of each window it got
    behind_s: float  # the stalest cell's arm state at any redraw
    cells_seen: int


async def watch(spec: MonitorSpec) -> MonitorResult:
    from cadence.tools.plant import Plant, plant_watch
    from common.runtime.bus import Bus, BusConfig
    from schemas.topology import decode_any

    plant = Plant()
    transit: list[tuple[int, int]] = []
    windows: list[tuple[str, int]] = []
    behind = 0.0
    async with await Bus.open(BusConfig(config_file=spec.config), "plant") as bus:

        def came(key: str, payload: bytes) -> None:
            now = time.monotonic_ns()
            plant.on(key, payload, now / 1e9)
            with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
                msg = decode_any(payload)
                transit.append((msg.t_ns, now - msg.t_ns))
                if key.endswith("/hrv/window"):
                    windows.append((key.split("/")[1], msg.t_ns))

        for key in plant_watch():
            bus.subscribe_raw(key, came)
        print("ready", flush=True)
        while time.monotonic_ns() < spec.until_ns:
            await asyncio.sleep(REFRESH_S)
            now = time.monotonic()
            Console(file=io.StringIO(), width=200).print(plant.view(now=now))
            if now * 1e9 < spec.phase_end_ns:  # after it, the last round's cells have stopped
                ages = [now - c.robot[0] for c in plant.cells.values() if c.robot is not None]
                behind = max([behind, *ages])
    return MonitorResult(transit, windows, behind, len(plant.cells))


def main(spec_path: str) -> None:
    from cadence.tools.plant import yield_to_cells

    yield_to_cells()  # as `cadence plant` does, before any thread starts (threads keep their own)
    spec = msgspec.json.decode(Path(spec_path).read_bytes(), type=MonitorSpec)
    Path(spec.out).write_bytes(msgspec.json.encode(asyncio.run(watch(spec))))


if __name__ == "__main__":
    main(sys.argv[1])
