"""`cadence report`: figures and an index.html from a recording (MCAP) or a demo folder (paper §III-C, §IV).

Both sources become one ``Run``: the windows, the selections, the cycles (time, k per path), the
operator's errors and the robot's events, on data time from the run's first message. The production
rate φ is cycles per minute and the error rate ε errors per cycle, as in the paper.
"""

from __future__ import annotations

import html
import json
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np

from cadence.lab.marks import counted
from common.runtime.errors import InputError
from common.runtime.storage import write_readable
from common.safety.states import idle_spans, routine_change
from schemas import (
    CycleReport,
    EcgChunk,
    HrvWindow,
    OperatorError,
    ParetoSet,
    RobotEvent,
    RobotState,
    Selection,
)
from schemas.topology import decode_any
from services.registry import EXECUTOR


@dataclass
class Run:
    source: str
    duration_s: float
    windows: list[dict] = field(default_factory=list)
    selections: list[dict] = field(default_factory=list)
    cycles: list[dict] = field(default_factory=list)  # {"end_s", "cycle_time_s", "k": {path: k}}
    errors: int = 0
    error_times_s: list[float] = field(default_factory=list)  # when each was marked
    events: list[dict] = field(default_factory=list)
    sets: dict[str, ParetoSet] = field(default_factory=dict)
    scale: list[dict] = field(default_factory=list)  # {"t_s", "scale", "separation_m"}: scale_row
    notes: list[str] = field(default_factory=list)  # what the source lacked (a recording cut short)

    @property
    def productivity_per_min(self) -> float:
        return len(self.cycles) / (self.duration_s / 60.0) if self.duration_s > 0 else 0.0

    @property
    def error_rate(self) -> float:
        return self.errors / len(self.cycles) if self.cycles else 0.0


def load_sets(folder: Path) -> dict[str, ParetoSet]:
    """The Pareto sets an executor cached (``<data>/executor/*.msgpack``)."""
    decoder = msgspec.msgpack.Decoder(ParetoSet)
    out = {}
    for f in sorted(folder.glob("*.msgpack")):
        try:
            s = decoder.decode(f.read_bytes())
        except msgspec.DecodeError:
            continue
        out[s.path_id] = s
    return out


def from_demo(folder: Path) -> Run:
    try:
        s = json.loads((folder / "summary.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{folder}/summary.json: {exc}") from None
    cycles = [
        {"end_s": e, "cycle_time_s": t, "k": k}
        for e, t, k in zip(
            s["cycle_ends_s"],
            s["cycle_times_s"],
            s.get("cycle_k", [{}] * len(s["cycle_ends_s"])),
            strict=True,
        )
    ]
    return Run(
        source=str(folder),
        duration_s=s["duration_s"],
        windows=s["windows"],
        selections=s["selections"],
        cycles=cycles,
        errors=s["errors"],
        error_times_s=s.get("error_times_s", []),
        events=s["events"],
        sets=load_sets(folder / "data" / EXECUTOR.name),
        scale=s.get("scale", []),
    )


def window_row(w: HrvWindow, end_s: float) -> dict:
    """A window as a run keeps it (and a demo's summary.json)."""
    return {"end_s": end_s, "mean_rr_s": w.mean_rr_s, "quality": w.quality, "reason": w.reason,
            "movement_mg": w.movement_mg}  # fmt: skip


SCALE_EVERY_S = 0.25  # the scale trace keeps a robot state this often (robot/state comes at 50 Hz)


def scale_row(rows: list[dict], state: RobotState, t_s: float) -> None:
    """Keep ``state``'s time scale and separation in ``rows`` if the last kept is ``SCALE_EVERY_S`` old,
    or the scale changed from it by a tenth (a hold is never missed)."""
    last = rows[-1] if rows else None
    if last is None or t_s - last["t_s"] >= SCALE_EVERY_S or abs(state.scale - last["scale"]) >= 0.1:
        rows.append({"t_s": t_s, "scale": round(state.scale, 3), "separation_m": state.separation_m})


def event_row(t_s: float, source: str, kind: str, message: str,
              change: tuple[str | None, str | None] = (None, None)) -> dict:  # fmt: skip
    """An event as a run keeps it; ``change``: a state change's (from, to)."""
    return {
        "t_s": t_s,
        "source": source,
        "kind": kind,
        "message": message,
        "from": change[0],
        "to": change[1],
    }


def from_mcap(path: Path, sets_folder: Path | None = None) -> Run:
    from cadence.tools.recording import read

    msgs, notes = [], list[str]()
    for rec in read(path, notes=notes):
        if rec.encoding != "msgpack":
            continue
        try:
            msgs.append(decode_any(rec.data))
        except msgspec.DecodeError:
            continue
    # the run's data time: what the cell did while it was recorded (not plan times, not health's wall
    # clock, and not a selection's stamp: a republished one carries the time it was decided, which on a
    # recording joined mid-run is long before it began: φ once came over 500 s of a 240 s recording)
    run_types = (HrvWindow, CycleReport, OperatorError, RobotEvent, EcgChunk, RobotState)
    data_times = [m.t_ns for m in msgs if isinstance(m, run_types) and m.t_ns > 0]
    data_times += [m.start_ns for m in msgs if isinstance(m, HrvWindow)]
    if not data_times:  # selections alone: their stamps are all there is
        data_times = [m.t_ns for m in msgs if isinstance(m, Selection) and m.t_ns > 0]
    if not data_times:
        raise InputError(f"{path}: no Cadence messages in this recording")
    t0 = min(data_times)

    def t(ns: int) -> float:
        return round((ns - t0) / 1e9, 3)

    run = Run(str(path), (max(data_times) - t0) / 1e9, notes=notes)
    marked: list[OperatorError] = []
    for m in msgs:
        if isinstance(m, HrvWindow):
            run.windows.append(window_row(m, t(m.end_ns)))
        elif isinstance(m, Selection):
            last = run.selections[-1] if run.selections else None
            if last is None or (last["k"], last.get("window_end_ns")) != (m.k, m.window_end_ns):
                run.selections.append(
                    {
                        "t_s": max(0.0, t(m.t_ns)),
                        "k": m.k,
                        "delta": m.delta,
                        "reason": m.reason,
                        "window_end_ns": m.window_end_ns,
                        **thresholds(m),
                    }
                )
        elif isinstance(m, CycleReport):
            run.cycles.append({"end_s": t(m.t_ns), "cycle_time_s": m.cycle_time_s, "k": dict(m.k_per_path)})
        elif isinstance(m, OperatorError):
            marked.append(m)
        elif isinstance(m, RobotEvent) and not (
            m.kind == "state" and routine_change(m.from_state, m.to_state)
        ):
            run.events.append(
                event_row(t(m.t_ns), EXECUTOR.name, m.kind, m.message, (m.from_state, m.to_state))
            )
        elif isinstance(m, ParetoSet):
            run.sets[m.path_id] = m
        elif isinstance(m, RobotState):
            scale_row(run.scale, m, t(m.t_ns))
    kept = counted(marked)
    run.errors, run.error_times_s = len(kept), [t(e.t_ns) for e in kept]
    if sets_folder is not None:
        run.sets.update(load_sets(sets_folder))
    return run


def movement_row(run: Run) -> str:
    mg = [w["movement_mg"] for w in run.windows if w.get("movement_mg") is not None]
    if not mg:
        return "no accelerometer: every window read as mental load"
    held = sum(s["reason"] == "movement" for s in run.selections)
    return (f"median {np.median(mg):.0f} mg, max {max(mg):.0f} mg; {held} window{'s' * (held != 1)} held "
            "for movement")  # fmt: skip


def monitored(rows: list[dict]) -> bool:
    """Whether the run had speed and separation monitoring: a distance in its scale trace."""
    return any(r["separation_m"] is not None for r in rows)


def scale_summary(rows: list[dict]) -> str:
    if not monitored(rows):
        return "no separation monitoring: as planned throughout"
    t = np.array([r["t_s"] for r in rows])
    sc = np.array([r["scale"] for r in rows])
    dt = np.diff(t, append=t[-1])
    held, slowed = float(dt[sc <= 0.0].sum()), float(dt[(sc > 0.0) & (sc < 1.0)].sum())
    mean = np.average(sc, weights=dt) if dt.sum() > 0 else sc.mean()
    return f"mean {mean:.2f}; slowed {slowed:.0f} s, held {held:.0f} s"


CAPTIONS = {
    "rr_k.png": "Each window's mean RR (red; crosses: held windows) against data time, with RR_r and the "
    "decision thresholds RR_s and RR_s^max; the selected k on the right axis (blue); cycle ends as ticks "
    "along the bottom, the operator's errors as orange ticks along the top; shaded grey, the spans in which "
    "the robot was stopped or waiting (a k chosen there moved nothing). Like the paper's Fig. 6. With the "
    "strap's accelerometer, each window's movement below (green), and shaded green above the windows the "
    "decision held because the operator moved well above their level at work.",
    "pareto.png": "Each path's Pareto front, normalised (grey), its N chosen solutions (blue) and the k the "
    "robot ran with, circled by how often (red).",
    "separation.png": "The nearest person's distance to the robot (operator/separation, as the executor "
    "last had it) and the time scale the robot ran at (1: as planned; 0: holding on its path), from speed "
    "and separation monitoring (ISO/TS 15066).",
    "cycles.png": "Joint positions, velocities, accelerations and jerk of the first and last cycle as "
    "commanded (the planned trajectories, not the arm's measurement), in radians, path after path; "
    "dashed: the UR16e's limits.",
}


def thresholds(s: Selection) -> dict[str, float]:
    """The thresholds a selection was decided against (RR_r, RR_s, RR_s^max), those it carries."""
    got = {"rr_rest_s": s.rr_rest_s, "rr_stress_s": s.rr_stress_s, "rr_stress_max_s": s.rr_stress_max_s}
    return {k: v for k, v in got.items() if v is not None}


def in_force(selections: list[dict]) -> dict[str, float]:
    """The thresholds of the last selection that carries RR_r: what the run was last decided against."""
    return next((x for x in reversed(selections) if "rr_rest_s" in x), {})


def write_report(run: Run, out: Path, rr_rest_s: float | None = None) -> list[str]:
    """The figures and index.html; returns the names of the files written. RR_r: ``rr_rest_s``, else the
    one the recorded selections were decided against, else a stand-in that the figure names as such."""
    from cadence.lab.plots import cycle_kinematics_figure, front_usage_figure, rr_k_figure, separation_figure

    out.mkdir(parents=True, exist_ok=True)
    written = []
    good = [w["mean_rr_s"] for w in run.windows if w["mean_rr_s"] is not None and w["quality"] == "good"]
    lines = in_force(run.selections)
    if rr_rest_s is not None:
        rest, label, lines = rr_rest_s, "RR_r (the subject's calibration)", {}
    elif lines:
        rest, label = lines["rr_rest_s"], "RR_r in force (the recorded selections')"
    else:  # no calibration given or recorded: a stand-in, and the figure says so rather than call it rest
        rest = float(np.max(good)) if good else 0.85
        label = "no RR_r given (--rr-rest): the highest good window's, in its place"
    ends = [c["end_s"] for c in run.cycles]
    idle = idle_spans(run.events, run.duration_s)
    figure = rr_k_figure(run.windows, run.selections, rest, label, ends, run.error_times_s, idle,
                         lines.get("rr_stress_s"), lines.get("rr_stress_max_s"))  # fmt: skip
    write_readable(out / "rr_k.png", figure)
    written.append("rr_k.png")
    if run.sets:
        used: dict[str, dict[int, int]] = {}
        for c in run.cycles:
            for pid, k in c["k"].items():
                used.setdefault(pid, {}).setdefault(k, 0)
                used[pid][k] += 1
        write_readable(out / "pareto.png", front_usage_figure(run.sets, used))
        written.append("pareto.png")
        with_k = [
            {**c, "label": f"cycle {i + 1}"}
            for i, c in enumerate(run.cycles)
            if c["k"] and all(p in run.sets for p in c["k"])
        ]
        if with_k:
            pick = [with_k[0], with_k[-1]] if len(with_k) > 1 else with_k[:1]
            write_readable(out / "cycles.png", cycle_kinematics_figure(run.sets, pick))
            written.append("cycles.png")
    if monitored(run.scale):
        write_readable(out / "separation.png", separation_figure(run.scale, idle))
        written.append("separation.png")
    write_readable(out / "index.html", _html(run, written).encode())
    written.append("index.html")
    return written


def _html(run: Run, figures: list[str]) -> str:
    times = [c["cycle_time_s"] for c in run.cycles]
    rows = [
        ("source", html.escape(run.source)),
        ("duration (data time)", f"{run.duration_s:.0f} s"),
        ("cycles", str(len(run.cycles))),
        ("φ, production rate", f"{run.productivity_per_min:.2f} cycles/min"),
        ("errors", str(run.errors)),
        ("ε, error rate", f"{run.error_rate:.3f} errors/cycle"),
        (
            "cycle time γ",
            f"mean {np.mean(times):.2f} s, min {min(times):.2f} s, max {max(times):.2f} s" if times else "—",
        ),
        ("windows", f"{len(run.windows)} ({sum(w['quality'] == 'good' for w in run.windows)} good)"),
        ("movement", movement_row(run)),
        ("selections", " → ".join(str(s["k"]) for s in run.selections) or "—"),
        ("time scale", scale_summary(run.scale)),
        *(("note", html.escape(n)) for n in run.notes),
    ]
    table = "\n".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    cycle_rows = "\n".join(
        f"<tr><td>{i + 1}</td><td>{c['end_s']:.1f}</td><td>{c['cycle_time_s']:.2f}</td>"
        f"<td>{html.escape(', '.join(f'{p} {k}' for p, k in c['k'].items()))}</td></tr>"
        for i, c in enumerate(run.cycles)
    )
    event_rows = "\n".join(
        f"<tr><td>{e['t_s']:.1f}</td><td>{html.escape(e['source'])}</td><td>{html.escape(e['kind'])}</td>"
        f"<td>{html.escape(e['message'])}</td></tr>"
        for e in run.events
    )
    imgs = "\n".join(
        f'<figure><img src="{f}" alt="{f}"><figcaption>{html.escape(CAPTIONS.get(f, f))}</figcaption>'
        "</figure>"
        for f in figures
        if f.endswith(".png")
    )
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Cadence report</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}} img{{max-width:100%}}
table{{border-collapse:collapse;margin:1em 0}} figcaption{{color:#444;font-size:90%}}
td,th{{border:1px solid #ccc;padding:4px 8px;text-align:left}}</style>
</head><body>
<h1>Cadence report</h1>
<table>{table}</table>
{imgs}
<h2>Cycles</h2>
<table><tr><th>#</th><th>end [s]</th><th>γ [s]</th><th>k per path</th></tr>{cycle_rows}</table>
<h2>Events</h2>
<table><tr><th>t [s]</th><th>source</th><th>kind</th><th>message</th></tr>{event_rows}</table>
</body></html>
"""
