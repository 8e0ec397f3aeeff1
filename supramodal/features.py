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

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from supramodal.errors import InputError
from supramodal.peaks import Peaks


@dataclass(frozen=True)
class Feature:
    """One per-window feature: how a peak contributes to it, and what it means.

    Attributes
    ----------
    name : str
    description : str
        One line, for help texts and error messages.
    needs_frequency : bool
        Whether :attr:`term` uses the peaks' instantaneous frequencies (they are
        computed only if some selected feature needs them).
    term : callable(amplitude, frequency) -> ndarray
        A peak's contribution to the window's sum, from its amplitude ``A_k`` and
        instantaneous frequency ``f_k`` in Hz (``None`` when not needed), shape (peaks,).
    unit : str
        The unit of the window's sum, as stream meta-data names it (amplitudes in full scale:
        a sample of 1.0 is the driver's full scale).
    """

    name: str
    description: str
    needs_frequency: bool
    term: Callable[[np.ndarray, np.ndarray | None], np.ndarray]
    unit: str = ""


def _given(freq: np.ndarray | None) -> np.ndarray:
    """Return the peaks' frequencies, which a feature that ``needs_frequency`` is always given."""
    assert freq is not None, "FeatureWindows computes them when a selected feature needs_frequency"
    return freq


#: The one table of features: the names a scene, the command line or a model file may use,
#: the check of a selection and the computation all come from it.
FEATURE_TABLE: dict[str, Feature] = {f.name: f for f in (
    Feature("Af", "sum of A_k f_k, the equivalent noise level (Hz x amplitude)", True,
            lambda amp, freq: amp * _given(freq), "Hz*fullscale"),
    Feature("A", "sum of the peak amplitudes A_k (full scale 1.0)", False, lambda amp, freq: amp, "fullscale"),
    Feature("f", "sum of the instantaneous frequencies f_k (Hz)", True, lambda amp, freq: _given(freq), "Hz"),
)}
#: Every feature name, in the table's order (the default selection computes all of them); made at import, so
#: a check of a name reads :data:`FEATURE_TABLE` itself, which a row added later is in.
FEATURES = tuple(FEATURE_TABLE)
#: Feature window, seconds (the paper's 100 ms; the one home of this default, also for the
#: pipeline, the scene and the command line).
DEFAULT_WINDOW = 0.1


def check_features(features) -> tuple[str, ...]:
    """Validate a feature selection; returns it as a tuple in the given order.

    Raises
    ------
    InputError
        An empty selection, a name not in :data:`FEATURE_TABLE` (the message lists the
        known ones) or a name given twice.
    """
    if isinstance(features, str):
        features = (features,)
    features = tuple(features)
    if not features:
        raise InputError(f"choose at least one feature from {list(FEATURE_TABLE)}")
    unknown = [f for f in features if f not in FEATURE_TABLE]
    if unknown:
        known = "; ".join(f"{f.name}: {f.description}" for f in FEATURE_TABLE.values())
        raise InputError(f"unknown feature(s) {unknown}; the features are {known}")
    if len(set(features)) != len(features):
        raise InputError(f"features repeat in {features}")
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
            raise InputError(f"windows are not consecutive: {a.first}+{len(a)} then {b.first}")
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
    features : sequence of str
        Names from :data:`FEATURE_TABLE`; only these are computed, in this order.

    Notes
    -----
    Not thread-safe. Memory holds only the windows not yet closed.
    """

    def __init__(self, channels: int, fs: float, length: int, features=FEATURES) -> None:
        if not (isinstance(length, (int, np.integer)) and length >= 1):
            raise InputError(f"window length must be a whole number of samples >= 1, got {length!r}")
        if not (np.isfinite(fs) and fs > 0):
            raise InputError(f"sample rate must be > 0 Hz, got {fs!r}")
        self.channels = int(channels)
        self.fs = float(fs)
        self.length = int(length)
        self.features = check_features(features)
        self._terms = tuple(FEATURE_TABLE[name].term for name in self.features)
        self._need_f = any(FEATURE_TABLE[name].needs_frequency for name in self.features)
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
                raise InputError("a peak falls in a window already emitted: peaks must come in stream order")
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
            for k, term in enumerate(self._terms):
                row[k] += np.bincount(ch, weights=term(amp, freq), minlength=C)
            return
        slot = ((idx + 1) // self.length - self._next) * C + ch     # (window of detection, channel) bin
        nbins = self._open.shape[0] * C
        for k, term in enumerate(self._terms):
            self._open[:, k, :] += np.bincount(slot, weights=term(amp, freq), minlength=nbins).reshape(-1, C)

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
        """Windows emitted so far: the index the next window gets."""
        return self._next
