"""Noisy variants of a recording, as a chest strap at work gives them: white noise at a given
signal-to-noise ratio, baseline wander (breathing and slow drift) and motion bursts (electrode motion:
a few seconds of large low-frequency artefact). Seeded, so a benchmark's variants are the same in every
run."""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from common.runtime.errors import InputError

Variant = Literal["clean", "white12", "white6", "wander", "motion"]
VARIANTS: tuple[Variant, ...] = ("clean", "white12", "white6", "wander", "motion")


def _power(x: NDArray[np.float64], fs: float) -> float:
    """The ECG's power above its own baseline (0.5 Hz high-pass), which the SNR refers to."""
    sos = signal.butter(2, 0.5, btype="high", fs=fs, output="sos")
    return float(np.mean(signal.sosfiltfilt(sos, x) ** 2))


def noisy(uv: NDArray[np.float64], fs: float, variant: Variant, seed: int = 0) -> NDArray[np.float64]:
    """``uv`` with one kind of noise added; ``clean`` returns it unchanged."""
    if variant == "clean":
        return uv
    rng = np.random.default_rng(seed)
    n = len(uv)
    t = np.arange(n) / fs
    p = _power(uv, fs)
    if variant in ("white12", "white6"):
        snr_db = 12.0 if variant == "white12" else 6.0
        return uv + rng.normal(0.0, np.sqrt(p / 10 ** (snr_db / 10)), n)
    amp = np.sqrt(2 * p)  # about the QRS's height for a typical lead
    if variant == "wander":
        breathing = 0.5 * amp * np.sin(2 * np.pi * rng.uniform(0.15, 0.35) * t + rng.uniform(0, 2 * np.pi))
        drift = np.cumsum(rng.normal(0.0, 1.0, n))
        drift = signal.sosfiltfilt(signal.butter(2, 0.05, fs=fs, output="sos"), drift)
        return uv + breathing + amp * drift / (np.std(drift) or 1.0)
    # motion: every 20-60 s a burst of 1-4 s, 1-15 Hz, one to three times the QRS's height
    out = uv.copy()
    sos = signal.butter(2, (1.0, 15.0), btype="band", fs=fs, output="sos")
    at = rng.uniform(5.0, 30.0)
    while at < t[-1]:
        m = int(rng.uniform(1.0, 4.0) * fs)
        i = int(at * fs)
        burst = signal.sosfilt(sos, rng.normal(0.0, 1.0, m)) * np.hanning(m)
        burst *= rng.uniform(1.0, 3.0) * amp / (np.max(np.abs(burst)) or 1.0)
        out[i : i + m] += burst[: n - i]
        at += rng.uniform(20.0, 60.0)
    return out


def variants_named(spec: str | None) -> tuple[Variant, ...]:
    """``--variants V,…`` (all when not given); an unknown name is an input error."""
    asked = spec.split(",") if spec else list(VARIANTS)
    unknown = [v for v in asked if v not in VARIANTS]
    if unknown:
        raise InputError(f"--variants: unknown {', '.join(unknown)} (known: {', '.join(VARIANTS)})")
    return tuple(v for v in VARIANTS if v in asked)
