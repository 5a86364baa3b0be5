"""The Empatica E4 export (common/hrv/e4.py) and decisions on real people (`cadence bench decide`): a
wrist's intervals become windows held for too few beats, a broken export is named by file and line, and
on whole sessions the personal mode slows the robot under stress where Alg. 1 barely moves."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from cadence.bench import decide as bd
from common.decision import Params, Personal
from common.hrv.e4 import MG_PER_UNIT, read_e4
from common.runtime.errors import InputError
from tests.support.cell import CELL
from tests.support.paths import SHARED_DATA

START = 1_644_226_061
STRESS_PREDICT = SHARED_DATA / "stress_predict"
GUDB = SHARED_DATA / "gudb"


def write_e4(folder: Path, rr_of: list[tuple[float, float]], gaps: tuple[tuple[float, float], ...] = (),
             acc: bool = True) -> Path:  # fmt: skip
    """An export whose heart beats at ``rr`` from each (time from the start, rr) on, with no interval read
    inside ``gaps`` (the wrist lost the pulse)."""
    folder.mkdir(parents=True, exist_ok=True)
    end = rr_of[-1][0] + 300.0
    t, rows, rng = 5.0, [f"{START}.000000, IBI"], np.random.default_rng(3)
    while t < end:
        rr = next(r for a, r in reversed(rr_of) if t >= a) + rng.normal(0, 0.01)
        t += rr
        if not any(a <= t < b for a, b in gaps):
            rows.append(f"{t:.6f},{rr:.6f}")
    (folder / "IBI.csv").write_text("\n".join(rows) + "\n")
    if acc:
        n = int(end * 32)
        xyz = np.column_stack([np.zeros(n), np.zeros(n), np.full(n, 64.0)])  # still, gravity along z
        lines = [f"{START}.0, {START}.0, {START}.0", "32.0, 32.0, 32.0"] + [
            f"{x:.0f},{y:.0f},{z:.0f}" for x, y, z in xyz
        ]
        (folder / "ACC.csv").write_text("\n".join(lines) + "\n")
    (folder / "tags_x.csv").write_text(f"{START + 100}\n")
    return folder


def test_an_export_is_read_with_its_gaps_and_units(tmp_path: Path) -> None:
    rec = read_e4(write_e4(tmp_path / "S01", [(0.0, 0.8)], gaps=((100.0, 160.0),)))
    assert rec.start_ns == START * 10**9
    assert rec.acc_hz == 32.0
    assert rec.tags_ns.tolist() == [(START + 100) * 10**9]
    assert abs(rec.acc_mg[0, 2] - 64 * MG_PER_UNIT) < 1e-9  # 1/64 g → mg: 1 g
    t = (rec.beat_ns - rec.start_ns) / 1e9
    assert not np.any((t >= 100) & (t < 160))
    assert abs(float(np.median(rec.ibi_s)) - 0.8) < 0.01


def test_a_window_with_too_few_intervals_is_held_for_coverage(tmp_path: Path) -> None:
    from common.hrv.e4 import e4_windows

    rec = read_e4(write_e4(tmp_path / "S01", [(0.0, 0.8)], gaps=((95.0, 118.0), (120.0, 150.0))))
    wins = {round((a - rec.start_ns) / 1e9): w for a, w in e4_windows(rec)}
    assert wins[60].quality == "good"
    assert abs(wins[60].mean_rr_s - 0.8) < 0.01  # type: ignore[operator]
    assert wins[90].quality == "low"
    assert wins[90].reason == "coverage"
    assert 0 < wins[90].n_beats < 10
    assert wins[120].quality == "none"
    assert wins[120].mean_rr_s is None


@pytest.mark.parametrize(
    ("file", "text", "words"),
    [
        ("IBI.csv", "yesterday, IBI\n1.0,0.8\n", "IBI.csv:1: expected the session's start"),
        ("IBI.csv", f"{START}, IBI\n1.0,0.8\n2.0,zero\n", "IBI.csv:3: expected numbers"),
        ("IBI.csv", f"{START}, IBI\n2.0,0.8\n1.0,0.8\n", "beat times must rise"),
        ("ACC.csv", f"{START},{START},{START}\n0.0,0.0,0.0\n", "ACC.csv:2: a rate of 0.0 Hz"),
        ("IBI.csv", b"\xff\xfe", "not text"),
    ],
)
def test_a_broken_export_is_named_by_file_and_line(
    tmp_path: Path, file: str, text: str | bytes, words: str
) -> None:
    folder = write_e4(tmp_path / "S01", [(0.0, 0.8)], acc=False)
    (folder / file).write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(InputError, match=words.replace("(", r"\(")):
        read_e4(folder)


def write_study(data: Path, blocks: list[tuple[str, float, float, float]]) -> None:
    """One subject through ``blocks``: (name, from s, to s, mean RR)."""
    write_e4(data / "S01", [(a, rr) for _, a, _, rr in blocks])
    rows = ["subject,block,start_unix_s,end_unix_s"] + [
        f"S01,{n},{START + a:.0f},{START + b:.0f}" for n, a, b, _ in blocks
    ]
    (data / "blocks.csv").write_text("\n".join(rows) + "\n")


SESSION = [("baseline", 0, 300, 0.80), ("stroop", 300, 600, 0.76), ("relax1", 600, 900, 0.80),
           ("interview", 900, 1200, 0.75), ("relax2", 1200, 1500, 0.80)]  # fmt: skip


def test_a_stress_drop_of_one_person_slows_the_personal_mode_where_alg_1_runs_fast(tmp_path: Path) -> None:
    """A 40–50 ms drop under stress: within one person clear, against the spread between people (σ_r
    0.14 s) small."""
    write_study(tmp_path, SESSION)
    (s,) = bd.stress_predict(tmp_path, movement=True)
    assert s.problem is None
    assert s.calibration is not None
    assert abs(s.calibration.rr_rest_s - 0.80) < 0.01
    paper, personal = (bd.score(s, bd.run(s, q)) for q in (None, Personal()))
    assert personal.lower_in_stress
    assert personal.order.balanced is not None and personal.order.balanced > 0.75
    k = personal.k_by_block
    assert k["stroop"] < k["relax1"] > k["interview"] < k["relax2"]
    # the play leaves k a step behind: back at the reference exactly, k stays one below k0, no further
    assert round(min(k["relax1"], k["relax2"])) >= Params.of(0.80).k0 - 1
    # Alg. 1 steps up on any rise (eq. 7) and saturates: the stressed person works near top speed
    assert paper.k_stress > Params.of(0.80).k0 + 3 > personal.k_stress + 3
    assert personal.held == 0  # a still wrist: nothing held for movement


def test_bench_decide_writes_its_figures_decisions_and_a_json_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from cadence.cli import main

    write_study(tmp_path / "data", SESSION)
    out = tmp_path / "figs"
    assert main(["bench", "decide", "--data", str(tmp_path / "data"), "--gudb", "", "--out", str(out)]) == 0
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(figures) == {"paper", "personal", "controls"}
    assert figures["personal"]["subjects"] == 1
    assert figures["personal"]["lower_in_stress"] == 1.0
    assert figures["personal"]["balanced_median"] > 0.75
    assert figures["controls"]["time"]["balanced_median"] == 0.5  # time alone, exactly
    assert figures["controls"]["mean RR"]["balanced_median"] > 0.9
    assert (out / "data_S01.png").read_bytes()[:4] == b"\x89PNG"
    rows = list(csv.DictReader((out / "decisions.csv").open()))
    assert {r["mode"] for r in rows} == {"paper", "personal"}
    assert len(rows) == 2 * 50  # 1,500 s of 30 s windows, two modes
    first = rows[0]
    assert (first["dataset"], first["subject"], first["window_start_s"], first["window_end_s"]) == (
        "data", "S01", "0.000", "30.000")  # fmt: skip
    assert {(r["block"], r["label"]) for r in rows} == {("baseline", "other"), ("stroop", "stress"),
        ("relax1", "calm"), ("interview", "stress"), ("relax2", "calm")}  # fmt: skip
    assert {r["held"] for r in rows} == {"0"}


def test_the_order_balanced_score_pairs_each_stressor_with_the_calm_blocks_around_it(tmp_path: Path) -> None:
    """Block order alone scores 0.5; a heart that answers the stressor scores 1 whichever way the session
    runs; a heart that only drifts down over the session scores 0.5, where the old AUC credited it."""
    write_study(tmp_path, SESSION)
    (s,) = bd.stress_predict(tmp_path, movement=False)
    assert bd.pairs(s) == [("after", "stroop", "relax1"), ("before", "interview", "relax1"),
                           ("after", "interview", "relax2")]  # fmt: skip
    t = bd.order(s, bd.CONTROLS["time"](s))
    assert (t.before, t.after, t.balanced) == (0.0, 1.0, 0.5)
    rr = bd.order(s, bd.CONTROLS["mean RR"](s))
    assert rr.balanced == 1.0
    rising = bd.order(s, [-float(i) for i in range(len(s.windows))])  # a heart that only speeds up
    assert rising.balanced == 0.5
    # a label column says what a block is where its name does not
    rows = (tmp_path / "blocks.csv").read_text().replace("end_unix_s", "end_unix_s,label").splitlines()
    rows = [rows[0]] + [r + (",calm" if ",baseline," in r else ",") for r in rows[1:]]
    (tmp_path / "blocks.csv").write_text("\n".join(rows) + "\n")
    (s,) = bd.stress_predict(tmp_path, movement=False)
    assert ("before", "stroop", "baseline") in bd.pairs(s)
    (tmp_path / "blocks.csv").write_text(rows[0] + "\n" + rows[1].rsplit(",", 1)[0] + ",tense\n")
    with pytest.raises(InputError, match=r"blocks.csv:2: the label 'tense' is none of calm, stress, other"):
        bd.stress_predict(tmp_path)


def test_a_bad_blocks_file_is_named_by_its_line(tmp_path: Path) -> None:
    write_study(tmp_path, SESSION)
    (tmp_path / "blocks.csv").write_text("subject,block,start_unix_s,end_unix_s\nS01,stroop,later,1\n")
    with pytest.raises(InputError, match=r"blocks.csv:2: expected subject, block"):
        bd.stress_predict(tmp_path)


@pytest.mark.skipif(
    not (STRESS_PREDICT.is_dir() and GUDB.is_dir()), reason="../shared/data/stress_predict or gudb absent"
)
def test_on_real_people_held_out_the_personal_mode_slows_under_stress_whichever_way_the_session_runs() -> (
    None
):
    """The issue's bar, held out (each subject scored with the settings chosen on the others, among those
    that keep a steady person steady): the order-balanced score's median ≥ 0.75 and above 0.5 for ≥ 85 %
    of subjects, the before-pairs alone a median ≥ 0.65, while time alone scores 0.5; the settings
    shipped are the ones chosen, and Alg. 1 scores below."""
    sessions = [
        s for s in bd.stress_predict(STRESS_PREDICT, movement=False) + bd.gudb(GUDB) if s.problem is None
    ]
    assert len(sessions) >= 25
    cv = bd.cross_validate(sessions)
    held = bd.summary(cv.held_out)
    assert held["balanced_median"] >= 0.75  # type: ignore[operator]
    assert held["balanced_above_half"] >= 0.85  # type: ignore[operator]
    assert held["before_median"] >= 0.65  # type: ignore[operator]
    time = bd.order_summary([bd.order(s, bd.CONTROLS["time"](s)) for s in sessions])
    assert time["balanced_median"] == 0.5
    assert time["balanced_above_half"] == 0.0
    assert cv.on_all == Personal()
    assert all(bd.steady(q) for q in cv.chosen)
    paper = bd.summary([bd.score(s, bd.run(s, None)) for s in sessions])
    assert paper["balanced_median"] < held["balanced_median"]  # type: ignore[operator]
    assert all(math.isfinite(x.order.score) for x in cv.held_out)


@pytest.mark.asyncio
async def test_a_wristbands_export_replays_through_the_gateway_into_windows(
    tmp_path: Path, endpoint: str
) -> None:
    """source = "e4": its intervals on ``ecg/rr``, a lost pulse flagged as a gap, read by the analyser with
    ``input = "rr"`` into windows over data time; the window over the gap is held, the others read 0.8 s."""
    import asyncio

    from common.runtime.bus import Bus, BusConfig
    from schemas import HrvWindow, RrIntervals
    from services.ecg_gateway.__main__ import Settings as GatewaySettings
    from services.ecg_gateway.__main__ import main as gateway_main
    from services.hrv_analyser.__main__ import Settings as AnalyserSettings
    from services.hrv_analyser.__main__ import main as analyser_main
    from tests.support.cell import InProcessService, now_ns

    folder = write_e4(tmp_path / "S01", [(0.0, 0.8)], gaps=((95.0, 150.0),), acc=False)
    start = now_ns() - 300 * 10**9  # replayed 40× faster than the clock: it ends by now
    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as bus:
        rr = aiter(bus.subscribe(bus.key("ecg/rr"), RrIntervals, maxsize=1000))
        wins = aiter(bus.subscribe(bus.key("hrv/window"), HrvWindow))
        analyser = InProcessService(
            "hrv_analyser", analyser_main, AnalyserSettings(input="rr"), tmp_path / "a", endpoint
        )
        await analyser.listening(bus, "ecg/rr")
        replay = GatewaySettings(source="e4", record=str(folder), speed=40.0, start_ns=start)
        gateway = InProcessService("ecg_gateway", gateway_main, replay, tmp_path / "g", endpoint)
        got: list[HrvWindow] = []
        gaps = 0
        async with asyncio.timeout(30):
            while len(got) < 7:
                _, w = await anext(wins)
                got.append(w)
            while True:  # the intervals up to well after the gap: one says the pulse was lost before it
                _, msg = await anext(rr)
                gaps += msg.gap
                if msg.t_ns > start + 200 * 10**9:
                    break
        for svc in (gateway, analyser):
            await svc.close()
    assert gaps == 1
    good = [w for w in got if w.quality == "good"]
    assert good
    assert all(abs(w.mean_rr_s - 0.8) < 0.01 for w in good)  # type: ignore[operator]
    over_gap = [w for w in got if w.start_ns < start + 150 * 10**9 and w.end_ns > start + 95 * 10**9]
    assert over_gap
    assert all(w.quality != "good" for w in over_gap)
