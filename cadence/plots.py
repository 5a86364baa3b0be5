"""Figures people look at before they read the numbers (matplotlib, PNG, no display needed)."""

from __future__ import annotations

import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from common import bspline as bs
from common.limits import JOINT_NAMES
from common.planner import ParetoResult


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
            if lims[row] is not None:
                top = float(np.max(lims[row]))
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


def cycle_figure(cycles: dict[str, list]) -> bytes:
    """Joint positions of whole cycles, path after path at the k each path ran with (motion only;
    the waits between paths are left out)."""
    fig, axes = plt.subplots(
        len(cycles), 1, figsize=(11, 3.2 * len(cycles)), constrained_layout=True, squeeze=False
    )
    for ax, (label, paths) in zip(axes[:, 0], cycles.items(), strict=True):
        t0 = 0.0
        for i, (pid, k, h, path) in enumerate(paths):
            t, q, _, _ = bs.sample(h, path.waypoints, path.boundary, 100.0)
            for j in range(q.shape[1]):
                ax.plot(
                    t0 + t, np.degrees(q[:, j]), c=f"C{j}", lw=1.2, label=JOINT_NAMES[j] if i == 0 else None
                )
            ax.axvline(t0, c="0.85", lw=0.8)
            ax.text(
                t0 + t[-1] / 2,
                1.01,
                f"{pid}\nk={k}",
                transform=ax.get_xaxis_transform(),
                ha="center",
                fontsize=7,
            )
            t0 += t[-1]
        ax.set_ylabel(f"{label}\nq [deg]")
    axes[-1, 0].set_xlabel("motion time [s]")
    axes[0, 0].legend(ncol=6, fontsize=8, loc="lower right")
    return _png(fig)
