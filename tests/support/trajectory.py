"""SciPy's B-splines, the reference the planner's own evaluation is held against."""

from __future__ import annotations

import numpy as np
from scipy.interpolate import BSpline, make_interp_spline

from common.trajectory import bspline as bs
from common.trajectory.task import PathPlan


def scipy_reference(h: np.ndarray, path: PathPlan) -> BSpline:
    b = path.boundary
    return make_interp_spline(
        bs.waypoint_sites(h[None])[0],
        path.waypoints,
        k=5,
        t=bs.knots(h[None])[0],
        bc_type=([(1, b.v0), (2, b.a0), (3, b.j0)], [(1, b.v1), (2, b.a1), (3, b.j1)]),
    )
