"""The replay driver: a recording delivered block by block as a live driver would.

:class:`ReplayDriver` follows :class:`supramodal.drivers.base.Driver` exactly. It reads an
in-memory array, a WAV file or a session once, at construction (so ``rate`` and
``channels`` are known before ``open()``), optionally selects channels and
resamples, and then hands out :class:`supramodal.drivers.base.Block` objects that tile the
stream exactly: each block starts where the previous one ended, and the
concatenation of all blocks equals the (resampled) source, repeated when looping.

Pacing
------
Block ``k`` covering stream frames ``[start, end)`` is released at
:func:`release_time` ``(end, rate, speed, t0)`` = ``t0 + end / (rate * speed)``,
with ``t0`` the ``time.monotonic()`` of ``open()``: the moment its last frame
would have been measured by a live device, scaled by ``speed``. The schedule is
absolute, so waiting never accumulates drift, and a consumer that falls behind
finds the due blocks ready at once (like a driver's input buffer, but one that
never overflows). ``speed='max'`` releases every block at once.

Threading
---------
``read()`` is called from one thread. ``close()`` may be called from any thread;
it wakes a ``read()`` that is waiting for a block's release time, which then
raises :class:`supramodal.drivers.base.DriverClosed`.
"""

from __future__ import annotations

import math
import numbers
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np
from numpy.typing import ArrayLike

from supramodal.checks import Key, flag, integer, is_number, one_of, text
from supramodal.drivers.base import Block, DeviceUnavailable, DriverBase, DriverClosed, DriverError
from supramodal.drivers.spec import BuildContext, Built, DriverSpec, OptionError, ReplayedSession, given
from supramodal.logs import get_logger
from supramodal.replay.errors import ReplayError
from supramodal.replay.session import Label, Session, load_session, session_paths
from supramodal.replay.wavio import read_wav

_LOG = get_logger("drivers.replay")

__all__ = ["ReplayDriver", "DeviceClock", "SPEC", "SPEED_HELP", "SPEED_MAX", "TIMINGS", "is_speed", "release_time",
           "random_block_sizes", "RandomBlockSizes", "BlockSize"]

#: What ``block_size`` accepts: frames per block, a sequence cycled through,
#: or a callable drawing each size from a :class:`numpy.random.Generator`.
BlockSize = int | Sequence[int] | Callable[[np.random.Generator], int] | None
#: What :class:`ReplayDriver` replays: ``(samples, rate)``, a session, or a WAV or session path.
ReplaySource = tuple[ArrayLike, float] | Session | str | os.PathLike[str]
#: A source as :meth:`ReplayDriver._load` reads it: samples (frames, channels) float64, rate, labels,
#: filled mask or None, marks, name, arrivals or None.
_Loaded = tuple[np.ndarray, float, tuple[Label, ...], np.ndarray | None, tuple[tuple[int, str], ...], str,
                tuple[np.ndarray, np.ndarray, float] | None]


#: How a replay is paced: ``"nominal"``, block ``k`` when its last frame is due at the source's
#: rate; ``"recorded"``, the recorded blocks at their recorded times (a session recorded by a
#: node of several sources: its sidecar's ``arrivals``).
TIMINGS = ("nominal", "recorded")

#: The replay speed that releases every block at once (in a scene and after ``--speed``).
SPEED_MAX = "max"
#: Slowest and fastest finite replay speed a scene or ``--speed`` may ask for: a thousandth of real
#: time (a 10 ms block every 10 s) to a million times faster (beyond that, ask for "max").
SPEED_RANGE = (1e-3, 1e6)
SPEED_HELP = (f'1.0 (real time), a factor from {SPEED_RANGE[0]:g} to {SPEED_RANGE[1]:g}, or "{SPEED_MAX}" '
              "(every block at once)")


def is_speed(v: Any) -> bool:
    """Whether ``v`` is a replay speed a scene may ask for.

    That is :data:`SPEED_MAX` or a number within :data:`SPEED_RANGE`.
    """
    return v == SPEED_MAX or is_number(v) and SPEED_RANGE[0] <= v <= SPEED_RANGE[1]


def release_time(end_frame: int, rate: float, speed: float = 1.0, t0: float = 0.0) -> float:
    """When a block ending at ``end_frame`` is released: the pacing schedule.

    A pure function of the block's end, so it can be tested without a clock.
    For equal blocks of ``n`` frames, block ``k`` (0-based) ends at
    ``(k + 1) * n`` and is released at ``t0 + (k + 1) * n / rate / speed``.

    Parameters
    ----------
    end_frame : int
        Stream index one past the block's last frame.
    rate : float
        Frames per second of the stream, Hz.
    speed : float, default 1.0
        Replay speed factor (2.0 = twice real time); ``math.inf`` for 'max'.
    t0 : float, default 0.0
        Time of stream frame 0, seconds (``time.monotonic()`` at ``open()``).

    Returns
    -------
    float
        Seconds on the same clock as ``t0``.
    """
    if speed == math.inf:
        return t0
    return t0 + end_frame / (rate * speed)


@dataclass(frozen=True)
class DeviceClock:
    """How a simulated live device's blocks reach the host, for a replay paced like one.

    A real board or sound card samples on its own crystal, a few tens of ppm off its nominal
    rate, starts some time after the host asks, and delivers each block late by a variable delay
    (USB polling, the audio server's period, the scheduler), never out of order. A replay with a
    ``DeviceClock`` releases block ``k`` ending at frame ``end`` at

        ``max(previous release, t0 + (start + end / (rate (1 + ppm 1e-6))) / speed + delay_k)``

    with ``delay_k`` drawn from an exponential distribution of mean ``mean_delay`` (host seconds,
    not scaled by the speed), and stamps that time as the block's arrival. At ``speed='max'`` it
    has no effect. The node's clock model (``supramodal.node.runtime.clock``) must then find the line.

    Attributes
    ----------
    ppm : float
        The device's crystal error, parts per million (default 0), |ppm| < 1e4.
    start : float
        Seconds after ``open()`` at which the device takes its first sample (default 0), >= 0.
    mean_delay : float
        Mean delivery delay, seconds (default 0: on time), >= 0.
    seed : int or None
        Seed of the delays.
    """

    ppm: float = 0.0
    start: float = 0.0
    mean_delay: float = 0.0
    seed: int | None = None

    def __post_init__(self) -> None:
        for name, value, ok in (("ppm", self.ppm, lambda v: abs(v) < 1e4), ("start", self.start, lambda v: v >= 0),
                                ("mean_delay", self.mean_delay, lambda v: v >= 0)):
            if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
                    and ok(value)):
                raise ReplayError(f"DeviceClock {name} out of range: {value!r}")


class RandomBlockSizes:
    """Block sizes drawn uniformly from ``[low, high]`` frames (both included).

    Pass an instance as ``ReplayDriver(block_size=...)`` together with
    ``seed=`` to mimic a driver whose blocks vary in size, reproducibly.
    """

    def __init__(self, low: int, high: int):
        if not (_is_count(low) and _is_count(high) and low <= high):
            raise ReplayError(f"random block sizes need integers 1 <= low <= high, got {low!r}, {high!r}")
        self.low, self.high = int(low), int(high)

    def __call__(self, rng: np.random.Generator) -> int:
        """Draw one block size from ``rng``, frames in ``[low, high]``."""
        return int(rng.integers(self.low, self.high + 1))

    def __repr__(self) -> str:
        return f"random_block_sizes({self.low}, {self.high})"


def random_block_sizes(low: int, high: int) -> RandomBlockSizes:
    """Block sizes drawn uniformly from ``[low, high]`` frames; see :class:`RandomBlockSizes`."""
    return RandomBlockSizes(low, high)


def _is_count(v: object) -> TypeGuard[numbers.Integral]:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool) and int(v) >= 1


def _log_notice(message: str) -> None:
    """Log ``message`` on the package logger's ``supramodal.drivers.replay`` (INFO): the default ``on_notice``."""
    _LOG.info(message)


class ReplayDriver(DriverBase):
    """Replays an array, a WAV file or a session as a :class:`supramodal.drivers.base.Driver`.

    Parameters
    ----------
    source : (ndarray, rate) tuple, Session, str or path-like
        * ``(array, rate)``: float samples of shape (frames, channels) (or
          (frames,) for one channel) scaled to +-1, and their rate in Hz;
        * a :class:`supramodal.replay.session.Session`;
        * a path: ``NAME.json`` is a session; ``NAME.wav`` is a session when
          ``NAME.json`` exists beside it, else a bare WAV file (no labels).
    rate : float, optional
        Rate of the replayed stream, Hz. Default: the source's rate. When it
        differs, the source is resampled once, at construction, with
        :func:`scipy.signal.resample_poly` by ``up/down`` =
        ``Fraction(rate / source_rate).limit_denominator(max_denominator)``;
        :attr:`rate` is then the effective rate ``source_rate * up / down``,
        which a notice reports if it is not exactly the requested one.
    block_size : int, sequence of int, callable or None, default None
        Frames per block. ``None``: about 10 ms at :attr:`rate`. A sequence is
        cycled through. A callable is called as ``block_size(rng)`` with a
        :class:`numpy.random.Generator` seeded by ``seed`` for each block and
        returns its size (see :func:`random_block_sizes`). The last block of
        a stream that does not loop is shorter if the stream ends first.
    speed : float or 'max', default 1.0
        Replay speed: 1.0 real time, 2.0 twice as fast, 'max' (or
        ``math.inf``) as fast as the reader reads. See :func:`release_time`.
    loop : bool or int, default False
        False: play once. True: loop forever. An int ``n >= 1``: play ``n``
        passes. Stream indices keep counting across passes.
    channels : int, sequence of int or None, default None
        None: all channels. An int: the number of channels the source must
        have (refused otherwise), e.g. 20 for a whisker recording. A sequence:
        the source channels to keep, in that order.
    seed : int, optional
        Seed of the generator handed to a callable ``block_size``. The
        generator is re-created at every ``open()``, so sizes repeat.
    max_denominator : int, default 1000
        Largest ``down`` factor the resampling ratio may use.
    device_clock : DeviceClock, optional
        Pace the replay like a live device on its own crystal, with a start delay and
        delivery jitter (see :class:`DeviceClock`); default: exactly on the nominal schedule.
    timing : {"nominal", "recorded"}, default "nominal"
        "recorded": a session recorded by a node of several sources replays its recorded
        blocks, each released at its recorded time (divided by ``speed``; at once at
        ``"max"``) and carrying it in :attr:`Block.recorded`, so that the sources of one
        recording replay with their original relative timing, drift and jitter included. Needs
        the session's ``arrivals``, no ``block_size``, no ``device_clock`` and no ``loop``; a
        resampled session's block ends map to the first output frame at or after them.
    on_notice : callable or None, default the package logger (``supramodal.drivers.replay``, INFO)
        Called once with each notice (e.g. "resampling ..."), for a driver used
        on its own; None silences them. They are kept in :attr:`notices` and
        are ``notice`` events (:meth:`take_events`) either way; the node passes
        None and shows the events through its sinks.

    Attributes
    ----------
    rate : float
        Frames per second of the replayed stream, Hz.
    channels : int
        Channels per frame.
    source_rate : float
        The source's own rate, Hz.
    notices : list of str
        What the driver chose to tell (today: that it resamples, and how).

    Events (:meth:`take_events`): ``notice`` (each notice; those made at construction come
    with the first call) and ``gap`` (a run of frames the recording marked filled begins; its
    stream index). A session's board
    restart and overrun marks come back as the blocks' ``restarts`` and ``overruns``,
    so that the node flags the same windows as it did live.

    Raises
    ------
    DeviceUnavailable
        If a source file does not exist.
    ReplayError
        (a ``ValueError``) for bad arguments, unsupported or corrupt files and
        invalid sidecars, all at construction; only a ``block_size`` callable
        returning something other than an int >= 1 is caught later, by ``read()``.

    Notes
    -----
    * The whole source is held in memory as float64 (a 10-minute 20-channel
      5 kHz session is 480 MB); blocks are copies of slices of it.
    * Resampling is done once on one pass of the source. When looping, each
      seam therefore shows the filter's edge transient (``resample_poly``
      pads with zeros), as the source's own ends do; the blocks still equal
      :attr:`data` repeated, exactly.
    * Filled ranges are mapped to the new rate rounding outwards: a mark may
      widen by up to one output frame, it is never lost. Filter ringing from
      a filled stretch can reach further than that and is not marked.
    """

    def __init__(self, source: ReplaySource, rate: float | None = None, block_size: BlockSize = None,
                 speed: float | str = 1.0, loop: bool | int = False,
                 channels: int | Sequence[int] | np.ndarray | None = None,
                 seed: int | None = None, max_denominator: int = 1000,
                 on_notice: Callable[[str], None] | None = _log_notice, device_clock: DeviceClock | None = None,
                 timing: str = "nominal") -> None:
        super().__init__()
        self.notices: list[str] = []
        self._on_notice = on_notice
        data, src_rate, labels, filled, marks, self.name, arrivals = self._load(source, timing == "recorded")
        if data.shape[0] == 0:
            raise ReplayError(f"{self.name}: the source has no frames; nothing to replay")
        data = self._select(data, channels)
        self.source_rate = float(src_rate)

        # --- resampling (once, whole source: blocks are then plain slices) ---
        if rate is not None and (isinstance(rate, bool) or not isinstance(rate, numbers.Real)
                                 or not math.isfinite(rate) or rate <= 0):
            raise ReplayError(f"rate must be a positive number of Hz, got {rate!r}")
        up = down = 1
        if rate is not None and rate != src_rate:
            if not _is_count(max_denominator):
                raise ReplayError(f"max_denominator must be a positive integer, got {max_denominator!r}")
            ratio = (Fraction(rate) / Fraction(src_rate)).limit_denominator(max_denominator)
            up, down = ratio.numerator, ratio.denominator
            if up == 0:
                raise ReplayError(f"{self.name}: cannot resample {src_rate:g} Hz to {rate:g} Hz: more than "
                                  f"{2 * max_denominator} times slower, beyond what the replay resamples; resample "
                                  "the recording nearer that rate first, or give its stream a bank at a rate nearer "
                                  "the recording's")
        self.up, self.down = up, down
        self.rate = float(Fraction(src_rate) * up / down)  # the effective rate, exact or not
        if rate is not None and rate != src_rate:
            n_in = data.shape[0]
            if (up, down) != (1, 1):
                from scipy.signal import resample_poly  # here: scipy.signal takes 0.6 s to import
                data = resample_poly(data, up, down, axis=0)
                if filled is not None:
                    filled = self._resample_mask(filled, up, down, data.shape[0])
                msg = (f"replay: resampling {self.name} from {src_rate:g} Hz to {self.rate:g} Hz "
                       f"(resample_poly up={up} down={down}; {n_in} -> {data.shape[0]} frames)")
            else:
                msg = f"replay: not resampling {self.name}: {src_rate:g} Hz kept"
            if self.rate != rate:
                # Say it: the node would otherwise believe the requested rate.
                msg += (f"; requested {rate:g} Hz is not a ratio with denominator <= {max_denominator}, "
                        f"rate error {(self.rate - rate) / rate:+.2e}")
            self._notice(msg)
        self._data = np.ascontiguousarray(data, dtype=np.float64)
        self._data.flags.writeable = False
        self.channels = int(self._data.shape[1])
        self._filled = filled if filled is not None and filled.any() else None
        self._labels = tuple(labels)
        # A session's restart and overrun marks, at the replayed rate: a mark's frame lands on the
        # output frame at or after its time, so it marks the same window as in the live run.
        self._marks = tuple((-((-frame * up) // down), kind) for frame, kind in marks
                            if -((-frame * up) // down) < self._data.shape[0])

        # --- block sizes, speed, looping ---
        block_given = block_size is not None
        self._sizes: int | list[int] | Callable[[np.random.Generator], int]
        if block_size is None:
            block_size = max(1, round(self.rate * 0.010))
        if _is_count(block_size):
            self._sizes = int(block_size)
        elif callable(block_size):
            self._sizes = block_size
        elif isinstance(block_size, (Sequence, np.ndarray)) and not isinstance(block_size, (str, bytes)):
            sizes = list(block_size)
            if not sizes or not all(_is_count(s) for s in sizes):
                raise ReplayError(f"a block_size sequence must be non-empty positive integers, got {block_size!r}")
            self._sizes = [int(s) for s in sizes]
        else:
            raise ReplayError(f"block_size must be a positive int, a sequence of them or a callable, "
                              f"got {block_size!r}")
        self._seed = seed
        if timing not in TIMINGS:
            raise ReplayError(f"timing must be one of {TIMINGS}, got {timing!r}")
        self.timing = timing
        self._arrivals: tuple[np.ndarray, np.ndarray] | None = None
        #: With timing "recorded": the nominal rate of the recording node's clock for this source.
        self.recorded_rate: float | None = None
        if timing == "recorded":
            frames, seconds, self.recorded_rate = self._recorded_blocks(arrivals, up, down, block_given, device_clock)
            self._arrivals = (frames, seconds)
            self._sizes = list(np.diff(np.r_[0, self._arrivals[0]]).astype(int))
        if device_clock is not None and not isinstance(device_clock, DeviceClock):
            raise ReplayError(f"device_clock must be a DeviceClock, got {device_clock!r}")
        self.device_clock = device_clock
        if speed == "max" or speed == math.inf:
            self.speed = math.inf
        elif isinstance(speed, numbers.Real) and not isinstance(speed, bool) and math.isfinite(speed) and speed > 0:
            self.speed = float(speed)
        else:
            raise ReplayError(f"speed must be a positive number or 'max', got {speed!r}")
        if isinstance(loop, bool):
            self._passes = None if loop else 1
        elif _is_count(loop):
            self._passes = int(loop)
        else:
            raise ReplayError(f"loop must be True, False or a number of passes >= 1, got {loop!r}")
        if timing == "recorded" and self._passes != 1:
            raise ReplayError(f"{self.name}: a replay with the recorded timing plays the session once; "
                              "leave loop out")

        self._closed = threading.Event()
        self._is_open = False
        self._reset()

    # --- construction helpers -------------------------------------------------

    def _notice(self, message: str, kind: str = "notice", stream_index: int | None = None) -> None:
        """Keep ``message`` in :attr:`notices`, then log and hand it on as every driver does."""
        self.notices.append(message)
        super()._notice(message, kind, stream_index)

    def _load(self, source: ReplaySource, need_session: bool = False) -> _Loaded:
        """-> (data (n, ch) float64, rate, labels, filled mask or None, marks, name, arrivals or None).

        ``need_session``: a path is read as a session even without its sidecar (timing "recorded"
        needs the sidecar's arrivals: its absence is then said as such).
        """
        if isinstance(source, Session):
            # A Session may be built by hand: check its samples like any array.
            data, rate, _, _, _, _, _ = self._load((source.data, source.rate))
            return (data, rate, source.labels, source.filled_mask(), source.marks,
                    str(source.path) if source.path else "session", source.arrivals)
        if isinstance(source, (str, os.PathLike)):
            path = Path(source)
            wav, js = session_paths(path)
            as_session = need_session or path.suffix.lower() == ".json" or (path.suffix.lower() == ".wav"
                                                                            and js.exists())
            try:
                if as_session:
                    s = load_session(path)
                    return s.data, s.rate, s.labels, s.filled_mask(), s.marks, str(wav), s.arrivals
                if path.suffix.lower() != ".wav":
                    raise ReplayError(f"{path}: expected NAME.wav or NAME.json")
                data, rate = read_wav(path)
                return data, rate, (), None, (), str(path), None
            except FileNotFoundError as e:
                raise DeviceUnavailable(str(e)) from e
        if isinstance(source, np.ndarray):
            raise ReplayError("an in-memory source needs its rate: pass (array, rate)")
        if isinstance(source, tuple) and len(source) == 2:
            array, rate = source
            if isinstance(rate, bool) or not isinstance(rate, numbers.Real) or not math.isfinite(rate) or rate <= 0:
                raise ReplayError(f"the source rate must be a positive number of Hz, got {rate!r}")
            a = np.asarray(array)
            if a.ndim == 1:
                a = a.reshape(-1, 1)
            if a.ndim != 2 or a.shape[1] < 1:
                raise ReplayError(f"an in-memory source must have shape (frames, channels), got {a.shape}")
            if a.dtype.kind != "f":
                # Integers would need a full scale we would have to guess.
                raise ReplayError(f"an in-memory source must be float scaled to +-1, got {a.dtype}")
            if not np.all(np.isfinite(a)):
                raise ReplayError("the in-memory source holds NaN or infinite samples")
            return a.astype(np.float64), rate, (), None, (), f"array{a.shape}", None
        raise ReplayError(f"source must be (array, rate), a Session or a path, got {type(source).__name__}")

    def _recorded_blocks(self, arrivals: tuple[np.ndarray, np.ndarray, float] | None, up: int, down: int,
                         block_given: bool, device_clock: DeviceClock | None) -> tuple[np.ndarray, np.ndarray, float]:
        """Return the session's block ends, arrival times and clock rate, for ``timing="recorded"``.

        The last block reaches the end of the data (its time the last one recorded).
        """
        if arrivals is None:
            raise ReplayError(f"{self.name}: timing = 'recorded' needs a session recorded by a node of several "
                              "sources (its sidecar's 'arrivals'); this source has none: use timing = 'nominal'")
        if block_given or device_clock is not None:
            raise ReplayError(f"{self.name}: with timing = 'recorded' the blocks are the recorded ones, at their "
                              "recorded times; leave out the block size and the device clock")
        frames, seconds, clock_rate = np.asarray(arrivals[0]), np.asarray(arrivals[1]), float(arrivals[2])
        n = self._data.shape[0]
        if (up, down) != (1, 1):
            # Resampled: a block ends at the first output frame at or after its recorded end, and
            # the recording node's clock counts output frames.
            frames = np.minimum(-((-frames.astype(np.int64) * up) // down), n)
            keep = np.r_[np.diff(frames) > 0, True] if frames.size else frames.astype(bool)
            frames, seconds = frames[keep], seconds[keep]
            clock_rate *= up / down
        if frames[-1] < n:
            frames, seconds = np.r_[frames, n], np.r_[seconds, seconds[-1]]
        return frames.astype(np.int64), seconds.astype(np.float64), clock_rate

    def _select(self, data: np.ndarray, channels: int | Sequence[int] | np.ndarray | None) -> np.ndarray:
        have = data.shape[1]
        if channels is None:
            return data
        if _is_count(channels):
            if channels != have:
                raise ReplayError(f"{self.name}: has {have} channels, {channels} expected")
            return data
        if isinstance(channels, (Sequence, np.ndarray)) and not isinstance(channels, (str, bytes)):
            idx = list(channels)
            if not idx or not all(isinstance(i, numbers.Integral) and not isinstance(i, bool)
                                  and 0 <= int(i) < have for i in idx):
                raise ReplayError(f"{self.name}: channels must be indices in [0, {have}), got {channels!r}")
            return data[:, [int(i) for i in idx]]
        raise ReplayError(f"channels must be None, a count or a sequence of indices, got {channels!r}")

    @staticmethod
    def _resample_mask(mask: np.ndarray, up: int, down: int, n_out: int) -> np.ndarray:
        # Output frame j sits at source time j*down/up. Mark every output frame
        # whose time falls within a filled range's span, rounding outwards:
        # a filled mark may spread, it must never be lost.
        out = np.zeros(n_out, dtype=bool)
        m = np.asarray(mask, dtype=bool)
        edges = np.diff(np.concatenate(([False], m, [False])).astype(np.int8))
        for s, e in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
            a = (int(s) * up) // down
            b = -((-int(e) * up) // down)
            out[a:min(b, n_out)] = True
        return out

    # --- Driver contract ------------------------------------------------------

    def _reset(self) -> None:
        self._pos = 0              # stream index of the next frame to deliver
        self._blocks = 0
        self._filled_count = 0
        self._last_filled = False  # was the last delivered frame filled?
        self._next_size: int | None = None  # drawn but not yet delivered (read timed out)
        self._k = 0                # blocks drawn, for cycling a sequence
        self._rng = np.random.default_rng(self._seed)
        self._t0 = time.monotonic()
        self._next_delay = 0.0
        self._last_due = -math.inf
        self._delay_rng = np.random.default_rng(self.device_clock.seed if self.device_clock else None)

    def open(self) -> None:
        """Start (or restart) the stream at frame 0; counters reset; ``t0`` is now."""
        self._closed.clear()
        self._reset()
        self._is_open = True

    def close(self) -> None:
        """End the stream; a ``read()`` waiting in another thread wakes and raises. Idempotent."""
        self._is_open = False
        self._closed.set()

    def _draw_size(self) -> int:
        if isinstance(self._sizes, int):
            size = self._sizes
        elif isinstance(self._sizes, list):
            size = self._sizes[self._k % len(self._sizes)]
        else:
            size = self._sizes(self._rng)
            if not _is_count(size):
                raise ReplayError(f"block_size callable returned {size!r}; it must return an int >= 1")
        self._k += 1
        return int(size)

    @property
    def opened_at(self) -> float:
        """Host monotonic time of the last ``open()``, seconds.

        A paced stream's schedule (and a :class:`DeviceClock`'s start) counts from it.
        """
        return self._t0

    # passes, period and labels: DriverBase's defaults are plain class attributes, which a driver with
    # something to say overrides; a replay derives them from its source (labels: and from how far it
    # has been read), read-only. mypy holds a read-only override of a settable attribute unsafe
    # (nothing sets them: the node only reads them).
    @property
    def passes(self) -> int | None:  # type: ignore[override]  # read-only: see above
        """Passes of the source the stream plays: 1 without looping, None looping forever."""
        return self._passes

    @property
    def total_frames(self) -> float:
        """Frames in the whole stream (``math.inf`` when looping forever)."""
        return math.inf if self._passes is None else self._passes * self._data.shape[0]

    def release_time(self, end_frame: int) -> float:
        """:func:`release_time` of a block ending at ``end_frame`` since the last ``open()``.

        With a :class:`DeviceClock`, on the device's own clock, before its delivery delay.
        """
        c = self.device_clock
        if self._arrivals is not None:
            frames, seconds = self._arrivals
            k = min(int(np.searchsorted(frames, end_frame)), len(frames) - 1)
            return self._t0 + (seconds[k] / self.speed if self.speed != math.inf else 0.0)
        if c is None or self.speed == math.inf:
            return release_time(end_frame, self.rate, self.speed, self._t0)
        return self._t0 + (c.start + end_frame / (self.rate * (1.0 + c.ppm * 1e-6))) / self.speed

    def read(self, timeout: float | None = None) -> Block | None:
        """Return the next block once its release time has come.

        Parameters
        ----------
        timeout : float or None, default None
            Longest wait in seconds; None waits as long as needed, 0 polls.

        Returns
        -------
        Block or None
            ``data`` float64 of shape (frames, channels), a fresh copy;
            ``start`` its first stream index; ``arrival`` its release time on
            the ``time.monotonic()`` clock (when a live device would have
            delivered its last frame; ``time.monotonic()`` at read for
            'max'); ``filled`` from the session's filled ranges, or None.
            None if the block is not due within ``timeout``; the same block
            is returned by the next call.

        Raises
        ------
        DriverClosed
            At the end of the stream, or when ``close()`` is or was called.
        DriverError
            If the driver was never opened.
        """
        if self._closed.is_set():
            raise DriverClosed(f"{self.name}: closed")
        if not self._is_open:
            raise DriverError(f"{self.name}: read() before open(); use `with driver:` or call open()")
        remaining = self.total_frames - self._pos
        if remaining <= 0:
            raise DriverClosed(f"{self.name}: end of stream after {self._pos} frames")
        if self._next_size is None:
            self._next_size = self._draw_size()
            c = self.device_clock
            self._next_delay = 0.0
            if c is not None and c.mean_delay > 0 and self.speed != math.inf:     # paced like a device
                self._next_delay = float(self._delay_rng.exponential(c.mean_delay))
        size = int(min(self._next_size, remaining))
        end = self._pos + size
        due = max(self.release_time(end) + self._next_delay, self._last_due)   # delivered in order
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        while True:
            now = time.monotonic()
            if now >= due:
                break
            wait = due - now
            if deadline is not None:
                if now >= deadline:
                    return None
                wait = min(wait, deadline - now)
            if self._closed.wait(wait):  # close() interrupts the wait at once
                raise DriverClosed(f"{self.name}: closed")
        data = self._take(self._data, self._pos, size)
        filled = None
        if self._filled is not None:
            filled = self._take(self._filled, self._pos, size)
            n = int(np.count_nonzero(filled))
            self._filled_count += n
            if n:
                starts = np.flatnonzero(filled & ~np.concatenate(([self._last_filled], filled[:-1])))
                for i in starts.tolist():
                    self._record("gap", f"replay: {self.name}: frames from {self._pos + i} were filled "
                                 "in the recording (lost when it was made)", self._pos + i)
            self._last_filled = bool(filled[-1])
            if n == 0:
                filled = None
        recorded = None
        if self._arrivals is not None:
            recorded = float(self._arrivals[1][int(np.searchsorted(self._arrivals[0], end))])
        block = Block(data=data, start=self._pos, arrival=due if self.speed != math.inf else time.monotonic(),
                      filled=filled, restarts=self._marks_in(self._pos, size, "restart"),
                      overruns=self._marks_in(self._pos, size, "overrun"), recorded=recorded)
        self._pos = end
        self._blocks += 1
        self._next_size = None
        self._last_due = due
        return block

    def _marks_in(self, pos: int, size: int, kind: str) -> tuple[int, ...]:
        """Offsets within the block ``[pos, pos + size)`` of the session's marks of ``kind``.

        Marks on every pass of a looped source count.
        """
        n = self._data.shape[0]
        out: list[int] = []
        for frame, k in self._marks:
            if k == kind:
                first = pos + (frame - pos) % n          # the mark's first stream index at or after pos
                out += range(first - pos, size, n)
        return tuple(sorted(out))

    @staticmethod
    def _take(src: np.ndarray, pos: int, size: int) -> np.ndarray:
        """Copy of ``size`` frames from stream index ``pos`` of ``src`` repeated end to end."""
        n = src.shape[0]
        i = pos % n
        if i + size <= n:
            return src[i:i + size].copy()
        parts: list[np.ndarray] = []
        left = size
        while left:  # a block may straddle the loop seam, or be longer than the source
            k = min(left, n - i)
            parts.append(src[i:i + k])
            left -= k
            i = 0
        return np.concatenate(parts)

    def stats(self) -> dict[str, int]:
        """Counters since ``open()``.

        Returns
        -------
        dict
            ``frames`` delivered; ``filled`` delivered frames marked filled by
            the recording; ``blocks`` delivered; ``loops`` times the stream
            went back to the source's first frame.
        """
        n = self._data.shape[0]
        return {"frames": self._pos, "filled": self._filled_count, "blocks": self._blocks,
                "loops": max(0, (self._pos - 1) // n)}

    # --- what the replay knows beyond a live driver ------------------------------

    @property
    def data(self) -> np.ndarray:
        """One pass of the stream as replayed (channels selected, resampled); read-only, (frames, channels)."""
        return self._data

    @property
    def period(self) -> float:  # type: ignore[override]  # read-only: see passes
        """Seconds per pass of the source at :attr:`rate`, ``frames / rate``."""
        return int(self._data.shape[0]) / self.rate

    @property
    def labels(self) -> tuple[Label, ...]:  # type: ignore[override]  # read-only: see passes
        """The source's labels for every pass delivered so far, in stream seconds.

        Pass ``k`` is shifted by ``k * period``. Before any frame is delivered,
        the first pass's labels. Empty for sources without labels.
        """
        n = self._data.shape[0]
        last_pass = max(0, (self._pos - 1) // n)
        return tuple(lab.shifted(k * self.period) for k in range(last_pass + 1) for lab in self._labels)

    def labels_between(self, t0: float, t1: float) -> tuple[Label, ...]:
        """Labels overlapping stream time ``[t0, t1)`` seconds, shifted for their pass.

        Pure: does not depend on how far the stream has been read.
        """
        if not self._labels or t1 <= t0:
            return ()
        p = self.period
        k_first = max(0, math.floor(t0 / p) - 1)
        k_last = math.floor(t1 / p)
        if self._passes is not None:
            k_last = min(k_last, self._passes - 1)
        out: list[Label] = []
        for k in range(k_first, k_last + 1):
            for lab in self._labels:
                s = lab.shifted(k * p)
                if s.end > t0 and s.start < t1:
                    out.append(s)
        return tuple(out)

    def __repr__(self) -> str:
        speed = "max" if self.speed == math.inf else self.speed
        loop = {None: True, 1: False}.get(self._passes, self._passes)
        return (f"ReplayDriver({self.name}, rate={self.rate:g}, channels={self.channels}, "
                f"speed={speed}, loop={loop})")


# -- as a scene names it ---------------------------------------------------------------------------

def speed_key() -> Key:
    """Return the ``speed`` key of a paced source (its default: the replay driver's)."""
    return Key(is_speed, SPEED_HELP + " (default: the replay driver's)", None)


#: Most frames per block a scene may ask of a replay (a second at 1 MHz).
MAX_BLOCK = 2**20


def block_key() -> Key:
    """Return the ``block`` key of a paced source, frames per block (its default: 10 ms)."""
    return Key(integer(1, MAX_BLOCK), f"frames per block, 1..{MAX_BLOCK} (default: the replay driver's)", None)


def pacing(options: Mapping[str, Any], context: BuildContext) -> dict[str, Any]:
    """Return the replay driver's ``speed`` and ``block_size`` arguments from a scene's options.

    The command line's ``--speed`` comes first; absent ones keep the driver's defaults.
    """
    speed = context.speed if context.speed is not None else options.get("speed")
    return given({**options, "speed": speed}, {"speed": "speed", "block": "block_size"})


def _build(options: Mapping[str, Any], context: BuildContext) -> Built:
    path = context.resolve(options["path"])
    if not path.exists():
        raise OptionError(f"path: no recording at {path} (a relative path is taken from the scene file's folder)")
    try:
        # Notices reach the sinks as events, not stderr.
        driver = ReplayDriver(str(path), rate=context.rate, loop=options["loop"], timing=options["timing"],
                              on_notice=None, **pacing(options, context))
    except ReplayError as exc:
        if options["timing"] != "recorded":
            raise
        raise OptionError(f'timing = "recorded": {exc}') from None
    return Built(driver, source_rate=driver.source_rate)   # its labels are the driver's own


def _timebase(options: Mapping[str, Any], driver: ReplayDriver) -> tuple[str, float, float]:
    if options["timing"] == "recorded":
        assert driver.recorded_rate is not None, "a replay with the recorded timing knows its clock's rate"
        return "recorded", 0.0, float(driver.recorded_rate)   # the clock set up as when it was recorded
    return "stream", 0.0, driver.rate


SPEC = DriverSpec(
    type="replay",
    summary="a WAV file or a recorded session, paced like the device that recorded it",
    keys={
        "path": Key(text, "a WAV file or session path", path=True),
        "speed": speed_key(),
        "block": block_key(),
        "loop": Key(flag, "true or false", False),
        "timing": Key(one_of(*TIMINGS), '"nominal" (the rate\'s schedule) or "recorded" (a session recorded by a '
                      "graph: its blocks at their recorded times, in step with the other sources)", "nominal"),
    },
    build=_build, live=False, timebase=_timebase,
    replays=lambda options: ReplayedSession(str(options["path"]), options["timing"] == "recorded"))
