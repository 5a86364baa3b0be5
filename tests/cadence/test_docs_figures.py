"""The figures the guides quote are what the commands give (issue 56: a guide's table drifts from the
code that made it unless a test holds it). The simulated study's and the fit's tables are held by
tests/cadence/lab/test_study.py, `cadence decide`'s example by tests/cadence/test_readme.py; here the
decisions on real people (docs/decision.md): the order-balanced table, the counts quoted beside it, and the
scenarios."""

from __future__ import annotations

import csv
import itertools
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.paths import DOCS, PAGES, SHARED_DATA

DECISION = DOCS / "decision.md"


def row_of(text: str, name: str) -> list[str]:
    """A markdown table row's cells after its first, by the first cell; bold dropped."""
    (line,) = [ln for ln in text.splitlines() if ln.startswith(f"| {name} |")]
    return [c.strip().replace("**", "") for c in line.strip().strip("|").split("|")][1:]


def cells(d: dict, with_dk: bool) -> list[str]:
    """One mode's row as docs/decision.md writes it, from `cadence bench decide`'s JSON."""
    n = d["balanced_subjects"]
    out = [f"{d['balanced_median']:.3f}", f"{round(d['balanced_above_half'] * n)} of {n}",
           f"{d['before_median']:.3f}", f"{d['after_median']:.3f}"]  # fmt: skip
    if with_dk:
        lo, hi = d["dk_ci95"]
        out += [f"{d['dk_median']:+.1f} ({lo:.1f}–{hi:.1f})", f"{d['auc_median']:.3f}"]
    else:
        out += ["", ""]
    return out


def changes_and_reversals(ks: list[int]) -> tuple[int, int]:
    """Windows where k changed, and changes followed at once by one the other way."""
    d = [b - a for a, b in itertools.pairwise(ks)]
    return sum(1 for x in d if x), sum(1 for x, y in itertools.pairwise(d) if x * y < 0)


@pytest.mark.skipif(not (SHARED_DATA / "stress_predict").is_dir(), reason=f"{SHARED_DATA} is absent")
def test_the_decision_guides_table_and_counts_are_what_bench_decide_gives(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "cadence", "bench", "decide", "--cv", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout.strip().splitlines()[-1])
    text = DECISION.read_text()
    rows = {
        "paper (Alg. 1, condition (c))": cells(doc["paper"], True),
        "personal, held out (leave one subject out)": cells(doc["personal, held out"], True),
        "(control: the window's mean RR)": cells(doc["controls"]["mean RR"], False),
        "(control: time alone)": cells(doc["controls"]["time"], False),
        "(control: RMSSD)": cells(doc["controls"]["RMSSD"], False),
    }
    for name, want in rows.items():
        assert row_of(text, name) == want, name

    by_mode: dict[str, list[dict]] = {}
    for row in csv.DictReader((tmp_path / "decisions.csv").open()):
        by_mode.setdefault(row["mode"], []).append(row)

    def counts(mode: str) -> tuple[int, int, int, int]:
        rows = by_mode[mode]
        changed = reversed_ = 0
        for _, g in itertools.groupby(rows, key=lambda w: (w["dataset"], w["subject"])):
            c, r = changes_and_reversals([int(w["k"]) for w in g])
            changed, reversed_ = changed + c, reversed_ + r
        return len(rows), sum(1 for w in rows if w["k"] == "15"), changed, reversed_

    n, top, changed, reversed_ = counts("paper")
    said = " ".join(text.split())
    assert f"k = 15 in {round(100 * top / n)} % of the {n:,} windows ({top:,}), changes k in {changed} and " \
           f"reverses a change at once in {reversed_}" in said  # fmt: skip
    assert f"on the real sessions {counts('personal')[3]} immediate reversals in {n:,} windows" in said
    # the balanced score of the chosen settings: what the prose and the table say
    assert re.search(rf"\*\*{doc['personal, held out']['balanced_median']:.3f}\*\*", text)


def test_the_scenarios_table_is_what_bench_decide_scenarios_gives() -> None:
    """The same rows as `cadence bench decide --scenarios` prints, one a scenario, as written."""
    from cadence.bench.scenarios import table

    text = DECISION.read_text()
    for row in table():
        line = "| " + " | ".join(row) + " |"
        assert line in text, f"docs/decision.md, the scenarios: expected the row\n{line}"


def test_the_personal_modes_examples_are_what_cadence_decide_gives() -> None:
    """docs/decision.md: "120 windows at 0.79 s give k 4–5 in every window; 960 of 0.85 s with 20 ms
    Gaussian noise (numpy seed 54, to 0.1 ms) change k in 83 (8.6 %), median 8", as `cadence decide`
    prints them."""
    import numpy as np

    def decide(values: list[float]) -> list[int]:
        cmd = ["decide", "--mode", "personal", "--rr-rest", "0.85"]
        r = subprocess.run([sys.executable, "-m", "cadence", *cmd],
                           input="\n".join(f"{v:.4f}" for v in values), capture_output=True, text=True,
                           timeout=120)  # fmt: skip
        assert r.returncode == 0, r.stderr
        return [int(x) for x in r.stdout.split()]

    low = decide([0.79] * 120)
    noisy = decide(list(0.85 + np.random.default_rng(54).normal(0.0, 0.020, 960)))
    changed, _ = changes_and_reversals(noisy)
    said = " ".join(DECISION.read_text().split())
    assert f"120 windows at 0.79 s give k {min(low)}–{max(low)} in every window" in said
    share = f"{100 * changed / len(noisy):.1f} %"
    assert f"change k in {changed} ({share}), median {int(np.median(noisy))}" in said


def test_the_ssm_table_is_what_the_executor_computes_for_the_shipped_sets() -> None:
    """docs/robot.md's S_p table: for each robot, listed path and k of the example task's shipped sets, T_s
    and the stop that bounds it, the top speed of arm and tool, S_p at rest and at full speed, as the
    executor computes them with its default settings for that backend (the sim: T_r 0.55 s; a UR16e:
    0.65 s, its stops the stated model), the default tool, a sensor that sees the body (C 0.85 m)."""
    import re

    import numpy as np

    from common.runtime.resources import EXAMPLE_TASK, SHIPPED_SETS
    from common.safety.separation import Figures, Ssm
    from common.trajectory.scaling import Curve
    from common.trajectory.shipped import read_shipped
    from common.trajectory.task import load_task
    from services.executor.settings import Settings

    task = load_task(EXAMPLE_TASK)
    sets = {p.path_id: p for p in read_shipped(SHIPPED_SETS / "box_filling.json").sets}
    text = (DOCS / "robot.md").read_text()
    cell = r" ([0-9.]+) (?:s|m/s|m) \|"
    row = rf"^\s*\| (sim|UR16e) \| (\w+) \| (\d+) \|{cell} ([^|]+) \|{cell}{cell}{cell}"
    rows = re.findall(row, text, flags=re.MULTILINE)
    assert len(rows) == 10, rows
    backends = {"sim": Settings(), "UR16e": Settings(backend="ur_rtde")}
    reactions = {name: sum(s.reaction_parts(0.05).values()) for name, s in backends.items()}
    assert reactions == {"sim": pytest.approx(0.55), "UR16e": pytest.approx(0.65)}
    for robot, path_id, k, *shown in rows:
        s = backends[robot]
        h = np.array(sets[path_id].solutions[int(k) - 1].h)
        figures = Figures.of(Curve.of(h, task.paths[path_id]), task.limits, arm=s.arm())
        ssm = figures.ssm(Ssm(s.human_speed_m_s, reactions[robot], s.stop_time_s, 0.85, s.uncertainty_m))
        full = ssm.protective_distance(figures.speed_m_s)
        got = [f"{ssm.stop_time_s:.3f}", figures.stop_by, f"{figures.speed_m_s:.2f}",
               f"{ssm.protective_distance(0.0):.2f}", f"{full:.2f}"]  # fmt: skip
        assert got == [x.strip() for x in shown], (robot, path_id, k, got, shown)


SECONDS = {"h": 3600.0, "min": 60.0, "s": 1.0, "ms": 1e-3, "µs": 1e-6}
# a setting quoted with its value: `name` (V …, `name` (`[section]`, V …, `name`, V …, `name` = V …
QUOTED = re.compile(
    r"`(\w+)`(?: \((?:`\[[\w.]+\]`, )?|, | = )(-?[0-9][0-9,]*(?:\.[0-9]+)?)(?: ?(h|min|ms|µs|s)\b)?"
)


def setting_defaults() -> dict[str, set[float]]:
    """Every numeric setting's default, by name, over every service's section (nested ones included: the
    twin's) and ``[cadence]``; a name two sections share has both."""
    import msgspec

    from common.runtime.config import CommonSettings
    from services.registry import SERVICES

    out: dict[str, set[float]] = {}

    def walk(cls: type) -> None:
        for f in msgspec.structs.fields(cls):
            if isinstance(f.default, msgspec.Struct):
                walk(type(f.default))
            elif isinstance(f.default, int | float) and not isinstance(f.default, bool):
                out.setdefault(f.name, set()).add(float(f.default))

    for s in SERVICES:
        if hasattr(s.module(), "Settings"):
            walk(s.settings())
    walk(CommonSettings)
    return out


def test_every_setting_a_guide_quotes_with_its_value_is_its_default() -> None:
    """A guide that says "`separation_max_age_s` (0.3 s)" says what a cell gets when its config is
    silent: every such quote in every page, in the setting's own unit (2 h for 7200 s)."""
    defaults = setting_defaults()
    quoted = []
    for page in PAGES:
        for m in QUOTED.finditer(page.read_text()):
            name, value, unit = m.group(1), float(m.group(2).replace(",", "")), m.group(3)
            if name not in defaults:
                continue
            if unit and name.endswith("_s"):
                value *= SECONDS[unit]
            quoted.append(name)
            assert any(abs(value - d) < 1e-9 for d in defaults[name]), (
                f"{page.name}: {m.group(0)!r}, {defaults[name]}"
            )
    assert {"separation_max_age_s", "clock_skew_s", "human_speed_m_s", "personal_ref_tau_s"} <= set(quoted)


def test_the_robot_guides_geometry_and_reaction_time_are_the_codes() -> None:
    """docs/robot.md's ISO 13855 C, the default tool, the links' radii, the wrist speeds and T_r."""
    from common.safety.geometry import LINK_RADII_M, intrusion_iso13855
    from services.executor.settings import DEFAULT_TOOL, Settings
    from tests.support.arm import wrist_speeds

    said = " ".join((DOCS / "robot.md").read_text().split())
    c = {h: intrusion_iso13855("legs", None, h) for h in (0.0, 0.3)}
    assert f"8 (d − 14) mm, at least 0: {intrusion_iso13855('hand', 30.0):.3f} m at d = 30 mm" in said
    assert f"{c[0.0]:.1f} m at the floor, {c[0.3]:.2f} m at 0.3 m" in said
    assert f"| `arm` (40 < d ≤ 70 mm) | {1000 * intrusion_iso13855('arm', 60.0):.0f} mm |" in said
    assert f"adds {c[0.0] - intrusion_iso13855('body'):.2f} m to each" in said
    x, y, z, r = DEFAULT_TOOL
    assert (x, y) == (0.0, 0.0) and f"one of {r:.2f} m at {z:.2f} m" in said
    upper, fore, wrist = LINK_RADII_M[1], LINK_RADII_M[2], LINK_RADII_M[3:]
    assert f": {upper:.2f} m; the forearm {fore:.2f} m; the wrists {wrist.max():.3f} m)" in said
    assert wrist.min() == wrist.max()
    w = wrist_speeds()
    spin = (
        f"reads {w['spin_flange']:.2f} m/s on the bare arm (the wrist's housing) and {w['spin_tip']:.2f} m/s"
    )
    turn = f"a wrist-1 turn {w['turn_flange']:.2f} m/s on the bare arm and {w['turn_tip']:.2f} m/s at the tip"
    assert spin in said and f"{turn} of a 0.2 m tool" in said
    skew = setting_defaults()["clock_skew_s"].pop()
    sim = sum(Settings().reaction_parts(skew).values())
    real = sum(Settings(backend="ur_rtde").reaction_parts(skew).values())
    assert f"{sim:.2f} s on the sim, {real:.2f} s on a UR16e, by default" in said
