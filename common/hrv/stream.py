"""RR intervals from R peaks, cleaned, and tumbling windows on data time (paper §II-C; DESIGN §6).

Why cleaning is not optional: one missed or extra beat moves a 30 s window's mean RR by about 20 ms,
the size of Δ_rs, so one detection error could move k. An interval is excluded when it departs from the
median of its neighbours by more than ``TOLERANCE``; its kind says why (``missed``: about twice the
median, ``extra``: a fragment, ``ectopic``: a premature beat and its compensatory pause). What RR alone
cannot tell, the ECG around each beat can (issue 19; ``rpeaks.Peak``): a beat whose QRS is unlike the
rhythm's own (a ventricular beat only mildly early, a spike of noise) takes both its intervals with it
(``unlike``), and so does a burst of noise between two beats (``noise``). A window in which noise and
excluded beats meet is held: where beats are hidden in noise, even the annotators' truth disagrees on
how many there were. An interval that spans a gap in the data is never formed.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from common.hrv.rpeaks import LIKE, Peak, RPeakDetector
from schemas.hrv import Beats, HoldReason, HrvWindow, Quality

TOLERANCE = 0.2  # relative departure from the local median that excludes an interval
PREMATURE, PAUSE = 0.08, 0.05  # a beat this much early, then a pause this much long: premature
NEIGHBOURS = 5  # on each side, for the local median
MIN_RR_S, MAX_RR_S = 0.25, 2.5  # physiological bounds (240 and 24 beats per minute)
MAX_EXCLUDED = 0.2  # a window with more excluded intervals than this is low quality
MIN_COVERAGE = 0.6  # clean intervals must cover this share of the window
RR_RESYNC_S = 3.0  # device RR whose summed beat clock strays this far from the notification time: a gap
NOISE = 0.8  # band-passed noise between two beats above this share of the QRS amplitude excludes it
# a window with HOLD_NOISY intervals noisier than HOLD_NOISE that are excluded, or next to one, is held
HOLD_NOISE, HOLD_NOISY = 1.0, 2
LEVEL_N, LEVEL_MIN = 30, 10  # the rhythm's level: the median of the last LEVEL_N clean intervals, once 10
RELEVEL = 40  # intervals in a row at twice the level: a rhythm that slow is believed, and the level relearnt

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
    kept = np.nonzero(keep)[0]
    starts = {j for j in range(1, len(kept)) if kept[j] != kept[j - 1] + 1}  # the first interval after a gap
    rr, t = rr[keep], t[keep]
    return Intervals(t, rr, classify(rr, like_iv, noise_iv, starts), noise_iv)


def peak_intervals(peaks: Sequence[Peak], fs: float, gaps_s: Gaps = ()) -> Intervals:
    """``intervals`` of the detector's peaks (``rpeaks.detect_peaks``), with what it saw of the ECG."""
    found = sorted(peaks)
    return intervals(
        np.array([p.sample / fs for p in found]),
        gaps_s,
        np.array([p.likeness for p in found]),
        np.array([p.noise for p in found]),
    )


class Level:
    """The rhythm's level: the median of the last clean intervals of a segment, which a run of doubled
    intervals cannot move. A strap's own RR leaves premature beats out (the H10 does), so a run of
    bigeminy reaches the cleaning as a run of intervals twice as long, regular to any local median; no
    heart halves its rate from one beat to the next, so against the level they are missed beats."""

    def __init__(self) -> None:
        self._clean: deque[float] = deque(maxlen=LEVEL_N)
        self._doubled = 0  # in a row

    @property
    def value(self) -> float | None:
        return float(np.median(self._clean)) if len(self._clean) >= LEVEL_MIN else None

    def classify(
        self,
        rr: NDArray[np.float64] | list[float],
        i: int,
        likeness: NDArray[np.float64] | Sequence[float] | None = None,
        noise: NDArray[np.float64] | Sequence[float] | None = None,
    ) -> Kind:
        """``classify_one`` against this level, which then takes in interval i: the one step that both
        the offline ``classify`` and the stream take for each interval, in order."""
        level = self.value
        kind = classify_one(rr, i, likeness, noise, level)
        if kind == "ok":
            self._clean.append(rr[i])
            self._doubled = 0
        elif doubled(rr[i], level):
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
) -> list[Kind]:
    """Every interval in order, as the stream does: the level carries from one to the next, and starts
    afresh at each of ``segment_starts`` (the first interval after a gap)."""
    kinds: list[Kind] = []
    level = Level()
    for i in range(len(rr)):
        if i in segment_starts:
            level = Level()
        kinds.append(level.classify(rr, i, likeness, noise))
    return kinds


def doubled(rr: float, level: float | None) -> bool:
    return level is not None and 1.6 <= rr / level <= 2.4


def classify_one(
    rr: NDArray[np.float64] | list[float],
    i: int,
    likeness: NDArray[np.float64] | Sequence[float] | None = None,
    noise: NDArray[np.float64] | Sequence[float] | None = None,
    level: float | None = None,
) -> Kind:
    """Interval i, from ``rr[i - NEIGHBOURS : i + NEIGHBOURS + 1]`` only (the stream classifies an
    interval once NEIGHBOURS follow it); ``likeness[i]`` (the lesser of its two beats') and ``noise[i]``
    are the ECG's word on it, when there is an ECG; ``level`` is the rhythm's (``Level``).

    The reference is the median of the plausible intervals around i, leaving out i and its two
    neighbours (a premature beat moves two intervals). An interval is excluded when it departs from the
    reference by more than TOLERANCE, or when a beat at either end of it is premature: the interval
    that beat closes is short by more than TOLERANCE, or short by more than PREMATURE with the next
    one long by more than PAUSE (a mildly early beat and its compensatory pause). The reference counts
    intervals between normal beats (NN), as the annotations' truth does: both intervals around an
    ectopic beat go. The second half of an interval that a false beat split is not premature: its
    closing beat is a real one. An interval next to a fragment goes too: which end of the fragment is the
    false beat cannot be told, so the other piece of the split interval may be either neighbour. An
    interval regular to its neighbours but twice the level is a missed beat in a run of them.
    """
    x = rr[i]
    if not MIN_RR_S <= x <= MAX_RR_S:
        return "implausible"
    n = len(rr)
    lo, hi = max(0, i - NEIGHBOURS), min(n, i + NEIGHBOURS + 1)
    neigh = [rr[j] for j in range(lo, hi) if abs(j - i) > 1 and MIN_RR_S <= rr[j] <= MAX_RR_S]
    if len(neigh) < 2:
        return "ok"
    ref = float(np.median(neigh))
    ratio = x / ref
    if abs(ratio - 1.0) > TOLERANCE:
        if 1.6 <= ratio <= 2.4:
            return "missed"
        if ratio <= 0.6:
            return "extra"
        return "ectopic"
    if doubled(x, level):
        return "missed"

    def premature(a: int) -> bool:  # the beat that closes interval a
        if not 0 <= a < n or not MIN_RR_S <= rr[a] <= MAX_RR_S:
            return False
        if (
            a >= 1
            and rr[a - 1] < (1.0 - TOLERANCE) * ref
            and abs((rr[a - 1] + rr[a]) / ref - 1.0) <= TOLERANCE
        ):
            return False  # the second half of an interval a false beat split: its beat is the real one
        short = rr[a] / ref
        if short < 1.0 - TOLERANCE:
            return True
        return a + 1 < n and short < 1.0 - PREMATURE and rr[a + 1] / ref > 1.0 + PAUSE

    if premature(i) or premature(i - 1):
        return "ectopic"
    if likeness is not None and likeness[i] < LIKE:
        return "unlike"
    if noise is not None and noise[i] > NOISE:
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


def window_stats(start_s: float, end_s: float, iv: Intervals, gaps_s: Gaps = ()) -> Window:
    """One window [start, end): the intervals whose ending beat falls inside it. A window that a gap in
    the data overlaps is low quality whatever is left of it (DESIGN §6)."""
    sel = (iv.t_s >= start_s) & (iv.t_s < end_s)
    idx = np.nonzero(sel)[0]
    rr = iv.rr_s[sel]
    bad = iv.excluded[sel]
    clean = rr[~bad]
    n = int(rr.size)
    excluded = float(bad.mean()) if n else 1.0
    if clean.size == 0:
        return Window(start_s, end_s, None, n, excluded, "none", None, None, "no_clean_beats")
    coverage = float(clean.sum()) / (end_s - start_s)
    reason: HoldReason | None = None
    if any(g0 < end_s and g1 > start_s for g0, g1 in gaps_s):
        reason = "gap"
    elif excluded > MAX_EXCLUDED:
        reason = "excluded"
    elif coverage < MIN_COVERAGE:
        reason = "coverage"
    elif iv.noise is not None and noisy_exclusions(iv, idx) >= HOLD_NOISY:
        reason = "noise"
    # successive differences only between intervals that are next to each other and both clean
    pairs = [
        (iv.rr_s[a], iv.rr_s[b])
        for a, b in itertools.pairwise(idx)
        if b == a + 1 and not iv.excluded[a] and not iv.excluded[b]
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


def noisy_exclusions(iv: Intervals, idx: NDArray[np.intp]) -> int:
    """How many of the intervals ``idx`` (one window's, in order) are noisy beyond HOLD_NOISE and were
    excluded by the RR or the shape of their beats, or lie next to one that was, in the window."""
    assert iv.noise is not None
    inside = set(idx.tolist())

    def beat_excluded(j: int) -> bool:
        return j in inside and iv.kind[j] not in ("ok", "noise")

    return sum(
        1
        for i in idx
        if iv.noise[i] > HOLD_NOISE and (beat_excluded(i) or beat_excluded(i - 1) or beat_excluded(i + 1))
    )


def windows(
    iv: Intervals, length_s: float = 30.0, start_s: float = 0.0, end_s: float | None = None, gaps_s: Gaps = ()
) -> list[Window]:
    """Tumbling windows of ``length_s`` from ``start_s``; the last one ends at or before ``end_s``."""
    end = end_s if end_s is not None else (float(iv.t_s[-1]) if iv.t_s.size else start_s)
    out = []
    t = start_s
    while t + length_s <= end + 1e-9:
        out.append(window_stats(t, t + length_s, iv, gaps_s))
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
        self, fs: float, window_s: float = 30.0, detector_factory: Callable[[], RPeakDetector] | None = None
    ) -> None:
        self.fs = fs
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
        self._ecg = False  # fed samples, so the detector's likeness and noise exist
        self._level = Level()  # the segment's
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
        self._seg_like_iv, self._seg_noise = [], []
        self._level = Level()

    def _add_peaks(self, found: list[Peak]) -> list[float]:
        found = sorted(found)
        times = [self._seg_t0 + p.sample / self.fs for p in found]
        return self._add_times(times, [p.likeness for p in found], [p.noise for p in found])

    def _add_times(
        self, times: list[float], likeness: list[float] | None = None, noise: list[float] | None = None
    ) -> list[float]:
        for k, t in enumerate(times):
            like = 1.0 if likeness is None else likeness[k]
            if self._seg_peaks:
                self._seg_rr.append(t - self._seg_peaks[-1])
                self._seg_t.append(t)
                self._seg_like_iv.append(min(like, self._last_like))
                self._seg_noise.append(0.0 if noise is None else noise[k])
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
                kind = self._level.classify(self._seg_rr, i, self._seg_like_iv, self._seg_noise)
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
            out.append(window_stats(self._win_start, end, iv, self.gaps))
            self._win_start = end
        if out:  # what closed windows used is no longer needed: the stream runs for hours
            keep = next((i for i, t in enumerate(self._done_t) if t >= self._win_start), len(self._done_t))
            del self._done_t[:keep], self._done_rr[:keep], self._done_kind[:keep], self._done_noise[:keep]
            self.gaps = [g for g in self.gaps if g[1] > self._win_start]
        return out
