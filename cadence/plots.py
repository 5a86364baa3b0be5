"""Figures people look at before they read the numbers (matplotlib, PNG, no display needed)."""

from __future__ import annotations

import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from common.trajectory import bspline as bs
from common.trajectory.limits import JOINT_NAMES
from common.trajectory.planner import ParetoResult


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


def rr_k_figure(windows: list[dict], selections: list[dict], rr_rest_s: float) -> bytes:
    """Mean RR per window and the selected k over data time, like the paper's Fig. 6."""
    fig, ax = plt.subplots(figsize=(11, 4.5), constrained_layout=True)
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
            label="mean RR (low quality)",
        )
    ax.axhline(rr_rest_s, ls="--", c="tab:red", lw=0.8, label="RR at rest")
    ax.set_xlabel("data time [s]")
    ax.set_ylabel("mean RR per window [s]", color="tab:red")
    ax2 = ax.twinx()
    if selections:
        t = [s["t_s"] for s in selections]
        k = [s["k"] for s in selections]
        end = max([*t, *(w["end_s"] for w in windows)])
        ax2.step([*t, end], [*k, k[-1]], where="post", c="tab:blue", label="selected k")
    ax2.set_ylabel("k (1 smoothest … N fastest)", color="tab:blue")
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], loc="lower left", fontsize=8)
    ax.set_title("Operator's mean RR and the robot's selected solution")
    return _png(fig)


def cycle_kinematics_figure(sets: dict, cycles: list[dict]) -> bytes:
    """q, q̇, q̈ and jerk of whole cycles, path after path at the k each ran with (motion only; the
    waits between paths are left out). ``cycles``: [{"k": {path: k}, …}], one column each."""
    labels = ("q [deg]", "q̇ [deg/s]", "q̈ [deg/s²]", "jerk [deg/s³]")
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
                    ax.plot(t0 + t, np.degrees(curves[row][:, j]), c=f"C{j}", lw=1.0, label=label)
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
        axes[0, col].set_title(cycle.get("label", f"cycle {col + 1}"), pad=22)
        axes[3, col].set_xlabel("motion time [s]")
    for row in range(4):
        axes[row, 0].set_ylabel(labels[row])
    axes[0, 0].legend(ncol=3, fontsize=7, loc="lower right")
    return _png(fig)


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
            ax.annotate(f"k={k} ×{c}", (x, y), textcoords="offset points", xytext=(6, 4), fontsize=7)
        ax.set_title(pid, fontsize=9)
        ax.set_xlabel("time (normalised)")
        ax.set_ylabel("jerk (normalised)")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7)
    return _png(fig)


def study_figure(values: dict[str, dict[str, list[float]]], names: dict[str, str]) -> bytes:
    """Box plots per condition of normalised mean RR, φ and ε (like the paper's Fig. 7), simulated."""
    metrics = (("mean_rr_norm", "mean RR / resting RR"), ("productivity_per_min", "φ [cycles/min]"),
               ("error_rate", "ε [errors/cycle]"))  # fmt: skip
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), constrained_layout=True)
    conds = list(values)
    for ax, (m, label) in zip(axes, metrics, strict=True):
        ax.boxplot([values[c][m] for c in conds], tick_labels=[f"({c}) {names[c]}" for c in conds])
        ax.set_ylabel(label)
        ax.tick_params(axis="x", labelsize=8)
    fig.suptitle("Simulated operators (operator twin), not a study of people")
    return _png(fig)
