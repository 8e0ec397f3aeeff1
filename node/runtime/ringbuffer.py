"""A fixed-capacity ring of frames: one writer, one or more readers, thread-safe.

The node's driver thread writes each block it reads from a driver; each
consumer (a model block, a recorder, a monitor) reads through its own
:class:`Reader` at its own pace. This module knows nothing of drivers or of
the model: it moves ``(frames, channels)`` arrays and their per-frame
``filled`` flags, and accounts for every frame.

Filled frames lost
------------------
A reader's ``lost`` counts every frame it will never receive; ``lost_filled``
counts those of them that were written with a True ``filled`` flag (frames a
driver synthesised, never measured). The difference is measured data lost.
The node needs the split: a long gap fill is written as one block, and when
it is longer than the ring the ring drops its oldest rows, which are zeros,
not data (docs/node.md, "Every frame has one fate").

Stream indices
--------------
Every frame offered to :meth:`RingBuffer.write` gets the next absolute stream
index (a Python int: it never wraps), whether it is kept or refused. A read
returns the stream index of its first frame, and the frames of one read are
always consecutive in the stream, so a reader that expected index ``i`` and
got ``start > i`` knows it lost exactly ``start - i`` frames.

Overrun policies
----------------
The ring holds ``capacity`` frames. When the slowest reader would lag by more
than that, the policy chosen at construction decides:

``'drop-oldest'`` (default)
    The write always succeeds; each lagging reader's cursor jumps forward to
    the oldest frame still held, and the frames it skipped are added to that
    reader's ``lost`` counter. Suits live monitoring: late readers catch up.
``'drop-newest'``
    The write keeps what fits and refuses the rest. Refused frames still take
    their stream indices (so every reader sees the gap), are counted in
    ``refused``, and in the ``lost`` counter of every reader attached.
``'block'``
    The write waits (up to its ``timeout``) until the slowest reader frees
    space, writing piece by piece as it does. Suits offline replay, where
    nothing may be lost and the source can wait.

With no reader attached nobody lags: writes always succeed and only the last
``capacity`` frames are kept.

End of stream
-------------
:meth:`RingBuffer.close` marks the end. Readers first receive every frame still
held, then :meth:`Reader.read` raises :class:`RingClosed` (an exception, not an
end marker, so that the end can never be mistaken for data). A writer waiting
under the ``'block'`` policy also wakes and raises :class:`RingClosed`.

Threading rules
---------------
* One writer thread calls :meth:`RingBuffer.write`. (Writes are serialised by
  the lock, so several writers would not corrupt the ring, but their blocks
  would interleave in no defined order.)
* Each :class:`Reader` is used by one thread; several readers may run in
  several threads.
* :meth:`RingBuffer.close`, :meth:`RingBuffer.stats`, :meth:`RingBuffer.add_reader`
  and the readers' properties may be called from any thread.
* All state is guarded by one :class:`threading.Lock`; copies into and out of
  the ring happen under it, which is what makes ``drop-oldest`` safe (a copy
  can never race the overwrite of the same slots). Blocks are small (10 ms is
  50 frames of 20 channels at 5 kHz), so the lock is held for microseconds.
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from typing import NamedTuple, TypedDict

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

from supramodal.errors import InputError, SupramodalError

__all__ = ["RingBuffer", "Reader", "Chunk", "ReaderStats", "RingStats", "RingBufferError", "RingClosed",
           "OVERRUN_POLICIES"]

OVERRUN_POLICIES = ("drop-oldest", "drop-newest", "block")


class RingBufferError(SupramodalError):
    """Base class of the ring buffer's errors."""


class RingClosed(RingBufferError):
    """The ring (or this reader) is closed and, for a reader, drained: no more frames will come."""


class ReaderStats(TypedDict):
    """A reader's frame counts (:meth:`Reader.stats`).

    ``start``: the stream index when it was added; ``read``, ``lost``: frames read and lost; ``available``:
    frames it may read now; ``read_filled``, ``lost_filled``: of the frames read and lost, those written
    with a True filled flag.
    """

    start: int
    read: int
    lost: int
    available: int
    read_filled: int
    lost_filled: int


class RingStats(TypedDict):
    """A ring's counters since construction (:meth:`RingBuffer.stats`: what each key counts)."""

    written: int
    filled: int
    stored: int
    refused: int
    capacity: int
    readers: dict[str, ReaderStats]


class Chunk(NamedTuple):
    """Frames returned by :meth:`Reader.read`.

    Attributes
    ----------
    start : int
        Stream index of the first frame.
    data : ndarray, shape (frames, channels)
        A contiguous copy, the ring's dtype.
    filled : ndarray of bool, shape (frames,)
        The flags written with the frames (all False where none were given).
    """

    start: int
    data: np.ndarray
    filled: np.ndarray


def flag_runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """Return the runs of True in a chunk's per-frame flags, as ``(start, end)`` offsets (end exclusive).

    In order. E.g. the filled frames of a read, or (of ``~filled``) the measured ones.
    """
    edges = np.flatnonzero(np.diff(np.r_[0, np.asarray(flags, dtype=np.int8), 0]))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


class Reader:
    """One consumer's cursor into a :class:`RingBuffer`; create with :meth:`RingBuffer.add_reader`.

    Use a reader from one thread only.
    """

    def __init__(self, ring: RingBuffer, name: str, cursor: int, start: int, lost: int,
                 lost_filled: int):
        self._ring = ring
        self.name = name
        self._cursor = cursor   # storage position of the next frame to read
        self._start = start     # stream index at attach time
        self._read = 0          # frames returned
        self._read_filled = 0   # of them, written with a True filled flag
        self._lost = lost       # frames between start and the stream end it will never receive
        self._lost_filled = lost_filled  # of them, written with a True filled flag
        self._closed = False

    def read(self, max_frames: int | None = None, timeout: float | None = None,
             min_frames: int = 1) -> Chunk | None:
        """Return the next frames, waiting for them if needed.

        Parameters
        ----------
        max_frames : int or None, default None
            Most frames to return; None returns all that are available.
        timeout : float or None, default None
            Longest wait in seconds for ``min_frames``; None waits without
            limit, 0 polls.
        min_frames : int, default 1
            Wait until at least this many frames are available. Fewer are
            returned only at a gap (frames refused under 'drop-newest': a read
            never spans one) or when the ring is closed.

        Returns
        -------
        Chunk or None
            ``(start, data, filled)``; None if ``timeout`` passed first.

        Raises
        ------
        RingClosed
            If the ring is closed and this reader has received every frame it
            held, or if this reader was closed.
        """
        if max_frames is not None and max_frames < 1:
            raise InputError(f"max_frames must be >= 1 or None, got {max_frames!r}")
        if min_frames < 1:
            raise InputError(f"min_frames must be >= 1, got {min_frames!r}")
        ring = self._ring
        with ring._lock:
            deadline = None
            while True:
                if self._closed:
                    raise RingClosed(f"reader {self.name!r} is closed")
                avail = ring._stored - self._cursor
                if avail >= min_frames or (avail > 0 and ring._closed):
                    break
                if ring._closed:
                    raise RingClosed(f"ring closed; reader {self.name!r} has read all {ring._end} frames "
                                     f"({self._read} received, {self._lost} lost)")
                if timeout is not None:
                    now = time.monotonic()
                    if deadline is None:
                        deadline = now + timeout
                    if now >= deadline:
                        return None
                    ring._readable.wait(deadline - now)
                else:
                    ring._readable.wait()
            return ring._copy_out(self, max_frames)

    @property
    def available(self) -> int:
        """Frames held for this reader now (across gaps)."""
        with self._ring._lock:
            return self._ring._stored - self._cursor

    @property
    def position(self) -> int:
        """Stream index of the next frame this reader will receive (jumps after a loss)."""
        with self._ring._lock:
            return self._cursor + self._ring._offset(self._cursor)

    @property
    def lost(self) -> int:
        """Frames this reader lost since it was added (overrun or refused)."""
        with self._ring._lock:
            return self._lost

    @property
    def lost_filled(self) -> int:
        """Of :attr:`lost`, the frames written with a True filled flag (never measured)."""
        with self._ring._lock:
            return self._lost_filled

    def close(self) -> None:
        """Detach: the ring stops waiting for this reader; later reads raise :class:`RingClosed`."""
        self._ring._remove(self)

    def stats(self) -> ReaderStats:
        """Return this reader's frame counts.

        ``start`` stream index when added, ``read`` and ``lost`` frames, ``available`` now,
        and ``read_filled``, ``lost_filled``: of the frames read and lost, those written with a
        True filled flag.
        """
        with self._ring._lock:
            return self._stats()

    def _stats(self) -> ReaderStats:
        return {"start": self._start, "read": self._read, "lost": self._lost,
                "available": self._ring._stored - self._cursor,
                "read_filled": self._read_filled, "lost_filled": self._lost_filled}

    def __repr__(self) -> str:
        return f"<Reader {self.name!r} of {self._ring!r}>"


class RingBuffer:
    """A fixed-capacity ring of frames with per-frame filled flags.

    Parameters
    ----------
    capacity_frames : int
        Frames held, >= 1. Memory is ``capacity_frames * channels * itemsize``
        plus one byte per frame for the flags, allocated once here.
    channels : int
        Channels per frame, >= 1.
    dtype : numpy dtype, default float64
        Sample type held; writes must be castable to it (``same_kind``).
    overrun : {'drop-oldest', 'drop-newest', 'block'}, default 'drop-oldest'
        What happens when the slowest reader lags by more than the capacity;
        see the module documentation.

    Notes
    -----
    Thread-safe under the rules in the module documentation: one writer
    thread, one thread per reader.
    """

    def __init__(self, capacity_frames: int, channels: int, dtype: DTypeLike = np.float64,
                 overrun: str = "drop-oldest") -> None:
        if not isinstance(capacity_frames, int) or isinstance(capacity_frames, bool) or capacity_frames < 1:
            raise InputError(f"capacity_frames must be an int >= 1, got {capacity_frames!r}")
        if not isinstance(channels, int) or isinstance(channels, bool) or channels < 1:
            raise InputError(f"channels must be an int >= 1, got {channels!r}")
        if overrun not in OVERRUN_POLICIES:
            raise InputError(f"overrun must be one of {OVERRUN_POLICIES}, got {overrun!r}")
        self.capacity = capacity_frames
        self.channels = channels
        self.dtype = np.dtype(dtype)
        self.overrun = overrun
        self._data = np.zeros((capacity_frames, channels), dtype=self.dtype)
        self._flags = np.zeros(capacity_frames, dtype=bool)
        self._lock = threading.Lock()
        self._readable = threading.Condition(self._lock)   # frames arrived, or closed
        self._writable = threading.Condition(self._lock)   # a reader freed space, or closed
        # Storage positions count kept frames; frame at position p sits in slot
        # p % capacity and has stream index p + offset(p). The offset grows only
        # where frames were refused ('drop-newest'), recorded as holes.
        self._stored = 0
        self._end = 0            # stream index one past the last frame offered
        self._refused = 0
        self._filled_in = 0              # frames offered with a True filled flag (kept or refused)
        self._hole_pos: list[int] = []   # storage positions where a gap starts, ascending
        self._hole_off: list[int] = []   # offset from that position on
        self._hole_fill: list[int] = []  # filled frames refused before that position's frame, cumulative
        self._base_offset = 0            # offset before the first hole
        self._base_fill = 0              # refused filled frames before the first hole
        self._readers: list[Reader] = []
        self._names = 0
        self._closed = False

    # --- readers --------------------------------------------------------------

    def add_reader(self, name: str | None = None, position: str = "newest") -> Reader:
        """Attach a new reader.

        Parameters
        ----------
        name : str, optional
            For stats; default ``reader0``, ``reader1``, ...
        position : {'newest', 'oldest'}, default 'newest'
            'newest': the reader receives frames written from now on.
            'oldest': it starts at the oldest frame still held.

        Returns
        -------
        Reader
        """
        if position not in ("newest", "oldest"):
            raise InputError(f"position must be 'newest' or 'oldest', got {position!r}")
        with self._lock:
            if name is None:
                name = f"reader{self._names}"
            self._names += 1
            if any(r.name == name for r in self._readers):
                raise InputError(f"a reader named {name!r} is already attached")
            cursor = self._stored if position == "newest" else max(0, self._stored - self.capacity)
            start = cursor + self._offset(cursor)
            # Frames refused inside the part it will read were lost to it too:
            # count them, so that read + lost == stream end - start at the end.
            lost = (self._end - start) - (self._stored - cursor)
            lost_filled = self._refused_fill(self._stored) - self._refused_fill(cursor)
            reader = Reader(self, name, cursor, start, lost, lost_filled)
            self._readers.append(reader)
            return reader

    def _remove(self, reader: Reader) -> None:
        with self._lock:
            reader._closed = True
            if reader in self._readers:
                self._readers.remove(reader)
            self._prune()
            self._writable.notify_all()
            self._readable.notify_all()

    @property
    def readers(self) -> tuple[Reader, ...]:
        """The readers attached now (a copy, taken under the ring's lock)."""
        with self._lock:
            return tuple(self._readers)

    # --- writer ---------------------------------------------------------------

    def write(self, block: ArrayLike, filled_mask: ArrayLike | None = None, timeout: float | None = None) -> int:
        """Append frames (from the writer thread).

        Parameters
        ----------
        block : array_like, shape (frames, channels)
            Frames to append; (frames,) is accepted for one channel. Cast to
            the ring's dtype.
        filled_mask : array_like of bool, shape (frames,), optional
            Per-frame filled flags; None means no frame was filled.
        timeout : float or None, default None
            Under 'block' only: longest wait for space, seconds; None waits
            without limit.

        Returns
        -------
        int
            Frames kept. Under 'drop-oldest', always all. Under 'drop-newest'
            the rest were refused: counted, and their stream indices skipped.
            Under 'block', fewer only if ``timeout`` passed: the rest were
            *not* taken (no index skipped), and the caller may write
            ``block[kept:]`` again.

        Raises
        ------
        RingClosed
            If the ring is closed (also while waiting under 'block').
        ValueError
            For a wrong shape or dtype.
        """
        a = np.asarray(block)
        if a.ndim == 1 and self.channels == 1:
            a = a.reshape(-1, 1)
        if a.ndim != 2 or a.shape[1] != self.channels:
            raise InputError(f"block must have shape (frames, {self.channels}), got {a.shape}")
        if not np.can_cast(a.dtype, self.dtype, "same_kind"):
            raise InputError(f"cannot store {a.dtype} in a {self.dtype} ring")
        n = a.shape[0]
        if filled_mask is None:
            f = None
        else:
            f = np.asarray(filled_mask, dtype=bool)
            if f.shape != (n,):
                raise InputError(f"filled_mask must have shape ({n},), got {f.shape}")
        with self._lock:
            if self._closed:
                raise RingClosed("write() on a closed ring")
            if n == 0:
                return 0
            if f is not None and self.overrun != "block":
                self._filled_in += int(np.count_nonzero(f))  # 'block' counts what it takes, in _store
            if self.overrun == "drop-oldest":
                self._store(a, f)
                kept = n
            elif self.overrun == "drop-newest":
                kept = min(n, self._space())
                if kept:
                    self._store(a[:kept], None if f is None else f[:kept])
                if kept < n:
                    self._refuse(n - kept, 0 if f is None else int(np.count_nonzero(f[kept:])))
            else:
                kept = 0
                deadline = None
                while kept < n:
                    space = self._space()
                    if space == 0:
                        if timeout is None:
                            self._writable.wait()
                        else:
                            now = time.monotonic()
                            if deadline is None:
                                deadline = now + timeout
                            if now >= deadline:
                                break
                            self._writable.wait(deadline - now)
                        if self._closed:
                            raise RingClosed(f"ring closed while write() waited; {kept} of {n} frames kept")
                        continue
                    k = min(n - kept, space)
                    self._store(a[kept:kept + k], None if f is None else f[kept:kept + k])
                    kept += k
                    self._readable.notify_all()  # let readers free space while we wait
            self._readable.notify_all()
            return int(kept)

    def _space(self) -> float:
        """Frames that fit before the slowest reader would be overrun (inf with no reader)."""
        if not self._readers:
            return math.inf
        slowest = min(r._cursor for r in self._readers)
        return self.capacity - (self._stored - slowest)

    def _store(self, a: np.ndarray, f: np.ndarray | None) -> None:
        n = n_offered = a.shape[0]
        cap = self.capacity
        new_stored = self._stored + n
        if self.overrun == "block" and f is not None:
            self._filled_in += int(np.count_nonzero(f))
        # Readers further back than one capacity lose what is about to be overwritten.
        limit = new_stored - cap
        for r in self._readers:
            if r._cursor < limit:
                r._lost += limit - r._cursor
                r._lost_filled += self._filled_between(r._cursor, limit, f)
                r._cursor = limit
        if n > cap:  # only the newest capacity frames can be held
            a, f = a[n - cap:], (None if f is None else f[n - cap:])
            n = cap
        i = (new_stored - n) % cap
        k = min(n, cap - i)
        self._data[i:i + k] = a[:k]
        self._data[:n - k] = a[k:]
        if f is None:
            self._flags[i:i + k] = False
            self._flags[:n - k] = False
        else:
            self._flags[i:i + k] = f[:k]
            self._flags[:n - k] = f[k:]
        self._stored = new_stored
        self._end += n_offered

    def _filled_between(self, a: int, b: int, f: np.ndarray | None) -> int:
        """Count the flagged frames at storage positions ``a .. b - 1``, before the block ``f`` is stored.

        Positions below ``self._stored`` are still in the ring (a reader's cursor never lags
        more than one capacity); those from ``self._stored`` on are the head of the block being
        written, when it is longer than the space left (``f``: its flags, or None).
        """
        cap = self.capacity
        held_end = min(b, self._stored)
        count = 0
        if held_end > a:
            i, m = a % cap, held_end - a
            k = min(m, cap - i)
            count += int(np.count_nonzero(self._flags[i:i + k])) + int(np.count_nonzero(self._flags[:m - k]))
        if f is not None and b > self._stored:
            count += int(np.count_nonzero(f[max(a, self._stored) - self._stored:b - self._stored]))
        return count

    def _refuse(self, n: int, n_filled: int) -> None:
        offset = self._offset(self._stored) + n
        fill = self._refused_fill(self._stored) + n_filled
        if self._hole_pos and self._hole_pos[-1] == self._stored:
            self._hole_off[-1] = offset  # refused again before anything was kept: one gap
            self._hole_fill[-1] = fill
        else:
            self._hole_pos.append(self._stored)
            self._hole_off.append(offset)
            self._hole_fill.append(fill)
        self._refused += n
        self._end += n
        for r in self._readers:
            r._lost += n
            r._lost_filled += n_filled

    def _offset(self, position: int) -> int:
        """Stream index minus storage position for the frame at ``position``."""
        i = bisect.bisect_right(self._hole_pos, position) - 1
        return self._hole_off[i] if i >= 0 else self._base_offset

    def _refused_fill(self, position: int) -> int:
        """Refused frames flagged filled, before the frame at storage ``position`` (cumulative)."""
        i = bisect.bisect_right(self._hole_pos, position) - 1
        return self._hole_fill[i] if i >= 0 else self._base_fill

    def _prune(self) -> None:
        # A hole is only needed while some reader, or a reader added at
        # 'oldest', could still stand before it.
        floor = max(0, self._stored - self.capacity)
        if self._readers:
            floor = min(floor, min(r._cursor for r in self._readers))
        i = bisect.bisect_right(self._hole_pos, floor)
        if i:
            self._base_offset = self._hole_off[i - 1]
            self._base_fill = self._hole_fill[i - 1]
            del self._hole_pos[:i], self._hole_off[:i], self._hole_fill[:i]

    def _copy_out(self, reader: Reader, max_frames: int | None) -> Chunk:
        """Copy the reader's next frames, never across a hole; called under the lock."""
        cur = reader._cursor
        stop = self._stored
        j = bisect.bisect_right(self._hole_pos, cur)
        if j < len(self._hole_pos):
            stop = min(stop, self._hole_pos[j])  # a read never spans a gap
        n = stop - cur
        if max_frames is not None:
            n = min(n, max_frames)
        cap = self.capacity
        i = cur % cap
        k = min(n, cap - i)
        if k == n:
            data = self._data[i:i + n].copy()
            flags = self._flags[i:i + n].copy()
        else:
            data = np.concatenate((self._data[i:], self._data[:n - k]))
            flags = np.concatenate((self._flags[i:], self._flags[:n - k]))
        start = cur + self._offset(cur)
        reader._cursor = cur + n
        reader._read += n
        reader._read_filled += int(np.count_nonzero(flags))
        if self._hole_pos:
            self._prune()
        if self.overrun == "block":
            self._writable.notify_all()
        return Chunk(start, data, flags)

    # --- lifetime and accounting ----------------------------------------------

    def close(self) -> None:
        """Mark the end of the stream; wakes every waiting reader and writer. Idempotent."""
        with self._lock:
            self._closed = True
            self._readable.notify_all()
            self._writable.notify_all()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` has been called (the end of the stream is marked)."""
        return self._closed

    @property
    def written(self) -> int:
        """Stream index one past the last frame offered (kept or refused)."""
        with self._lock:
            return self._end

    def stats(self) -> RingStats:
        """Counters since construction.

        Returns
        -------
        RingStats
            ``written``: frames offered to :meth:`write` (the stream's length);
            ``filled``: of them, frames offered with a True filled flag;
            ``stored``: frames kept (equal to ``written`` unless refused);
            ``refused``: frames refused under 'drop-newest';
            ``capacity``: frames held at most;
            ``readers``: ``{name: {"start", "read", "lost", "available",
            "read_filled", "lost_filled"}}`` for each attached reader. For each,
            once the ring is closed and the reader drained,
            ``read + lost == written - start``, and ``read_filled + lost_filled``
            is the number of filled frames offered from ``start`` on.
        """
        with self._lock:
            return {"written": self._end, "filled": self._filled_in, "stored": self._stored,
                    "refused": self._refused, "capacity": self.capacity,
                    "readers": {r.name: r._stats() for r in self._readers}}

    def __repr__(self) -> str:
        return (f"RingBuffer(capacity_frames={self.capacity}, channels={self.channels}, "
                f"dtype={self.dtype.name}, overrun={self.overrun!r})")
