"""A study's plan (cadence/lab/design.py): the Williams design's balance, the registry on disk, a subject's
next session from the session files, and the yoked condition's k."""

from __future__ import annotations

import itertools
import re
from collections import Counter
from pathlib import Path

import pytest

from cadence.lab.design import load_plan, make_plan, next_session, williams, write_plan
from cadence.lab.session import SessionOptions, condition_parameters
from cadence.lab.session_file import Session, SessionWriter
from common.runtime.errors import InputError
from schemas import Calibration, Selection
from schemas.session import SessionEnd, SessionInfo
from tests.support.cell import CELL

T0 = 1_800_000_000_000_000_000
MIN = 60_000_000_000


@pytest.mark.parametrize("k", [2, 3, 4, 5])
def test_a_williams_design_balances_places_and_what_follows_what(k: int) -> None:
    seqs = williams(k)
    assert len(seqs) == (k if k % 2 == 0 else 2 * k)
    assert all(sorted(s) == list(range(k)) for s in seqs)
    for place in range(k):  # each condition equally often in each place
        assert set(Counter(s[place] for s in seqs).values()) == {len(seqs) // k}
    follows = Counter(pair for s in seqs for pair in itertools.pairwise(s))  # and right after each other
    assert set(follows) == {(a, b) for a in range(k) for b in range(k) if a != b}
    assert len(set(follows.values())) == 1


def test_a_plan_deals_balanced_blocks_keeps_the_yoked_control_last_and_reads_back(tmp_path: Path) -> None:
    plan = make_plan("pilot", 12, ["a", "b", "c", "y"], seed=3)
    assert [s.id for s in plan.subjects][:3] == ["S01", "S02", "S03"]
    assert all(s.order[-1] == "y" for s in plan.subjects)
    for block in (plan.subjects[:6], plan.subjects[6:]):  # any 6 in a row: each sequence once
        assert len({tuple(s.order) for s in block}) == 6
    assert make_plan("pilot", 12, ["a", "b", "c"], seed=3) != make_plan("pilot", 12, ["a", "b", "c"], seed=4)
    written = write_plan(plan, tmp_path / "study.toml")
    assert written == [tmp_path / "study.toml", tmp_path / "demographics.csv"]
    assert load_plan(tmp_path / "study.toml") == plan
    (tmp_path / "demographics.csv").write_text("id,age\nS01,34\n")  # filled in: never overwritten
    write_plan(plan, tmp_path / "again.toml")
    assert (tmp_path / "demographics.csv").read_text() == "id,age\nS01,34\n"
    with pytest.raises(InputError, match="subject 'S13' is not in study 'pilot' \\(S01 … S12\\)"):
        plan.subject("S13")
    (tmp_path / "bad.toml").write_text('name = "x"\n[[subjects]]\nid = "S01"\norder = ["a", "q"]\n')
    with pytest.raises(InputError, match=r"bad\.toml: not a study plan"):
        load_plan(tmp_path / "bad.toml")


def session_file(folder: Path, subject: str, condition: str, start_min: float, complete: bool = True,
                 study: str = "pilot") -> Path:  # fmt: skip
    path = folder / f"{subject}_{condition}_{start_min:g}.mcap"
    w = SessionWriter(path, CELL)
    cal = Calibration(t_ns=1, seq=0, subject=subject, rr_rest_s=0.85)
    w.begin(SessionInfo(subject=subject, condition=condition, cell=CELL, calibration=cal,  # type: ignore[arg-type]
                        start_ns=T0 + round(start_min * MIN), minutes=10, task="t.toml", task_sha256="0" * 64,
                        software="cadence", study=study))  # fmt: skip
    w.close(SessionEnd(end_ns=T0 + round((start_min + 10) * MIN), complete=complete))
    return path


def test_the_next_session_is_the_first_in_order_without_a_complete_file(tmp_path: Path) -> None:
    plan = make_plan("pilot", 6, ["a", "b", "c"])
    order = plan.subjects[0].order
    first = next_session(plan, tmp_path, "S01")
    assert first is not None
    assert (first.condition, first.period, first.training) == (order[0], 1, True)
    session_file(tmp_path, "S01", order[0], 0)
    session_file(tmp_path, "S01", order[1], 20, complete=False)  # cut short: run again
    session_file(tmp_path, "S02", order[1], 30)  # another subject's
    session_file(tmp_path, "S01", order[2], 40, study="other")  # another study's
    nxt = next_session(plan, tmp_path, "S01")
    assert nxt is not None
    assert (nxt.condition, nxt.period, nxt.training) == (order[1], 2, False)
    assert nxt.previous is not None
    assert nxt.previous.end.end_ns == T0 + 30 * MIN  # the cut-short one's end
    session_file(tmp_path, "S01", order[1], 50)
    session_file(tmp_path, "S01", order[2], 70)
    assert next_session(plan, tmp_path, "S01") is None


def test_the_yoked_k_is_cs_mean_k_over_its_data_time_and_is_asked_as_a_fixed_k() -> None:
    cal = Calibration(t_ns=1, seq=0, subject="S01", rr_rest_s=0.85)
    info = SessionInfo(subject="S01", condition="c", cell=CELL, calibration=cal, start_ns=T0, minutes=10,
                       task="t.toml", task_sha256="0" * 64, software="cadence")  # fmt: skip
    sels = [Selection(t_ns=T0 - MIN, seq=0, k=8, n=15, delta=0, reason="initial"),
            Selection(t_ns=T0 + 2 * MIN, seq=1, k=6, n=15, delta=-2, reason="stress"),
            Selection(t_ns=T0 + 7 * MIN, seq=2, k=9, n=15, delta=3, reason="rest")]  # fmt: skip
    s = Session(Path("c.mcap"), info, SessionEnd(end_ns=T0 + 10 * MIN, complete=True), selections=sels)
    assert s.mean_k == pytest.approx((8 * 2 + 6 * 5 + 9 * 3) / 10)  # 7.3: k = 7 for (y)


def test_each_condition_is_asked_of_the_decision_maker_as_it_holds_k(tmp_path: Path) -> None:
    def opts(condition: str, k: int | None = None) -> SessionOptions:
        return SessionOptions(subject="S01", condition=condition, minutes=1, out=tmp_path / "x.mcap",  # type: ignore[arg-type]
                              data_dir=tmp_path, task=tmp_path / "t.toml", yoked_k=k)  # fmt: skip

    assert condition_parameters(opts("a")) == "mode=fixed;k=a;by=session S01/a"
    assert condition_parameters(opts("c"), 5) == "mode=adaptive;by=session S01/c;calibration=5"
    assert condition_parameters(opts("y", 7)) == "mode=fixed;k=7;by=session S01/y"
    with pytest.raises(InputError, match="condition y holds the subject's mean k of \\(c\\)"):
        condition_parameters(opts("y"))


def test_an_undo_withdraws_the_experimenters_last_mark_and_counts_for_nothing() -> None:
    from cadence.lab.marks import counted
    from schemas import OperatorError

    def e(t: int, source: str, kind: str = "wrong_object") -> OperatorError:
        return OperatorError(t_ns=T0 + t, seq=t, kind=kind, source=source)  # type: ignore[arg-type]

    twin1, mark2, mark3, twin5 = e(1, "twin"), e(2, "experimenter"), e(3, "experimenter"), e(5, "twin")
    errors = [twin5, e(6, "experimenter", "undo"), twin1, mark3, e(4, "experimenter", "undo"), mark2]
    assert counted(errors) == [twin1, twin5]  # in data time: the undo at 4 takes 3, the one at 6 takes 2
    assert counted([e(0, "experimenter", "undo"), twin1]) == [twin1]  # nothing of theirs to withdraw


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ('name = "s"\nsubjects = []\n', "of length >= 1 - at `$.subjects`"),
        ('name = "s"\n[[subjects]]\nid = "S01"\norder = ["a", "b"]\n'
         '[[subjects]]\nid = "S01"\norder = ["b", "a"]\n', "subjects listed more than once: S01"),
        ('name = "s"\n[[subjects]]\nid = "S01"\norder = ["a", "a", "a"]\n', "a condition twice"),
        ('name = "s"\nsessions = "../elsewhere"\n[[subjects]]\nid = "S01"\norder = ["a"]\n',
         "a folder inside the plan's"),
        ('name = "s"\nsessions = "/tmp/x"\n[[subjects]]\nid = "S01"\norder = ["a"]\n', "a folder inside"),
    ],
)  # fmt: skip
def test_a_plan_that_could_not_be_run_as_written_is_refused_naming_why(
    tmp_path: Path, text: str, said: str
) -> None:
    """Accepted before: no subjects, a subject twice, conditions a,a,a, a sessions folder outside it
    (issue 40)."""
    path = tmp_path / "plan.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=f"{path}: not a study plan: .*{re.escape(said)}"):
        load_plan(path)


def test_a_plan_that_is_not_utf8_is_one_line_not_a_traceback(tmp_path: Path) -> None:
    path = tmp_path / "plan.toml"
    path.write_bytes(b'name = "s\xff"\n')
    with pytest.raises(InputError, match=r"not UTF-8 text \(byte 9\)"):
        load_plan(path)
