"""The straightforward evaluation of a population, kept as the benchmark's baseline and a test oracle.

One ``scipy.interpolate.make_interp_spline`` per individual, jerk² sampled at 1000 points and integrated
with the trapezoidal rule, limits from the derivative splines' control points (hull) or from the same
1000 samples (exact). This is what ``common.trajectory.bspline`` replaces; ``cadence bench plan`` times both.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import make_interp_spline

from common.robot.ur16e import JointLimits
from common.trajectory import bspline as bs
from common.trajectory.planner import Evaluation
from common.trajectory.task import Constraints, PathPlan

N_SAMPLES = 1000


def evaluate_naive(h: bs.Array, path: PathPlan, limits: JointLimits, constraints: Constraints) -> Evaluation:
    b = path.boundary
    bc = ([(1, b.v0), (2, b.a0), (3, b.j0)], [(1, b.v1), (2, b.a1), (3, b.j1)])
    d = path.waypoints.shape[1]
    f = np.empty((len(h), 2))
    maxima = np.empty((len(h), 3, d))
    for i, row in enumerate(h):
        row2 = row[None, :]
        spl = make_interp_spline(
            bs.waypoint_sites(row2)[0], path.waypoints, k=5, t=bs.knots(row2)[0], bc_type=bc
        )
        t = np.linspace(0.0, float(row.sum()), N_SAMPLES)
        derivs = [spl.derivative(n) for n in (1, 2, 3)]
        jerk = derivs[2](t)
        f[i] = (d * row.sum(), np.trapezoid(np.sum(jerk**2, axis=1), t))
        for n, der in enumerate(derivs):
            vals = der.c if constraints == "hull" else (jerk if n == 2 else der(t))
            maxima[i, n] = np.abs(vals).max(axis=0)
    return Evaluation(f, maxima / limits.kinematic()[None])
