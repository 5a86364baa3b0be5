"""The personal mode as a controller, on made-up people whose truth is known (DESIGN §7;
`cadence bench decide --scenarios`; tests/services/decision_maker/test_personal.py): each scenario is a
sequence of 30 s windows played through the decision maker's own ``Decider``, as the service answers
them, and summed up by the figures its stated behaviour is about. The real sessions (``decide.py``) say
whether the mode reads people; these say what it does over hours, which no recording here lasts.
"""

from __future__ import annotations

import itertools
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.decision import Params, Personal
from schemas import Calibration, HrvWindow
from services.decision_maker import Decider

N = 15
RR_REST_S = 0.85
WINDOW_S = 30.0
PER_HOUR = round(3600 / WINDOW_S)
BEATS = 37  # a chest strap's beats in 30 s at rest
STILL_MG, MOVING_MG = 10.0, 250.0  # the strap's movement at the bench and in an effort
_NS = 1_000_000_000
T0_NS = 1_700_000_000 * _NS


@dataclass(frozen=True, slots=True)
class Played:
    k: list[int]
    reason: list[str]

    @property
    def k0(self) -> int:
        return Params.of(RR_REST_S, N).k0

    def changes(self, a: int = 0, b: int | None = None) -> float:
        """The share of windows a … b whose k differs from the window before."""
        k = self.k[max(0, a - 1) : b]
        return sum(x != y for x, y in itertools.pairwise(k)) / max(1, len(k) - 1)

    def reversals(self) -> float:
        """The share of windows whose change of k undoes the one just before (up then down at once)."""
        d = np.diff(self.k)
        return float(np.sum(d[1:] * d[:-1] < 0) / max(1, len(self.k)))


def play(
    rr: Sequence[float], movement: Sequence[float] | None = None, mode: Personal | None = None
) -> Played:
    """Windows of mean RR ``rr`` (and the strap's movement, mg) through a ``Decider`` in the personal mode
    (``mode``, default as shipped), calibrated at rest on RR_REST_S."""
    decider = Decider(Path(tempfile.gettempdir()), N, personal=mode or Personal())
    cal = Calibration(t_ns=T0_NS, seq=0, subject="scenario", rr_rest_s=RR_REST_S)
    decider.commit(decider.starting(cal, T0_NS))
    ks: list[int] = []
    why: list[str] = []
    moves = movement if movement is not None else [STILL_MG] * len(rr)
    for i, (x, mg) in enumerate(zip(rr, moves, strict=True)):
        start = T0_NS + round(i * WINDOW_S * _NS)
        end = start + round(WINDOW_S * _NS)
        w = HrvWindow(t_ns=end, seq=i, start_ns=start, end_ns=end, mean_rr_s=round(float(x), 6),
                      n_beats=BEATS, excluded_fraction=0.0, quality="good", movement_mg=mg)  # fmt: skip
        rec = decider.answer(w)
        decider.commit(rec)
        ks.append(rec.k)
        why.append(rec.reason)
    return Played(ks, why)


def noise(sd_s: float, n: int, seed: int = 1) -> list[float]:
    return list(sd_s * np.random.default_rng(seed).standard_normal(n))


def stress_then_rest(drop_s: float = 0.06, hours: float = 1.0) -> list[float]:
    """An hour at ``drop_s`` below rest, an hour of rest, the same stress again, an hour of rest."""
    h = round(hours * PER_HOUR)
    return (
        [RR_REST_S - drop_s] * h + [RR_REST_S] * PER_HOUR + [RR_REST_S - drop_s] * h + [RR_REST_S] * PER_HOUR
    )


def drift(total_s: float, hours: float = 8.0, sd_s: float = 0.01) -> list[float]:
    n = round(hours * PER_HOUR)
    return [
        RR_REST_S + a + b for a, b in zip(np.linspace(0.0, total_s, n), noise(sd_s, n, seed=2), strict=True)
    ]


def effort(tau_s: float, drop_s: float = 0.2) -> tuple[list[float], list[float]]:
    """Half an hour at rest, 5 minutes of effort (RR 0.2 s down), then a recovery of time constant
    ``tau_s`` over an hour, at the bench again."""
    before, during, after = PER_HOUR // 2, 10, PER_HOUR
    t = np.arange(1, after + 1) * WINDOW_S
    rr = [RR_REST_S] * before + [RR_REST_S - drop_s] * during + list(RR_REST_S - drop_s * np.exp(-t / tau_s))
    mg = [STILL_MG] * before + [MOVING_MG] * during + [STILL_MG] * after
    return rr, mg


def first(ks: Sequence[int], ok: Callable[[int], bool], start: int = 0) -> float | None:
    """Minutes from window ``start`` to the first window whose k passes ``ok``."""
    return next(((i - start + 1) * WINDOW_S / 60 for i in range(start, len(ks)) if ok(ks[i])), None)


def span(ks: Sequence[int]) -> str:
    return f"{min(ks)}" if min(ks) == max(ks) else f"{min(ks)}–{max(ks)}"


def minutes(x: float | None) -> str:
    return "never" if x is None else f"{x:.1f} min"


def table() -> list[tuple[str, str, str]]:
    """(scenario, what is stated, what the shipped mode does), a row a scenario (docs/decision.md)."""
    rows = []
    h = PER_HOUR
    p = play(stress_then_rest())
    k0 = p.k0
    down = first(p.k, lambda k: k <= k0 - 2)
    rows.append(("60 min at −60 ms", "k ≥ 2 below k0 from minute 5 to the end of the stress",
                 f"k {span(p.k[10:h])} (k0 {k0}); {minutes(down)} to k0 − 2"))  # fmt: skip
    back = first(p.k, lambda k: k >= k0 - 1, h)
    rows.append(("rest after it", "back within 1 of k0 within 10 min, and stays",
                 f"{minutes(back)} to k0 − 1; k {span(p.k[h + 20 : 2 * h])} after"))  # fmt: skip
    again = first(p.k, lambda k: k <= k0 - 2, 2 * h)
    rows.append(("the same stress an hour later", "the same response as the first",
                 f"k {span(p.k[2 * h + 10 : 3 * h])}; {minutes(again)} to k0 − 2"))  # fmt: skip
    for sd in (0.01, 0.02, 0.03):
        s = play([RR_REST_S + x for x in noise(sd, 8 * h)])
        figures = f"changes {s.changes():.1%}, reversed at once {s.reversals():.1%}"
        said = (
            "k changes in ≤ 10 % of windows, median k0 ± 1"
            if sd <= 0.02
            else "median k0 ± 1 (noise of 2 steps)"
        )
        rows.append((f"steady, {sd * 1000:.0f} ms noise, 8 h", said,
                     f"{figures}, median {np.median(s.k):.0f}, range {span(s.k)}"))  # fmt: skip
    for total in (-0.1, 0.1):
        last = play(drift(total)).k[-h:]
        said = "followed: within 3 of k0 at the end, no ratchet"
        rows.append((f"drift {total * 1000:+.0f} ms over 8 h", said,
                     f"k in the last hour {span(last)}, median {np.median(last):.0f}"))  # fmt: skip
    for tau in (120.0, 300.0, 600.0):
        rr, mg = effort(tau)
        e = play(rr, mg)
        held = sum(r == "movement" for r in e.reason)
        rows.append((f"effort, recovery τ {tau:.0f} s", "no step for the effort; k0 ± 1 after the hold",
                     f"{held} windows held; k after {span(e.k[h // 2 + 10 :])}"))  # fmt: skip
    return rows
