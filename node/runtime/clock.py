"""A source's clock: its sample index mapped to the host's monotonic time.

A serial board and a sound card each count samples on their own crystal, tens of ppm away from
the nominal rate, and their blocks reach the host late by a variable delay (USB polling, the
audio server's period, the scheduler). To put two sources on one time line, each gets a
:class:`ClockModel` fed with every block's last sample index and arrival time; it estimates the
line ``t = offset + index / rate`` on which the samples were really taken.

Why a lower envelope. Delays are never negative: every arrival lies on or above the true line,
and the earliest arrivals lie closest to it. So the model keeps, per segment of the stream (1 s by
default), the one block that arrived earliest relative to the current line, and fits a straight
line by least squares through the last ``window`` segments' minima (2 min by default), rejecting
minima far off the line (a segment with no quick block at all: a stall, a burst of load). Taking
minima first makes the fit insensitive to the delay's distribution and its mean: with ~100 blocks a
segment, the minimum of 2 ms of jitter sits tens of microseconds above the line, and the rate
over a 2-minute window is good to a fraction of a ppm. A delay-locked loop (as JACK and PipeWire
run) tracks the mean arrival instead, which carries the mean delay as an offset and needs its
bandwidth tuned against the jitter; LSL's time correction also keeps the minimum-delay samples
of each exchange (Kothe et al., liblsl ``time_receiver``). The window bounds memory and lets the
estimate follow a rate that wanders with temperature.

Cost: O(1) per block (a comparison and a few float operations); a fit of at most ``window``
points once per segment. Not thread-safe: one source thread updates it; readers take
:meth:`ClockModel.estimate`, a frozen snapshot.

:func:`frames_at` runs a recorded source's block times through a model, as the node ran them, to map
times on the node's common time to that source's frames: a recorder's marks and a recorded graph's
labels (``supramodal.node.workflows.labels``) are put on each source's stream with it.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from supramodal.errors import InputError

#: Length of the segments whose earliest arrivals are fitted, seconds of stream.
DEFAULT_SEGMENT_SECONDS = 1.0
#: Segments in the fit: 2 minutes of stream.
DEFAULT_WINDOW_SEGMENTS = 120
#: A segment minimum further above the fitted line than the minima's median by this many robust
#: spreads (and by MIN_OUTLIER_SECONDS) is left out of the fit: no block of that segment came quickly.
OUTLIER_SPREADS = 5.0
#: Most fits of one update (each refit drops or restores minima; it settles in two or three).
MAX_REFITS = 8
#: Floor of the outlier threshold, seconds (a perfectly regular source has no spread at all).
MIN_OUTLIER_SECONDS = 2e-4
#: Blocks whose delays make up the jitter figure (the most recent ones).
JITTER_BLOCKS = 512


class ClockError(InputError):
    """A clock update or query that cannot be right (time going backwards, a non-finite time).

    The message names the value and the fix.
    """


@dataclass(frozen=True)
class ClockEstimate:
    """What a :class:`ClockModel` believes, at one moment.

    Attributes
    ----------
    nominal_rate : float
        The rate the source claims, Hz.
    rate : float
        The estimated true rate, Hz (the nominal rate until the first fit).
    ppm : float
        ``(rate / nominal_rate - 1) * 1e6``: the source's crystal error, parts per million.
    offset : float
        Host monotonic time of sample 0, seconds.
    jitter : float
        Spread of the recent blocks' delays above the line, seconds: the difference between the
        95th and 5th percentiles of the last ``JITTER_BLOCKS`` delays.
    delay : float
        Median delay of the recent blocks above the line, seconds.
    blocks : int
        Updates since the start or the last :meth:`ClockModel.reset`.
    segments : int
        Segment minima in the current fit.
    outliers : int
        Segment minima left out of fits so far (a segment with no quick block).
    fitted : bool
        Whether ``rate`` comes from a fit (at least two segments) rather than the nominal rate.
    """

    nominal_rate: float
    rate: float
    ppm: float
    offset: float
    jitter: float
    delay: float
    blocks: int
    segments: int
    outliers: int
    fitted: bool


class ClockModel:
    """Maps a source's sample index to host monotonic time, from its blocks' arrivals.

    Parameters
    ----------
    nominal_rate : float
        The rate the source claims, Hz, > 0.
    segment_seconds : float
        Length of a segment of stream whose earliest block is kept, seconds (default 1.0).
    window_segments : int
        Segments fitted (default 120: 2 minutes at 1 s segments), >= 2.

    Notes
    -----
    Call :meth:`update` from the source's thread with every block, in stream order; call
    :meth:`reset` when the source reports that its sample count restarted (a board reset) or
    jumped. Until two segments are complete, times are extrapolated at the nominal rate from the
    earliest arrival so far.
    """

    def __init__(self, nominal_rate: float, segment_seconds: float = DEFAULT_SEGMENT_SECONDS,
                 window_segments: int = DEFAULT_WINDOW_SEGMENTS) -> None:
        if not _finite_positive(nominal_rate):
            raise ClockError(f"nominal rate must be a positive number of Hz, got {nominal_rate!r}")
        if not _finite_positive(segment_seconds):
            raise ClockError(f"segment_seconds must be a positive number of seconds, got {segment_seconds!r}")
        if isinstance(window_segments, bool) or not isinstance(window_segments, int) or window_segments < 2:
            raise ClockError(f"window_segments must be an integer >= 2, got {window_segments!r}")
        self.nominal_rate = float(nominal_rate)
        self.segment_samples = max(1, int(round(segment_seconds * self.nominal_rate)))
        self.window_segments = window_segments
        self._outliers = 0
        self.reset()

    def reset(self) -> None:
        """Forget every block: the source's sample count restarted or jumped."""
        self._minima: collections.deque[tuple[int, float]] = collections.deque(maxlen=self.window_segments)
        self._segment: int | None = None   # current segment number
        # (index, arrival) of its earliest block relative to the line
        self._best: tuple[int, float] | None = None
        self._slope = 1.0 / self.nominal_rate   # seconds per sample
        self._offset = math.nan         # time of sample 0
        self._fitted = False
        self._last_index: int | None = None
        self._last_arrival = -math.inf
        self._blocks = 0
        self._delays = np.zeros(JITTER_BLOCKS)
        self._delay_count = 0

    def update(self, index: int, arrival: float) -> None:
        """Take one block: ``index`` of its last sample, ``arrival`` its host monotonic time, s.

        Raises
        ------
        ClockError
            If ``arrival`` is not finite or goes backwards, or ``index`` does not grow (call
            :meth:`reset` when the source's count restarts).
        """
        if not math.isfinite(arrival):
            raise ClockError(f"arrival time must be finite, got {arrival!r}")
        if self._last_index is not None and index <= self._last_index:
            raise ClockError(f"sample index {index} does not follow {self._last_index}: blocks must come in "
                             "stream order; reset() the clock when the source's count restarts")
        if arrival < self._last_arrival:
            raise ClockError(f"arrival {arrival!r} s is before the previous block's {self._last_arrival!r} s: "
                             "give times of one monotonic clock (time.monotonic())")
        self._last_index, self._last_arrival = index, arrival
        self._blocks += 1
        # The line through this block at the current slope: its intercept is the block's sample-0 time.
        intercept = arrival - index * self._slope
        if not self._fitted and not intercept >= self._offset:   # before a fit: the earliest block so far
            self._offset = intercept
        self._delays[self._delay_count % JITTER_BLOCKS] = intercept - self._offset
        self._delay_count += 1
        segment = index // self.segment_samples
        if segment != self._segment:
            if self._best is not None:
                self._minima.append(self._best)
                if len(self._minima) >= 2:
                    self._fit()
            self._segment, self._best = segment, (index, arrival)
        elif self._best is not None and intercept < self._best[1] - self._best[0] * self._slope:
            self._best = (index, arrival)

    def _fit(self) -> None:
        n = np.array([m[0] for m in self._minima], dtype=np.float64)
        t = np.array([m[1] for m in self._minima], dtype=np.float64)
        n0, t0 = n[-1], t[-1]           # centred on the latest minimum: no cancellation at large index
        x, y = n - n0, t - t0
        # Start from the line so far (a burst of late segments after an outage cannot tilt it), or
        # from all points the first time; then keep the minima near the line and refit, until the
        # kept set is stable. The final line is always the fit of the final kept set.
        if self._fitted:
            slope, icpt = self._slope, self._offset + n0 * self._slope - t0
        else:
            slope, icpt = _line(x, y, self._slope)
        keep = np.ones(len(n), dtype=bool)
        for _ in range(MAX_REFITS):
            resid = y - (icpt + slope * x)
            centre = float(np.median(resid))
            spread = 1.4826 * float(np.median(np.abs(resid - centre)))
            new_keep = resid - centre <= max(OUTLIER_SPREADS * spread, MIN_OUTLIER_SECONDS)
            if new_keep.sum() < 2:
                break
            slope, icpt = _line(x[new_keep], y[new_keep], slope)
            if np.array_equal(new_keep, keep):
                break
            keep = new_keep
        self._outliers += int(not keep[-1])      # each segment judged once, when it joins the fit
        if not (math.isfinite(slope) and slope > 0):
            # Blocks that all came at one instant (a device far faster than real time, stamps equal
            # to the microsecond) say nothing of the rate: keep the line so far.
            return
        self._slope = slope
        self._offset = t0 + icpt - n0 * slope
        self._fitted = True

    def line(self) -> tuple[float, float]:
        """Return ``(offset, slope)``: host time of sample 0, seconds, and seconds per sample.

        Cheaper than :meth:`estimate`, for a caller that maps many indices.
        """
        return self._offset, self._slope

    @overload
    def time_of(self, index: float) -> float: ...
    @overload
    def time_of(self, index: np.ndarray) -> np.ndarray: ...

    def time_of(self, index: float | np.ndarray) -> float | np.ndarray:
        """Return the host monotonic time of sample ``index`` (scalar or array), seconds."""
        return self._offset + np.asarray(index, dtype=np.float64) * self._slope if np.ndim(index) else \
            self._offset + float(index) * self._slope

    @overload
    def index_at(self, time: float) -> float: ...
    @overload
    def index_at(self, time: np.ndarray) -> np.ndarray: ...

    def index_at(self, time: float | np.ndarray) -> float | np.ndarray:
        """Return the sample index (fractional) taken at host monotonic ``time`` (scalar or array), seconds."""
        return (np.asarray(time, dtype=np.float64) - self._offset) / self._slope if np.ndim(time) else \
            (float(time) - self._offset) / self._slope

    def estimate(self) -> ClockEstimate:
        """Return a snapshot of the current estimate."""
        k = min(self._delay_count, JITTER_BLOCKS)
        recent = self._delays[:k]
        if k:
            p5, p50, p95 = np.percentile(recent, [5, 50, 95])
        else:
            p5 = p50 = p95 = 0.0
        rate = 1.0 / self._slope
        return ClockEstimate(self.nominal_rate, rate, (rate / self.nominal_rate - 1.0) * 1e6, self._offset,
                             float(p95 - p5), float(p50), self._blocks, len(self._minima), self._outliers,
                             self._fitted)


def frames_at(arrivals: tuple[Sequence[int], Sequence[float], float], times: ArrayLike,
              marks: Iterable[tuple[int, str]] = ()) -> NDArray[np.float64]:
    """Return the stream position (fractional frame) a source had reached at each common time in ``times``.

    The source's clock model is fed its blocks as the node fed it live and as its replay feeds it
    (``update(end - 1, time)`` per block, ``reset()`` at a ``restart`` mark); a time is mapped by the
    line as it stood after the first block complete at or after it (the last block's line past the
    end), as the node maps a window by the line of the block that completed it.

    Parameters
    ----------
    arrivals : (frames, seconds, rate)
        Each block's end frame, the common time it was complete (seconds), and the clock model's
        nominal rate (Hz): a session's ``arrivals``.
    times : array_like of float
        Seconds of common time.
    marks : iterable of (frame, kind)
        The session's marks (only ``"restart"`` counts: the count restarted, the old line is void).

    Returns
    -------
    ndarray of float64
        Frames, same shape as ``times``; not clipped to the stream.
    """
    ends = np.asarray(arrivals[0], dtype=np.int64)
    stamps = np.asarray(arrivals[1], dtype=np.float64)
    clock = ClockModel(float(arrivals[2]))
    restarts = sorted(i for i, kind in marks if kind == "restart")
    lines = np.empty((len(ends), 2))
    r = 0
    for j, (end, stamp) in enumerate(zip(ends.tolist(), stamps.tolist())):
        if r < len(restarts) and restarts[r] < end:       # a restart inside this block, as the source resets
            while r < len(restarts) and restarts[r] < end:
                r += 1
            clock.reset()
        clock.update(end - 1, stamp)
        lines[j] = clock.line()
    t = np.asarray(times, dtype=np.float64)
    k = np.minimum(np.searchsorted(stamps, t, side="left"), len(ends) - 1)
    offset, slope = lines[k, 0], lines[k, 1]
    frames: NDArray[np.float64] = (t - offset) / slope
    return frames


def _line(x: np.ndarray, y: np.ndarray, slope_now: float) -> tuple[float, float]:
    """Least-squares ``y = icpt + slope x``; with all x equal, the line at ``slope_now``."""
    xm, ym = x.mean(), y.mean()
    sxx = float(((x - xm) ** 2).sum())
    if sxx == 0.0:
        return slope_now, float(ym - slope_now * xm)
    slope = float(((x - xm) * (y - ym)).sum() / sxx)
    return slope, float(ym - slope * xm)


def _finite_positive(v: object) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v > 0
