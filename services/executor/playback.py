"""What the servo loop sends, one controller step at a time (services/executor/servo.py).

``Samples``: targets computed before the motion (the tests' and the benchmarks' fixed motions).
``Playback``: a path's curve at path time s(t), under a time scale that another thread may change while
it runs (common/trajectory/scaling.py): a new ``Ramp`` from a controller step still ahead, or a new curve
(a switch of solution) from a path time still ahead. Both are handed over as one reference each, which
the loop takes at its next step: a change that arrives too late for its step is dropped, never applied
late, and the thread that offered it sees that (``missed``) and plans again.

Inside ``next`` there is no lock, no logging and no container that grows: a few floats and one Horner
evaluation of the current span (six coefficients of six joints).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from common.trajectory.scaling import DT, Curve, Ramp

Array = NDArray[np.float64]


class Samples:
    def __init__(self, targets: Sequence[object]) -> None:
        self.targets, self.sent = targets, 0
        self.last = targets[-1]

    @property
    def done(self) -> bool:
        return self.sent >= len(self.targets)

    def next(self) -> object | None:
        if self.sent >= len(self.targets):
            return None
        self.sent += 1
        return self.targets[self.sent - 1]


class Playback:
    """One path at a time scale. ``tick`` counts the samples sent; playback time is ``tick · DT``."""

    def __init__(self, curve: Curve, ramp: Ramp, convert: Callable[[Array], object]) -> None:
        self.curve, self.ramp, self.convert = curve, ramp, convert
        self.tick = 0
        self.s = 0.0
        self.sigma = float(ramp.c[0])
        self.last = convert(curve.at(np.array([curve.t_f]), order=0)[0, 0])
        self.finished = False
        # (the change, what it was planned from): it applies only if that is still what is in force
        self.pending_ramp: tuple[Ramp, Ramp] | None = None
        self.pending_curve: tuple[float, Curve, Curve] | None = None
        self.missed = 0  # offers dropped because they came too late for their step
        self.span = 0

    @property
    def done(self) -> bool:
        return self.finished

    @property
    def t(self) -> float:
        return self.tick * DT

    def offer_ramp(self, ramp: Ramp, base: Ramp) -> bool:
        """From another thread: take ``ramp`` (planned from the σ-state of ``base``) at its start, a step
        not yet sent. False: too late already; a later miss is counted in ``missed``."""
        if ramp.t0 < self.t + DT / 2 or base is not self.ramp:
            return False
        self.pending_ramp = (ramp, base)
        return True

    def offer_curve(self, s_switch: float, curve: Curve, base: Curve) -> bool:
        """From another thread: from path time ``s_switch`` on, the joined ``curve`` (``base`` up to
        there). False: too late already; a later miss is counted in ``missed``."""
        if s_switch <= self.s or base is not self.curve:
            return False
        self.pending_curve = (s_switch, curve, base)
        return True

    def next(self) -> object | None:
        t = self.tick * DT
        offer = self.pending_ramp
        if offer is not None and t >= offer[0].t0 - DT / 2:
            self.pending_ramp = None
            if abs(offer[0].t0 - t) < DT / 2 and offer[1] is self.ramp:
                self.ramp = offer[0]
            else:
                self.missed += 1
        s, sigma = self.ramp.at(t)
        joined = self.pending_curve
        if joined is not None and s >= joined[0]:
            self.pending_curve = None
            # nothing past the switch was sent from the old curve, and it is the one it was joined to
            if self.s < joined[0] and joined[2] is self.curve:
                self.curve, self.span = joined[1], 0
            else:
                self.missed += 1
        if s >= self.curve.t_f:
            self.finished = True
            return None
        self.tick += 1
        self.s, self.sigma = s, sigma
        return self.convert(self._point(s))

    def _point(self, s: float) -> Array:
        starts, spans = self.curve.starts, len(self.curve.starts)
        i = self.span
        while i + 1 < spans and starts[i + 1] <= s:  # s never goes back: walk forward from the last span
            i += 1
        self.span = i
        tau = s - starts[i]
        coeffs = self.curve.taylor[i]
        q = coeffs[5] * tau
        for k in (4, 3, 2, 1):
            q = (q + coeffs[k]) * tau
        q += coeffs[0]
        return q

    def state(self) -> Ramp:
        """The σ-state now, for the next path's playback (the scale carries over)."""
        return self.ramp.rebased(self.t)
