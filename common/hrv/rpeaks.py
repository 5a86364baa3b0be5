"""Online R-peak detection at the strap's 130 Hz (paper §II-C; DESIGN §6).

A streaming detector in the manner of Pan & Tompkins (1985): band-pass, derivative, square, moving-window
integration (MWI), then decisions on the MWI's local maxima with adaptive signal and noise levels, a
T-wave check and a search-back for missed beats. Every filter keeps its state between chunks and every
decision waits for a fixed look-ahead, so a record fed whole or in chunks of any size gives the same
peaks (tested), and a peak is published at most ``LOOKAHEAD_S`` plus the filter delay after it occurs.

The filters run vectorised over each chunk; only MWI maxima (a few per beat) go through Python, which
keeps the detector hundreds of times faster than real time on one core.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import signal

Array = NDArray[np.float64]

BAND_HZ = (5.0, 18.0)
MWI_S = 0.15
REFRACTORY_S = 0.2
T_WAVE_S = 0.36
LOOKAHEAD_S = 0.21  # a maximum is final once the refractory span after it (0.2 s) has been seen
LEARN_S = 2.0
SEARCHBACK_FACTOR = 1.66
SHAPE_S = 0.1  # each side of the R peak: the QRS whose shape is compared with the template
TEMPLATE_BEATS = 8  # the template is the median of the last this many beats like it
RELEARN_BEATS = 8  # this many beats in a row unlike the template: the QRS itself changed, learn it anew
LIKE = 0.8  # correlation with the template below which a beat is not like the rhythm's own (ectopic, noise)
ALIGN_S = 0.05  # each side: the shift within which a beat's QRS is aligned to the template before comparing
NOISE_BEATS = 32  # the person's own between-beat level: the median of the last this many beats' excursions
NOISE_FLOOR = 0.35  # of the QRS height: a lower own level counts as this (a clean ECG's is 0.15-0.5)


class Peak(NamedTuple):
    """An R peak and what the cleaning needs to know of the ECG around it, which RR intervals alone
    cannot tell: ``likeness``, the correlation of its QRS with the template of the recent normal beats (a
    ventricular beat that is only mildly early, or a spike of noise, is unlike it); ``noise``, the largest
    band-passed excursion between the previous peak's QRS and this one's, relative to the recent QRS
    amplitude and then to this person's own usual level of it (a burst of noise in which beats may be
    hidden or invented; 0 for a segment's first).

    Both are relative to the person: a bundle branch block's wide QRS and large T wave put a
    band-passed excursion between beats as high as the QRS itself in every beat (MIT-BIH 109), so the
    excursion counts against the median of the last NOISE_BEATS, not against a fixed share of the QRS;
    and a QRS with two peaks of like height (rSR', 118) is located on either from beat to beat, so a
    beat is aligned to the template (within ALIGN_S) before it is compared, and its time is the aligned
    one: the same point of every beat like the template, so the interval between two beats has no jitter
    from which peak was found."""

    sample: int  # from the first sample fed
    likeness: float
    noise: float
    excursion: float = 0.0  # the largest between the beats, relative to the QRS height only (not the person)


@dataclass
class _Stream:
    """The filter chain with its state: band-pass → derivative → square → MWI."""

    fs: float
    sos: Array = field(init=False)
    zi_bp: Array = field(init=False)
    deriv: Array = field(init=False)
    zi_d: Array = field(init=False)
    mwi: Array = field(init=False)
    zi_m: Array = field(init=False)

    def __post_init__(self) -> None:
        self.sos = signal.butter(2, BAND_HZ, btype="band", fs=self.fs, output="sos")
        self.zi_bp = np.zeros((self.sos.shape[0], 2))
        self.deriv = np.array([1.0, 2.0, 0.0, -2.0, -1.0]) * (self.fs / 8.0)
        self.zi_d = np.zeros(len(self.deriv) - 1)
        n = max(1, round(MWI_S * self.fs))
        self.mwi = np.ones(n) / n
        self.zi_m = np.zeros(n - 1)

    def feed(self, x: Array) -> tuple[Array, Array]:
        bp, self.zi_bp = signal.sosfilt(self.sos, x, zi=self.zi_bp)
        d, self.zi_d = signal.lfilter(self.deriv, [1.0], bp, zi=self.zi_d)
        m, self.zi_m = signal.lfilter(self.mwi, [1.0], d * d, zi=self.zi_m)
        return bp, m


class RPeakDetector:
    """Feed samples (µV or mV, any scale) with ``feed``; it returns the R peaks now final, as absolute
    sample indices from the first sample fed. ``flush`` ends the stream and returns the rest."""

    def __init__(self, fs: float) -> None:
        self.fs = fs
        self._stream = _Stream(fs)
        self._n = 0  # samples fed so far
        # buffers of recent samples, from absolute index self._base
        self._base = 0
        self._raw = np.empty(0)
        self._bp = np.empty(0)
        self._mwi = np.empty(0)
        self._next_scan = 1  # first MWI index not yet examined for a maximum
        self._lookahead = max(2, round(LOOKAHEAD_S * fs))
        self._refractory = round(REFRACTORY_S * fs)
        self._t_wave = round(T_WAVE_S * fs)
        self._learning: list[tuple[int, float]] | None = []
        self._spki = 0.0
        self._npki = 0.0
        self._last_r: int | None = None
        self._last_slope = 0.0
        self._rr: list[int] = []
        self._pending: list[tuple[int, float]] = []  # below-threshold maxima since the last R
        self._out: list[Peak] = []
        self._shape = round(SHAPE_S * fs)
        self._qrs = (round(0.045 * fs), round(0.03 * fs))  # around the R peak, for its band-passed height
        self._between = (round(0.12 * fs), round(0.08 * fs))  # after one QRS, before the next: noise there
        self._templates: deque[Array] = deque(maxlen=TEMPLATE_BEATS)  # QRS shapes of beats like the rhythm
        self._unlike: deque[Array] = deque(maxlen=RELEARN_BEATS)  # the latest run of beats unlike it
        self._amps: deque[float] = deque(maxlen=TEMPLATE_BEATS)  # recent QRS amplitudes, band-passed
        self._excursions: deque[float] = deque(maxlen=NOISE_BEATS)  # between beats, relative to the QRS
        self._align = round(ALIGN_S * fs)
        self._last_peak: int | None = None  # the last R peak given out (absolute index)

    # -- public ----------------------------------------------------------------------------------

    def feed(self, x: Array) -> list[int]:
        return [p.sample for p in self.feed_peaks(x)]

    def flush(self) -> list[int]:
        return [p.sample for p in self.flush_peaks()]

    def feed_peaks(self, x: Array) -> list[Peak]:
        """As ``feed``, with each peak's likeness and noise."""
        x = np.asarray(x, dtype=float)
        if x.size == 0:
            return []
        bp, m = self._stream.feed(x)
        self._raw = np.concatenate([self._raw, x])
        self._bp = np.concatenate([self._bp, bp])
        self._mwi = np.concatenate([self._mwi, m])
        self._n += x.size
        self._scan(final=False)
        return self._take()

    def flush_peaks(self) -> list[Peak]:
        self._scan(final=True)
        return self._take()

    # -- internals -------------------------------------------------------------------------------

    def _take(self) -> list[Peak]:
        out, self._out = self._out, []
        self._trim()
        return out

    def _trim(self) -> None:
        """Keep only what later decisions can still look at (a few seconds)."""
        keep_from = self._n - round(4.0 * self.fs)
        if self._last_r is not None:
            keep_from = min(keep_from, self._last_r - self._t_wave)
        if self._last_peak is not None:  # the noise since it is measured at the next peak
            keep_from = min(keep_from, self._last_peak)
        keep_from = min(keep_from, self._next_scan - self._refractory - 2)
        cut = keep_from - self._base
        if cut > 0:
            self._raw, self._bp, self._mwi = self._raw[cut:], self._bp[cut:], self._mwi[cut:]
            self._base += cut

    def _scan(self, final: bool) -> None:
        """Find MWI maxima that are final: the largest within ±refractory, with look-ahead seen."""
        end = self._n if final else self._n - self._lookahead
        if end <= self._next_scan:
            return
        lo = self._next_scan - self._base
        hi = end - self._base
        m = self._mwi
        seg = slice(max(lo, 1), min(hi, len(m) - 1))
        i = np.arange(seg.start, seg.stop)
        if i.size:
            is_max = (m[i] > m[i - 1]) & (m[i] >= m[i + 1])
            for j in i[is_max]:
                a, b = max(0, j - self._refractory), min(len(m), j + self._refractory + 1)
                if m[j] >= m[a:b].max():
                    self._candidate(int(j) + self._base, float(np.sqrt(m[j])))
        self._next_scan = end
        if final:
            self._search_back(self._n)

    def _slope(self, idx: int) -> float:
        j = idx - self._base
        seg = self._bp[max(0, j - round(0.075 * self.fs)) : j + 1]
        return float(np.max(np.abs(np.diff(seg)))) if seg.size > 1 else 0.0

    def _candidate(self, idx: int, peak: float) -> None:
        if self._learning is not None:
            self._learning.append((idx, peak))
            if idx >= LEARN_S * self.fs:
                learned, self._learning = self._learning, None
                peaks = np.array([p for _, p in learned])
                self._spki = float(np.max(peaks)) * 0.5
                self._npki = float(np.median(peaks)) * 0.5
                for i, p in learned:
                    self._candidate(i, p)
            return
        # Search-back is decided at candidate times only (and at the end), never at chunk boundaries,
        # so how the stream is cut into chunks cannot change a decision.
        self._search_back(idx)
        threshold = self._npki + 0.25 * (self._spki - self._npki)
        if self._last_r is not None and idx - self._last_r < self._refractory:
            return
        if peak > threshold:
            slope = self._slope(idx)
            if (
                self._last_r is not None
                and idx - self._last_r < self._t_wave
                and slope < 0.5 * self._last_slope
            ):
                self._npki = 0.125 * peak + 0.875 * self._npki  # a T wave
                return
            self._accept(idx, peak, slope, 0.125)
        else:
            self._npki = 0.125 * peak + 0.875 * self._npki
            self._pending.append((idx, peak))

    def _accept(self, idx: int, peak: float, slope: float, weight: float) -> None:
        self._spki = weight * peak + (1 - weight) * self._spki
        if self._last_r is not None:
            self._rr.append(idx - self._last_r)
            self._rr = self._rr[-8:]
        self._last_r = idx
        self._last_slope = slope
        self._pending.clear()
        self._out.append(self._describe(self._locate(idx)))

    def _qrs_shape(self, j: int, extra: int = 0) -> Array:
        """The raw QRS centred on buffer index j (±SHAPE_S, and ``extra`` samples more each side), less
        its local median; edge-padded."""
        h = self._shape + extra
        seg = self._raw[max(0, j - h) : j + h + 1]
        seg = np.pad(seg, (max(0, h - j), 2 * h + 1 - len(seg) - max(0, h - j)), mode="edge")
        out: Array = seg - np.median(self._raw[max(0, j - 3 * self._shape) : j + 1])
        return out

    def _describe(self, r: int) -> Peak:
        """The peak, aligned to the template, with its likeness and the noise since the previous peak."""
        j = r - self._base
        n = 2 * self._shape + 1
        wide = self._qrs_shape(j, self._align)  # every shift's QRS is a slice of it
        seg = wide[self._align : self._align + n]
        if len(self._templates) < 3:
            likeness = 1.0  # learning the template
        else:
            # the correlation with the template at every shift within ±ALIGN_S, at once
            t = np.median(np.array(self._templates), axis=0)
            t = t - t.mean()
            shifts = np.lib.stride_tricks.sliding_window_view(wide, n)
            centred = shifts - shifts.mean(axis=1, keepdims=True)
            norms = np.linalg.norm(centred, axis=1) * np.linalg.norm(t)
            c = np.divide(centred @ t, norms, out=np.zeros(len(shifts)), where=norms > 0)
            k = int(np.argmax(c))
            likeness = max(float(c[k]), 0.0)
            if likeness >= LIKE:  # the template's own point of this beat
                lag = k - self._align
                r, j, seg = r + lag, j + lag, shifts[k]
        if likeness >= LIKE:
            self._templates.append(seg)
            self._unlike.clear()
        else:
            self._unlike.append(seg)
            if len(self._unlike) == RELEARN_BEATS:  # not ectopy: the QRS itself changed (electrodes, posture)
                self._templates.clear()
                self._templates.extend(self._unlike)
                self._unlike.clear()
        before, after = self._qrs
        amp = float(np.max(np.abs(self._bp[max(0, j - before) : j + after]))) if j >= 0 else 0.0
        self._amps.append(amp)
        noise = excursion = 0.0
        if self._last_peak is not None:
            lo = self._last_peak + self._between[0] - self._base
            hi = j - self._between[1]
            level = float(np.median(self._amps))
            if hi > lo and level > 0:
                excursion = float(np.max(np.abs(self._bp[max(0, lo) : hi]))) / level
                own = float(np.median(self._excursions)) if self._excursions else NOISE_FLOOR
                noise = excursion / max(own, NOISE_FLOOR)
                self._excursions.append(excursion)
        self._last_peak = r
        return Peak(r, likeness, noise, excursion)

    def _search_back(self, now: int) -> None:
        """No beat for 1.66 mean RR: take the largest skipped maximum above half the threshold."""
        if self._last_r is None or len(self._rr) < 2 or not self._pending:
            return
        if now - self._last_r <= SEARCHBACK_FACTOR * float(np.mean(self._rr)):
            return
        threshold = self._npki + 0.25 * (self._spki - self._npki)
        idx, peak = max(self._pending, key=lambda c: c[1])
        if peak > 0.5 * threshold and idx - self._last_r >= self._refractory:
            self._accept(idx, peak, self._slope(idx), 0.25)

    def _locate(self, mwi_idx: int) -> int:
        """The R peak: the band-passed signal's extreme before the MWI maximum, then the raw signal's
        extreme (after removing its local median) close to it, so the time is the ECG's own."""
        j = mwi_idx - self._base
        w = round(MWI_S * self.fs) + round(0.05 * self.fs)
        a = max(0, j - w)
        k = a + int(np.argmax(np.abs(self._bp[a : j + 1])))
        r0, r1 = max(0, k - round(0.08 * self.fs)), min(len(self._raw), k + round(0.03 * self.fs) + 1)
        raw = self._raw[r0:r1]
        base = np.median(self._raw[max(0, k - round(0.3 * self.fs)) : k + 1])
        return r0 + int(np.argmax(np.abs(raw - base))) + self._base


def detect_peaks(x: Array, fs: float, chunk: int | None = None) -> list[Peak]:
    """All R peaks of a record with their likeness and noise; ``chunk`` feeds it in pieces of that many
    samples."""
    det = RPeakDetector(fs)
    out: list[Peak] = []
    step = chunk or len(x)
    for i in range(0, len(x), step):
        out += det.feed_peaks(x[i : i + step])
    return out + det.flush_peaks()


def detect(x: Array, fs: float, chunk: int | None = None) -> NDArray[np.intp]:
    """All R peaks of a record (sample indices)."""
    return np.array(sorted({p.sample for p in detect_peaks(x, fs, chunk)}), dtype=np.intp)
