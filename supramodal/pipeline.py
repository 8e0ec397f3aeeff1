"""Filterbank -> peaks -> feature windows, chained: a block of samples in, closed windows out.

The same object serves the offline experiments (one call on a whole file, or a
few large blocks) and the live node (one call per driver block): the output does
not depend on how the signal was cut into blocks.
"""

from __future__ import annotations

import numpy as np

from supramodal.banks import Bank
from supramodal.features import FEATURES, FeatureWindows, Windows, check_features, concat_windows
from supramodal.gammatone import DEFAULT_SUBBLOCK, GammatoneFilterbank
from supramodal.peaks import PeakExtractor

DEFAULT_WINDOW = 0.1


def window_length(window: float, fs: float) -> int:
    """Window length in samples for ``window`` seconds at ``fs`` Hz (rounded to the nearest sample)."""
    if not (np.isfinite(window) and window > 0):
        raise ValueError(f"window must be a positive number of seconds, got {window!r}")
    n = int(round(window * fs))
    if n < 2:
        raise ValueError(f"a window of {window} s is {n} sample(s) at {fs:g} Hz; it needs at least 2")
    return n


class FeaturePipeline:
    """Gammatone filterbank, peak extractor and feature windows for one stream.

    Parameters
    ----------
    bank : Bank
    features : sequence of {"Af", "A", "f"}
        Features to compute (default all three); only these are computed.
    window : float
        Window length in seconds (default 0.1), rounded to whole samples.
    dtype : {numpy.float64, numpy.float32}
        Filterbank arithmetic (default float64).
    peak_mode : {"maxima", "extrema"}
    peak_threshold : float
        Smallest peak amplitude counted (default 0), see :class:`~supramodal.peaks.PeakExtractor`.
    nonfinite : {"raise", "zero"}
        NaN/Inf input policy, see :class:`~supramodal.gammatone.GammatoneFilterbank`.
    subblock : int
        Filterbank sub-block length.
    """

    def __init__(self, bank: Bank, features=FEATURES, window: float = DEFAULT_WINDOW, dtype=np.float64,
                 peak_mode: str = "maxima", nonfinite: str = "raise", subblock: int = DEFAULT_SUBBLOCK,
                 peak_threshold: float = 0.0) -> None:
        self.bank = bank
        self.features = check_features(features)
        self.window = float(window)
        self.window_samples = window_length(window, bank.fs)
        self.filterbank = GammatoneFilterbank(bank, dtype=dtype, subblock=subblock, nonfinite=nonfinite)
        self.peaks = PeakExtractor(bank.channels, mode=peak_mode, threshold=peak_threshold)
        self.windows = FeatureWindows(bank.channels, bank.fs, self.window_samples, self.features)

    def process(self, x) -> Windows:
        """Feed one block, shape (L,) or (channels, L); return the windows it closes."""
        return self.windows.process(self.peaks.process(self.filterbank.process(x)))

    def finish(self) -> Windows:
        """End of stream: close the last complete window. A trailing partial window is dropped
        (see :attr:`partial_samples`)."""
        return self.windows.process(self.peaks.finish())

    @property
    def partial_samples(self) -> int:
        """Samples after the last complete window: not part of any emitted window."""
        return self.peaks.samples_seen - self.windows.windows_emitted * self.window_samples

    def run(self, x, block: int | None = None) -> Windows:
        """Whole signal through the pipeline (optionally in blocks of ``block`` samples), finished."""
        x = np.asarray(x)
        L = x.shape[-1]
        step = L if not block else int(block)
        parts = [self.process(x[..., i : i + step]) for i in range(0, max(L, 1), max(step, 1))]
        parts.append(self.finish())
        return concat_windows(parts, self.features, self.bank.channels)


def extract_features(x, bank: Bank, features=FEATURES, window: float = DEFAULT_WINDOW, block: int | None = 65536,
                     **kwargs) -> Windows:
    """Features of a whole signal, offline: shape (windows, features, channels)."""
    return FeaturePipeline(bank, features, window, **kwargs).run(x, block=block)
