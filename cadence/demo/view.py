"""What the terminal shows while a demo runs, and how it takes a Ctrl-C."""

from __future__ import annotations

import asyncio
import math
import signal

from rich.console import Console, Group
from rich.table import Table

from cadence.demo.observe import Observed
from cadence.demo.options import DemoOptions
from cadence.demo.supervise import Supervised


def live_view(obs: Observed, opts: DemoOptions, now_s: float, procs: dict[str, Supervised]) -> Group:
    shown = min(now_s, opts.duration_s)  # the run ends at its duration, whatever a late message says
    pace = (f"at {opts.speed:g}×" if opts.processes else f"lockstep, at most {opts.speed:g}×"
            if math.isfinite(opts.speed) else "lockstep, as fast as the host allows")  # fmt: skip
    t = Table(title=f"cadence demo — data time {shown:6.0f} / {opts.duration_s:.0f} s {pace}")
    for col in ("mean RR (last window)", "movement", "k", "cycles", "last cycle", "errors", "restarts"):
        t.add_column(col, justify="right")
    w = obs.windows[-1] if obs.windows else None
    rr = f"{w['mean_rr_s']:.3f} s ({w['quality']})" if w and w["mean_rr_s"] else "—"
    moved = f"{w['movement_mg']:.0f} mg" if w and w.get("movement_mg") is not None else "—"
    k = str(obs.selections[-1]["k"]) if obs.selections else "—"
    last = f"{obs.cycles[-1].cycle_time_s:.1f} s" if obs.cycles else "—"
    restarts = ", ".join(f"{n} {p.restarts}" for n, p in procs.items() if p.restarts) or "none"
    t.add_row(rr, moved, k, str(obs.n_cycles), last, str(obs.errors), restarts)
    ev = Table(show_header=False, box=None)
    for e in obs.events[-5:]:
        ev.add_row(f"{e['t_s']:7.1f} s", e["source"], e["kind"], e["message"][:90])
    stops = sum(e["kind"] == "protective_stop" for e in obs.events)
    if stops:  # what a person sees first and should not misread as the method's doing
        t.caption = (
            f"{stops} protective stop(s): the servo loop missed its deadlines, as a busy machine "
            f"does at {opts.speed:g}× (try a lower --speed); the demo resumes by itself, a real cell does not"
        )
    return Group(t, ev)


def taking_the_interrupt(console: Console) -> None:
    """The first Ctrl-C (or SIGTERM), caught: the task goes on to stop the cell and write what ran (its
    cancellation taken back, so the waits that follow keep their own timeouts), and a second one says so
    rather than cutting the summary and the report off half-written."""
    if (me := asyncio.current_task()) is not None:
        me.uncancel()

    def again(*_: object) -> None:
        console.print("already stopping: the summary and the report follow", style="yellow")

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, again)
