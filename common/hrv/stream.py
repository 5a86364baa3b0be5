"""RR intervals from R peaks, cleaned, and tumbling windows on data time (paper §II-C; DESIGN §6).

Why cleaning is not optional: one missed or extra beat moves a 30 s window's mean RR by about 20 ms,
the size of Δ_rs, so one detection error could move k. An interval is excluded when it departs from the
median of its neighbours by more than the person's own tolerance (``Rules``, ``Level``: what is normal
is learnt per person); its kind says why (``missed``: about twice the median, ``extra``: a
fragment, ``ectopic``: a premature beat and its compensatory pause). What RR alone
cannot tell, the ECG around each beat can (``rpeaks.Peak``): a beat whose QRS is unlike the
rhythm's own (a ventricular beat only mildly early, a spike of noise) takes both its intervals with it
(``unlike``), and so does a burst of noise between two beats (``noise``). A window in which noise and
excluded beats meet is held: where beats are hidden in noise, even the annotators' truth disagrees on
how many there were; so is a window whose rhythm is irregular beat to beat (atrial fibrillation). An
interval that spans a gap in the data is never formed.
"""

from __future__ import annotations

import itertools
import statistics
from collections import deque
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from common.hrv.rpeaks import Peak, RPeakDetector
from schemas.hrv import Beats, HoldReason, HrvWindow, Quality

NEIGHBOURS = 5  # on each side, for the local median
MIN_RR_S, MAX_RR_S = 0.25, 2.5  # physiological bounds (240 and 24 beats per minute)
MIN_COVERAGE = 0.6  # clean intervals must cover this share of the window
RR_RESYNC_S = 3.0  # device RR whose summed beat clock strays this far from the notification time: a gap
LEVEL_N, LEVEL_MIN = 30, 10  # the rhythm's level: the median of the last LEVEL_N clean intervals, once 10
RELEVEL = 40  # intervals in a row at twice the level: a rhythm that slow is believed, and the level relearnt
STEP_BEATS = 6  # the clean intervals on each side of a jump in rate (``rhythm_jumps``)
RUN_BEATS = 3  # early beats in a row: a run of tachycardia, not an ectopic beat (``early_run``)
LOOK_BACK = 100  # intervals before a window that ``early_run`` learns the rhythm from
RHYTHM_HOLD_S = 300.0  # a jump in rate holds the windows until the rate is back, this long at most
SPREAD_N, SPREAD_MIN = 60, 5  # the person's own spread and step: medians of the last 60 plausible intervals


@dataclass(frozen=True, slots=True)
class Rules:
    """The cleaning's thresholds. The defaults were chosen by leave-one-out cross-validation across the
    annotated records and the GUDB subjects (``cadence bench hrv --windows --cv``; docs/decision.md, "HRV
    windows"), never on the record they are scored on; a bench passes other values to compare.

    What a healthy heart does differs from person to person: a breathing rhythm swings RR by
    ±10-20 % in a few beats. So the departure that excludes an interval is the larger of ``tolerance``
    and ``spread`` times the person's own median departure from the local median (up to
    ``tolerance_max``), and a mildly early beat (``premature``, then a pause of ``pause``) is ectopic
    only when the drop into it is ``sharp`` times the person's median beat-to-beat step: a breath
    shortens RR over several beats, a premature beat in one."""

    tolerance: float = 0.2  # relative departure from the local median that excludes an interval, at least
    tolerance_max: float = 0.3  # and at most, whatever the person's spread
    spread: float = 6.0  # times the person's median departure
    premature: float = 0.08  # a beat this much early, then a pause this much long: premature …
    pause: float = 0.05
    sharp: float = 3.0  # … when the drop into it is this many times the person's median step
    long_ok: float = 1.5  # a long interval after no premature beat, up to this ratio: the person's own pause
    quiet: float = 0.5  # an interval twice the rhythm's with nothing above this share of a QRS in it: a pause
    like: float = 0.8  # a beat whose QRS correlates less with the template's is unlike the rhythm's own
    noise: float = 2.8  # noise between two beats above this many times the person's own level excludes it
    hold_noise: float = 2.9  # a window with hold_noisy intervals noisier than this that are excluded, …
    hold_noisy: int = 3  # … or next to one that is, is held
    irregular: float = 0.09  # a window whose median step is this share of its median RR is held (AF)
    step: float = 1.6  # a window where the rate of STEP_BEATS beats jumps by this ratio: held (rhythm)
    max_excluded: float = 0.2  # a window with a larger share of its intervals excluded is held


RULES = Rules()

Kind = Literal["ok", "missed", "extra", "ectopic", "implausible", "unlike", "noise"]
Gaps = tuple[tuple[float, float], ...] | list[tuple[float, float]]  # (start, end) of missing data, s


@dataclass(frozen=True, slots=True)
class Intervals:
    """``t_s[i]`` is the time of the beat that ends interval ``rr_s[i]``."""

    t_s: NDArray[np.float64]
    rr_s: NDArray[np.float64]
    kind: list[Kind]
    noise: NDArray[np.float64] | None = None  # from the ECG, per interval; None for device RR

    @property
    def excluded(self) -> NDArray[np.bool_]:
        return np.array([k != "ok" for k in self.kind], dtype=bool)


def intervals(
    peaks_s: NDArray[np.float64],
    gaps_s: Gaps = (),
    likeness: NDArray[np.float64] | None = None,
    noise: NDArray[np.float64] | None = None,
    rules: Rules = RULES,
    excursion: NDArray[np.float64] | None = None,
) -> Intervals:
    """RR intervals between consecutive peaks, classified; none across a gap (start, end) in the data.
    ``likeness`` and ``noise`` are the detector's, per peak (``rpeaks.Peak``): without them (device RR),
    the cleaning has the intervals only."""
    peaks_s = np.asarray(peaks_s, dtype=float)
    if len(peaks_s) < 2:
        return Intervals(np.empty(0), np.empty(0), [], None if noise is None else np.empty(0))
    rr = np.diff(peaks_s)
    t = peaks_s[1:]
    keep = np.ones(len(rr), dtype=bool)
    for g0, g1 in gaps_s:
        keep &= ~((peaks_s[:-1] < g1) & (peaks_s[1:] > g0))
    like_iv = None if likeness is None else np.minimum(likeness[:-1], likeness[1:])[keep]
    noise_iv = None if noise is None else np.asarray(noise, dtype=float)[1:][keep]
    quiet_iv = None if excursion is None else (np.asarray(excursion, dtype=float)[1:] < rules.quiet)[keep]
    kept = np.nonzero(keep)[0]
    starts = {j for j in range(1, len(kept)) if kept[j] != kept[j - 1] + 1}  # the first interval after a gap
    rr, t = rr[keep], t[keep]
    return Intervals(t, rr, classify(rr, like_iv, noise_iv, starts, rules, quiet_iv), noise_iv)


def peak_intervals(peaks: Sequence[Peak], fs: float, gaps_s: Gaps = (), rules: Rules = RULES) -> Intervals:
    """``intervals`` of the detector's peaks (``rpeaks.detect_peaks``), with what it saw of the ECG."""
    found = sorted(peaks)
    return intervals(
        np.array([p.sample / fs for p in found]),
        gaps_s,
        np.array([p.likeness for p in found]),
        np.array([p.noise for p in found]),
        rules,
        np.array([p.excursion for p in found]),
    )


@dataclass(frozen=True, slots=True)
class Person:
    """What the cleaning has learnt of this person's rhythm so far (``Level``): ``level``, the median of
    the last clean intervals; ``spread``, the median relative departure of an interval from its local
    median; ``step``, the median relative change from one interval to the next. None until learnt."""

    level: float | None = None
    spread: float | None = None
    step: float | None = None


class Level:
    """The rhythm's level, and the person's own spread and step (``Person``), learnt from the intervals
    of a segment in order.

    The level is the median of the last clean intervals, which a run of doubled intervals cannot move. A
    strap's own RR leaves premature beats out (the H10 does), so a run of bigeminy reaches the cleaning
    as a run of intervals twice as long, regular to any local median; no heart halves its rate from one
    beat to the next, so against the level they are missed beats. The spread and step are medians over
    every plausible interval, excluded or not (up to half of them may be ectopic), so what the rules
    exclude cannot shrink the scale that decides what they exclude."""

    def __init__(self, rules: Rules = RULES) -> None:
        self.rules = rules
        self._clean: deque[float] = deque(maxlen=LEVEL_N)
        self._dev: deque[float] = deque(maxlen=SPREAD_N)
        self._step: deque[float] = deque(maxlen=SPREAD_N)
        self._doubled = 0  # in a row

    @property
    def value(self) -> float | None:
        return statistics.median(self._clean) if len(self._clean) >= LEVEL_MIN else None

    @property
    def person(self) -> Person:
        def med(d: deque[float]) -> float | None:
            return statistics.median(d) if len(d) >= SPREAD_MIN else None

        return Person(self.value, med(self._dev), med(self._step))

    def classify(
        self,
        rr: NDArray[np.float64] | list[float],
        i: int,
        likeness: NDArray[np.float64] | Sequence[float] | None = None,
        noise: NDArray[np.float64] | Sequence[float] | None = None,
        quiet: NDArray[np.bool_] | Sequence[bool] | None = None,
    ) -> Kind:
        """``classify_one`` against what is learnt so far, which then takes in interval i: the one step
        that both the offline ``classify`` and the stream take for each interval, in order."""
        person = self.person
        kind = classify_one(rr, i, likeness, noise, person, self.rules, quiet)
        x = rr[i]
        ref = reference(rr, i)
        if ref is not None and MIN_RR_S <= x <= MAX_RR_S:
            self._dev.append(abs(x / ref - 1.0))
            if i >= 1 and MIN_RR_S <= rr[i - 1] <= MAX_RR_S:
                self._step.append(abs(x - rr[i - 1]) / ref)
        if kind == "ok":
            self._clean.append(x)
            self._doubled = 0
        elif doubled(x, person.level):
            self._doubled += 1
            if self._doubled >= RELEVEL:  # over a minute of it: a slow rhythm, not dropped beats
                self._clean.clear()
                self._doubled = 0
        return kind


def classify(
    rr: NDArray[np.float64],
    likeness: NDArray[np.float64] | Sequence[float] | None = None,
    noise: NDArray[np.float64] | Sequence[float] | None = None,
    segment_starts: Collection[int] = (),
    rules: Rules = RULES,
    quiet: NDArray[np.bool_] | Sequence[bool] | None = None,
) -> list[Kind]:
    """Every interval in order, as the stream does: what is learnt of the person carries from one to
    the next, and starts afresh at each of ``segment_starts`` (the first interval after a gap)."""
    kinds: list[Kind] = []
    level = Level(rules)
    for i in range(len(rr)):
        if i in segment_starts:
            level = Level(rules)
        kinds.append(level.classify(rr, i, likeness, noise, quiet))
    return kinds


def doubled(rr: float, level: float | None) -> bool:
    return level is not None and 1.6 <= rr / level <= 2.4


def reference(rr: NDArray[np.float64] | list[float], i: int) -> float | None:
    """The median of the plausible intervals within NEIGHBOURS of i, leaving out i and its two
    neighbours (a premature beat moves two intervals); None with fewer than two."""
    lo, hi = max(0, i - NEIGHBOURS), min(len(rr), i + NEIGHBOURS + 1)
    neigh = [rr[j] for j in range(lo, hi) if abs(j - i) > 1 and MIN_RR_S <= rr[j] <= MAX_RR_S]
    return float(statistics.median(neigh)) if len(neigh) >= 2 else None


def classify_one(
    rr: NDArray[np.float64] | list[float],
    i: int,
    likeness: NDArray[np.float64] | Sequence[float] | None = None,
    noise: NDArray[np.float64] | Sequence[float] | None = None,
    person: Person = Person(),
    rules: Rules = RULES,
    quiet: NDArray[np.bool_] | Sequence[bool] | None = None,
) -> Kind:
    """Interval i, from ``rr[i - NEIGHBOURS : i + NEIGHBOURS + 1]`` only (the stream classifies an
    interval once NEIGHBOURS follow it); ``likeness[i]`` (the lesser of its two beats') and ``noise[i]``
    are the ECG's word on it, when there is an ECG; ``person`` is what was learnt before i (``Level``).

    An interval is excluded when it departs from its ``reference`` by more than the person's tolerance
    (``Rules``), or when a beat at either end of it is premature: the interval that beat closes is short
    by more than the tolerance, or short by more than ``premature`` with the next one long by more than
    ``pause`` and a drop into it sharper than a breath gives (a mildly early beat and its compensatory
    pause). The reference counts intervals between normal beats (NN), as the annotations' truth does:
    both intervals around an ectopic beat go. The second half of an interval that a false beat split is
    not premature: its closing beat is a real one. An interval next to a fragment goes too: which end of
    the fragment is the false beat cannot be told, so the other piece of the split interval may be
    either neighbour. An interval regular to its neighbours but twice the level is a missed beat in a
    run of them.
    """
    x = rr[i]
    if not MIN_RR_S <= x <= MAX_RR_S:
        return "implausible"
    n = len(rr)
    ref = reference(rr, i)
    if ref is None:
        return "ok"
    tol = rules.tolerance
    if person.spread is not None:
        tol = min(max(tol, rules.spread * person.spread), rules.tolerance_max)
    ratio = x / ref
    # a pause with no QRS in it is the heart's (a blocked beat), not the detector's: its truth is NN
    nothing_in_it = quiet is not None and bool(quiet[i])
    pause = nothing_in_it and 1.6 <= ratio <= 2.4
    if abs(ratio - 1.0) > tol and (1.6 <= ratio <= 2.4 or ratio <= 0.6) and not pause:
        return "missed" if ratio > 1.0 else "extra"
    sharp = rules.sharp * (person.step or 0.0)

    def premature(a: int) -> bool:  # the beat that closes interval a
        if not 0 <= a < n or not MIN_RR_S <= rr[a] <= MAX_RR_S:
            return False
        if a >= 1 and rr[a - 1] < (1.0 - tol) * ref and abs((rr[a - 1] + rr[a]) / ref - 1.0) <= tol:
            return False  # the second half of an interval a false beat split: its beat is the real one
        short = rr[a] / ref
        if short < 1.0 - tol:
            return True
        return (
            a + 1 < n
            and short < 1.0 - rules.premature
            and rr[a + 1] / ref > 1.0 + rules.pause
            and (a < 1 or (rr[a - 1] - rr[a]) / ref > sharp)
        )

    if abs(ratio - 1.0) > tol and not pause and not (1.0 < ratio < rules.long_ok and not premature(i - 1)):
        return "ectopic"  # a lone long interval is a breath or a pause of the person's own: kept
    if doubled(x, person.level) and not nothing_in_it:
        return "missed"
    if premature(i) or premature(i - 1):
        return "ectopic"
    if likeness is not None and likeness[i] < rules.like:
        return "unlike"
    if noise is not None and noise[i] > rules.noise:
        return "noise"
    if any(0 <= j < n and (rr[j] < MIN_RR_S or rr[j] / ref <= 0.6) for j in (i - 1, i + 1)):
        return "extra"
    return "ok"


@dataclass(frozen=True, slots=True)
class Window:
    start_s: float
    end_s: float
    mean_rr_s: float | None
    n_beats: int
    excluded: float
    quality: Quality
    rmssd_s: float | None
    sdnn_s: float | None
    reason: HoldReason | None = None  # why it is not good

    @property
    def excluded_fraction(self) -> float:
        """As ``HrvWindow`` names it, so a calibration reads either."""
        return self.excluded


@dataclass(frozen=True, slots=True)
class Beat:
    """A beat once the cleaning has decided on the interval it ends (``rr_s`` 0 and kind ``start`` for
    the first beat of a segment, which ends no interval): what ``hrv/beats`` publishes."""

    t_s: float
    rr_s: float
    kind: Kind | Literal["start"]

    @property
    def excluded(self) -> bool:
        return self.kind != "ok"


def window_stats(
    start_s: float, end_s: float, iv: Intervals, gaps_s: Gaps = (), rules: Rules = RULES
) -> Window:
    """One window [start, end): the intervals whose ending beat falls inside it. A window that a gap in
    the data overlaps is low quality whatever is left of it (DESIGN §6)."""
    sel = (iv.t_s >= start_s) & (iv.t_s < end_s)
    idx = np.nonzero(sel)[0]
    rr = iv.rr_s[sel]
    excluded_all = iv.excluded  # built once: the pairs below look at it per interval
    bad = excluded_all[sel]
    clean = rr[~bad]
    n = int(rr.size)
    excluded = float(bad.mean()) if n else 1.0
    if clean.size == 0:
        return Window(start_s, end_s, None, n, excluded, "none", None, None, "no_clean_beats")
    coverage = float(clean.sum()) / (end_s - start_s)
    reason: HoldReason | None = None
    if any(g0 < end_s and g1 > start_s for g0, g1 in gaps_s):
        reason = "gap"
    elif irregularity(iv.rr_s[idx[0] : idx[-1] + 1]) > rules.irregular:
        reason = "irregular"
    elif rhythm_jumps(iv, excluded_all, gaps_s, start_s, end_s, rules.step) or early_run(iv, idx, rules):
        reason = "rhythm"
    elif excluded > rules.max_excluded:
        reason = "excluded"
    elif coverage < MIN_COVERAGE:
        reason = "coverage"
    elif iv.noise is not None and noisy_exclusions(iv, idx, rules.hold_noise) >= rules.hold_noisy:
        reason = "noise"
    # successive differences only between intervals that are next to each other and both clean
    pairs = [
        (iv.rr_s[a], iv.rr_s[b])
        for a, b in itertools.pairwise(idx)
        if b == a + 1 and not excluded_all[a] and not excluded_all[b]
    ]
    rmssd = float(np.sqrt(np.mean([(b - a) ** 2 for a, b in pairs]))) if pairs else None
    return Window(
        start_s,
        end_s,
        float(clean.mean()),
        n,
        excluded,
        "good" if reason is None else "low",
        rmssd,
        float(clean.std(ddof=1)) if clean.size > 1 else None,
        reason,
    )


def irregularity(rr: NDArray[np.float64]) -> float:
    """The median step from one plausible interval to the next, as a share of the median interval. A
    breathing rhythm, however deep, stays under 0.07 (GUDB, 12 people sitting, doing maths, walking, on a
    hand bike); atrial fibrillation is 0.15 and over (MIT-BIH 201): no mean RR of such a rhythm says what
    load does to it, and no cleaning can tell which of its intervals are normal."""
    ok = (rr >= MIN_RR_S) & (rr <= MAX_RR_S)
    steps = np.abs(np.diff(rr))[ok[1:] & ok[:-1]]
    return float(np.median(steps) / np.median(rr[ok])) if steps.size >= 2 else 0.0


def rhythm_jumps(
    iv: Intervals, excluded: NDArray[np.bool_], gaps_s: Gaps, start_s: float, end_s: float, step: float
) -> bool:
    """Whether a jump in rate makes the window [start, end) no sinus rhythm: a jump in it, or its median
    still away from the rate before the first jump of the RHYTHM_HOLD_S before it by more than half a
    jump (in ratio: the square root of ``step``). A jump is a ratio over ``step`` between the medians of
    the STEP_BEATS clean intervals after a beat and before it, dated by the last of those after it
    (``excluded``: ``iv.excluded``, which the caller has built).

    Clean intervals only: a missed or a false beat is the detector's, not the heart's; none across a gap.
    A premature beat and its pause, a run of bigeminy or a breath move a median of six little (of four,
    a strap's deep breathing, 750 to 1,100 ms in three beats, read as a jump of 1.5); a run of
    supraventricular tachycardia starts, and a 2:1 block halves the rate, from one beat to the next. Held
    until the rate is back where it was, not until a jump back is seen: a run may end less sharply than
    it began, and a jump the rate never followed (one odd median) holds only its own window."""
    since = max([start_s - RHYTHM_HOLD_S, *(g1 for _, g1 in gaps_s if g1 <= end_s)])
    sel = ~excluded & (iv.t_s >= since) & (iv.t_s < end_s)
    rr, t = iv.rr_s[sel], iv.t_s[sel]
    n = STEP_BEATS
    if rr.size < 2 * n:
        return False
    # ratios, square roots and medians only: IEEE rounds them alike on every processor, which numpy's
    # log does not (development.md, "The same story on every machine"), and the threshold must not flip
    level = np.median(np.lib.stride_tricks.sliding_window_view(rr, n), axis=1)  # of rr[j : j + n]
    ratio = level[n:] / level[:-n]  # at the beat that ends interval j + n − 1
    dated = t[2 * n - 1 :]
    jumps = np.flatnonzero((ratio > step) | (ratio * step < 1.0))
    if jumps.size == 0:
        return False
    if np.any(dated[jumps] >= start_s):
        return True
    inside = rr[t >= start_s]
    away = float(np.median(inside)) / float(level[jumps[0]]) if inside.size else 1.0  # from before the first
    half = float(np.sqrt(step))
    return away > half or away * half < 1.0


def early_run(iv: Intervals, idx: NDArray[np.intp], rules: Rules = RULES) -> bool:
    """Whether a run of RUN_BEATS early beats or more reaches into the window ``idx`` (its intervals, in a
    row): beats in a row, each closing an interval shorter than the rhythm before it by more than the
    tolerance, the first sharply (shorter than the interval before it by that much too), the last
    RUN_BEATS of them a run of beats (``_a_run``). The rhythm before it is the median of the last
    STEP_BEATS intervals the cleaning kept that were not early themselves: a run is not its own baseline.

    Three ectopic beats in a row are a run of tachycardia, ventricular or supraventricular (the clinical
    definition): not sinus rhythm. Too short to move the medians ``rhythm_jumps`` compares, a run was cut
    out as ectopic beats, or, a little early, kept as the person's own, and its window passed as sinus. A
    lone premature beat, a couplet and bigeminy are runs of one or two; a breath shortens RR over several
    beats, not in one. A run past twice STEP_BEATS is a rate that stays, a jump: the rhythm the next beats
    are held to. Looks back, never past the window's end: the stream decides a window as the offline
    pass does."""
    if idx.size == 0:
        return False
    rr, first, last = iv.rr_s, int(idx[0]), int(idx[-1])
    base: deque[float] = deque(maxlen=STEP_BEATS)
    run = 0
    for j in range(max(0, first - LOOK_BACK), last + 1):
        ref = statistics.median(base) if len(base) >= STEP_BEATS // 2 else None
        x = float(rr[j])
        early = (
            ref is not None
            and MIN_RR_S <= x < (1.0 - rules.tolerance) * ref
            and (run > 0 or (j >= 1 and float(rr[j - 1]) - x > rules.tolerance * ref))
        )
        run = run + 1 if early else 0
        if run > 2 * STEP_BEATS:  # a rate that stays is a jump (``rhythm_jumps``), and the rhythm from now on
            base.extend(float(r) for r in rr[j - STEP_BEATS + 1 : j + 1])
            run = 0
        elif (
            run >= RUN_BEATS
            and j >= first
            and ref is not None
            and _a_run(rr[j - RUN_BEATS + 1 : j + 1], ref, rules)
        ):
            return True
        elif not early and iv.kind[j] == "ok":
            base.append(x)
    return False


def _a_run(rr: NDArray[np.float64], ref: float, rules: Rules) -> bool:
    """Whether early intervals are a run of beats, not the pieces of a false beat: together longer than
    one interval of the rhythm, and within the tolerance of each other (a tachycardia is regular; an
    extra beat drawn among two leaves three unlike pieces)."""
    return float(rr.sum()) > ref and float(rr.max()) <= (1.0 + rules.tolerance) * float(rr.min())


def noisy_exclusions(iv: Intervals, idx: NDArray[np.intp], hold_noise: float) -> int:
    """How many of the intervals ``idx`` (one window's, in order) are noisy beyond ``hold_noise`` and were
    excluded by the RR or the shape of their beats, or lie next to one that was, in the window."""
    assert iv.noise is not None
    inside = set(idx.tolist())

    def beat_excluded(j: int) -> bool:
        return j in inside and iv.kind[j] not in ("ok", "noise")

    return sum(
        1
        for i in idx
        if iv.noise[i] > hold_noise and (beat_excluded(i) or beat_excluded(i - 1) or beat_excluded(i + 1))
    )


def windows(
    iv: Intervals,
    length_s: float = 30.0,
    start_s: float = 0.0,
    end_s: float | None = None,
    gaps_s: Gaps = (),
    rules: Rules = RULES,
) -> list[Window]:
    """Tumbling windows of ``length_s`` from ``start_s``; the last one ends at or before ``end_s``."""
    end = end_s if end_s is not None else (float(iv.t_s[-1]) if iv.t_s.size else start_s)
    out = []
    t = start_s
    while t + length_s <= end + 1e-9:
        out.append(window_stats(t, t + length_s, iv, gaps_s, rules))
        t += length_s
    return out


def match_beats(
    ref_s: NDArray[np.float64], found_s: NDArray[np.float64], tol_s: float = 0.15
) -> tuple[int, int, int]:
    """(TP, FP, FN): detected beats matched one-to-one to reference beats within ``tol_s`` (the usual
    150 ms of ANSI/AAMI EC57), each reference taking the nearest unused detection."""
    found_s = np.asarray(found_s, dtype=float)
    used = np.zeros(len(found_s), dtype=bool)
    tp = 0
    idx = np.searchsorted(found_s, ref_s)
    for k, t in enumerate(ref_s):
        cands = [
            c
            for c in (idx[k] - 1, idx[k])
            if 0 <= c < len(found_s) and not used[c] and abs(found_s[c] - t) <= tol_s
        ]
        if cands:
            used[min(cands, key=lambda c: abs(found_s[c] - t))] = True
            tp += 1
    return tp, len(found_s) - tp, len(ref_s) - tp


# --- to the wire (hrv/beats, hrv/window): data time in ns from the stream's origin ------------------


def _ns(origin_ns: int, t_s: float) -> int:
    return origin_ns + round(t_s * 1e9)


def beats_message(beats: Sequence[Beat], origin_ns: int, seq: int) -> Beats:
    """Flagged as the windows use them: the cleaning's verdict on the interval each ends."""
    return Beats(
        t_ns=_ns(origin_ns, beats[-1].t_s),
        seq=seq,
        peak_t_ns=[_ns(origin_ns, b.t_s) for b in beats],
        rr_s=[b.rr_s for b in beats],
        excluded=[b.excluded for b in beats],
    )


def window_message(w: Window, origin_ns: int, seq: int) -> HrvWindow:
    return HrvWindow(
        t_ns=_ns(origin_ns, w.end_s),
        seq=seq,
        start_ns=_ns(origin_ns, w.start_s),
        end_ns=_ns(origin_ns, w.end_s),
        mean_rr_s=w.mean_rr_s,
        n_beats=w.n_beats,
        excluded_fraction=w.excluded,
        quality=w.quality,
        rmssd_s=w.rmssd_s,
        sdnn_s=w.sdnn_s,
        reason=w.reason,
    )


class HrvStream:
    """The online form of ``intervals`` + ``windows``, on data time: what the HRV analyser runs.

    Fed chunks of samples with the data time of their first sample, it returns the beats and the windows
    that are final. A gap (flagged, or a jump in data time) ends a segment: the detector starts afresh
    and no interval spans the gap. An interval is classified once its NEIGHBOURS following intervals exist
    (or its segment ended), exactly as ``classify`` does offline, so a record streamed in chunks gives the
    windows that ``windows(peak_intervals(detect_peaks(...)))`` gives for it whole.
    """

    def __init__(
        self,
        fs: float,
        window_s: float = 30.0,
        detector_factory: Callable[[], RPeakDetector] | None = None,
        rules: Rules = RULES,
    ) -> None:
        self.fs = fs
        self.rules = rules
        self.window_s = window_s
        self._factory = detector_factory or (lambda: RPeakDetector(fs))
        self._det: RPeakDetector | None = None
        self._seg_t0 = 0.0  # data time of the segment's first sample, s
        self._seg_n = 0
        self._next_t: float | None = None  # expected data time of the next sample
        self._seg_peaks: list[float] = []
        self._seg_rr: list[float] = []
        self._seg_t: list[float] = []
        self._last_like = 1.0  # the segment's last beat's likeness (1 for device RR)
        self._seg_like_iv: list[float] = []  # per interval, the lesser of its beats'
        self._seg_noise: list[float] = []  # per interval
        self._seg_quiet: list[bool] = []  # per interval
        self._ecg = False  # fed samples, so the detector's likeness and noise exist
        self._level = Level(rules)  # the segment's
        self._classified = 0  # of the segment's intervals
        self._done_t: list[float] = []
        self._done_rr: list[float] = []
        self._done_kind: list[Kind] = []
        self._done_noise: list[float] = []
        self._beats: list[Beat] = []  # final since the last feed
        self.gaps: list[tuple[float, float]] = []
        self._win_start: float | None = None
        self._now = 0.0
        self._rr_gap = False
        self.segments = 0  # counts the detector's fresh starts (the first, and one after each gap)

    def feed(
        self, t0_s: float, samples: NDArray[np.float64] | Sequence[float], gap: bool = False
    ) -> tuple[list[Beat], list[Window]]:
        """Returns (beats now final, windows now final)."""
        samples = np.asarray(samples, dtype=float)
        if self._win_start is None:
            self._win_start = t0_s
        jumped = self._next_t is not None and abs(t0_s - self._next_t) > 1.5 / self.fs
        if self._det is None or gap or jumped:
            if self._det is not None:
                self._end_segment()
                assert self._next_t is not None  # set by the segment's first samples
                self.gaps.append((self._next_t, t0_s))
            self._det, self._seg_t0, self._seg_n = self._factory(), t0_s, 0
            self.segments += 1
        self._ecg = True
        found = self._det.feed_peaks(samples)
        self._seg_n += samples.size
        self._next_t = t0_s + samples.size / self.fs
        self._now = self._next_t
        self._add_peaks(found)
        self._classify(final=False)
        return self._take_beats(), self._close_windows(final=False)

    def feed_rr(self, t_s: float, rr_s: list[float], gap: bool = False) -> tuple[list[Beat], list[Window]]:
        """Device RR (a strap that sends no ECG) instead of samples; ``t_s`` is the notification time.

        The device gives intervals, not beat times: the beats are placed by summing them from an anchor,
        the notification time of a segment's first intervals. A flagged gap, or a summed clock that
        strays from the notification time by more than ``RR_RESYNC_S`` (notifications were lost), starts
        a new segment, so no interval is formed across missing beats. The same cleaning and windows as
        for samples follow.
        """
        if self._win_start is None:
            self._win_start = t_s - sum(rr_s)
        gap, self._rr_gap = gap or self._rr_gap, bool(gap and not rr_s)  # a gap flagged with no RR yet
        peaks: list[float] = []
        last = self._seg_peaks[-1] if self._seg_peaks else None
        strayed = last is not None and abs(last + sum(rr_s) - t_s) > RR_RESYNC_S
        if rr_s and (gap or strayed or last is None):
            if last is not None:
                self._end_segment()
                self.gaps.append((last, t_s - sum(rr_s)))
            self.segments += 1
            last = t_s - sum(rr_s)
            peaks += self._add_times([last])
        for rr in rr_s:
            assert last is not None  # a segment was started above for these intervals
            last += rr
            peaks += self._add_times([last])
        self._now = max(self._now, t_s, *peaks)
        self._classify(final=False)
        return self._take_beats(), self._close_windows(final=False)

    def flush(self) -> tuple[list[Beat], list[Window]]:
        if self._det is not None or self._seg_peaks:
            self._end_segment()
        self._det = None
        return self._take_beats(), self._close_windows(final=True)

    def _take_beats(self) -> list[Beat]:
        out, self._beats = self._beats, []
        return out

    def _end_segment(self) -> None:
        if self._det is not None:
            self._add_peaks(self._det.flush_peaks())
        self._classify(final=True)
        self._seg_peaks, self._seg_rr, self._seg_t, self._classified = [], [], [], 0
        self._seg_like_iv, self._seg_noise, self._seg_quiet = [], [], []
        self._level = Level(self.rules)

    def _add_peaks(self, found: list[Peak]) -> list[float]:
        found = sorted(found)
        times = [self._seg_t0 + p.sample / self.fs for p in found]
        quiet = [p.excursion < self.rules.quiet for p in found]
        return self._add_times(times, [p.likeness for p in found], [p.noise for p in found], quiet)

    def _add_times(
        self,
        times: list[float],
        likeness: list[float] | None = None,
        noise: list[float] | None = None,
        quiet: list[bool] | None = None,
    ) -> list[float]:
        for k, t in enumerate(times):
            like = 1.0 if likeness is None else likeness[k]
            if self._seg_peaks:
                self._seg_rr.append(t - self._seg_peaks[-1])
                self._seg_t.append(t)
                self._seg_like_iv.append(min(like, self._last_like))
                self._seg_noise.append(0.0 if noise is None else noise[k])
                self._seg_quiet.append(quiet is not None and quiet[k])
            else:
                self._beats.append(Beat(t, 0.0, "start"))
            self._seg_peaks.append(t)
            self._last_like = like
        return times

    def _classify(self, final: bool) -> None:
        upto = len(self._seg_rr) if final else len(self._seg_rr) - NEIGHBOURS
        for i in range(self._classified, max(self._classified, upto)):
            self._done_t.append(self._seg_t[i])
            self._done_rr.append(self._seg_rr[i])
            if self._ecg:
                kind = self._level.classify(
                    self._seg_rr, i, self._seg_like_iv, self._seg_noise, self._seg_quiet
                )
            else:
                kind = self._level.classify(self._seg_rr, i)
            self._done_kind.append(kind)
            self._done_noise.append(self._seg_noise[i])
            self._beats.append(Beat(self._seg_t[i], self._seg_rr[i], self._done_kind[-1]))
        self._classified = max(self._classified, upto)

    def _close_windows(self, final: bool) -> list[Window]:
        out: list[Window] = []
        assert self._win_start is not None
        # intervals not yet classified end at or after this time; a window must end before it
        pending_from = self._seg_t[self._classified] if self._classified < len(self._seg_t) else float("inf")
        while self._win_start + self.window_s <= self._now + 1e-9:
            end = self._win_start + self.window_s
            if not final and pending_from < end:
                break
            noise = np.array(self._done_noise) if self._ecg else None
            iv = Intervals(np.array(self._done_t), np.array(self._done_rr), list(self._done_kind), noise)
            out.append(window_stats(self._win_start, end, iv, self.gaps, self.rules))
            self._win_start = end
        if out:  # what closed windows used is no longer needed: the stream runs for hours
            since = self._win_start - RHYTHM_HOLD_S  # what a jump in rate before the next window needs
            keep = next((i for i, t in enumerate(self._done_t) if t >= since), len(self._done_t))
            del self._done_t[:keep], self._done_rr[:keep], self._done_kind[:keep], self._done_noise[:keep]
            self.gaps = [g for g in self.gaps if g[1] > since]
        return out
