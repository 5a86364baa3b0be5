"""Figures people look at before they read the numbers (matplotlib, PNG, no display needed)."""

from __future__ import annotations

import io
from collections import Counter
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import patheffects
from matplotlib.ticker import MaxNLocator

from common.robot.ur16e import JOINT_NAMES
from common.trajectory import bspline as bs
from common.trajectory.planner import ParetoResult
from schemas.pareto import ParetoSet


def pareto_figure(result: ParetoResult) -> bytes:
    """The front (normalised, like the paper's Fig. 3) with the N chosen solutions, and q, q̇, q̈, jerk
    of solutions 1 (smoothest) and N (fastest), dashed lines at the limits."""
    fig = plt.figure(figsize=(13, 9), constrained_layout=True)
    grid = fig.add_gridspec(4, 3)
    ax = fig.add_subplot(grid[:, 0])
    f = result.front
    ideal, nadir = f.min(axis=0), f.max(axis=0)
    z = (f - ideal) / np.where(nadir > ideal, nadir - ideal, 1.0)
    chosen = np.array([[s.f_time, s.f_jerk] for s in result.solutions])
    zc = (chosen - ideal) / np.where(nadir > ideal, nadir - ideal, 1.0)
    ax.scatter(z[:, 0], z[:, 1], s=14, c="0.65", label=f"front F ({len(f)} points)")
    ax.scatter(zc[:, 0], zc[:, 1], s=36, c="tab:blue", label=f"chosen F* (N = {len(chosen)})", zorder=3)
    for s, (x, y) in zip(result.solutions, zc, strict=True):
        ax.annotate(str(s.k), (x, y), textcoords="offset points", xytext=(5, 4), fontsize=8)
    ax.set_xlabel("f_time (normalised)")
    ax.set_ylabel("f_jerk (normalised)")
    ax.set_title(f"{result.path.id}: Pareto front ({result.settings.constraints} limits)")
    ax.legend()

    labels = ["q [rad]", "q̇ [rad/s]", "q̈ [rad/s²]", "jerk [rad/s³]"]
    lims = [None, result.limits.velocity, result.limits.acceleration, result.limits.jerk]
    for col, sol in enumerate((result.solutions[0], result.solutions[-1]), start=1):
        t = np.linspace(0.0, sol.t_f, 1500)
        vals = bs.evaluate_dense(sol.h, result.path.waypoints, result.path.boundary, t)
        for row in range(4):
            a = fig.add_subplot(grid[row, col])
            for j in range(vals.shape[2]):
                a.plot(t, vals[row, :, j], lw=1.1, label=JOINT_NAMES[j])
            lim = lims[row]
            if lim is not None:
                top = float(np.max(lim))
                a.axhline(top, ls="--", c="0.4", lw=0.8)
                a.axhline(-top, ls="--", c="0.4", lw=0.8)
            if row == 0:
                a.set_title(f"k = {sol.k}: t_f = {sol.t_f:.3f} s")
                sites = bs.waypoint_sites(sol.h[None])[0]
                a.plot(sites, result.path.waypoints, "k.", ms=4)
            a.set_ylabel(labels[row])
            if row == 3:
                a.set_xlabel("t [s]")
    fig.axes[1].legend(fontsize=7, ncol=2)
    return _png(fig)


def _png(fig: plt.Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def rr_k_figure(*args: Any, **kwargs: Any) -> bytes:
    return _png(rr_k_axes(*args, **kwargs))


def held_label(low: list[dict]) -> str:
    """The legend of the windows the analyser held, with why and how often (a run recorded before
    windows carried their reason says only "low quality")."""
    reasons = Counter(w.get("reason") for w in low if w.get("reason"))
    if not reasons:
        return "mean RR (low quality)"
    return "mean RR, held: " + ", ".join(f"{why} {n}" for why, n in reasons.most_common())


def rr_k_axes(
    windows: list[dict],
    selections: list[dict],
    rr_rest_s: float,
    rest_label: str = "RR_r",
    cycle_ends_s: list[float] | None = None,
    error_times_s: list[float] | None = None,
    idle: list[tuple[float, float, str]] | None = None,
    rr_stress_s: float | None = None,
    rr_stress_max_s: float | None = None,
) -> plt.Figure:
    """Mean RR per window and the selected k over data time, like the paper's Fig. 6: RR_r and the
    decision thresholds RR_s, RR_s^max (as recorded, else the paper's defaults about RR_r) as lines, k on
    integer ticks, cycle ends as ticks along the bottom, the operator's errors as ticks along the top, and
    shaded the spans in which the robot did not work (``motion.idle_spans``): a k chosen there moved
    nothing. With the strap's accelerometer, a panel below gives each window's movement, and the windows
    the decision held for it are shaded above."""
    from common.decision import Params

    moving = [w for w in windows if w.get("movement_mg") is not None]
    if moving:
        fig, (ax, axm) = plt.subplots(2, 1, figsize=(11, 6), sharex=True, height_ratios=[3, 1],
                                      constrained_layout=True)  # fmt: skip
        axm.bar([w["end_s"] for w in moving], [w["movement_mg"] for w in moving], width=-25.0, align="edge",
                color="tab:green", label="movement (mean dynamic acceleration)")  # fmt: skip
        axm.set_ylabel("movement [mg]", color="tab:green")
        axm.legend(loc="upper left", fontsize=8)
    else:
        fig, ax = plt.subplots(figsize=(11, 4.5), constrained_layout=True)
    held = [x["t_s"] for x in selections if x["reason"] == "movement"]
    for i, end in enumerate(held):
        ax.axvspan(end - 30.0, end, color="tab:green", alpha=0.12, lw=0,
                   label="held: moving (not read as stress)" if i == 0 else None)  # fmt: skip
    good = [w for w in windows if w["mean_rr_s"] is not None and w["quality"] == "good"]
    low = [w for w in windows if w["mean_rr_s"] is not None and w["quality"] != "good"]
    ax.plot(
        [w["end_s"] for w in good], [w["mean_rr_s"] for w in good], "o-", c="tab:red", label="mean RR (good)"
    )
    if low:
        ax.plot(
            [w["end_s"] for w in low],
            [w["mean_rr_s"] for w in low],
            "x",
            c="0.5",
            label=held_label(low),
        )
    for i, (a, b) in enumerate(drawn_spans(idle)):
        ax.axvspan(a, b, color="0.85", lw=0, label="robot stopped or waiting" if i == 0 else None)
    p = Params.of(rr_rest_s)
    ax.axhline(rr_rest_s, ls="--", c="tab:red", lw=0.8, label=rest_label)
    recorded = rr_stress_s is not None
    stress = rr_stress_s if rr_stress_s is not None else float(p.rr_stress)
    stress_max = rr_stress_max_s if rr_stress_max_s is not None else float(p.rr_stress_max)
    ax.axhline(
        stress, ls="-.", c="0.4", lw=0.8, label="RR_s (recorded)" if recorded else "RR_s = RR_r − 0.08 s"
    )
    ax.axhline(
        stress_max,
        ls=":",
        c="0.4",
        lw=0.8,
        label="RR_s^max" + (" (recorded)" if recorded else " = RR_s − σ_s"),
    )
    for end in cycle_ends_s or []:
        ax.axvline(end, ymin=0.0, ymax=0.03, c="0.2", lw=0.8)
    for i, at in enumerate(error_times_s or []):
        label = "operator error" if i == 0 else None
        ax.axvline(at, ymin=0.95, ymax=1.0, c="tab:orange", lw=1.5, label=label)
    marks = (("bottom: cycle ends", cycle_ends_s), ("top: errors", error_times_s))
    ticks = [what for what, there in marks if there]
    (axm if moving else ax).set_xlabel(
        "data time [s]" + (f" (ticks at the {'; '.join(ticks)})" if ticks else "")
    )
    ax.set_ylabel("mean RR per window [s]", color="tab:red")
    ax2 = ax.twinx()
    if selections:
        t = [s["t_s"] for s in selections]
        k = [s["k"] for s in selections]
        end = max([*t, *(w["end_s"] for w in windows)])
        ax2.step([*t, end], [*k, k[-1]], where="post", c="tab:blue", label="selected k")
        # from 1 to the largest k seen (or N), whole steps: a k that stayed at 1 once drew 0.945–1.050
        top = max([*k, *(s.get("n", 0) or 0 for s in selections)])
        ax2.set_ylim(0.5, top + 0.5)
    ax2.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax2.set_ylabel("k (1 smoothest … N fastest)", color="tab:blue")
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], loc="lower left", fontsize=8)
    ax.set_title("Operator's mean RR and the robot's selected solution")
    return fig


def drawn_spans(idle: list[tuple[float, float, str]] | None) -> list[tuple[float, float]]:
    """The spans that are seen: one of no length draws nothing, and its legend entry would name it."""
    return [(a, b) for a, b, _ in idle or [] if b > a]


def separation_figure(rows: list[dict], idle: list[tuple[float, float, str]] | None = None) -> bytes:
    return _png(separation_axes(rows, idle))


def separation_axes(rows: list[dict], idle: list[tuple[float, float, str]] | None = None) -> plt.Figure:
    """The nearest person's distance and the robot's time scale over data time (report/separation.png),
    in two panels on one time axis: on twin axes the two lines crossed and hid each other."""
    fig, (ax, scale) = plt.subplots(2, 1, figsize=(11, 4.5), sharex=True, height_ratios=[3, 2],
                                    constrained_layout=True)  # fmt: skip
    fig.suptitle("Speed and separation monitoring: the nearest person, and the pace the robot kept")
    t = [r["t_s"] for r in rows]
    ax.plot(t, [r["separation_m"] if r["separation_m"] is not None else np.nan for r in rows],
            color="tab:purple", lw=1.2, label="separation")  # fmt: skip
    ax.set_ylabel("separation [m]", color="tab:purple")
    ax.set_ylim(bottom=0.0)
    for i, (a, b) in enumerate(drawn_spans(idle)):
        ax.axvspan(a, b, color="0.85", lw=0, label="robot not working" if i == 0 else None)
        scale.axvspan(a, b, color="0.85", lw=0)
    scale.step(t, [r["scale"] for r in rows], where="post", color="tab:blue", lw=1.2, label="time scale σ")
    scale.set_ylim(-0.05, 1.05)
    scale.set_ylabel("time scale σ", color="tab:blue")
    scale.set_xlabel("data time [s]")
    ax.legend(loc="lower left", fontsize=8)
    scale.legend(loc="lower left", fontsize=8)
    return fig


def cycle_kinematics_figure(sets: dict, cycles: list[dict]) -> bytes:
    """q, q̇, q̈ and jerk of whole cycles as commanded (the planned trajectories, not the arm's
    measurement), path after path at the k each ran with (motion only; the waits between paths are left
    out), in radians as the plans are, with the UR16e's limits as dashed lines (a task may only lower
    them). ``cycles``: [{"k": {path: k}, …}], one column each."""
    from common.robot.ur16e import UR16E

    labels = ("q [rad]", "q̇ [rad/s]", "q̈ [rad/s²]", "jerk [rad/s³]")
    limits = (None, UR16E.velocity, UR16E.acceleration, UR16E.jerk)
    fig, axes = plt.subplots(
        4, len(cycles), figsize=(6.5 * len(cycles), 10), constrained_layout=True, squeeze=False
    )
    for col, cycle in enumerate(cycles):
        t0 = 0.0
        for i, (pid, k) in enumerate(cycle["k"].items()):
            s = sets[pid]
            h = np.array(s.solutions[k - 1].h)
            t = np.linspace(0.0, float(h.sum()), max(50, int(h.sum() * 100)))
            curves = bs.evaluate_dense(h, np.array(s.waypoints), bs.Boundary.from_ends(s.start, s.end), t)
            for row in range(4):
                ax = axes[row, col]
                for j in range(curves.shape[2]):
                    label = JOINT_NAMES[j] if i == 0 and row == 0 else None
                    ax.plot(t0 + t, curves[row][:, j], c=f"C{j}", lw=1.0, label=label)
                ax.axvline(t0, c="0.85", lw=0.8)
            top = axes[0, col]
            top.text(
                t0 + t[-1] / 2,
                1.01,
                f"{pid}\nk={k}",
                transform=top.get_xaxis_transform(),
                ha="center",
                fontsize=6,
            )
            t0 += float(t[-1])
        axes[0, col].set_title(f"{cycle.get('label', f'cycle {col + 1}')} (commanded)", pad=22)
        axes[3, col].set_xlabel("motion time [s]")
        for row in range(1, 4):
            lim = limits[row]
            assert lim is not None
            for sign in (1, -1):
                axes[row, col].axhline(sign * float(np.max(lim)), ls="--", c="0.4", lw=0.8)
    for row in range(4):
        axes[row, 0].set_ylabel(labels[row])
    fig.suptitle("As commanded (the plans the executor ran, not measured); dashed: the UR16e's limits")
    axes[0, 0].legend(ncol=3, fontsize=7, loc="lower right")
    return _png(fig)


def front_title(pid: str, s: ParetoSet) -> str:
    """A path's durations as people read them: t_f of its fastest and slowest solution (f_time is D·t_f,
    six times that, and once stood here as if it were seconds of motion)."""
    t_f = [x.t_f for x in s.solutions]
    return f"{pid}: t_f {min(t_f):.2f}–{max(t_f):.2f} s"


def front_usage_figure(sets: dict, used: dict[str, dict[int, int]]) -> bytes:
    """Each path's Pareto front (normalised) with its N solutions, and how often each k was used."""
    n = len(sets)
    cols = min(3, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(
        rows, cols, figsize=(4.5 * cols, 3.8 * rows), constrained_layout=True, squeeze=False
    )
    for ax, (pid, s) in zip(axes.flat, sets.items(), strict=False):
        f = np.array(s.front)
        ideal, nadir = f.min(axis=0), f.max(axis=0)
        scale = np.where(nadir > ideal, nadir - ideal, 1.0)
        z = (f - ideal) / scale
        chosen = (np.array([[x.f_time, x.f_jerk] for x in s.solutions]) - ideal) / scale
        ax.scatter(z[:, 0], z[:, 1], s=8, c="0.7", label="front")
        ax.scatter(chosen[:, 0], chosen[:, 1], s=22, c="tab:blue", label=f"N = {len(chosen)}")
        counts = used.get(pid, {})
        for k, c in counts.items():
            x, y = chosen[k - 1]
            ax.scatter([x], [y], s=40 + 25 * c, facecolors="none", edgecolors="tab:red", lw=1.5)
        # the k used, each on its own line from its circle up to a label row: neighbours on the front
        # sit a few pixels apart, so labels beside them would overlap
        for i, (k, c) in enumerate(sorted(counts.items(), key=lambda kc: chosen[kc[0] - 1][0])):
            x, y = chosen[k - 1]
            ax.annotate(f"k={k} ×{c}", (x, y), xytext=(0.35 + 0.2 * (i % 3), 0.55 + 0.12 * (i // 3)),
                        textcoords="axes fraction", fontsize=7,
                        arrowprops={"arrowstyle": "-", "lw": 0.6, "color": "tab:red"})  # fmt: skip
        ax.set_title(front_title(pid, s), fontsize=9)
        ax.set_xlabel("f_time = D·t_f, normalised: 0 fastest … 1 slowest")
        ax.set_ylabel("f_jerk, normalised: 0 smoothest … 1")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7)
    return _png(fig)


def study_figure(
    values: dict[str, dict[str, list[float]]],
    names: dict[str, str],
    marks: dict[str, dict[str, str]],
    simulated: bool,
) -> bytes:
    """Per condition, one point per subject over a box: normalised mean RR (the paper's Fig. 7), φ and ε,
    with a bracket per pair of conditions marked with its Wilcoxon result (``marks["a-b"][metric]``)."""
    metrics = (("mean_rr_norm", "mean RR / RR_r"), ("productivity_per_min", "φ [cycles/min]"),
               ("error_rate", "ε [errors/cycle]"))  # fmt: skip
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.6), constrained_layout=True)
    conds = list(values)
    for ax, (m, label) in zip(axes, metrics, strict=True):
        data = [[v for v in values[c][m] if np.isfinite(v)] for c in conds]
        ax.boxplot(data, tick_labels=[f"({c}) {names[c]}" for c in conds], showfliers=False)
        for i, d in enumerate(data, start=1):
            jitter = np.linspace(-0.08, 0.08, len(d)) if len(d) > 1 else np.zeros(len(d))
            ax.plot(i + jitter, d, "o", ms=3.5, alpha=0.6, c="tab:blue")
        finite = [v for d in data for v in d]
        if finite:
            lo, hi = min(finite), max(finite)
            step = (hi - lo) * 0.09 or 0.05 * abs(hi) or 0.05
            level = hi + step
            for pair, ms in marks.items():
                a, b = pair.split("-")
                if a in conds and b in conds and m in ms:
                    xa, xb = conds.index(a) + 1, conds.index(b) + 1
                    top = level + step / 3
                    ax.plot([xa, xa, xb, xb], [level, top, top, level], c="0.3", lw=0.9)
                    ax.text((xa + xb) / 2, level + step / 2.5, ms[m], ha="center", va="bottom", fontsize=8)
                    level += step * 1.3
            ax.set_ylim(lo - step, level + step)
        ax.set_ylabel(label)
        ax.tick_params(axis="x", labelsize=8)
    fig.suptitle(
        "Simulated operators (operator twins), not a study of people" if simulated else "Study sessions"
    )
    return _png(fig)


def subject_figure(sessions: list) -> bytes:
    """One subject, one row per condition (like the paper's Fig. 6): each window's mean RR (good filled,
    held hollow) against minutes into the session, RR_r and the decision thresholds RR_s and RR_s^max,
    the selected k on the right axis (integer ticks), cycle ends as ticks along the bottom and errors as
    red crosses. ``sessions``: cadence.lab.session_file.Session objects of one subject."""
    from common.decision import Params
    from schemas.session import CONDITION_NAMES

    rows = len(sessions)
    fig, axes = plt.subplots(rows, 1, figsize=(11, 2.9 * rows), squeeze=False)
    # fixed margins, in inches: a layout engine draws every figure twice, and a study has one per subject
    height = 2.9 * rows
    fig.subplots_adjust(left=0.7 / 11, right=1 - 0.75 / 11, top=1 - 0.35 / height, bottom=0.5 / height,
                        hspace=0.45)  # fmt: skip
    for ax, s in zip(axes[:, 0], sessions, strict=True):
        t0 = s.info.start_ns

        def minutes(ns: int, t0: int = t0) -> float:
            return (ns - t0) / 60e9

        cal = s.info.calibration
        p = Params.of(cal.rr_rest_s, 1, cal.sigma_rest_s, cal.rr_stress_offset_s, cal.sigma_stress_s)
        shown = [w for w in s.windows if w.mean_rr_s is not None and s.inside(w.end_ns)]
        for good, face in ((True, "tab:red"), (False, "none")):  # one artist each: a figure per subject
            mine = [w for w in shown if (w.quality == "good") == good]
            ax.plot([minutes(w.end_ns) for w in mine], [w.mean_rr_s for w in mine], "o", ms=4,
                    c="tab:red", mfc=face, ls="none")  # fmt: skip
        for y, what, style in ((float(p.rr_rest), "RR_r", "-"), (float(p.rr_stress), "RR_s", "--"),
                               (float(p.rr_stress_max), "RR_s^max", ":")):  # fmt: skip
            ax.axhline(y, c="0.35", ls=style, lw=0.9)
            ax.annotate(what, (0.0, y), xycoords=("axes fraction", "data"), xytext=(2, 2),
                        textcoords="offset points", fontsize=7, color="0.3")  # fmt: skip
        ax.set_ylabel("window mean RR [s]", color="tab:red")
        ax.set_xlim(0.0, s.minutes)
        ends = [minutes(c.t_ns) for c in s.cycles if s.inside(c.t_ns)]
        ax.vlines(ends, 0.0, 0.04, transform=ax.get_xaxis_transform(), colors="0.2", lw=0.8)
        ax2 = ax.twinx()
        sel = [x for x in s.selections if x.t_ns <= s.end.end_ns]
        if sel:
            ts = [max(0.0, minutes(x.t_ns)) for x in sel] + [s.minutes]
            ks = [x.k for x in sel] + [sel[-1].k]
            # outlined: where k runs along a threshold's line, it is still seen (it was hidden under RR_r)
            outline = [patheffects.Stroke(linewidth=3.6, foreground="white"), patheffects.Normal()]
            ax2.step(ts, ks, where="post", c="tab:blue", lw=1.6, path_effects=outline, zorder=3)
            top = max(x.n for x in sel)
            ax2.set_ylim(0.5, top + 0.5)
            ax2.yaxis.set_major_locator(MaxNLocator(integer=True))
        errs = [minutes(e.t_ns) for e in s.errors if s.inside(e.t_ns)]
        if errs:
            ax2.plot(errs, [ax2.get_ylim()[1] - 0.3] * len(errs), "x", c="red", ms=7)
        ax2.set_ylabel("k (1 smoothest … N fastest)", color="tab:blue")
        ax.set_title(
            f"subject {s.info.subject}, ({s.info.condition}) {CONDITION_NAMES[s.info.condition]}: "
            f"{s.n_cycles} cycles, "
            f"{s.n_errors} errors, φ = {s.productivity_per_min:.2f}/min"
            + ("" if s.end.complete else f" — cut short: {s.end.reason}"),
            fontsize=9,
        )
    axes[-1, 0].set_xlabel("minutes into the session (data time)")
    return _png(fig)


def fit_figure(paper: dict[str, tuple[float, float]], twin: dict[str, tuple[float, float]]) -> bytes:
    """φ relative to (a), and ε, per condition: the paper beside the fitted twin; (c) was not fitted."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    x = np.arange(3)
    for ax, (i, label) in zip(axes, ((0, "φ / φ_a"), (1, "ε [errors/cycle]")), strict=True):
        norm = (lambda v, c: v[c][0] / v["a"][0]) if i == 0 else (lambda v, c: v[c][1])
        ax.bar(x - 0.18, [norm(paper, c) for c in "abc"], 0.36, label="paper (people)", color="0.6")
        ax.bar(x + 0.18, [norm(twin, c) for c in "abc"], 0.36, label="twin (simulated)", color="tab:blue")
        ax.set_xticks(x, ["(a) fitted", "(b) fitted", "(c) predicted"])
        ax.set_ylabel(label)
    axes[0].legend()
    fig.suptitle("Operator twin fitted to Table I on (a) and (b): a simulation, not people")
    return _png(fig)
