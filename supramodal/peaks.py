"""Streaming peak extractor: the hair cell / mechanoreceptor stage (paper Sect. 3).

Every sample that is not a local extremum is set to zero; what remains is kept
as sparse events (channel, stream index, amplitude). The choice of the project
(the paper says "local extrema"): by default only positive local maxima,
``x[n-1] < x[n] >= x[n+1]`` and ``x[n] > 0``, like a half-wave rectifying hair
cell; ``mode="extrema"`` keeps minima too, with their absolute value as
amplitude.

In a stream the last sample of a block cannot be decided until the next
sample arrives: it is decided with the next block, or by :meth:`finish` at the
end of the stream (where it counts as no peak, having no successor).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import DTypeLike

from supramodal.checks import is_number
from supramodal.errors import InputError, StreamEndedError

PEAK_MODES = ("maxima", "extrema")
DEFAULT_PEAK_MODE = "maxima"
#: A peak's amplitude must exceed this, whatever the threshold (0 included). A filterbank left in
#: exact silence rings down through 1e-300 and below, and flushes its state to zero at times that
#: depend on where block boundaries fall (gammatone's ``_flush_tiny``): peaks of that residue would
#: make the first window after a long silence depend on the chunking (up to 2.7e-3 of Af, measured).
#: 1e-250 lies some 200 orders of magnitude below any physical signal and far above the residue's
#: flush level (about 1e-287), so it changes no feature of real input (docs/stability.md).
PEAK_FLOOR = 1e-250


@dataclass(frozen=True)
class Peaks:
    """Peaks decided by one call, sorted by channel then stream index.

    Attributes
    ----------
    channel : ndarray of intp, shape (n,)
    index : ndarray of int64, shape (n,)
        Stream index of the peak sample (0 = first sample of the stream).
    amplitude : ndarray of float, shape (n,)
        Peak value (absolute value for minima in ``"extrema"`` mode), > 0.
    decided : int
        Every sample with stream index below this is decided: later calls never
        report a peak before it.
    seen : int
        Samples the extractor has received. Mid-stream ``decided + 1`` (the last
        sample waits for its successor); after :meth:`PeakExtractor.finish` equal
        to ``decided``. A feature window is complete once all its samples are seen.
    """

    channel: np.ndarray
    index: np.ndarray
    amplitude: np.ndarray
    decided: int
    seen: int = -1

    def __post_init__(self) -> None:
        if self.seen < 0:
            object.__setattr__(self, "seen", self.decided + 1)

    def __len__(self) -> int:
        return int(self.index.size)


class PeakExtractor:
    """Turns filterbank output blocks into peak events, block by block.

    Parameters
    ----------
    channels : int
        Number of channels of the blocks it will receive.
    mode : {"maxima", "extrema"}
        Positive local maxima only (default), or all local extrema.
    threshold : float
        Smallest peak amplitude kept (default 0: every local maximum above 0, the
        paper's rule). A real sensor's noise floor, or the filters' ring-down
        after a contact ends, gives peaks of no meaning; a threshold drops them.
        Whatever the threshold, a peak must also exceed :data:`PEAK_FLOOR` (1e-250).

    Notes
    -----
    The stream starts at rest: the two samples before the first are taken as 0,
    which is what the filterbank outputs at rest. Not thread-safe.
    """

    def __init__(self, channels: int, mode: str = DEFAULT_PEAK_MODE, threshold: float = 0.0) -> None:
        if mode not in PEAK_MODES:
            raise InputError(f"peak mode must be one of {PEAK_MODES}, got {mode!r}")
        if not (is_number(threshold) and threshold >= 0):
            raise InputError(f"peak threshold must be a finite amplitude >= 0, got {threshold!r}")
        self.threshold = float(threshold)
        if channels < 1:
            raise InputError(f"channels must be >= 1, got {channels}")
        self.channels = int(channels)
        self.mode = mode
        self._z: np.ndarray | None = None      # (channels, 2 + L): the last two samples seen, then the block
        self._staged: np.ndarray | None = None
        self._scratch: dict[str, np.ndarray] = {}
        self.samples_seen = 0
        self._finished = False

    def staging(self, length: int, dtype: DTypeLike = np.float64) -> np.ndarray:
        """Return a (channels, length) array to write the next block into.

        Pass that very array to :meth:`process` next, which then skips copying it (an
        optimisation for the pipeline).
        """
        self._staged = self._buffer(int(length), np.dtype(dtype))[:, 2:]
        return self._staged

    def _buffer(self, L: int, dtype: np.dtype) -> np.ndarray:
        """Return the (channels, L + 2) work array, its first two columns holding the last two samples.

        It is a view of one flat array kept between blocks and grown only when a block is longer
        than any before: a pipeline's stages of varying length (three chunks, then one) would
        otherwise allocate and fault in a fresh array at each change of length.
        """
        z = self._z
        if z is not None and z.shape[1] == L + 2 and z.dtype == dtype:
            return z
        tail = None if z is None else z[:, :2].copy()     # the old layout's first columns, before the new overwrites
        size = self.channels * (L + 2)
        backing = self._scratch.get("z")
        if backing is None or backing.size < size or backing.dtype != dtype:
            backing = self._scratch["z"] = np.empty(max(size, 0 if backing is None else backing.size), dtype=dtype)
        self._z = z = backing[:size].reshape(self.channels, L + 2)
        z[:, :2] = 0.0 if tail is None else tail
        return z

    def process(self, y: np.ndarray) -> Peaks:
        """Decide the peaks that ``y`` makes decidable.

        Parameters
        ----------
        y : ndarray, shape (channels, L)
            Next block of filterbank output; L may be 0.

        Returns
        -------
        Peaks
            Peaks among stream samples ``samples_seen - 1 .. samples_seen + L - 2``
            (the previous block's last sample and all but this block's last).
        """
        if self._finished:
            raise StreamEndedError("finish() was called: this peak extractor's stream has ended")
        staged, self._staged = self._staged, None
        y = np.asarray(y)
        if y.ndim != 2 or y.shape[0] != self.channels:
            raise InputError(f"expected a block of shape ({self.channels}, L), got {y.shape}")
        L = y.shape[1]
        n0 = self.samples_seen
        if L == 0:
            return self._empty(max(n0 - 1, 0), n0)
        if y is staged:
            z = self._z
            assert z is not None, "staging() made the work array"
        else:
            if self._z is not None and np.may_share_memory(y, self._z):
                y = y.copy()                                   # part of the work array, which is laid out anew
            z = self._buffer(L, y.dtype if y.dtype.kind == "f" else np.dtype(np.float64))
            z[:, 2:] = y                                       # stream samples n0-2 .. n0+L-1
        self.samples_seen = n0 + L
        peaks = self._find(z, first_index=n0 - 1)
        z[:, :2] = z[:, L : L + 2]                             # the tail for the next block
        return Peaks(*peaks, decided=n0 + L - 1, seen=n0 + L)

    def finish(self) -> Peaks:
        """End of stream: the last sample has no successor and is not a peak.

        Returns the (empty) final decision, with ``decided`` = every sample seen.
        """
        self._finished = True
        return self._empty(self.samples_seen, self.samples_seen)

    def _find(self, z: np.ndarray, first_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        C, n = z.shape                                         # n = L + 2: two samples of the past first
        flat = z.reshape(-1)
        N = flat.size
        t = max(self.threshold, PEAK_FLOOR)
        if self.mode == "maxima":
            # The local maxima of the flattened rows, z[n-1] < z[n] >= z[n+1], as the samples the
            # signal rises into and does not rise out of; those at or below t are dropped after
            # (a tenth of the samples, where a max(z, t) first would be another pass over all).
            # The two columns whose neighbours lie in another row (the first and the last) are
            # cleared below.
            rise = np.greater(flat[1:], flat[:-1], out=self._work("rise", N - 1, bool))
            is_peak = self._work("peak", N, bool)
            np.greater(rise[:-1], rise[1:], out=is_peak[1:-1])
        else:
            left, mid, right = flat[:-2], flat[1:-1], flat[2:]
            is_peak = np.empty(N, dtype=bool)
            is_peak[1:-1] = ((left < mid) & (mid >= right) & (mid > t)) | ((left > mid) & (mid <= right) & (mid < -t))
        grid = is_peak.reshape(C, n)
        grid[:, 0] = False
        grid[:, -1] = False
        if first_index < 0:
            grid[:, : 1 - first_index] = False                 # samples before the stream began
        where = is_peak.nonzero()[0]
        amplitude = flat[where]
        if self.mode == "extrema":
            amplitude = np.abs(amplitude)
        else:
            loud = amplitude > t
            if not loud.all():
                where, amplitude = where[loud], amplitude[loud]
        channel, column = np.divmod(where, n)
        column += first_index - 1                              # stream index of each peak
        return channel, column, amplitude

    def _work(self, name: str, size: int, dtype: DTypeLike) -> np.ndarray:
        """Return a scratch array kept between blocks (fresh large arrays cost page faults every block)."""
        a = self._scratch.get(name)
        if a is None or a.size < size or a.dtype != dtype:
            a = self._scratch[name] = np.empty(size, dtype=dtype)
        return a[:size]

    def _empty(self, decided: int, seen: int) -> Peaks:
        return Peaks(np.empty(0, np.intp), np.empty(0, np.int64), np.empty(0), decided, seen)
