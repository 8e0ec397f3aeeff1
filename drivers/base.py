"""The contract every driver follows, a base that gives its common part, and the package's exceptions.

Threading and real-time rules
-----------------------------
* :meth:`Driver.read` is called from one thread only (the node's driver thread).
  It may block for at most ``timeout`` seconds and returns ``None`` when no block
  arrived in that time; it raises :class:`DriverClosed` once the stream has ended
  for good (end of file, ``close()`` called).
* A driver never drops, repairs or skips a sample without counting it in
  :meth:`Driver.stats`: ``frames`` (delivered, including filled ones), ``filled``
  (frames synthesised to fill a gap, never measured), and driver-specific counters
  (CRC errors, skipped bytes, overflows, reconnects, ...).
* A driver whose filled frames all stand for samples the host received and lost
  itself (a buffer overflow, not a loss on the line or at the source) says so
  with a true ``fills_are_drops`` attribute; the node then reports them as
  *dropped*, not *filled* (docs/node.md, "Every frame has one fate").
  :class:`DriverBase` says False.
* Drivers are context managers: ``with driver: ...`` opens and closes the device.
* A driver says what its hardware is doing as :class:`DriverEvent` objects kept in
  an :class:`EventLog`: ``take_events()`` returns and clears the new ones, from
  any thread, without waiting on anything but a short lock. The driver starts no
  thread for them; whoever runs it (the node's driver thread) polls.

A driver derives from :class:`DriverBase`, which owns the event log, ``take_events``,
notices, the context manager and the labels of a driver that has none; the node calls
every member of :class:`Driver` without probing for it, and a source refuses at
construction a driver that lacks one (:func:`missing_members`).
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, Self, runtime_checkable

import numpy as np

from supramodal.errors import SupramodalError


class DriverError(SupramodalError):
    """Base class of every error a driver raises."""


class DeviceUnavailable(DriverError):
    """The device (port, sound card, file) is missing or cannot be opened."""


class DriverClosed(DriverError):
    """The stream has ended: end of file, or the driver was closed."""


@dataclass(frozen=True)
class Block:
    """A block of samples from a driver.

    Attributes
    ----------
    data : ndarray, shape (frames, channels)
        Samples, float32 or float64, scaled so that full scale is +-1.0.
    start : int
        Index of the first frame in the driver's stream (0-based). Filled frames
        count: blocks tile the stream with no holes, so ``start`` of a block is
        ``start + frames`` of the previous one.
    filled : ndarray of bool, shape (frames,), or None
        True where a frame was synthesised by the driver to fill a gap (lost
        bytes, dropped frames) rather than measured. ``None`` means none was.
    arrival : float
        ``time.monotonic()`` when the driver received the block's last frame;
        the node measures decision latency from it.
    restarts : tuple of int, default ()
        Offsets (frames, within the block) of frames that do not follow the
        frame before them in the source's time: the board restarted, or a
        sequence jump too long to fill. ``start`` still tiles the stream; the
        time between the two frames is unknown.
    overruns : tuple of int, default ()
        Offsets of frames before which the source lost samples it could not
        count or fill (the board's OVERRUN flag, an audio overflow without a
        timestamp): from there on, the stream index runs behind real time by
        the unknown loss.
    recorded : float or None, default None
        For a block replayed with its recorded timing: when it was complete on the
        common time of the node that recorded it, seconds (a session's
        ``arrivals``). None for a live or freshly paced block.
    timestamp : float or None, default None
        For a source that stamps its own samples (an LSL stream: the sender's
        timestamps, clock-corrected): when the block's last frame was taken, on
        this host's ``time.monotonic()`` clock. The node's clock model then fits
        these instead of ``arrival``. None: the driver knows only the arrival.
    """

    data: np.ndarray
    start: int
    arrival: float
    filled: np.ndarray | None = field(default=None)
    restarts: tuple[int, ...] = ()
    overruns: tuple[int, ...] = ()
    recorded: float | None = None
    timestamp: float | None = None

    @property
    def frames(self) -> int:
        """Frames in the block (rows of ``data``)."""
        return int(self.data.shape[0])

    @property
    def n_filled(self) -> int:
        """Frames of the block that were filled (0 when ``filled`` is None)."""
        return 0 if self.filled is None else int(np.count_nonzero(self.filled))


@dataclass(frozen=True)
class DriverEvent:
    """Something a driver's hardware did, said as it happened.

    Attributes
    ----------
    kind : str
        A short, stable name: ``"channels"`` (a frame of the wrong channel
        count), ``"version"``, ``"unplug"``, ``"reconnect"``, ``"restart"``,
        ``"gap"``, ``"overrun"``, ``"silence"``, ``"overflow"``, ``"error"``,
        ``"notice"``, ...; each driver documents its kinds. A node's fusion block says
        ``"sense_lost"``, ``"sense_back"`` and ``"sense_ended"`` with the same event
        (source ``"fused"``).
    message : str
        One line for a person: what happened and, for a fault, the likely fix.
    time : float
        ``time.time()`` (s since the epoch) when the driver saw it.
    stream_index : int or None
        Stream frame where it happened, when it has a place in the stream.
    count : int, default 1
        Occurrences this event stands for: more than 1 when a rate limiter
        folded repeats of the same kind into it (its message is the latest).
    source : str or None
        The name of the source whose driver it came from, where a node runs
        several (set by the node; a driver leaves it None).
    """

    kind: str
    message: str
    time: float
    stream_index: int | None = None
    count: int = 1
    source: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """Return the event as a JSON-ready dict: ``{"event": kind, "message": ..., ...}``."""
        out = {"event": self.kind, "message": self.message, "time": round(self.time, 3),
               "stream_index": self.stream_index, "count": self.count}
        if self.source is not None:
            out["source"] = self.source
        return out


class EventLog:
    """A bounded, thread-safe queue of :class:`DriverEvent` plus a short history.

    Parameters
    ----------
    capacity : int, default 1024
        Events kept for :meth:`take`; beyond it the oldest is dropped and counted
        per kind (returned by the next :meth:`take`), so nothing goes unsaid.
    history : int, default 200
        Events kept for :meth:`history` (read, never cleared by :meth:`take`).

    Notes
    -----
    Every method may be called from any thread (also an audio callback: a
    method holds a lock for a few microseconds and never blocks otherwise).
    """

    def __init__(self, capacity: int = 1024, history: int = 200) -> None:
        self._lock = threading.Lock()
        self._new: deque[DriverEvent] = deque()
        self._capacity = int(capacity)
        self._history: deque[DriverEvent] = deque(maxlen=int(history))
        self._dropped: Counter[str] = Counter()

    def record(self, kind: str, message: str, stream_index: int | None = None, count: int = 1) -> DriverEvent:
        """Add an event (timestamped now) and return it."""
        ev = DriverEvent(kind, message, time.time(), stream_index, count)
        with self._lock:
            if len(self._new) >= self._capacity:
                old = self._new.popleft()
                self._dropped[old.kind] += old.count
            self._new.append(ev)
            self._history.append(ev)
        return ev

    def take(self) -> tuple[list[DriverEvent], dict[str, int]]:
        """Return and clear the new events, and the per-kind counts dropped since the last call."""
        with self._lock:
            if not self._new and not self._dropped:
                return [], {}
            out, self._new = list(self._new), deque()
            dropped, self._dropped = dict(self._dropped), Counter()
        return out, dropped

    def history(self) -> list[DriverEvent]:
        """Return the last ``history`` events, oldest first (a copy)."""
        with self._lock:
            return list(self._history)

    def clear(self) -> None:
        """Forget everything (a driver's ``open()`` restarts its counters)."""
        with self._lock:
            self._new.clear()
            self._history.clear()
            self._dropped.clear()


class TruthLabel(Protocol):
    """A truth label a driver carries (:class:`supramodal.replay.session.Label` is one).

    It says what was sensed (``label``) over ``[start, end)``, stream seconds.
    """

    @property
    def start(self) -> float:
        """Start of the labelled span, stream seconds (inclusive)."""
        ...

    @property
    def end(self) -> float:
        """End of the labelled span, stream seconds (exclusive)."""
        ...

    @property
    def label(self) -> str:
        """What was sensed over the span."""
        ...


@runtime_checkable
class Driver(Protocol):
    """What the node needs of a source of blocks.

    :class:`DriverBase` gives all of it but ``rate``, ``channels``, ``read`` and ``stats``.

    Attributes
    ----------
    rate : float
        Frames per second, Hz.
    channels : int
        Channels per frame.
    fills_are_drops : bool
        True if every filled frame stands for a sample the host lost (see the
        module documentation); False for a driver that fills only what never
        reached the host.
    labels : sequence of Label
        Truth labels the driver carries, each with ``start``, ``end`` (stream
        seconds) and ``label``; empty for a live driver.
    passes : int or None
        Passes of its source the stream plays (a looped replay: more than 1, or
        None for ever); 1 for a live driver.
    period : float or None
        Seconds per pass, which the labels repeat with when ``passes != 1``.
    speed : float
        How fast the samples come, in times real time: 1 for a live device (and a replay paced in
        real time), ``math.inf`` for a replay at once.
    """

    rate: float
    channels: int
    fills_are_drops: bool
    labels: Sequence[TruthLabel]
    passes: int | None
    period: float | None
    speed: float

    def open(self) -> None:
        """Open the device or source; blocks may be read from then on."""
        ...

    def close(self) -> None:
        """Release the device or source."""
        ...

    def read(self, timeout: float | None = None) -> Block | None:
        """Return the next block, ``None`` if none arrived within ``timeout`` s.

        Raises :class:`DriverClosed` at the end of the stream.
        """
        ...

    def stats(self) -> dict[str, int]:
        """Counters since ``open()``: at least ``frames`` and ``filled``."""
        ...

    def take_events(self) -> tuple[list[DriverEvent], dict[str, int]]:
        """Return the new events since the last call, and per-kind counts of those dropped (bounded log).

        Any thread; never blocks but on a short lock.
        """
        ...

    def __enter__(self) -> Driver: ...

    def __exit__(self, *exc: object) -> None: ...


#: The members of :class:`Driver` the node calls or reads, as :func:`missing_members` checks them.
DRIVER_MEMBERS = ("rate", "channels", "open", "close", "read", "stats", "take_events", "fills_are_drops",
                  "labels", "passes", "period", "__enter__", "__exit__")


def missing_members(driver: object) -> tuple[str, ...]:
    """Return the members of :class:`Driver` that ``driver`` lacks, in :data:`DRIVER_MEMBERS`'s order.

    Empty for a complete driver. Checked once, where a driver enters the node, so that the
    node then calls every member without probing for it.
    """
    return tuple(name for name in DRIVER_MEMBERS if not hasattr(driver, name))


#: Guards the lazy creation of a driver's event log (see :attr:`DriverBase.event_log`).
_LOG_CREATION = threading.Lock()


class DriverBase:
    """The part of a driver every driver shares.

    That is its event log, ``take_events``, notices, the context manager, and the labels of a
    driver that has none.

    A subclass sets ``rate`` and ``channels`` and gives ``read`` and ``stats`` (see
    :class:`Driver`); it overrides ``open`` and ``close`` when it has a device to open, and
    ``fills_are_drops``, ``labels``, ``passes``, ``period`` and ``speed`` when it has something else to
    say. It need not call ``DriverBase.__init__``: the event log is made on first use.

    Attributes
    ----------
    fills_are_drops : bool, default False
        Class attribute: True for a driver whose every filled frame stands for a sample the
        host received and lost (module documentation).
    labels : tuple, default ()
        Truth labels the driver carries (a replayed session's); none.
    passes : int or None, default 1
        Passes of its source the stream plays; one.
    period : float or None, default None
        Seconds per pass, which looped labels repeat with; none.
    speed : float, default 1.0
        Times real time the samples come at: a device's own pace.
    EVENT_CAPACITY, EVENT_HISTORY : int
        Class attributes: the event log's ``capacity`` and ``history`` (see :class:`EventLog`).

    Notes
    -----
    Threads: :meth:`take_events`, :meth:`_record`, :attr:`event_log` and :attr:`events` may be
    called from any thread, an audio callback included: each holds a short lock and never waits
    otherwise. :meth:`_notice` calls ``on_notice`` on the caller's thread (the reading thread:
    it must not block). ``open``, ``close``, ``__enter__`` and ``__exit__`` follow the driver's
    own rules (by default: the thread that reads).
    """

    fills_are_drops: bool = False
    labels: Sequence[TruthLabel] = ()
    passes: int | None = 1
    period: float | None = None
    speed: float = 1.0
    EVENT_CAPACITY: ClassVar[int] = 1024
    EVENT_HISTORY: ClassVar[int] = 200
    #: Called with the text of each notice (:meth:`_notice`) on the thread that makes it;
    #: None: kept as an event only (the node's choice: it shows events through its sinks).
    _on_notice: Callable[[str], None] | None = None

    def __init__(self) -> None:
        if "_event_log" not in self.__dict__:          # events logged before it are kept
            self._event_log = EventLog(self.EVENT_CAPACITY, self.EVENT_HISTORY)

    @property
    def event_log(self) -> EventLog:
        """The driver's :class:`EventLog`; any thread.

        Made on first use by a subclass that did not call ``DriverBase.__init__``.
        """
        try:
            log: EventLog = self.__dict__["_event_log"]
            return log
        except KeyError:
            with _LOG_CREATION:
                if "_event_log" not in self.__dict__:
                    self._event_log = EventLog(self.EVENT_CAPACITY, self.EVENT_HISTORY)
                return self._event_log

    def take_events(self) -> tuple[list[DriverEvent], dict[str, int]]:
        """Return the new events since the last call, and per-kind counts the bounded log dropped.

        The counts are of the events dropped because nobody took them; ``([], {})`` when there
        is nothing new.

        Any thread; holds the log's lock for a few microseconds and never waits otherwise.
        """
        return self.event_log.take()

    def _record(self, kind: str, message: str, stream_index: int | None = None, count: int = 1) -> DriverEvent:
        """Log an event (timestamped now) and return it; any thread, never blocks but on a short lock."""
        return self.event_log.record(kind, message, stream_index, count)

    def _notice(self, message: str, kind: str = "notice", stream_index: int | None = None) -> None:
        """Log ``message`` as an event of ``kind`` and hand it to ``on_notice``, if one is set.

        ``on_notice`` is called on this thread (a driver used on its own prints its notices;
        the node sets none).
        """
        self._record(kind, message, stream_index)
        if self._on_notice is not None:
            self._on_notice(message)

    @property
    def events(self) -> list[str]:
        """The last ``EVENT_HISTORY`` events as timestamped lines, oldest first (a copy); any thread.

        :meth:`take_events` is not affected.
        """
        return [_stamp(ev.time) + " " + ev.message for ev in self.event_log.history()]

    def open(self) -> None:
        """Open the device; nothing to do here."""

    def close(self) -> None:
        """Close the device; nothing to do here."""

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _stamp(t: float) -> str:
    """``time.time()`` as local ``YYYY-MM-DDTHH:MM:SS.mmm``."""
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t)) + f".{int(t % 1 * 1000):03d}"
