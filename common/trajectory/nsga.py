"""NSGA-II for two objectives on whole arrays (Deb et al. 2002): the planner's default engine.

Why not pymoo's loop: it keeps every individual as a Python object, and on the example task that
bookkeeping took 60 % of a path's planning time (cProfile: 0.8 of 1.3 s in ``Population.get`` and its
callers), while the batched evaluation of 80 generations took 0.4 s. Here the population is one array and
each generation is a few dozen numpy calls. The operators are pymoo's NSGA-II defaults, so the two engines
search alike: binary tournaments by rank and crowding, simulated binary crossover (η = 15, probability
0.9, each variable 0.5) and polynomial mutation (η = 20, each variable 1/n). pymoo's loop stays as the
reference engine (``plan_path(engine="pymoo")``), which ``cadence bench plan`` runs beside this one.

Constraint handling as in NSGA-II: a feasible individual beats an infeasible one, infeasible ones compare
by their total violation. The planner's repair puts nearly every child on the limits, so this rarely acts.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
ETA_CROSSOVER = 15.0
ETA_MUTATION = 20.0
P_CROSSOVER = 0.9
P_CROSSOVER_VARIABLE = 0.5


def fronts(f: Array) -> list[NDArray[np.intp]]:
    """Non-dominated fronts of a 2-objective F, best first; each sorted by f_0 ascending.

    Peeled one at a time with the sort-and-sweep of a single front: with two objectives a point is on
    the current front iff its f_1 is below that of every remaining point with a smaller f_0. A duplicate
    falls to the next front, so copies never crowd one place of the front.
    """
    left = np.lexsort((f[:, 1], f[:, 0]))
    out = []
    while left.size:
        fj = f[left, 1]
        best_before = np.concatenate([[np.inf], np.minimum.accumulate(fj)[:-1]])
        on = fj < best_before
        out.append(left[on])
        left = left[~on]
    return out


def crowding(f: Array) -> Array:
    """Crowding distance of one front sorted by f_0 (so f_1 descending): its ends are infinitely far."""
    n = len(f)
    d = np.full(n, np.inf)
    if n > 2:
        span = np.ptp(f, axis=0)
        span[span == 0] = 1.0
        d[1:-1] = ((f[2:] - f[:-2]) * np.array([1.0, -1.0]) / span).sum(axis=1)
    return d


def rank_and_crowding(f: Array, cv: Array) -> tuple[NDArray[np.intp], Array]:
    """Rank (lower is better) and crowding (higher is better) of every row. Infeasible rows rank after
    every front, in order of violation."""
    n = len(f)
    rank = np.empty(n, dtype=np.intp)
    crowd = np.zeros(n)
    feasible = np.nonzero(cv <= 0.0)[0]
    r = 0
    for front in fronts(f[feasible]):
        rows = feasible[front]
        rank[rows] = r
        crowd[rows] = crowding(f[rows])
        r += 1
    infeasible = np.nonzero(cv > 0.0)[0]
    rank[infeasible[np.argsort(cv[infeasible], kind="stable")]] = r + np.arange(infeasible.size)
    return rank, crowd


def survivors(rank: NDArray[np.intp], crowd: Array, size: int) -> NDArray[np.intp]:
    by_rank_then_crowding: NDArray[np.intp] = np.lexsort((-crowd, rank))
    return by_rank_then_crowding[:size]


def tournament(rank: NDArray[np.intp], crowd: Array, n: int, rng: np.random.Generator) -> NDArray[np.intp]:
    """n winners of binary tournaments (crowded comparison; a tie goes to the first drawn)."""
    a, b = rng.integers(0, len(rank), size=(2, n))
    b_wins = (rank[b] < rank[a]) | ((rank[b] == rank[a]) & (crowd[b] > crowd[a]))
    winners: NDArray[np.intp] = np.where(b_wins, b, a)
    return winners


def _sbx_beta(u: Array, alpha: Array) -> Array:
    e = 1.0 / (ETA_CROSSOVER + 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(u <= 1.0 / alpha, (u * alpha) ** e, (1.0 / (2.0 - u * alpha)) ** e)


def crossover(p1: Array, p2: Array, xl: Array, xu: Array, rng: np.random.Generator) -> Array:
    """Simulated binary crossover within bounds (Deb & Agrawal): two children per pair, (2m, n)."""
    m, n = p1.shape
    y1, y2 = np.minimum(p1, p2), np.maximum(p1, p2)
    gap = y2 - y1
    cross = (rng.random((m, 1)) < P_CROSSOVER) & (rng.random((m, n)) < P_CROSSOVER_VARIABLE) & (gap > 1e-14)
    safe = np.where(gap > 1e-14, gap, 1.0)
    u = rng.random((m, n))
    alpha1 = 2.0 - (1.0 + 2.0 * (y1 - xl) / safe) ** -(ETA_CROSSOVER + 1.0)
    alpha2 = 2.0 - (1.0 + 2.0 * (xu - y2) / safe) ** -(ETA_CROSSOVER + 1.0)
    c1 = 0.5 * ((y1 + y2) - _sbx_beta(u, alpha1) * gap)
    c2 = 0.5 * ((y1 + y2) + _sbx_beta(u, alpha2) * gap)
    c1, c2 = np.clip(c1, xl, xu), np.clip(c2, xl, xu)
    swap = rng.random((m, n)) < 0.5
    c1, c2 = np.where(swap, c2, c1), np.where(swap, c1, c2)
    return np.concatenate([np.where(cross, c1, p1), np.where(cross, c2, p2)])


def mutate(x: Array, xl: Array, xu: Array, rng: np.random.Generator) -> Array:
    """Polynomial mutation within bounds (Deb), each variable with probability min(0.5, 1/n)."""
    m, n = x.shape
    hit = rng.random((m, n)) < min(0.5, 1.0 / n)
    width = xu - xl
    d1, d2 = (x - xl) / width, (xu - x) / width
    u = rng.random((m, n))
    e = ETA_MUTATION + 1.0
    low = (2.0 * u + (1.0 - 2.0 * u) * (1.0 - d1) ** e) ** (1.0 / e) - 1.0
    high = 1.0 - (2.0 * (1.0 - u) + 2.0 * (u - 0.5) * (1.0 - d2) ** e) ** (1.0 / e)
    step = np.where(u < 0.5, low, high) * width
    return np.where(hit, np.clip(x + step, xl, xu), x)


Evaluate = Callable[[Array], tuple[Array, Array]]  # X → (F, G), G ≤ 0 feasible
Repair = Callable[[Array], Array]


def evolve(
    x: Array,
    xl: Array,
    xu: Array,
    evaluate: Evaluate,
    repair: Repair,
    generations: int,
    rng: np.random.Generator,
    on_generation: Callable[[], None] | None = None,
) -> Array:
    """Run ``generations`` generations from the population x (repaired and evaluated first); the final
    population. ``size`` offspring per generation, as pymoo's NSGA-II makes."""
    size = len(x)
    x = repair(x)
    f, g = evaluate(x)
    cv = np.maximum(g, 0.0).sum(axis=1)
    rank, crowd = rank_and_crowding(f, cv)
    for _ in range(generations):
        half = (size + 1) // 2
        parents = tournament(rank, crowd, 2 * half, rng)
        kids = crossover(x[parents[:half]], x[parents[half:]], xl, xu, rng)[:size]
        kids = repair(mutate(kids, xl, xu, rng))
        fk, gk = evaluate(kids)
        x, f = np.concatenate([x, kids]), np.concatenate([f, fk])
        cv = np.concatenate([cv, np.maximum(gk, 0.0).sum(axis=1)])
        rank, crowd = rank_and_crowding(f, cv)
        keep = survivors(rank, crowd, size)
        x, f, cv = x[keep], f[keep], cv[keep]
        rank, crowd = rank_and_crowding(f, cv)
        if on_generation is not None:
            on_generation()
    return x
