"""Per-channel A, f and Af accumulated over windows (paper Sect. 3, Fig. 2).

For the peaks ``k`` of one channel that fall in one window:

* ``A  = sum A_k``, the peak amplitudes;
* ``f  = sum f_k``, with the instantaneous frequency ``f_k = fs / (n_k - n_{k-1})``
  from the interval to the channel's previous peak, wherever that lies (an
  earlier window or block);
* ``Af = sum A_k f_k``, Arabzadeh et al.'s "equivalent noise level".

A channel's very first peak has no predecessor: it adds to ``A`` but gives no
``f_k`` (its ``f`` and ``Af`` terms are 0). A window with no peak gives 0.

Windows are non-overlapping and aligned on the stream: window ``w`` covers
stream samples ``[w * length, (w + 1) * length)``. A peak is timed by its
*detection*, the sample after it (when it is known to be a peak, as a spike
would be): a peak at sample ``n`` counts in the window that holds sample
``n + 1``. So a window is complete, and emitted, as soon as its own last sample
has arrived: no look-ahead into the next block, no added latency in a stream.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from supramodal.peaks import Peaks

FEATURES = ("Af", "A", "f")


def check_features(features) -> tuple[str, ...]:
    """Validate a feature selection; returns it as a tuple in the given order."""
    if isinstance(features, str):
        features = (features,)
    features = tuple(features)
    if not features:
        raise ValueError(f"choose at least one feature from {FEATURES}")
    unknown = [f for f in features if f not in FEATURES]
    if unknown:
        raise ValueError(f"unknown feature(s) {unknown}; features are {', '.join(FEATURES)}")
    if len(set(features)) != len(features):
        raise ValueError(f"features repeat in {features}")
    return features


@dataclass(frozen=True)
class Windows:
    """Closed feature windows.

    Attributes
    ----------
    first : int
        Window number of ``values[0]`` (window ``w`` starts at sample ``w * length``).
    values : ndarray, shape (n, features, channels), float64
    features : tuple of str
        Feature names, in the order of axis 1.
    """

    first: int
    values: np.ndarray
    features: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.values.shape[0])

    @property
    def numbers(self) -> np.ndarray:
        """Window numbers, shape (n,)."""
        return np.arange(self.first, self.first + len(self), dtype=np.int64)

    def feature(self, name: str) -> np.ndarray:
        """Values of one feature, shape (n, channels)."""
        return self.values[:, self.features.index(name), :]


def concat_windows(parts: list[Windows], features: tuple[str, ...], channels: int) -> Windows:
    """Join consecutive :class:`Windows` (as returned block after block) into one."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return Windows(0, np.zeros((0, len(features), channels)), features)
    for a, b in zip(parts, parts[1:]):
        if b.first != a.first + len(a):
            raise ValueError(f"windows are not consecutive: {a.first}+{len(a)} then {b.first}")
    return Windows(parts[0].first, np.concatenate([p.values for p in parts]), features)


class FeatureWindows:
    """Accumulates peaks into per-window, per-channel features.

    Parameters
    ----------
    channels : int
    fs : float
        Sample rate, Hz (for the instantaneous frequency).
    length : int
        Window length in samples (100 ms is 500 at 5 kHz, 4410 at 44.1 kHz).
    features : sequence of {"Af", "A", "f"}
        Only these are computed, in this order.

    Notes
    -----
    Not thread-safe. Memory holds only the windows not yet closed.
    """

    def __init__(self, channels: int, fs: float, length: int, features=FEATURES) -> None:
        if not (isinstance(length, (int, np.integer)) and length >= 1):
            raise ValueError(f"window length must be a whole number of samples >= 1, got {length!r}")
        if not (np.isfinite(fs) and fs > 0):
            raise ValueError(f"sample rate must be > 0 Hz, got {fs!r}")
        self.channels = int(channels)
        self.fs = float(fs)
        self.length = int(length)
        self.features = check_features(features)
        self._need_f = "f" in self.features or "Af" in self.features
        self._last_peak = np.full(self.channels, -1, dtype=np.int64)
        self._next = 0                                   # first window not yet emitted
        self._open = np.zeros((0, len(self.features), self.channels))

    def process(self, peaks: Peaks) -> Windows:
        """Add decided peaks; return the windows they close (possibly none)."""
        W = self.length
        # A window is complete once its last sample has been seen: its peaks were all
        # detected by then (the last one it can hold sits one sample before its end).
        n_closed = peaks.seen // W - self._next
        span = n_closed
        idx = peaks.index
        if idx.size:
            first_w = (int(idx.min()) + 1) // W                # windows of the earliest and latest detection
            last_w = (int(idx.max()) + 1) // W
            if first_w < self._next:
                raise ValueError("a peak falls in a window already emitted: peaks must come in stream order")
            span = max(span, last_w - self._next + 1)
        if span > self._open.shape[0]:
            grown = np.zeros((span, len(self.features), self.channels))
            grown[: self._open.shape[0]] = self._open
            self._open = grown
        if idx.size:
            self._accumulate(peaks, first_w, last_w)
        out = Windows(self._next, self._open[:n_closed].copy(), self.features)
        if n_closed and n_closed == self._open.shape[0]:
            self._open.fill(0.0)                                # every open window emitted: reuse the rows
        else:
            self._open = self._open[n_closed:]
        self._next += n_closed
        return out

    def _accumulate(self, peaks: Peaks, first_w: int, last_w: int) -> None:
        ch, idx, amp = peaks.channel, peaks.index, peaks.amplitude
        C = self.channels
        freq = self._frequencies(ch, idx) if self._need_f else None
        if first_w == last_w:
            # The usual case (a block inside one window): plain per-channel sums.
            row = self._open[first_w - self._next]
            for k, name in enumerate(self.features):
                w = amp if name == "A" else freq if name == "f" else amp * freq
                row[k] += np.bincount(ch, weights=w, minlength=C)
            return
        slot = ((idx + 1) // self.length - self._next) * C + ch     # (window of detection, channel) bin
        nbins = self._open.shape[0] * C
        for k, name in enumerate(self.features):
            w = amp if name == "A" else freq if name == "f" else amp * freq
            self._open[:, k, :] += np.bincount(slot, weights=w, minlength=nbins).reshape(-1, C)

    def _frequencies(self, ch: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """``f_k = fs / (n_k - n_(k-1))`` per peak, 0 for a channel's first peak ever; updates the last peaks."""
        # Peaks come sorted by channel: a channel's run starts where the channel number changes.
        counts = np.bincount(ch, minlength=self.channels)
        ends = np.cumsum(counts)
        present = np.flatnonzero(counts)                      # channels with a peak in this call
        firsts = ends[present] - counts[present]
        prev = np.empty_like(idx)
        prev[1:] = idx[:-1]
        before = self._last_peak[present]                     # each channel's previous peak, -1 if none
        prev[firsts] = before
        self._last_peak[present] = idx[ends[present] - 1]
        freq = self.fs / (idx - prev)
        freq[firsts[before < 0]] = 0.0
        return freq

    @property
    def windows_emitted(self) -> int:
        return self._next
