"""`cadence study` on a small simulated cohort: the conditions order as the paper's do, and the output says
it is simulated."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from cadence.study import Subject, motions, simulate
from common.trajectory.planner import boundary_stretch, interval_bounds
from common.trajectory.task import load_task
from tests.conftest import EXAMPLE_TASK


def test_study_orders_the_conditions_and_labels_them_simulated(tmp_path: Path) -> None:
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "cadence",
            "study",
            "--subjects",
            "4",
            "--minutes",
            "4",
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "SIMULATED" in r.stdout and "Wilcoxon" in r.stdout
    doc = json.loads((tmp_path / "study.json").read_text())
    assert doc["simulated"] is True and len(doc["per_subject"]) == 4 * 3
    m = {c: {k: v[0] for k, v in doc["means_sd"][c].items()} for c in "abc"}
    # (a) fastest and most stressful, (b) slowest and most relaxed, (c) in between on all three
    assert m["a"]["productivity_per_min"] > m["c"]["productivity_per_min"] > m["b"]["productivity_per_min"]
    assert m["a"]["mean_rr_norm"] < m["c"]["mean_rr_norm"] < m["b"]["mean_rr_norm"]
    assert m["a"]["error_rate"] >= m["c"]["error_rate"] >= m["b"]["error_rate"]
    for pair in ("a-b", "a-c", "b-c"):
        assert 0 < doc["wilcoxon"][pair]["productivity_per_min"]["p"] <= 1
    assert (tmp_path / "study.png").read_bytes()[:4] == b"\x89PNG"


def test_online_tuning_lowers_k_for_an_intolerant_subject_and_keeps_it_high_for_a_tolerant_one() -> None:
    task = load_task(EXAMPLE_TASK)
    # a cheap set for the test: N = 3 time scalings of one shape per path (slow, middle, fast)
    sols = {}
    for pid, path in task.paths.items():
        lb, _ = interval_bounds(path.waypoints, task.limits, task.planner.kappa)
        fast = lb * boundary_stretch(lb[None], path, task.limits, "exact")[0]
        sols[pid] = [fast * 2.0, fast * 1.4, fast]
    moves = motions(task, sols)
    n = {pid: 3 for pid in sols}
    intolerant = simulate(task, moves, n, Subject(1, 7, 0.85, 0.3), "c", 8)
    tolerant = simulate(task, moves, n, Subject(2, 7, 0.85, 3.0), "c", 8)
    assert np.mean(intolerant.ks[-6:]) < np.mean(tolerant.ks[-6:])
    assert tolerant.ks[-1] == 3  # never stressed: the rest rule takes it to the fastest
