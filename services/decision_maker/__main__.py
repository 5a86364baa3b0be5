"""decision_maker: each ``hrv/window`` → the paper's Alg. 1 → ``decision/selection`` (DESIGN §7, §11).

The selection is state, not an event: it is republished every ``republish_s`` and answered on query, so a
publication lost while a router was down is not lost for long. k and RR_{i-1} are written atomically to
the data folder after every window, so a restarted service goes on where it stopped; a window it has
already answered (a replay, a duplicate) is skipped. Without a calibration it publishes nothing and says
so on its status, rather than guess the subject's resting RR.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import sys
from decimal import Decimal
from pathlib import Path

import msgspec

from common.bus import QueryError, Request
from common.decision import Params, State, step
from common.service import ServiceContext, service_main
from common.storage import atomic_write
from schemas.decision import Selection
from schemas.hrv import HrvWindow
from schemas.operator import Calibration

log = logging.getLogger("cadence.decision_maker")
NAME = "decision_maker"
STATE_FILE = "decision_state.json"
CALIBRATION_FILE = "calibration.json"


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    n: int = 15
    republish_s: float = 2.0
    # For a cell without `cadence calibrate`: the subject's resting mean RR, in seconds.
    rr_rest_s: float | None = None


def params_of(cal: Calibration, n: int) -> Params:
    return Params.of(cal.rr_rest_s, n, cal.sigma_rest_s, cal.rr_stress_offset_s, cal.sigma_stress_s)


class Decider:
    """The service's state and its persistence; the rule itself is ``common.decision.step``."""

    def __init__(self, data_dir: Path, n: int) -> None:
        self.path = data_dir / STATE_FILE
        self.n = n
        self.calibration: Calibration | None = None
        self.params: Params | None = None
        self.state: State | None = None
        self.last_end_ns = -1
        self.selection: Selection | None = None
        self.seq = 0

    def calibrate(self, cal: Calibration, t_ns: int) -> bool:
        """Adopt a calibration; False when it is the one in use already (a republish)."""
        if self.calibration is not None and _same(self.calibration, cal):
            return False
        self.calibration, self.params = cal, params_of(cal, self.n)
        self.state = State.initial(self.params)
        self.last_end_ns = -1
        self.selection = self._selection(0, "initial", t_ns, None)
        return True

    def resume(self) -> bool:
        """Reload k and RR_{i-1} written by an earlier run, if they belong to this calibration."""
        try:
            doc = json.loads(self.path.read_text())
            cal = msgspec.convert(doc["calibration"], Calibration)
        except FileNotFoundError:
            return False
        except (ValueError, KeyError, msgspec.ValidationError) as exc:
            log.warning("ignoring unreadable %s: %s", self.path, exc)
            return False
        if doc.get("n") != self.n:
            return False
        self.calibration, self.params = cal, params_of(cal, self.n)
        self.state = State(int(doc["k"]), Decimal(doc["rr_prev"]))
        self.last_end_ns = int(doc["last_end_ns"])
        self.seq = int(doc["seq"])
        self.selection = self._selection(
            int(doc["delta"]), doc["reason"], int(doc["t_ns"]), doc["window_end_ns"]
        )
        return True

    def on_window(self, w: HrvWindow) -> Selection | None:
        if self.params is None or self.state is None or w.end_ns <= self.last_end_ns:
            return None
        r = step(self.params, self.state, w.mean_rr_s, good_quality=w.quality == "good")
        self.state, self.last_end_ns = r.state, w.end_ns
        self.selection = self._selection(r.delta, r.reason, w.end_ns, w.end_ns)
        return self.selection

    def _selection(self, delta: int, reason: str, t_ns: int, window_end_ns: int | None) -> Selection:
        assert self.state is not None
        self.seq += 1
        return Selection(
            t_ns=t_ns,
            seq=self.seq,
            k=self.state.k,
            n=self.n,
            delta=delta,
            reason=reason,  # type: ignore[arg-type]
            window_end_ns=window_end_ns,
        )

    def persist(self) -> None:
        assert self.state is not None and self.selection is not None and self.calibration is not None
        s = self.selection
        doc = {
            "calibration": msgspec.to_builtins(self.calibration),
            "n": self.n,
            "k": self.state.k,
            "rr_prev": str(self.state.rr_prev),
            "last_end_ns": self.last_end_ns,
            "seq": self.seq,
            "delta": s.delta,
            "reason": s.reason,
            "t_ns": s.t_ns,
            "window_end_ns": s.window_end_ns,
        }
        atomic_write(self.path, json.dumps(doc, indent=1).encode())


def _same(a: Calibration, b: Calibration) -> bool:
    fields = ("subject", "rr_rest_s", "sigma_rest_s", "rr_stress_offset_s", "sigma_stress_s")
    return all(getattr(a, f) == getattr(b, f) for f in fields)


def load_calibration(data_dir: Path, settings: Settings) -> Calibration | None:
    """The calibration `cadence calibrate` stored, else one from ``rr_rest_s`` in the config."""
    path = data_dir / CALIBRATION_FILE
    if path.exists():
        try:
            return msgspec.json.decode(path.read_bytes(), type=Calibration)
        except (msgspec.ValidationError, msgspec.DecodeError) as exc:
            log.error("ignoring %s: %s", path, exc)
    if settings.rr_rest_s is not None:
        return Calibration(t_ns=0, seq=0, subject="config", rr_rest_s=settings.rr_rest_s)
    return None


async def main(ctx: ServiceContext) -> None:
    settings: Settings = ctx.settings
    bus = ctx.bus
    data = ctx.common.data_path
    decider = Decider(data, settings.n)
    key = bus.key("decision/selection")
    cal = await asyncio.to_thread(load_calibration, data, settings)
    if await asyncio.to_thread(decider.resume):
        log.info("resumed at k = %d", decider.state.k if decider.state else -1)
        if cal is not None and not _same(cal, decider.calibration):  # type: ignore[arg-type]
            decider.calibrate(cal, 0)
    elif cal is not None:
        decider.calibrate(cal, 0)
    ctx.state = "running" if decider.params else "waiting for calibration"

    def publish() -> None:
        if decider.selection is not None:
            bus.put(key, decider.selection, block=True)

    async def on_window(_: str, w: HrvWindow) -> None:
        ctx.counters["windows"] += 1
        if decider.params is None:
            ctx.counters["windows_without_calibration"] += 1
            return
        sel = decider.on_window(w)
        if sel is None:
            ctx.counters["windows_skipped"] += 1
            return
        await asyncio.to_thread(decider.persist)  # persisted before it is announced
        publish()

    async def on_calibration(_: str, cal: Calibration) -> None:
        if decider.calibrate(cal, cal.t_ns):
            log.info("calibration for %s: RR_r = %.3f s", cal.subject, cal.rr_rest_s)
            await asyncio.to_thread(decider.persist)
            ctx.state = "running"
            publish()

    async def on_query(req: Request) -> Selection:
        if decider.selection is None:
            raise QueryError("no calibration yet: run `cadence calibrate` or set rr_rest_s")
        return decider.selection

    bus.handle(bus.key("operator/calibration"), Calibration, on_calibration)
    bus.handle(bus.key("hrv/window"), HrvWindow, on_window)
    bus.serve(key, on_query)
    while not ctx.stop.is_set():
        publish()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(ctx.stop.wait(), settings.republish_s)


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv)


if __name__ == "__main__":
    sys.exit(run())
