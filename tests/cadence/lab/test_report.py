"""`cadence report` on an MCAP recording: the paper's metrics and the figures."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from cadence.tools.recording import Recorder
from common.trajectory.planner import content_hash
from common.trajectory.task import parse_task
from schemas import CycleReport, RobotEvent, Selection
from schemas.topology import encode
from services.pareto_store.jobs import plan_job
from tests.support.cell import CELL
from tests.support.executor import TASK
from tests.support.sessions import write_run

T0 = 1_800_000_000_000_000_000


def test_report_of_a_recording_gives_phi_epsilon_and_the_figures(tmp_path: Path) -> None:
    path = write_run(tmp_path)
    out = tmp_path / "report"
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "report", str(path), "--out", str(out)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    page = (out / "index.html").read_text()
    # 3 cycles in 120 s of data time: φ = 1.5 per minute; 1 error in 3 cycles: ε = 0.333
    assert re.search(r"φ, production rate</th><td>1\.50 cycles/min", page)
    assert re.search(r"ε, error rate</th><td>0\.333 errors/cycle", page)
    assert "5 → 3 → 4 → 5" in page and "&lt;overrun&gt;" in page  # event text escaped
    for fig in ("rr_k.png", "pareto.png", "cycles.png"):
        assert (out / fig).read_bytes()[:4] == b"\x89PNG"
        assert f'src="{fig}"' in page
    assert page.count("<figcaption>") == 3
    assert "commanded" in page
    assert "radians" in page
    assert "errors as orange ticks" in page
    for f in out.iterdir():  # what people open is readable by everyone (state files stay private)
        assert f.stat().st_mode & 0o777 == 0o644, f


def test_a_missing_sets_folder_is_one_line_naming_it(tmp_path: Path) -> None:
    """`--sets DIR` with no DIR said "pass --sets" as if none had been passed (issue 28)."""
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "report", str(write_run(tmp_path)),
         "--sets", str(tmp_path / "nope"), "--out", str(tmp_path / "report")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert "--sets" in r.stderr, r.stderr
    assert "nope: no such folder" in r.stderr, r.stderr


def test_the_operators_errors_are_marked_on_the_rr_figure(tmp_path: Path) -> None:
    from cadence.lab.plots import rr_k_figure
    from cadence.lab.report import from_mcap

    run = from_mcap(write_run(tmp_path))
    assert run.errors == 1
    assert run.error_times_s == [50.0]  # data time from the run's first message
    args = (run.windows, run.selections, 0.9, "RR_r", [c["end_s"] for c in run.cycles])
    assert rr_k_figure(*args, run.error_times_s) != rr_k_figure(*args, [])


def test_the_spans_the_robot_did_not_work_are_found_from_its_state_changes() -> None:
    """rr_k.png shades them, so that no figure shows adaptation that did not move the arm (issue 28): a
    protective stop until the resume brought it back to work, and a wait for a selection still open at
    the end of the run."""
    from common.safety.states import idle_spans

    def change(t_s: float, a: str, b: str, why: str) -> dict:
        return {"t_s": t_s, "kind": "state", "message": f"{a} → {b}: {why}", "from": a, "to": b}

    events = [
        {"t_s": 50.0, "kind": "overrun", "message": "5 servo overruns in a row"},
        change(51.0, "moving", "stopped", "5 servo overruns in a row"),
        change(80.0, "stopped", "recovering", "resumed by the operator"),
        change(84.0, "recovering", "ready", "back at the path's start"),
        change(90.0, "ready", "moving", "path there"),
        change(200.0, "ready", "waiting_for_selection", "no selection yet"),
    ]
    assert idle_spans(events, 300.0) == [(51.0, 84.0, "stopped"), (200.0, 300.0, "waiting_for_selection")]
    assert idle_spans(events[:1], 300.0) == []  # no state change: the robot worked throughout


def test_a_fronts_title_gives_its_paths_durations_not_f_time() -> None:
    """pareto.png said "f_time 7.60–22.50 s" for a path whose t_f is 1.27–3.75 s (f_time = D·Σh)."""
    from cadence.lab.plots import front_title

    task = parse_task(TASK, "shuttle.toml")
    p = task.paths["there"]
    s = plan_job(p, task, task.planner, content_hash(p, task.limits, task.planner))
    t_f = sorted(x.t_f for x in s.solutions)
    assert front_title("there", s) == f"there: t_f {t_f[0]:.2f}–{t_f[-1]:.2f} s"
    assert max(x.f_time for x in s.solutions) > 5 * t_f[-1]  # what the title said before


def test_a_recording_joined_mid_run_spans_its_streams_not_a_republished_selections_stamp(
    tmp_path: Path,
) -> None:
    """φ once came over 500 s where the streams span 240 s: the first message was the decision maker's
    republished selection, stamped when it was decided, long before the recording began."""
    from cadence.lab.report import from_mcap

    path = tmp_path / "joined.mcap"
    rec = Recorder(path)
    key = f"cadence/{CELL}/"
    old = Selection(t_ns=T0 - 260 * 10**9, seq=9, k=1, n=15, delta=0, reason="hold", window_end_ns=1)
    rec.write(key + "decision/selection", encode(old))  # republished: decided 260 s before
    for c in range(2):
        report = CycleReport(t_ns=T0 + (c + 1) * 120 * 10**9, seq=c, cycle=c, cycle_time_s=120.0,
                             k_per_path={"there": 1, "back": 1})  # fmt: skip
        rec.write(key + "robot/cycle", encode(report))
    rec.write(key + "robot/event", encode(RobotEvent(t_ns=T0, seq=0, kind="info", message="joined")))
    rec.close()
    run = from_mcap(path)
    assert run.duration_s == 240.0
    assert run.productivity_per_min == 0.5


def test_the_rr_figure_of_a_recording_draws_the_thresholds_its_selections_carry(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without --rr-rest the figure took the highest window for RR_r, though every recorded selection
    carries the thresholds it was decided against."""
    import cadence.lab.plots as plots
    from cadence.lab.report import from_mcap, write_report
    from cadence.tools.recording import Recorder
    from schemas import HrvWindow, Selection
    from schemas.topology import encode

    path = tmp_path / "run.mcap"
    rec, key = Recorder(path), "cadence/cell1/"
    for i, (rr, rest) in enumerate([(0.80, 0.95), (0.78, 0.90)]):  # a calibration changed mid-run: the last
        end = T0 + (i + 1) * 30 * 10**9
        rec.write(key + "hrv/window", encode(HrvWindow(t_ns=end, seq=i, start_ns=end - 30 * 10**9, end_ns=end,
                  mean_rr_s=rr, n_beats=35, excluded_fraction=0.0, quality="good")))  # fmt: skip
        sel = Selection(t_ns=end, seq=i, k=5, n=15, delta=0, reason="hold", window_end_ns=end, rr_rest_s=rest,
                        rr_stress_s=rest - 0.1, rr_stress_max_s=rest - 0.2)  # fmt: skip
        rec.write(key + "decision/selection", encode(sel))
    rec.close()
    drawn: dict[str, object] = {}

    def figure(*args: object) -> bytes:
        names = ("windows", "selections", "rest", "label", "ends", "errors", "idle", "s", "smax")
        drawn.update(zip(names, args, strict=False))
        return b"\x89PNG"

    monkeypatch.setattr(plots, "rr_k_figure", figure)
    write_report(from_mcap(path), tmp_path / "report")
    assert drawn["rest"] == 0.90
    assert drawn["s"] == pytest.approx(0.80)
    assert drawn["smax"] == pytest.approx(0.70)
    assert "recorded" in str(drawn["label"])
    write_report(from_mcap(path), tmp_path / "report", rr_rest_s=0.85)  # a given RR_r wins, defaults about it
    assert (drawn["rest"], drawn["s"], drawn["smax"]) == (0.85, None, None)


def test_the_legends_name_only_what_is_drawn() -> None:
    """A legend entry for a span that is not there (issue 56: rr_k.png and separation.png named "robot
    stopped or waiting" for spans of no length) tells the reader to look for what they cannot find."""
    import matplotlib.pyplot as plt

    from cadence.lab.plots import rr_k_axes, separation_axes

    def labels(fig: plt.Figure) -> set[str]:
        out = {t.get_text() for ax in fig.axes if (leg := ax.get_legend()) for t in leg.get_texts()}
        plt.close(fig)
        return out

    windows = [{"end_s": 30.0 * i, "mean_rr_s": 0.8, "quality": "good"} for i in range(1, 6)]
    selections = [{"t_s": 30.0, "k": 5, "reason": "initial", "n": 15}]
    rows = [{"t_s": float(t), "separation_m": 3.0, "scale": 1.0} for t in range(0, 150, 10)]
    empty = [(60.0, 60.0, "waiting")]  # a wait that took no time
    spans = [(60.0, 75.0, "waiting")]
    assert "robot stopped or waiting" not in labels(rr_k_axes(windows, selections, 0.85, idle=empty))
    assert "robot stopped or waiting" in labels(rr_k_axes(windows, selections, 0.85, idle=spans))
    assert "robot not working" not in labels(separation_axes(rows, empty))
    assert "robot not working" in labels(separation_axes(rows, spans))
    held = labels(
        rr_k_axes(windows, [*selections, {"t_s": 90.0, "k": 5, "reason": "movement", "n": 15}], 0.85)
    )
    assert "held: moving (not read as stress)" in held
    assert "held: moving (not read as stress)" not in labels(rr_k_axes(windows, selections, 0.85))


def test_the_figure_says_why_the_analyser_held_its_windows() -> None:
    """Issue 55: a window held for a jump in rate keeps k, and the figure says why, beside the other
    reasons and how often; a run recorded before windows carried a reason says only "low quality"."""
    import matplotlib.pyplot as plt

    from cadence.lab.plots import rr_k_axes

    def labels(windows: list[dict]) -> set[str]:
        fig = rr_k_axes(windows, [{"t_s": 30.0, "k": 5, "reason": "initial", "n": 15}], 0.85)
        out = {t.get_text() for ax in fig.axes if (leg := ax.get_legend()) for t in leg.get_texts()}
        plt.close(fig)
        return out

    good = [{"end_s": 30.0, "mean_rr_s": 0.8, "quality": "good", "reason": None}]
    held = [{"end_s": 30.0 * i, "mean_rr_s": 0.5, "quality": "low", "reason": why}
            for i, why in enumerate(["rhythm", "rhythm", "noise"], start=2)]  # fmt: skip
    assert "mean RR, held: rhythm 2, noise 1" in labels(good + held)
    old = [{k: v for k, v in w.items() if k != "reason"} for w in good + held]
    assert "mean RR (low quality)" in labels(old)
