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
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()
