"""Benchmark of R-peak detection at 130 Hz on the shared annotated records, against established
detectors in the same run (NeuroKit2, py-ecg-detectors). Prints every figure; asserts only quality."""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import subprocess
import sys

import pytest

from cadence.bench.hrv_peaks import bench_hrv
from tests.support.data import ECG, needs_data
from tests.support.paths import BENCH_QUICK, DOCS

pytestmark = pytest.mark.bench
# the detection table's rows in docs/decision.md, by the detector's name in `bench_hrv`'s scores
SHOWN = {
    "Cadence (streaming, 0.1 s chunks)": "cadence",
    "NeuroKit2 `neurokit` (batch)": "neurokit2:neurokit",
    "NeuroKit2 `pantompkins1985`": "neurokit2:pantompkins1985",
    "py-ecg-detectors `swt`": "py-ecg-detectors:swt",
    "py-ecg-detectors `pan_tompkins`": "py-ecg-detectors:pan_tompkins",
}


@needs_data
def test_bench_hrv_against_established_detectors() -> None:
    scores, extra = bench_hrv(str(ECG), only=("100",) if BENCH_QUICK else None)  # quick: one record
    for s in sorted(scores, key=lambda x: -x.f1):
        print(f"{s.name:40s} Se {s.se:.4f} PPV {s.ppv:.4f} F1 {s.f1:.4f} {s.realtime:8.0f}x real time")
    print(extra)
    ours = next(s for s in scores if s.name == "cadence")
    others = [s for s in scores if s.name != "cadence"]
    if not others:
        pytest.skip("no established detector installed (uv sync --extra bench)")
    assert ours.f1 >= 0.99
    assert extra["window_err_median_ms"] <= 2.0
    if not BENCH_QUICK:  # every record: the detection table of docs/decision.md, but its speeds (a host's)
        text = (DOCS / "decision.md").read_text()
        by = {s.name: s for s in scores}
        for shown, name in SHOWN.items():
            s = by[name]
            row = f"| {shown} | {100 * s.se:.2f} | {100 * s.ppv:.2f} | {100 * s.f1:.2f} |"
            assert row in text, f"docs/decision.md, the detection table: expected the row to begin\n{row}"


@needs_data
@pytest.mark.skipif(BENCH_QUICK, reason="quick: tests/common/hrv/test_hrv.py scores every record's windows")
def test_bench_hrv_windows_prints_cadence_and_neurokit2_per_noise_variant() -> None:
    """The window scorer's CLI on one noisy record (the whole set is `cadence bench hrv --windows`)."""
    figures, _ = bench_hrv_json("--windows", "--data", str(ECG), "--records", "105", "--variants",
                                "clean,white6,motion", timeout=600)  # fmt: skip
    assert set(figures) == {"clean", "white6", "motion"}
    for by_pipeline in figures.values():
        ours = by_pipeline["cadence"]
        # the held share is judged on the whole set (tests/common/hrv/test_hrv.py): 105, the noisiest
        # record, alone holds 30-35 % of its windows once noise is added to it
        assert ours["p95_ms"] <= 5.0
        assert ours["over_20_ms"] == 0
        if "neurokit2" in by_pipeline:  # the same windows scored for both (it holds none)
            peer = by_pipeline["neurokit2"]
            assert peer["good"] == ours["good"] + ours["held"]
            assert peer["held"] == 0
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "cadence",
            "bench",
            "hrv",
            "--windows",
            "--variants",
            "pink",
            "--data",
            str(ECG),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2
    assert "unknown pink" in bad.stderr


# docs/decision.md's names of `bench hrv --windows`'s variants and pipelines
VARIANTS = {"clean": "clean", "white12": "white 12 dB", "white6": "white 6 dB", "wander": "wander",
            "motion": "motion"}  # fmt: skip
PIPELINES = {"cadence": "Cadence", "neurokit2": "NeuroKit2", "cadence-rr": "Cadence on device RR",
             "gudb-cs": "GUDB strap beats, as RR", "gudb-cables": "GUDB cables beats, as RR"}  # fmt: skip
RHYTHMS = ("(N", "(AFIB", "(B", "(NOD", "(T")  # the per-rhythm table's columns, in its order


def window_row(variant: str, pipeline: str, f: dict) -> str:
    """One row of docs/decision.md's windows tables, as the guide writes it from the figures' JSON."""
    worst = f"{f['worst_ms']} ms" + (f" ({f['worst_records']})" if f["worst_records"] else "")
    return (f"| {VARIANTS[variant]} | {PIPELINES[pipeline]} | {f['good']} ({f['held']}) | "
            f"{100 * f['held_share_sinus']:.1f} % | {f['p95_ms']:.2f} ms | {f['over_10_ms']} | "
            f"{f['over_20_ms']} | {worst} |")  # fmt: skip


def table_rows(text: str, after: str) -> list[str]:
    """The rows of the first markdown table after the line that begins ``after``, header left out."""
    lines = text.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith(after))
    first = next(i for i in range(start, len(lines)) if lines[i].startswith("|"))
    rows = list(itertools.takewhile(lambda ln: ln.startswith("|"), lines[first:]))
    return rows[2:]


def bench_hrv_json(*args: str, timeout: float = 1800) -> tuple[dict, str]:
    """`cadence bench hrv`'s figures (its last line) and what it printed."""
    cmd = [sys.executable, "-m", "cadence", "bench", "hrv", *args]
    wide = {**os.environ, "COLUMNS": "300"}  # the fold lines whole
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=wide)
    assert r.returncode == 0, r.stderr
    print("\n" + r.stdout)
    return json.loads(r.stdout.strip().splitlines()[-1]), r.stdout


def window_rows(figures: dict, neurokit2: bool) -> list[str]:
    return [window_row(v, p, f) for v, by in figures.items() if v in VARIANTS for p, f in by.items()
            if p != "neurokit2" or (v == "clean" and neurokit2)]  # fmt: skip


@needs_data
@pytest.mark.skipif(BENCH_QUICK, reason="quick: every record in every variant takes a minute or two")
def test_the_decision_guides_window_tables_are_what_bench_hrv_windows_gives() -> None:
    """docs/decision.md's windows table (NeuroKit2 in full for the clean records, as a range for the
    noisy ones) and its per-rhythm table: every figure is the analyser's on the shared records, the same
    on any machine (the cleaning branches on no last bit: tests/cadence/test_other_machines.py)."""
    figures, _ = bench_hrv_json("--windows")
    text = (DOCS / "decision.md").read_text()
    shown = table_rows(text, "rhythm). On the 10 shared records at 130 Hz")
    nk = "neurokit2" in figures["clean"]
    assert shown == window_rows(figures, nk), "docs/decision.md, the windows table"
    if nk:
        peers = [by["neurokit2"] for by in figures.values()]
        p95 = [f["p95_ms"] for f in peers]
        over = [f["over_20_ms"] for f in peers]
        lo, hi = math.floor(min(p95)), math.ceil(max(p95))
        assert f"(NeuroKit2: p95 {lo}–{hi} ms and {min(over)}–{max(over)} windows over 20 ms in every" in text
    per_rhythm = table_rows(text, "is read as if it were sinus")
    clean = {p: f["by_rhythm"] for p, f in figures["clean"].items() if p in ("cadence", "cadence-rr")}
    expected = [
        f"| {PIPELINES[p]} | " + " | ".join(" / ".join(map(str, by[r].values())) for r in RHYTHMS) + " |"
        for p, by in clean.items()
    ]
    assert per_rhythm == expected, "docs/decision.md, the scored windows per rhythm"
    assert all(set(by) <= set(RHYTHMS) for by in clean.values()), "a rhythm the table has no column for"


@needs_data
@pytest.mark.skipif(BENCH_QUICK, reason="quick: the cross-validation takes minutes")
def test_the_decision_guides_held_out_table_and_choice_are_what_bench_hrv_cv_gives() -> None:
    """docs/decision.md's held-out table, and how many folds chose the thresholds Cadence ships."""
    figures, printed = bench_hrv_json("--cv")
    text = (DOCS / "decision.md").read_text()
    held_out = table_rows(text, "normal rhythm 1, of an arrhythmia 0.1.")
    assert held_out == window_rows(figures["held_out"], False), "docs/decision.md, the held-out table"
    assert figures["chosen"] == figures["shipped"], "chosen on all units, not what Cadence ships"
    folds = re.search(r"chosen in (\d+) of (\d+) folds: " + re.escape(figures["shipped"]), printed)
    assert folds, "no fold chose the shipped thresholds"
    said = " ".join(text.split())
    assert f"{folds[1]} of the {folds[2]} folds chose the shipped thresholds" in said
