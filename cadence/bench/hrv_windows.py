"""`cadence bench hrv --windows`: the windows a decision trusts, scored against the annotated NN mean."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from cadence.bench.ecg_noise import Variant
from cadence.bench.hrv_scoring import WindowScore
from cadence.bench.pool import spawned_pool
from common.hrv.stream import RULES


def bench_hrv_windows(
    data_dir: str,
    fs: float = 130.0,
    variants: tuple[Variant, ...] = ("clean",),
    records: tuple[str, ...] = (),
    progress: Callable[[str], None] | None = None,
    peers: bool = True,
    jobs: int | None = None,
    gudb_dir: str | None = None,
) -> dict[str, dict[str, WindowScore]]:
    """Issue 19's table: per noise variant, how far the windows each pipeline marks good are from the
    annotated NN mean (``hrv_scoring``), for Cadence (its detector, cleaning and quality gate) and
    for NeuroKit2 (its default detector with its own artefact correction, Kubios' ``signal_fixpeaks``,
    and MeanNN over the corrected intervals of each window: it has no quality gate, so every window
    counts as good), in the same run. Noise is seeded by the record's name (``cadence.bench.ecg_noise``).

    With the clean variant, also ``cadence-rr``: the same cleaning and gate on a strap's own RR (``input =
    "rr"``), simulated as the H10 gives it: the annotated beats less every beat that is not normal (the
    strap leaves premature beats out, so one interval spans each). Records are scored in ``jobs``
    processes (default: one per core); the figures do not depend on it.

    With ``gudb_dir`` and the clean variant, also ``gudb-cs`` and ``gudb-cables``: healthy people's
    chest-strap beats as a strap's RR, against the strap's and the cables' annotated beats
    (``hrv_cv.gudb_unit``)."""
    from concurrent.futures import as_completed

    paths = sorted(p.with_suffix("") for p in Path(data_dir).glob("*.atr"))
    if records:
        paths = [p for p in paths if p.name in records]
    out: dict[str, dict[str, WindowScore]] = {v: {} for v in variants}  # in the order asked
    with spawned_pool(jobs, len(paths)) as pool:
        futures = {pool.submit(_score_record, str(p), fs, variants, peers): p.name for p in paths}
        for fut in as_completed(futures):
            if progress:
                progress(f"{futures[fut]} scored")
            for v, by_name in fut.result().items():
                for name, score in by_name.items():
                    out[v].setdefault(name, WindowScore(name)).merge(score)
    if gudb_dir and "clean" in variants and Path(gudb_dir).is_dir():
        from cadence.bench.hrv_cv import gudb_unit

        for subject in sorted(Path(gudb_dir).glob("subject_*")):
            for (_, name), score in gudb_unit(subject).score(RULES).items():
                out["clean"].setdefault(name, WindowScore(name)).merge(score)
        if progress:
            progress("GUDB scored")
    return {v: scores for v, scores in out.items() if scores}  # no records: nothing scored


def _score_record(
    path: str, fs: float, variants: tuple[Variant, ...], peers: bool
) -> dict[str, dict[str, WindowScore]]:
    """One record's windows in every variant, each pipeline's scored (a worker of bench_hrv_windows):
    Cadence's and the strap RR's as the cross-validation scores them (``hrv_cv.ecg_unit``), NeuroKit2's on
    the same noisy signal and windows."""
    from cadence.bench.hrv_cv import ecg_unit

    try:
        import neurokit2 as nk
    except ImportError:
        nk = None
    nk = nk if peers else None
    unit = ecg_unit(path, fs, variants)
    ours = unit.score(RULES)
    out: dict[str, dict[str, WindowScore]] = {}
    for series in unit.ecg:
        v, tr = series.variant, series.truths
        scores = out[v] = {"cadence": ours[(v, "cadence")]}
        if nk is not None:
            cleaned = nk.ecg_clean(series.signal, sampling_rate=fs)
            _, info = nk.ecg_peaks(cleaned, sampling_rate=fs, correct_artifacts=True)
            peaks = np.asarray(info["ECG_R_Peaks"], dtype=float) / fs
            rr, t_end = np.diff(peaks), peaks[1:]
            means = []
            for t in tr:
                sel = (t_end >= t.start_s) & (t_end < t.end_s)
                means.append(float(rr[sel].mean()) if sel.any() else None)
            scores["neurokit2"] = WindowScore("neurokit2")
            scores["neurokit2"].add(unit.name, tr, means, ["no beats"] * len(tr), series.sinus)
        if (v, "cadence-rr") in ours:
            scores["cadence-rr"] = ours[(v, "cadence-rr")]
    return out
