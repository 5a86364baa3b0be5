"""`cadence top`: the cell's graph, live, in a terminal (what `ros2 topic hz` and `rqt_graph` give a ROS
user): every key that carries traffic with its message type, its publishers and readers from the graph,
its rate, the age of its last message and what did not decode; every service with its state, its age
(a status older than three periods: gone), and the messages it dropped or failed to handle; and the
operator as the cell reads them: the last window's mean RR and movement beside the k decided on it."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import msgspec
from rich.console import Group
from rich.table import Table

from schemas import HrvWindow, Selection, ServiceStatus
from schemas.topology import HEALTH, cell_roster, decode_any, topic_of
from schemas.topology import key as key_of

RATE_WINDOW_S = 10.0


@dataclass
class KeyStats:
    arrivals: deque[float] = field(default_factory=deque)  # monotonic times within the rate window
    count: int = 0
    undecodable: int = 0
    last: float = 0.0
    type_name: str = "?"

    def rate_hz(self, now: float) -> float:
        while self.arrivals and self.arrivals[0] < now - RATE_WINDOW_S:
            self.arrivals.popleft()
        if len(self.arrivals) < 2:
            return 0.0
        return len(self.arrivals) / max(now - self.arrivals[0], 1.0)


@dataclass
class Top:
    cell: str
    keys: dict[str, KeyStats] = field(default_factory=dict)
    statuses: dict[str, tuple[float, ServiceStatus]] = field(default_factory=dict)
    window: HrvWindow | None = None
    selection: Selection | None = None

    def on(self, key: str, payload: bytes, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        k = self.keys.setdefault(key, KeyStats())
        k.count += 1
        k.last = now
        k.arrivals.append(now)
        try:
            msg = decode_any(payload)
        except msgspec.DecodeError:
            k.undecodable += 1
            return
        k.type_name = type(msg).__struct_config__.tag  # type: ignore[assignment]
        if isinstance(msg, ServiceStatus):
            self.statuses[msg.service] = (now, msg)
        elif isinstance(msg, HrvWindow):
            self.window = msg
        elif isinstance(msg, Selection):
            self.selection = msg

    def operator(self) -> Table:
        t = Table(title="the operator (last window) and the decision")
        for col in ("mean RR", "quality", "movement", "seconds moving", "k", "why"):
            t.add_column(col, justify="right")
        w, sel = self.window, self.selection
        rr = f"{w.mean_rr_s:.3f} s" if w is not None and w.mean_rr_s is not None else "—"
        if w is None:
            moved = "—"
        elif w.movement_mg is None:
            moved = "no accelerometer"
        else:
            moved = f"{w.movement_mg:.0f} mg"
        share = f"{w.moving_fraction:.0%}" if w is not None and w.moving_fraction is not None else "—"
        k = f"{sel.k} of {sel.n}" if sel is not None else "—"
        t.add_row(rr, w.quality if w else "—", moved, share, k, sel.reason if sel else "—")
        return t

    def view(self, status_period_s: float = 5.0, now: float | None = None) -> Group:
        now = time.monotonic() if now is None else now
        keys = Table(title=f"cadence top — cell {self.cell}: keys (rates over the last {RATE_WINDOW_S:g} s)")
        prefix = key_of(self.cell, "")
        # the key whole, however narrow the terminal (at 80 columns two keys read "operator/s…"): the
        # other columns fold instead
        longest = max((len(k.removeprefix(prefix)) for k in self.keys), default=3)
        keys.add_column("key", no_wrap=True, min_width=longest)
        for col in ("type", "publishers → readers"):
            keys.add_column(col, overflow="fold")
        for col in ("rate [Hz]", "last [s ago]", "messages", "bad"):
            keys.add_column(col, justify="right")
        for key in sorted(self.keys):
            k = self.keys[key]
            topic = topic_of(key)
            flow = "?"
            if topic is not None:
                # a family's member has its own publisher (health/<service>: that service)
                pubs = [key.rsplit("/", 1)[-1]] if topic.suffix == HEALTH.suffix else topic.publishers
                flow = f"{', '.join(pubs)} → {', '.join(topic.subscribers) or '(tools)'}"
            keys.add_row(
                key.removeprefix(prefix),
                k.type_name,
                flow,
                f"{k.rate_hz(now):.1f}",
                f"{now - k.last:.1f}",
                str(k.count),
                f"[red]{k.undecodable}[/red]" if k.undecodable else "0",
            )
        services = Table(title="services (health/<service>)")
        for col in ("service", "alive", "state", "uptime [s]", "dropped", "handler errors", "detail"):
            services.add_column(col)
        for name in cell_roster(self.statuses):
            seen = self.statuses.get(name)
            if seen is None:
                services.add_row(name, "[red]no status[/red]", "", "", "", "", "")
                continue
            at, st = seen
            age = now - at
            dropped = sum(v for c, v in st.counters.items() if c.startswith(("decode_errors", "rejected/")))
            failed = sum(v for c, v in st.counters.items() if c.startswith("handler_errors/"))
            alive = age < 3 * status_period_s
            services.add_row(
                name,
                f"[green]yes[/green] ({age:.0f} s)" if alive else f"[red]gone {age:.0f} s[/red]",
                st.state,
                f"{st.uptime_s:.0f}",
                str(dropped),
                str(failed),
                st.detail[:60],
            )
        if self.window is None and self.selection is None:
            return Group(keys, services)
        return Group(keys, self.operator(), services)
