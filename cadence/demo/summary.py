"""A run's summary (``summary.json``, the terminal's table) and its report, in the run's folder; a folder
that cannot take them loses nothing that ran."""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from cadence.demo.observe import Observed
from cadence.demo.options import DemoOptions
from cadence.lab.report import from_demo, write_report
from common.runtime.errors import CadenceError, InputError
from common.runtime.numeric import numeric_build
from common.runtime.storage import write_readable
from common.sim.twin import TwinParams
from common.trajectory.shipped import digest_of_all
from common.trajectory.task import load_task
from schemas.pareto import ParetoSet


class NothingRan(CadenceError):
    """Interrupted before the cell's data time ran: there is nothing to summarise or report."""


def interrupted_before_data_time(opts: DemoOptions) -> NothingRan:
    return NothingRan(f"interrupted before the cell's data time ran: nothing to summarise in {opts.out}")


def summarise(
    obs: Observed,
    opts: DemoOptions,
    ran_s: float,
    cut_short: bool,
    restarts: dict[str, int],
    exit_codes: dict[str, int | None],
    sets: dict[str, ParetoSet],
    console: Console,
) -> dict[str, Any]:
    """``summary.json`` and the report (index.html and its figures) of a run, in its folder."""
    if ran_s <= 0 or (cut_short and ran_s < 1.0):  # a second of data time or less: nothing to say
        raise interrupted_before_data_time(opts)
    down, up = obs.k_steps()
    minutes = ran_s / 60.0
    cycles = obs.n_cycles
    if said := obs.gaps.said():
        console.print(said, style="yellow")
    summary = {
        "duration_s": round(ran_s, 3),
        "cut_short": cut_short,
        "speed": opts.speed if math.isfinite(opts.speed) else "max",
        "cell": "processes" if opts.processes else "lockstep",
        "cycles": cycles,
        "productivity_per_min": round(cycles / minutes, 3),
        "errors": obs.errors,
        "error_rate": round(obs.errors / cycles, 4) if cycles else 0.0,
        "error_times_s": obs.error_times_s,
        "windows": obs.windows,
        "selections": [{k: v for k, v in s.items() if k != "window_end_s"} for s in obs.selections],
        "k_steps_down": down,
        "k_steps_up": up,
        "restarts": restarts,
        "exit_codes": exit_codes,
        "cycle_times_s": [round(c.cycle_time_s, 3) for c in obs.cycles],
        "cycle_ends_s": [obs.t(c.t_ns) for c in obs.cycles],
        "cycle_k": [dict(c.k_per_path) for c in obs.cycles],
        "events": obs.events,
        "scale": obs.scale,
        # by key, messages the cell sent that the observer did not see (their figures above are missing)
        "unseen": {k.split("/", 2)[-1]: n for k, n in obs.gaps.missed.items() if n},
        # what the run computed on: the planned sets, all of them or no digest (the same bytes on every
        # machine when shipped, common/trajectory/shipped.py), and numpy's kernels and BLAS here
        # (common/runtime/numeric.py)
        "sets_sha256": digest_of_all(sets, load_task(opts.task).paths),
        "build": numeric_build(),
    }
    kept = keep_summary(opts.out, json.dumps(summary, indent=1).encode(), console)
    reported = kept.parent == opts.out  # a folder that could not take the summary takes no report either
    if reported:
        try:
            run = from_demo(opts.out)  # the report of the run (cadence/lab/report.py), into the run's folder
            run.sets.update(sets)
            write_report(run, opts.out, TwinParams().rr_rest_s)
        except (OSError, InputError) as exc:
            why = exc.strerror or exc if isinstance(exc, OSError) else exc
            console.print(f"{opts.out}: the report could not be written ({why}); the summary holds the "
                          "run's figures", style="red")  # fmt: skip
            reported = False
    # where it all went, for the last line the command prints (not in the file)
    return {**summary, "written": {"summary": str(kept), "report": reported}}


def keep_summary(out: Path, data: bytes, console: Console) -> Path:
    """``summary.json`` in ``out``; where that folder cannot take it (a full disk, no permission), in a
    new folder under the system's temporary one, said in one line: an hour's run keeps its results."""
    try:
        write_readable(out / "summary.json", data)
        return out / "summary.json"
    except OSError as exc:
        why = exc.strerror or str(exc)
    elsewhere = Path(tempfile.mkdtemp(prefix="cadence-demo-")) / "summary.json"
    try:
        write_readable(elsewhere, data)
    except OSError as exc:
        console.print(f"{out}: cannot write summary.json ({why}), nor {elsewhere.parent} "
                      f"({exc.strerror or exc}): the summary is lost", style="red")  # fmt: skip
        return out / "summary.json"
    console.print(f"{out}: cannot write summary.json ({why}); it is in {elsewhere} instead", style="red")
    return elsewhere


def summary_table(summary: dict[str, Any], wall_s: float) -> Table:
    """The demo's figures on the terminal: what ``summary.json`` holds, in one row."""
    cut = " (cut short)" if summary["cut_short"] else ""
    table = Table(title=f"cadence demo: {summary['duration_s']:g} s of data time in {wall_s:.0f} s{cut}")
    columns = (
        "cycles",
        "φ [cycles/min]",
        "errors",
        "ε [errors/cycle]",
        "windows",
        "k steps ↓ / ↑",
        "restarts",
    )
    for col in columns:
        table.add_column(col, justify="right")
    table.add_row(
        str(summary["cycles"]),
        f"{summary['productivity_per_min']:.2f}",
        str(summary["errors"]),
        f"{summary['error_rate']:.3f}",
        str(len(summary["windows"])),
        f"{summary['k_steps_down']} / {summary['k_steps_up']}",
        ", ".join(f"{k} {v}" for k, v in summary["restarts"].items() if v) or "none",
    )
    return table
