"""`cadence plant`: every cell on the mesh in one table, as `cadence top` is for one (issue 58): per cell
its services (how many still send their status, and any that is not serving), the robot (its safety state
and why), the selection in force, the operator's last window, and the age of each. What it reads is
what a plant monitor may read: statuses, the arm's state (downsampled on a line's uplink), selections
and windows; never the raw ECG."""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass, field

import msgspec
from rich.table import Table

from schemas import HrvWindow, RobotState, Selection, ServiceStatus
from schemas.topology import cell_roster, decode_any

WATCHED = ("health/*", "robot/state", "decision/selection", "hrv/window")  # under cadence/*/
# how much nicer than a cell's processes the plant's run (its routers, monitor and recorder): where they
# share a host with a cell (a line's router on a cell's PC), the cell's work takes the cores first
PLANT_NICE = 10


def yield_to_cells() -> None:
    """This process takes the plant's priority (``PLANT_NICE``), or keeps a lower one it already has. On
    Linux a nice value is a thread's, and a new thread takes its maker's: each thread there now is set
    (numpy's BLAS starts some on import), and the ones started later follow."""
    nice = max(os.getpriority(os.PRIO_PROCESS, 0), PLANT_NICE)
    threads = [int(t) for t in os.listdir("/proc/self/task")] if os.path.isdir("/proc/self/task") else [0]
    for tid in threads:
        with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
            os.setpriority(os.PRIO_PROCESS, tid, nice)


def plant_watch(root: str = "cadence") -> list[str]:
    return [f"{root}/*/{suffix}" for suffix in WATCHED]


@dataclass
class CellSeen:
    """What the plant view holds of one cell: each latest message with when it came (monotonic)."""

    statuses: dict[str, tuple[float, ServiceStatus]] = field(default_factory=dict)
    robot: tuple[float, RobotState] | None = None
    selection: tuple[float, Selection] | None = None
    window: tuple[float, HrvWindow] | None = None


@dataclass
class Plant:
    cells: dict[str, CellSeen] = field(default_factory=dict)

    def on(self, key: str, payload: bytes, now: float | None = None) -> None:
        parts = key.split("/", 2)
        if len(parts) < 3:
            return
        try:
            msg = decode_any(payload)
        except msgspec.DecodeError:
            return
        now = time.monotonic() if now is None else now
        cell = self.cells.setdefault(parts[1], CellSeen())
        if isinstance(msg, ServiceStatus):
            cell.statuses[msg.service] = (now, msg)
        elif isinstance(msg, RobotState):
            cell.robot = (now, msg)
        elif isinstance(msg, Selection):
            cell.selection = (now, msg)
        elif isinstance(msg, HrvWindow):
            cell.window = (now, msg)

    def view(self, status_period_s: float = 5.0, now: float | None = None) -> Table:
        now = time.monotonic() if now is None else now
        t = Table(title=f"cadence plant — {len(self.cells)} cells (ages in seconds)")
        for col in ("cell", "services", "robot", "k", "mean RR", "ages: robot / k / window"):
            t.add_column(col, overflow="fold")
        if not self.cells:
            t.add_row("no cell seen yet", "", "", "", "", "")
        for name in sorted(self.cells):
            c = self.cells[name]
            t.add_row(name, services(c, status_period_s, now), robot(c), k(c), window(c), ages(c, now))
        return t


def services(c: CellSeen, period_s: float, now: float) -> str:
    alive = {s for s, (at, _) in c.statuses.items() if now - at < 3 * period_s}
    expected = cell_roster(alive)
    up = sum(1 for s in expected if s in alive)
    wrong = [f"{s}: {st.state}" for s, (at, st) in sorted(c.statuses.items())
             if s in alive and st.state != "serving"]  # fmt: skip
    gone = [s for s in sorted(c.statuses) if s not in alive]
    said = f"{up} of {len(expected)} up"
    if gone:
        said += f"; [red]gone: {', '.join(gone)}[/red]"
    if wrong:
        said += f"; {', '.join(wrong)}"
    return said


def robot(c: CellSeen) -> str:
    if c.robot is None:
        return "—"
    r = c.robot[1]
    return r.state if not r.reason or r.state in ("moving", "ready") else f"{r.state}: {r.reason[:40]}"


def k(c: CellSeen) -> str:
    if c.selection is None:
        return "—"
    s = c.selection[1]
    return f"{s.k} of {s.n} ({s.reason})"


def window(c: CellSeen) -> str:
    if c.window is None:
        return "—"
    w = c.window[1]
    rr = f"{w.mean_rr_s:.3f} s" if w.mean_rr_s is not None else "no beats"
    return rr if w.quality == "good" else f"{rr} ({w.quality}: {w.reason})"


def ages(c: CellSeen, now: float) -> str:
    return " / ".join(
        "—" if seen is None else f"{now - seen[0]:.1f}" for seen in (c.robot, c.selection, c.window)
    )
