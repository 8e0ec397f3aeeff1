"""Filterbank -> peaks -> feature windows, chained: a block of samples in, closed windows out.

The same object serves the offline experiments (one call on a whole file, or a
few large blocks) and the live node (one call per driver block): the output does
not depend on how the signal was cut into blocks.
"""

from __future__ import annotations

import numpy as np

from supramodal.backends import make_filterbank
from supramodal.banks import Bank
from supramodal.checks import is_number
from supramodal.errors import InputError, StreamEndedError
from supramodal.features import DEFAULT_WINDOW, FEATURES, FeatureWindows, Windows, check_features, concat_windows
from supramodal.peaks import DEFAULT_PEAK_MODE, PeakExtractor

#: Most samples a feature window may span (2**20: 24 s at 44.1 kHz, 210 s at 5 kHz), a bound on
#: what a scene or a model file can make the node buffer.
MAX_WINDOW_SAMPLES = 2**20
#: Fewest channel-samples in one pass of the peak extractor and the feature windows when a
#: pipeline runs in chunks (a window's last pass excepted). Their cost per channel-sample, measured
#: on the cochlea bank (2026-11-30, one core): 5.2 ns in passes of 441 samples x 50 channels (a
#: pass's fixed cost, some 25 us of numpy calls, weighs), 3.0 ns in passes of 1323 x 50, 3.7 ns in
#: passes of a whole window, 4410 x 50 (its arrays outgrow the cache).
STAGE_CELLS = 65536


def window_length(window: float, fs: float) -> int:
    """Window length in samples for ``window`` seconds at ``fs`` Hz, rounded to the nearest sample.

    It must be 2 .. :data:`MAX_WINDOW_SAMPLES` (:class:`InputError` otherwise).
    """
    if not (is_number(window) and window > 0):
        raise InputError(f"window must be a positive number of seconds, got {window!r}")
    n = int(round(window * fs))
    if n < 2:
        raise InputError(f"a window of {window} s is {n} sample(s) at {fs:g} Hz; it needs at least 2")
    if n > MAX_WINDOW_SAMPLES:
        raise InputError(f"a window of {window:g} s is {n} samples at {fs:g} Hz, more than MAX_WINDOW_SAMPLES "
                         f"({MAX_WINDOW_SAMPLES}, {MAX_WINDOW_SAMPLES / fs:g} s); choose a shorter window")
    return n


class FeaturePipeline:
    """Gammatone filterbank, peak extractor and feature windows for one stream.

    Parameters
    ----------
    bank : Bank
    features : sequence of str
        Names from :data:`~supramodal.features.FEATURE_TABLE` to compute (default: every one); only
        these are computed.
    window : float
        Window length in seconds (default :data:`DEFAULT_WINDOW`), rounded to whole samples.
    dtype : {numpy.float64, numpy.float32}
        Filterbank arithmetic (default float64).
    peak_mode : {"maxima", "extrema"}
    peak_threshold : float
        Smallest peak amplitude counted (default 0), see :class:`~supramodal.peaks.PeakExtractor`.
    nonfinite : {"raise", "zero"}
        NaN/Inf input policy, see :class:`~supramodal.gammatone.FilterbankBase`.
    subblock : int or None
        Sub-block length of the fast filterbank (default: chosen per block length).
    backend : {"fast", "reference"}
        Filterbank backend (:mod:`supramodal.backends`).
    gather : bool
        True (default): blocks are checked on arrival and gathered; the filterbank,
        the peak extractor and the feature windows run once a window's last sample
        has arrived, on everything up to that window's end. The windows returned
        by each call are the same as without gathering (the filterbank's output
        does not depend on the partition beyond rounding), with far fewer numpy
        calls for small blocks. False runs every stage on every block as it comes.
    chunk : float or None
        With ``gather``, also run the stages on every ``chunk`` seconds of each
        window as soon as they are in (at stream indices ``w * W + k * C``, C the
        chunk rounded to whole samples), so that only a window's last chunk is left
        to run when it closes: the live node's decision latency. The peak extractor
        and the feature windows run on *stages* of whole chunks, each at least
        :data:`STAGE_CELLS` channel-samples or the rest of its window (three 10 ms
        chunks for the cochlea's 50 channels, one stage per window for the whisker
        array's 20), since a pass of theirs costs some 25 us whatever its length. The cut
        points are fixed by stream index, so the output does not depend on how the
        signal was cut into blocks, to the last bit. None or 0 (default): each
        window runs whole once its last sample is in.

    Notes
    -----
    Non-finite samples are refused or replaced (and counted) in the call that
    brings them, gathering or not.
    """

    def __init__(self, bank: Bank, features=FEATURES, window: float = DEFAULT_WINDOW, dtype=np.float64,
                 peak_mode: str = DEFAULT_PEAK_MODE, nonfinite: str = "raise", subblock: int | None = None,
                 peak_threshold: float = 0.0, backend: str = "fast", gather: bool = True,
                 chunk: float | None = None) -> None:
        self.bank = bank
        self.features = check_features(features)
        self.window = float(window)
        self.window_samples = window_length(window, bank.fs)
        options = {} if subblock is None else {"subblock": subblock}
        self.filterbank = make_filterbank(bank, backend, dtype=dtype, nonfinite=nonfinite, **options)
        self.peaks = PeakExtractor(bank.channels, mode=peak_mode, threshold=peak_threshold)
        self.windows = FeatureWindows(bank.channels, bank.fs, self.window_samples, self.features)
        self.gather = bool(gather)
        self.chunk_samples = self._chunk_samples(chunk)
        self._buf: np.ndarray | None = None   # gathered samples not yet filtered: (n,) mono or (channels, n)
        self._held = 0                          # how many (the first of _buf's last axis)
        self._stage: np.ndarray | None = None   # chunked: the filterbank's output of the stage begun
        self._staged = 0                        # how much of it is filled (filtered, peaks not yet run)
        self._finished = False
        self._empty: Windows | None = None

    def process(self, x) -> Windows:
        """Feed one block, shape (L,) or (channels, L); return the windows it closes."""
        if self._finished:
            raise StreamEndedError("finish() was called: this pipeline's stream has ended")
        x = self.filterbank.prepare(x)
        if not self.gather:
            return self._run(x)
        parts: list[Windows] = []
        if self._held and x.ndim != self._held_buffer().ndim:
            parts.append(self._release(self._held))          # mono after per-channel, or the reverse
        self._hold(x)
        start = self.peaks.samples_seen + self._staged         # stream index of the first held sample
        if self.chunk_samples:
            # One filterbank pass per chunk: the partition, and so the rounding, is fixed by stream index.
            while (cut := self._next_cut(start) - start) <= self._held:
                parts.append(self._release(cut))
                start += cut
        else:
            W = self.window_samples
            upto = (start + self._held) // W * W - start       # held samples up to the last window end
            if upto > 0:
                parts.append(self._release(upto))
        if not parts:
            return self._no_windows()
        return parts[0] if len(parts) == 1 else concat_windows(parts, self.features, self.bank.channels)

    def _chunk_samples(self, chunk) -> int:
        """``chunk`` seconds in whole samples; 0 when windows run whole."""
        if chunk is None or chunk == 0:
            return 0
        if not (is_number(chunk) and chunk > 0):
            raise InputError(f"chunk must be a positive number of seconds (or 0: whole windows), got {chunk!r}")
        n = int(round(chunk * self.bank.fs))
        if n < 1:
            raise InputError(f"a chunk of {chunk:g} s is less than one sample at {self.bank.fs:g} Hz; "
                             f"choose at least {1 / self.bank.fs:.3g} s, or 0 for whole windows")
        return 0 if n >= self.window_samples else n

    def _next_cut(self, index: int) -> int:
        """Return the first cut point after stream index ``index``: the next chunk end or window end."""
        W, C = self.window_samples, self.chunk_samples
        w0 = index // W * W
        return min(w0 + ((index - w0) // C + 1) * C, w0 + W)

    def _no_windows(self) -> Windows:
        """Return an empty result (shared: it holds nothing to change)."""
        first = self.windows.windows_emitted
        if self._empty is None or self._empty.first != first:
            self._empty = Windows(first, np.zeros((0, len(self.features), self.bank.channels)), self.features)
        return self._empty

    def _hold(self, x: np.ndarray) -> None:
        L = x.shape[-1]
        need = self._held + L
        if self._buf is None or self._buf.shape[-1] < need or x.ndim != self._buf.ndim:
            size = max(need, 2 * self.window_samples, 2 * (0 if self._buf is None else self._buf.shape[-1]))
            buf = np.empty(x.shape[:-1] + (size,), dtype=x.dtype)
            if self._held:
                buf[..., : self._held] = self._held_buffer()[..., : self._held]
            self._buf = buf
        self._buf[..., self._held : need] = x
        self._held = need

    def _held_buffer(self) -> np.ndarray:
        """:attr:`_buf`, when samples are held (there is one)."""
        assert self._buf is not None, "held samples are kept in _buf"
        return self._buf

    def _release(self, n: int) -> Windows:
        """Run the first ``n`` held samples through the stages; keep the rest held."""
        buf = self._held_buffer()
        out = self._run_chunk(buf[..., :n]) if self.chunk_samples else self._run(buf[..., :n])
        rest = self._held - n
        if rest:
            buf[..., :rest] = buf[..., n : self._held]
        self._held = rest
        return out

    def _run(self, x: np.ndarray) -> Windows:
        # The filterbank writes straight into the peak extractor's work array (no copy between them).
        y = self.peaks.staging(x.shape[-1], self.filterbank.dtype)
        self.filterbank.process(x, prepared=True, out=y)
        return self.windows.process(self.peaks.process(y))

    def _stage_end(self, start: int) -> int:
        """Where a stage begun at stream index ``start`` (a cut point) ends.

        That is the first chunk end at least :data:`STAGE_CELLS` channel-samples on, or its
        window's end.
        """
        W, C = self.window_samples, self.chunk_samples
        w0 = start // W * W
        need = -(-STAGE_CELLS // self.bank.channels)                 # samples, rounded up
        return min(w0 - (-(start + need - w0) // C) * C, w0 + W)

    def _run_chunk(self, x: np.ndarray) -> Windows:
        """Filter (part of) one chunk into the stage; at its end, find its peaks and close the windows ending there."""
        if self._stage is None:
            start = self.peaks.samples_seen
            self._stage = self.peaks.staging(self._stage_end(start) - start, self.filterbank.dtype)
        L = x.shape[-1]
        self.filterbank.process(x, prepared=True, out=self._stage[:, self._staged : self._staged + L])
        self._staged += L
        if self._staged < self._stage.shape[1]:
            return self._no_windows()
        return self._run_stage()

    def _run_stage(self) -> Windows:
        """Find the peaks and windows of the staged filterbank output.

        All of it: up to a window's end, or the stream's.
        """
        stage, n = self._stage, self._staged
        assert stage is not None, "a chunk was staged"
        self._stage, self._staged = None, 0
        return self.windows.process(self.peaks.process(stage if n == stage.shape[1] else stage[:, :n]))

    def finish(self) -> Windows:
        """End of stream: close the last complete window.

        A trailing partial window is dropped (see :attr:`partial_samples`).
        """
        parts = [self._release(self._held)] if self._held else []
        if self._staged:
            parts.append(self._run_stage())
        self._finished = True
        parts.append(self.windows.process(self.peaks.finish()))
        return concat_windows(parts, self.features, self.bank.channels)

    @property
    def partial_samples(self) -> int:
        """Samples after the last complete window: not part of any emitted window."""
        return (self.peaks.samples_seen + self._staged + self._held
                - self.windows.windows_emitted * self.window_samples)

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
