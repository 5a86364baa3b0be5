"""Summaries of the servo loop's tick timing, computed outside the loop from its preallocated ring."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, slots=True)
class TickSummary:
    """The servo loop's timing over a run, as a person reads it in the log at the end."""

    period_us: int
    ticks: int
    p50_err_us: float
    p99_err_us: float
    p999_err_us: float
    max_err_us: float
    overruns: int
    longest_overrun_run: int = 0  # the most consecutive overruns: what the overrun stop counts

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)

    def __str__(self) -> str:
        return (f"{self.ticks} ticks, p99.9 error {self.p999_err_us:.1f} µs, max {self.max_err_us:.1f} µs, "
                f"{self.overruns} overruns")  # fmt: skip


def summarise(
    errors_ns: NDArray[np.int64], ticks: int, overruns: int, period_ns: int, longest_run: int = 0
) -> TickSummary:
    """Percentiles of |tick time − deadline| over the ticks the ring still holds (the last len(ring))."""
    held = np.abs(errors_ns[: min(ticks, errors_ns.size)]).astype(float) / 1e3
    if held.size == 0:
        return TickSummary(round(period_ns / 1e3), 0, 0.0, 0.0, 0.0, 0.0, overruns, longest_run)
    p50, p99, p999 = np.percentile(held, [50.0, 99.0, 99.9])
    return TickSummary(
        round(period_ns / 1e3),
        ticks,
        round(float(p50), 1),
        round(float(p99), 1),
        round(float(p999), 1),
        round(float(held.max()), 1),
        overruns,
        longest_run,
    )
