"""Decisions on real people (`cadence bench decide`; docs/decision.md): whole sessions of
people under stress, run window by window through the decision maker's own code (its ``Decider``:
movement hold, holds, bounds, the mode in force), and scored per decision mode.

- Stress-Predict (``shared/data/stress_predict``): an Empatica E4 wristband through a baseline, a Stroop
  test, an interview, hyperventilation and relax blocks (``blocks.csv``). Calibrated on the baseline
  block as `cadence calibrate` would (refused where it would refuse); the relax blocks are the calm,
  the Stroop test and the interview the stress; hyperventilation, a change of breathing rather than of
  mental load, is reported apart.
- GUDB (``shared/data/gudb``): two minutes seated, then two minutes of a maths test, from a chest
  strap's beats. Calibrated on the seated minutes, which are the calm; the maths test is the stress.

A good decision slows the robot under stress: k in the stress blocks below k in the calm ones. In
Stress-Predict every relax block follows a stressor, so a score over all calm and all stress windows
credits block order: k = the window's index, ignoring the heart, scored as well as the personal mode.
So the score is order-balanced (``Order``): each stress block against the calm block just before it and
the one just after it, each a within-subject AUC (calm above stress; a tie counts half); a subject's score
is the mean of its before-pairs' mean and its after-pairs' mean, so time alone scores exactly 0.5.
Controls are scored from the same windows (``CONTROLS``): the raw window mean RR (what the signal
allows), the window's index (time alone) and the RMSSD. ``cross_validate`` chooses the personal mode's
settings leaving one subject out, among those that keep a steady person steady (``steady``), and scores
each subject with the settings chosen on the others.
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import math
import tempfile
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np

from common.decision import Params, Personal, PersonalState, personal_step
from common.hrv.calibration import calibration
from common.hrv.e4 import E4, e4_windows, read_e4
from common.hrv.movement import Movement
from common.hrv.stream import window_message
from common.runtime.errors import InputError
from schemas import Calibration, HrvWindow
from services.decision_maker import Decider, MovementRule

N = 15  # the paper's Pareto set: k = 1 … 15
WINDOW_S = 30.0
STRESS = frozenset({"stroop", "interview", "maths"})
APART = frozenset({"hyperventilation"})
CALM_PREFIX = ("relax", "sitting")
_NS = 1_000_000_000
# the personal mode's settings tried by the cross-validation: the size of a step of k in mean RR, how much
# the past weighs in the recent mean RR, how far past the middle between two k the play lets it go
GRID: dict[str, tuple[float, ...]] = {
    "step_s": (0.01, 0.015, 0.02, 0.03),
    "keep": (0.5, 0.7, 0.8, 0.9),
    "hysteresis": (0.25, 0.5, 0.75, 1.0),
}
LABELS = ("calm", "stress", "other")


def label_for(block: str) -> str:
    """A block's label by its name, where ``blocks.csv`` gives none."""
    return "stress" if block in STRESS else "calm" if block.startswith(CALM_PREFIX) else "other"


def calm(label: str | None) -> bool:
    return label is not None and label_for(label) == "calm"


@dataclass(frozen=True, slots=True)
class Block:
    name: str
    start_ns: int
    end_ns: int
    label: str = ""  # calm, stress or other; "" → by its name (``label_for``)

    @property
    def kind(self) -> str:
        return self.label or label_for(self.name)


@dataclass(frozen=True, slots=True)
class Session:
    """One person's session as the decision maker would see it: windows over data time, each with the
    block it falls in (half of it or more; None between blocks)."""

    name: str
    windows: tuple[HrvWindow, ...]
    labels: tuple[str | None, ...]
    blocks: tuple[Block, ...]
    calibration: Calibration | None
    problem: str | None = None  # why it cannot be scored (the calibration refused, no stress block …)
    note: str | None = None  # what a reader of its figures should know

    def kind(self, block: str | None) -> str:
        """calm, stress or other: what the block named ``block`` is (``Block.kind``)."""
        return next((b.kind for b in self.blocks if b.name == block), "other")

    @property
    def dataset(self) -> str:
        return self.name.split("/")[0]

    @property
    def subject(self) -> str:
        return self.name.split("/")[-1]


def read_blocks(path: Path) -> dict[str, list[Block]]:
    """``blocks.csv``: subject, block, start_unix_s, end_unix_s[, label]; InputError naming the line. The
    label (calm, stress or other) says what a block is where its name does not (``label_for``)."""
    try:
        text = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise InputError(
            f"{path}: no such file (subject, block, start_unix_s, end_unix_s per line)"
        ) from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not text (byte {exc.start})") from None
    rows = csv.reader(text)
    want = ["subject", "block", "start_unix_s", "end_unix_s"]
    header = next(rows, None)
    if header not in (want, [*want, "label"]):
        raise InputError(f"{path}:1: expected the header {','.join(want)}[,label]")
    out: dict[str, list[Block]] = {}
    for n, row in enumerate(rows, start=2):
        if not row:
            continue
        try:
            subject, name, a, b, *label = row
            if len(label) != len(header) - 4:
                raise ValueError
            block = Block(name, int(float(a) * _NS), int(float(b) * _NS), *label)
        except ValueError:
            raise InputError(
                f"{path}:{n}: expected {', '.join(header)} (times in Unix s), got {row}"
            ) from None
        if block.label not in ("", *LABELS):
            raise InputError(f"{path}:{n}: the label {block.label!r} is none of {', '.join(LABELS)}")
        if block.end_ns <= block.start_ns:
            raise InputError(f"{path}:{n}: the block {name!r} ends before it starts")
        out.setdefault(subject, []).append(block)
    return out


def label_of(blocks: Sequence[Block], start_ns: int, end_ns: int) -> str | None:
    for b in blocks:
        if min(end_ns, b.end_ns) - max(start_ns, b.start_ns) >= (end_ns - start_ns) / 2:
            return b.name
    return None


def movement_mg(rec: E4, starts_ns: Sequence[int], length_s: float) -> list[float | None]:
    """Each window's movement from the wristband's accelerometer, by the analyser's own ``Movement``
    (fed second by second, as chunks arrive)."""
    if rec.acc_start_ns is None or rec.acc_hz is None or not len(rec.acc_mg):
        return [None] * len(starts_ns)
    mv, per = Movement(), max(1, round(rec.acc_hz))
    for i in range(0, len(rec.acc_mg), per):
        mv.feed(rec.acc_start_ns + round(i * _NS / rec.acc_hz), rec.acc_hz, rec.acc_mg[i : i + per])
    return [mv.over(a, a + round(length_s * _NS))[0] for a in starts_ns]


def session_of(name: str, rec: E4, blocks: Sequence[Block], baseline: str, movement: bool) -> Session:
    wins = e4_windows(rec, WINDOW_S)
    moves = movement_mg(rec, [a for a, _ in wins], WINDOW_S) if movement else [None] * len(wins)
    msgs = tuple(
        msgspec.structs.replace(window_message(w, rec.start_ns, i), movement_mg=m)
        for i, ((_, w), m) in enumerate(zip(wins, moves, strict=True))
    )
    labels = tuple(label_of(blocks, m.start_ns, m.end_ns) for m in msgs)
    base = [m for m, lab in zip(msgs, labels, strict=True) if lab == baseline]
    cal, problem, note = None, None, None
    if not base:
        problem = f"no window in the {baseline} block"
    else:
        good = [w.mean_rr_s for w in base if w.quality == "good" and w.mean_rr_s is not None]
        try:
            cal = calibration(base, name.split("/")[-1], base[-1].end_ns, measured_sigma=False)[0]
        except ValueError as exc:
            # `cadence calibrate` refuses a baseline with fewer than 60 % of its windows readable (a strap
            # that cannot be read); a wrist's baseline often is, for a few beats too few a window. Its good
            # windows still give RR_r (the block's mean, as a lab would take it); the refusal is kept beside.
            if len(good) >= 2:
                cal = Calibration(t_ns=base[-1].end_ns, seq=0, subject=name.split("/")[-1],
                                  rr_rest_s=round(float(np.mean(good)), 6))  # fmt: skip
                note = f"`cadence calibrate` would refuse it ({len(good)} of {len(base)} windows readable)"
            else:
                problem = f"calibration on the {baseline} block refused: {exc}"
    session = Session(name, msgs, labels, tuple(blocks), cal, problem, note)
    if cal is not None and not any(session.kind(lab) == "stress" for lab in labels):
        session = dataclasses.replace(session, problem="no stress block")
    elif cal is not None and not any(session.kind(lab) == "calm" for lab in labels):
        session = dataclasses.replace(session, problem="no calm block")
    return session


def stress_predict(
    data: Path, movement: bool = True, progress: Callable[[str], None] | None = None
) -> list[Session]:
    """Every ``SNN/`` folder of ``data`` that ``blocks.csv`` names, as a session calibrated on its
    baseline block."""
    blocks = read_blocks(data / "blocks.csv")
    out = []
    for name in sorted(blocks):
        folder = data / name
        if not folder.is_dir():
            continue
        if progress:
            progress(f"reading {folder}")
        out.append(session_of(f"{data.name}/{name}", read_e4(folder), blocks[name], "baseline", movement))
    return out


GUDB_START_NS = 1_500_000_000 * _NS  # GUDB's files carry no date: any data time will do
GUDB_GAP_S = 60.0  # between the seated minutes and the maths test


def gudb(data: Path, progress: Callable[[str], None] | None = None) -> list[Session]:
    """Every ``subject_NN/`` of ``data`` with both a seated and a maths recording, the maths test a minute
    after the seated minutes end, as a session calibrated on the seated minutes."""
    from cadence.bench.hrv_cv import read_gudb_beats

    out = []
    for folder in sorted(p for p in data.glob("subject_*") if p.is_dir()):
        if progress:
            progress(f"reading {folder}")
        sit, maths = (read_gudb_beats(folder / act / "annotation_cs.tsv") for act in ("sitting", "maths"))
        if sit is None or maths is None:
            continue
        shift = sit[-1] + GUDB_GAP_S - maths[0]
        beats = np.concatenate([sit, maths + shift])
        ibi = np.diff(beats)
        keep = np.ones(ibi.size, dtype=bool)
        keep[sit.size - 1] = False  # not an interval: the gap between the recordings
        beat_ns = (GUDB_START_NS + np.round(beats[1:] * _NS)).astype(np.int64)[keep]
        start = GUDB_START_NS + round(sit[0] * _NS)
        rec = E4(folder, start, beat_ns, ibi[keep], None, None, np.empty((0, 3)), np.empty(0, dtype=np.int64))
        blocks = (
            Block("sitting", start, GUDB_START_NS + round(sit[-1] * _NS)),
            Block("maths", GUDB_START_NS + round((maths[0] + shift) * _NS), rec.end_ns + 1),
        )
        out.append(session_of(f"{data.name}/{folder.name}", rec, blocks, "sitting", movement=False))
    return out


@dataclass(frozen=True, slots=True)
class Decision:
    k: int
    reason: str

    @property
    def held(self) -> bool:
        return self.reason in ("movement", "low-quality")


def run(session: Session, personal: Personal | None, rule: MovementRule | None = None) -> list[Decision]:
    """The session's windows through the decision maker's own ``Decider``, one after the other, as the
    service answers them (nothing is persisted)."""
    assert session.calibration is not None
    decider = Decider(Path(tempfile.gettempdir()), N, rule, personal=personal)
    decider.commit(decider.starting(session.calibration, session.calibration.t_ns))
    out = []
    for w in session.windows:
        rec = decider.answer(w)
        decider.commit(rec)
        out.append(Decision(rec.k, rec.reason))
    return out


def auc(above: Sequence[float], below: Sequence[float]) -> float:
    """P(a calm window's k > a stress window's k), a tie counting half."""
    a, b = np.asarray(above, dtype=float)[:, None], np.asarray(below, dtype=float)[None, :]
    return float((a > b).mean() + 0.5 * (a == b).mean())


def pairs(session: Session) -> list[tuple[str, str, str]]:
    """(side, stress block, calm block): each stress block with the calm block just before it and the one
    just after it, where one is reached without crossing another stress block."""
    blocks = sorted(session.blocks, key=lambda b: b.start_ns)
    out = []
    for i, b in enumerate(blocks):
        if b.kind != "stress":
            continue
        for side, seq in (("before", reversed(blocks[:i])), ("after", blocks[i + 1 :])):
            for c in seq:
                if c.kind == "stress":
                    break
                if c.kind == "calm":
                    out.append((side, b.name, c.name))
                    break
    return out


@dataclass(frozen=True, slots=True)
class Order:
    """One subject's order-balanced figures: the mean AUC of its before-pairs and of its after-pairs
    (None where it has none), and their mean where it has both."""

    before: float | None
    after: float | None

    @property
    def balanced(self) -> float | None:
        return None if self.before is None or self.after is None else (self.before + self.after) / 2

    @property
    def score(self) -> float:
        """What the cross-validation weighs: balanced where it can be, else the one side there is."""
        got = [x for x in (self.before, self.after) if x is not None]
        return self.balanced if self.balanced is not None else float(np.mean(got)) if got else math.nan


def order(session: Session, values: Sequence[float]) -> Order:
    """``values``: one per window (k, or a control's value; NaN where it has none), higher = calmer."""
    by: dict[str | None, list[float]] = {}
    for lab, v in zip(session.labels, values, strict=True):
        if not math.isnan(v):
            by.setdefault(lab, []).append(v)
    sides: dict[str, list[float]] = {"before": [], "after": []}
    for side, stress, calm_block in pairs(session):
        if by.get(stress) and by.get(calm_block):
            sides[side].append(auc(by[calm_block], by[stress]))
    b, a = (float(np.mean(sides[x])) if sides[x] else None for x in ("before", "after"))
    return Order(b, a)


def usable(w: HrvWindow) -> bool:
    """A window the personal mode reads (common/decision.py ``personal_step``)."""
    return w.mean_rr_s is not None and (
        w.quality == "good" or (w.quality == "low" and w.reason == "coverage")
    )


CONTROLS: dict[str, Callable[[Session], list[float]]] = {
    # what the signal allows: the window's own mean RR, no controller
    "mean RR": lambda s: [w.mean_rr_s if usable(w) and w.mean_rr_s else math.nan for w in s.windows],
    # time alone: the window's index, ignoring the heart (0.5 by construction on balanced subjects)
    "time": lambda s: [float(i) for i in range(len(s.windows))],
    # the spread of successive beats (the analyser's RMSSD), higher at rest
    "RMSSD": lambda s: [w.rmssd_s if usable(w) and w.rmssd_s is not None else math.nan for w in s.windows],
}


@dataclass(frozen=True, slots=True)
class Score:
    name: str
    auc: float  # over all calm and all stress windows (credits block order: see the module's text)
    lower_in_stress: bool
    k_stress: float  # mean k over the stress windows
    k_calm: float
    k_apart: float | None  # hyperventilation's
    held: int  # windows whose k was held (movement, quality)
    windows: int
    order: Order = Order(None, None)
    k_by_block: dict[str, float] = field(default_factory=dict)

    @property
    def dk(self) -> float:
        """Mean k calm − mean k stress: how much slower the robot went under stress."""
        return self.k_calm - self.k_stress


def score(session: Session, decisions: Sequence[Decision]) -> Score:
    ks: dict[str, list[int]] = {}
    for lab, d in zip(session.labels, decisions, strict=True):
        if lab is not None:
            ks.setdefault(lab, []).append(d.k)
    stress = [k for lab, v in ks.items() if session.kind(lab) == "stress" for k in v]
    relax = [k for lab, v in ks.items() if session.kind(lab) == "calm" for k in v]
    apart = [k for lab, v in ks.items() if lab in APART for k in v]
    return Score(
        session.name,
        auc(relax, stress),
        float(np.mean(stress)) < float(np.mean(relax)),
        float(np.mean(stress)),
        float(np.mean(relax)),
        float(np.mean(apart)) if apart else None,
        sum(d.held for d in decisions),
        len(decisions),
        order(session, [float(d.k) for d in decisions]),
        {lab: float(np.mean(v)) for lab, v in ks.items()},
    )


def median_or_none(xs: Sequence[float]) -> float | None:
    return round(float(np.median(xs)), 3) if xs else None


def order_summary(orders: Sequence[Order]) -> dict[str, float | int | None]:
    """The order-balanced figures over subjects: the median balanced score (over subjects with both
    sides) and its share above 0.5, the medians of the before- and after-pairs apart."""
    bal = [o.balanced for o in orders if o.balanced is not None]
    before = [o.before for o in orders if o.before is not None]
    after = [o.after for o in orders if o.after is not None]
    return {
        "balanced_median": median_or_none(bal),
        "balanced_above_half": round(sum(x > 0.5 for x in bal) / len(bal), 3) if bal else None,
        "balanced_subjects": len(bal),
        "before_median": median_or_none(before),
        "before_above_half": round(sum(x > 0.5 for x in before) / len(before), 3) if before else None,
        "before_subjects": len(before),
        "after_median": median_or_none(after),
        "after_subjects": len(after),
    }


def bootstrap(xs: Sequence[float], seed: int = 0, draws: int = 2000) -> tuple[float, float]:
    """A 95 % interval of the median of ``xs`` by resampling the subjects."""
    a = np.asarray(xs, dtype=float)
    rng = np.random.default_rng(seed)
    meds = np.median(a[rng.integers(0, a.size, (draws, a.size))], axis=1)
    return round(float(np.quantile(meds, 0.025)), 2), round(float(np.quantile(meds, 0.975)), 2)


def summary(scores: Sequence[Score]) -> dict[str, object]:
    """The figures of one mode over subjects (medians over subjects of each one's figure)."""
    if not scores:
        return {"subjects": 0}
    apart = [s.k_apart for s in scores if s.k_apart is not None]
    lower = sum(s.lower_in_stress for s in scores)
    dk = [s.dk for s in scores]
    return {
        "subjects": len(scores),
        **order_summary([s.order for s in scores]),
        "dk_median": round(float(np.median(dk)), 2),
        "dk_ci95": bootstrap(dk),
        "auc_median": round(float(np.median([s.auc for s in scores])), 3),
        "lower_in_stress": round(lower / len(scores), 3),
        "lower_in_stress_n": lower,
        "k_stress_median": round(float(np.median([s.k_stress for s in scores])), 2),
        "k_relax_median": round(float(np.median([s.k_calm for s in scores])), 2),
        "k_hyperventilation_median": round(float(np.median(apart)), 2) if apart else None,
        "held_share": round(sum(s.held for s in scores) / max(1, sum(s.windows for s in scores)), 3),
    }


# --- the personal mode's settings, chosen ---------------------------------------------------------------

STEADY_NOISE_S = 0.02  # a steady person's window-to-window noise in mean RR
STEADY_WINDOWS = 960  # 8 hours of 30 s windows
STEADY_MAX_CHANGES = 0.10  # at most this share of windows may change k


def steady(q: Personal, seed: int = 7) -> bool:
    """Whether ``q`` keeps a steady person steady and a stressed one slow, as DESIGN §7 states the mode:
    8 h at RR_r = 0.85 s with 20 ms of Gaussian window noise change k in at most 10 % of windows with
    its median within 1 of k0; an hour at 60 ms below keeps k at least 2 below k0 from minute 5 on. A
    setting the data would favour but that dithers or forgets is not a candidate."""
    p = Params.of(0.85)
    rng = np.random.default_rng(seed)
    s, ks = PersonalState.initial(p), []
    for rr in 0.85 + STEADY_NOISE_S * rng.standard_normal(STEADY_WINDOWS):
        s = personal_step(p, q, s, float(rr), 1, True)[0]
        ks.append(s.k)
    changes = sum(a != b for a, b in itertools.pairwise([p.k0, *ks]))
    if changes > STEADY_MAX_CHANGES * STEADY_WINDOWS or abs(float(np.median(ks)) - p.k0) > 1:
        return False
    s = PersonalState.initial(p)
    for i in range(120):
        s = personal_step(p, q, s, 0.79, 1, True)[0]
        if i >= 10 and s.k > p.k0 - 2:
            return False
    return True


def grid() -> list[Personal]:
    """The settings tried: ``GRID``'s, those that pass ``steady``; the rest as shipped."""
    base = Personal()
    every = [
        dataclasses.replace(base, step_s=a, keep=b, hysteresis=c)
        for a, b, c in itertools.product(*GRID.values())
    ]
    return [q for q in every if steady(q)]


def objective(scores: Iterable[Score]) -> tuple[float, int]:
    """What the cross-validation maximises: the mean order-balanced score (each subject's ``Order.score``;
    the median moves by whole subjects), then how many are lower in stress."""
    s = list(scores)
    return round(float(np.nanmean([x.order.score for x in s])), 4), sum(x.lower_in_stress for x in s)


@dataclass(frozen=True, slots=True)
class CrossValidation:
    held_out: list[Score]  # each subject scored with the settings chosen on the others
    decisions: list[list[Decision]]  # … and those settings' decisions
    chosen: list[Personal]  # … which were these, per subject
    on_all: Personal  # the settings chosen on every subject


def cross_validate(
    sessions: Sequence[Session],
    rule: MovementRule | None = None,
    progress: Callable[[str], None] | None = None,
) -> CrossValidation:
    """Leave one subject out: choose the personal mode's settings from ``grid`` on the others (by
    ``objective``), score the one left out with them."""
    settings = grid()
    table: list[list[tuple[Score, list[Decision]]]] = []  # [setting][session]
    for i, q in enumerate(settings):
        if progress:
            progress(f"setting {i + 1} of {len(settings)}")
        runs = [run(s, q, rule) for s in sessions]
        table.append([(score(s, d), d) for s, d in zip(sessions, runs, strict=True)])
    held, decided, chosen = [], [], []
    for j in range(len(sessions)):
        best = max(
            range(len(settings)), key=lambda i: objective(x for m, (x, _) in enumerate(table[i]) if m != j)
        )
        held.append(table[best][j][0])
        decided.append(table[best][j][1])
        chosen.append(settings[best])
    on_all = max(range(len(settings)), key=lambda i: objective(x for x, _ in table[i]))
    return CrossValidation(held, decided, chosen, settings[on_all])


def write_decisions(path: Path, sessions: Sequence[Session], modes: dict[str, list[list[Decision]]]) -> None:
    """``decisions.csv``: one row per window and mode, for anyone to score as they see fit."""
    from common.runtime.storage import write_readable

    rows = [["dataset", "subject", "window_start_s", "window_end_s", "block", "label", "mode", "k", "held"]]
    for i, s in enumerate(sessions):
        t0 = s.windows[0].start_ns if s.windows else 0
        for mode, runs in modes.items():
            for w, lab, d in zip(s.windows, s.labels, runs[i], strict=True):
                a, b = (w.start_ns - t0) / _NS, (w.end_ns - t0) / _NS
                kind = s.kind(lab) if lab else ""
                rows.append([s.dataset, s.subject, f"{a:.3f}", f"{b:.3f}", lab or "", kind, mode, str(d.k),
                             str(int(d.held))])  # fmt: skip
    text = "".join(",".join(r) + "\n" for r in rows)
    write_readable(path, text.encode())


def figure(session: Session, decisions: dict[str, list[Decision]]) -> bytes:
    """The session's mean RR per window and k per mode over data time, its blocks shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cadence.lab.plots import _png

    t0 = session.windows[0].start_ns if session.windows else 0
    fig, (ax, axk) = plt.subplots(2, 1, figsize=(11, 5.5), sharex=True, constrained_layout=True)
    colours = {"baseline": "0.8", "sitting": "0.8", "hyperventilation": "tab:orange"}
    for i, b in enumerate(sorted(session.blocks, key=lambda b: b.start_ns)):
        c = colours.get(b.name, "tab:red" if b.name in STRESS else "tab:green" if calm(b.name) else "0.9")
        for a in (ax, axk):
            a.axvspan((b.start_ns - t0) / _NS, (b.end_ns - t0) / _NS, color=c, alpha=0.15, lw=0)
        ax.text((b.start_ns - t0) / _NS, 1.0 + 0.06 * (i % 2), b.name, transform=ax.get_xaxis_transform(),
                fontsize=7, va="bottom")  # fmt: skip
    t = np.array([(w.end_ns - t0) / _NS for w in session.windows])
    rr = np.array([np.nan if w.mean_rr_s is None else w.mean_rr_s for w in session.windows])
    good = np.array([w.quality == "good" for w in session.windows])
    ax.plot(t[good], rr[good], "o-", ms=3, c="tab:red", label="mean RR (good)")
    ax.plot(t[~good], rr[~good], "x", c="0.5", label="mean RR (held: few beats, noise)")
    if session.calibration is not None:
        ax.axhline(session.calibration.rr_rest_s, ls="--", c="tab:red", lw=0.8, label="RR_r (calibration)")
    ax.set_ylabel("mean RR [s]")
    ax.legend(fontsize=7, loc="lower left")
    for (mode, ds), c in zip(decisions.items(), ("tab:blue", "tab:purple", "tab:brown"), strict=False):
        k = [d.k for d in ds]
        axk.step(t, k, where="post", c=c, label=f"k, {mode}")
    axk.set_ylim(0.5, N + 0.5)
    axk.set_ylabel("k (1 smoothest … 15 fastest)")
    axk.set_xlabel("data time [s]")
    axk.legend(fontsize=7, loc="lower left")
    ax.set_title(session.name, fontsize=9, pad=24)
    return _png(fig)
