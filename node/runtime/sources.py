"""A source: one driver, its ring buffer and its thread, and the clock that puts its samples on the graph's common time.

Threads and real-time rules
---------------------------
The *source thread* (:meth:`Source.drive`) only moves blocks: ``driver.read()`` ->
``ring.write()``, noting each block's arrival (for the clock and for decision latency) and its
restart/overrun marks in every feed. It never waits on processing: when a reader lags by more
than the ring's capacity, the ring's overrun policy drops frames, and every dropped frame is
counted. After every read (a block or a timeout, at most 50 ms apart) it takes the driver's new
events (``take_events()``) and queues them for the graph's event thread, without waiting.

Common time
-----------
Every window event carries its start and end on one time line shared by all sources, in seconds
from the graph's start. Where it comes from depends on the source (``timebase``):

* ``"stream"`` (files: replay, synth, twosense): a file's time is its own sample count,
  ``index / rate`` (plus the source's ``time_offset``, seconds). A replay at ``max`` speed keeps
  its true timing.
* ``"host"`` (live drivers: serial, microphone): a :class:`~supramodal.node.runtime.clock.ClockModel`
  fitted to the blocks' arrival stamps maps the sample index to the host's monotonic clock, so
  two sources on their own crystals line up; minus the graph's start.
* ``"recorded"`` (sessions recorded by a node of several sources, replayed with their recorded
  timing): the same clock model, fitted to the times the recording node stamped on each block
  (``Block.recorded``, already on its common time), so that the sources of one recording are
  put on common time as they were when it was made, at any replay speed.

When a source is recorded (several sources), each block's end frame and the time it was
complete on common time go into its session (``arrivals``): the arrival stamp for the host
timebase, the line's time of its last sample otherwise.
"""

from __future__ import annotations

import collections
import math
import queue
import threading
from collections.abc import Callable
from typing import Protocol

import numpy as np

from supramodal.drivers.base import Block, Driver, DriverClosed, DriverEvent, missing_members
from supramodal.errors import InputError
from supramodal.node.runtime.clock import ClockModel
from supramodal.node.runtime.labels import Labels
from supramodal.node.runtime.ringbuffer import Reader, RingBuffer
from supramodal.node.runtime.summaries import ClockSummary


class ArrivalRecorder(Protocol):
    """What a source tells its recorder that no feed carries.

    The recorder: :class:`~supramodal.node.runtime.taps.recorder.SessionRecorder`. Called on the source's thread. (A
    protocol, not the recorder's class: the recorder imports the sources, and the sources need only these two calls
    of it.)
    """

    def note(self, index: int, kind: str) -> None:
        """Note a driver mark (``kind``) at the source's frame ``index``."""

    def arrival(self, end: int, seconds: float) -> None:
        """Note that a block ending at the source's frame ``end`` was complete at ``seconds`` of common time."""

#: What a source puts on the graph's event queue: (source name, driver events, dropped counts by kind).
EventItem = tuple[str, list[DriverEvent], dict[str, int]]

TIMEBASES = ("stream", "host", "recorded")


def _head(block: Block, n: int) -> Block:
    """Return the first ``n`` frames of a block."""
    n = max(n, 0)
    filled = None if block.filled is None else block.filled[:n]
    return Block(block.data[:n], block.start, block.arrival, filled,
                 tuple(i for i in block.restarts if i < n), tuple(i for i in block.overruns if i < n))


class Feed:
    """What one reader of a source gets: the ring reader, each block's arrival and the driver's marks.

    In stream order, each block's ``(end index, host arrival, common-time line after it)`` and the driver's marks
    (``(index, "restart" | "overrun")``). Filled by the source thread, consumed by one processing thread (deques:
    appends and pops from opposite ends are thread-safe). A feed that does not ``track`` (the recorder's: it takes
    marks and times from the source itself) gets neither, so nothing piles up unread.
    """

    def __init__(self, reader: Reader, track: bool = True) -> None:
        self.reader = reader
        self.track = track
        #: (end frame, host arrival, common-time line (offset, slope)) of each block, in order
        self.arrivals: collections.deque[tuple[int, float, tuple[float, float]]] = collections.deque()
        self.marks: collections.deque[tuple[int, str]] = collections.deque()

    def block_of(self, index: int) -> tuple[int, float, tuple[float, float]] | None:
        """Return ``(end, arrival, line)`` of the block that brought frame ``index``, or None.

        None if no block is known for it (the end of the stream). The blocks before it are dropped: call it with
        indices that never go back. The reader's thread.
        """
        arrivals = self.arrivals
        while arrivals and arrivals[0][0] <= index:
            arrivals.popleft()
        return arrivals[0] if arrivals else None


class Source:
    """A driver, its ring and its thread.

    Parameters
    ----------
    name : str
        The source's name in a scene (``[[source]] name``).
    driver : drivers.base.Driver
        Refused (:class:`~supramodal.errors.InputError`) if it lacks a member of the contract: a
        driver derives from :class:`~supramodal.drivers.base.DriverBase`.
    buffer_seconds : float
        Ring capacity, seconds of stream.
    overrun : {"drop-oldest", "drop-newest", "block"}
        The ring's policy. "block" makes the source thread wait for space: right for replay,
        where no sample need be lost; live drivers drop and count instead.
    timebase : {"stream", "host", "recorded"}
        How the source's samples are put on common time (see the module's docstring).
    time_offset : float
        For the stream timebase: seconds of common time at which the source's first sample was
        taken (a two-sense source's ``offset``; default 0).
    time_rate : float, optional
        The rate at which the source's samples advance on common time, Hz: for the stream
        timebase, the file's own clock (a two-sense source's true rate, its ``clock_ppm``
        included); for the host timebase, the clock model's nominal rate (a replay paced at
        ``speed`` delivers ``speed`` times its rate). Default: the driver's rate.
    """

    def __init__(self, name: str, driver: Driver, buffer_seconds: float = 2.0, overrun: str = "drop-oldest",
                 timebase: str = "stream", time_offset: float = 0.0, time_rate: float | None = None) -> None:
        if timebase not in TIMEBASES:
            raise InputError(f"a source's timebase is one of {TIMEBASES}, got {timebase!r}")
        missing = missing_members(driver)
        if missing:
            raise InputError(f"source {name!r}: the driver {type(driver).__name__} lacks {', '.join(missing)} of the "
                             "driver contract (supramodal.drivers.base.Driver): derive from "
                             "supramodal.drivers.base.DriverBase, which gives take_events, fills_are_drops, labels "
                             "and the context manager")
        self.name = name
        self.driver = driver
        self.rate = float(driver.rate)
        self.timebase = timebase
        capacity = max(int(buffer_seconds * driver.rate), 1)
        self.ring = RingBuffer(capacity, driver.channels, dtype=np.float64, overrun=overrun)
        self.feeds: list[Feed] = []
        #: The recorder of this source (:class:`~supramodal.node.runtime.taps.recorder.SessionRecorder`, a tap
        #: that set itself here in its ``start``), or None: the source thread tells it each
        #: block's driver marks (``note``) and time on common time (``arrival``), which no feed carries.
        self.recorder: ArrivalRecorder | None = None
        #: Truth labels of the source's samples (:class:`~supramodal.node.runtime.labels.Labels`), set by
        #: the graph from the first stream that reads the source; None: none known (a relay).
        self.labels: Labels | None = None
        time_rate = self.rate if time_rate is None else float(time_rate)
        #: Samples per second of common time the clock model starts from (its nominal rate).
        self.time_rate = time_rate
        self.clock = ClockModel(time_rate) if timebase in ("host", "recorded") else None
        self.time_offset = float(time_offset)
        # (offset, seconds per sample) of the common-time line, replaced whole by the source
        # thread so that a processing thread never reads half of an update.
        self._line = (self.time_offset, 1.0 / time_rate)
        self.epoch = 0.0                 # host time of the graph's start (set by the graph)
        self._last_arrival = -math.inf
        #: Blocks whose arrival stamp went backwards, left out of the clock fit.
        self.clock_skipped = 0
        #: Whether the driver has delivered any frame (a source that delivers none cannot reach its length).
        self.delivered_any = False
        self.max_frames: int | None = None
        #: Set by the source thread: the stream length (``max_frames``) was reached.
        self.reached_length = False
        #: source thread -> the graph's event thread: (source name, events, dropped); None ends.
        self.event_queue: queue.SimpleQueue[EventItem | None] | None = None

    def add_feed(self, name: str, track: bool = True) -> Feed:
        """Return a new reader of this source's ring (a stream or a tap).

        A tap that does not ``track`` arrivals and marks, such as the recorder, gets neither, see :class:`Feed`.
        """
        feed = Feed(self.ring.add_reader(name), track)
        self.feeds.append(feed)
        return feed

    def line(self) -> tuple[float, float]:
        """``(offset, slope)``: common time of sample 0, seconds, and seconds per sample, now."""
        return self._line

    def time_of(self, index: int) -> float:
        """Sample ``index`` on the graph's common time line, seconds."""
        offset, slope = self._line
        return offset + index * slope

    # -- source thread ----------------------------------------------------------------------

    def drive(self, stop: threading.Event, on_stop: Callable[[str], None]) -> None:
        """Move blocks from the driver to the ring until the stream ends or ``stop`` is set.

        Call ``on_stop(reason)`` when the stream length (``max_frames``) is reached.
        """
        try:
            while not stop.is_set():
                try:
                    block = self.driver.read(timeout=0.05)
                except DriverClosed:
                    break
                finally:
                    self._queue_events()
                if block is None:
                    continue
                self.delivered_any = self.delivered_any or block.frames > 0
                limit = self.max_frames
                last = limit is not None and block.start + block.frames >= limit
                if limit is not None and last:
                    block = _head(block, limit - block.start)
                self._note(block)
                self._write(block, stop)
                if last:
                    self.reached_length = True
                    on_stop("stream length reached")
                    break
        finally:
            self.ring.close()

    def _note(self, block: Block) -> None:
        end = block.start + block.frames
        for kind, offsets in (("restart", block.restarts), ("overrun", block.overruns)):
            for i in offsets:
                for feed in self.feeds:
                    if feed.track:
                        feed.marks.append((block.start + i, kind))
                if self.recorder is not None:
                    self.recorder.note(block.start + i, kind)
        stamp = None                    # the time the clock model took for this block, if it took one
        if self.clock is not None and block.frames:
            if self.timebase == "recorded":
                if block.recorded is None:
                    raise InputError(f"source {self.name!r}: a block without its recorded time; the recorded "
                                     "timebase needs a replay with timing = 'recorded'")
                stamp = block.recorded
            else:
                # On common time, to the microsecond: the numbers a recording keeps, so that its
                # replay feeds the clock model exactly what it was fed here. A source that stamps
                # its own samples (LSL) is fitted on those: the sender's timing, not the network's.
                taken = block.arrival if block.timestamp is None else block.timestamp
                stamp = round(taken - self.epoch, 6)
            if block.restarts:
                self.clock.reset()          # the board's count restarted: the old line is void
            if not stamp >= self._last_arrival:
                self.clock_skipped += 1     # a stamp out of order (a driver's fill): not a measurement
                stamp = None
            else:
                self._last_arrival = stamp
                self.clock.update(end - 1, stamp)
                self._line = self.clock.line()
        # The line as it stands after this block goes with it: a window's times are mapped by the
        # line of the block that completed it, whatever the processing thread's timing.
        for feed in self.feeds:
            if feed.track:
                feed.arrivals.append((end, block.arrival, self._line))
        if self.recorder is not None and block.frames:
            # What the clock model took (a skipped stamp is left out, as the clock left it out;
            # its block then replays as part of the next), or a file's own time of the block.
            if self.clock is None:
                self.recorder.arrival(end, self.time_of(end - 1))
            elif stamp is not None:
                self.recorder.arrival(end, stamp)

    def _queue_events(self) -> None:
        events, dropped = self.driver.take_events()
        if (events or dropped) and self.event_queue is not None:
            self.event_queue.put((self.name, events, dropped))

    def _write(self, block: Block, stop: threading.Event) -> None:
        # Under "block" the ring takes what fits and we wait for the rest (lossless replay);
        # under the drop policies one write is final: it takes everything and counts what it
        # drops, or ("drop-newest") refuses the rest, whose stream indices are then spent.
        # Offering refused frames again would put them in the stream twice.
        kept, n = 0, block.frames
        while kept < n:
            filled = None if block.filled is None else block.filled[kept:]
            kept += self.ring.write(block.data[kept:], filled, timeout=0.1)
            if self.ring.overrun != "block" or (kept < n and stop.is_set() and self.ring.closed):
                return

    # -- summary ----------------------------------------------------------------------------

    def frame_fates(self, feed: Feed) -> dict[str, int]:
        """Return the stream's frames, each counted once, as ``feed``'s reader saw it: delivered, filled or dropped.

        ``delivered``: measured by the driver and processed as measured.
        ``filled``: synthesised by the driver (``Block.filled``) for samples the host never
        received (lost on the line or by the board, unplugged), whether the ring kept its zeros
        or dropped them: zeros lost are still zeros, not data lost.
        ``dropped``: samples the host received and lost: measured frames the ring lost
        (``dropped_in_ring``; the pipeline gets zeros in their place, but they count here
        only), and a driver's fills for its own losses (``dropped_by_driver``: a driver with
        ``fills_are_drops``, the microphone, fills only for overflows and a full buffer).
        ``stream``: frames offered to the ring, the stream's length; once the processing
        thread has drained the ring, ``delivered + filled + dropped == stream`` exactly.
        ``filled_lost_in_ring``: filled frames the ring dropped (counted in ``filled``, or in
        ``dropped_by_driver``), for the record.
        """
        ring = self.ring.stats()
        r = feed.reader.stats()
        # The ring knows each row's flag when it drops it: the split is exact per frame,
        # whatever the timing (a fill longer than the ring loses its own head on write).
        synthesised = r["read_filled"] + r["lost_filled"]
        driver_drops = synthesised if self.driver.fills_are_drops else 0
        in_ring = r["lost"] - r["lost_filled"]
        return {"stream": ring["written"],
                "delivered": r["read"] - r["read_filled"],
                "filled": synthesised - driver_drops,
                "dropped": in_ring + driver_drops,
                "dropped_in_ring": in_ring,
                "dropped_by_driver": driver_drops,
                "filled_lost_in_ring": r["lost_filled"]}

    def clock_summary(self) -> ClockSummary | None:
        """Return the clock's estimate (rate error in ppm, jitter and delay in ms), for a host timebase."""
        if self.clock is None:
            return None
        e = self.clock.estimate()
        return ClockSummary(round(e.ppm, 3), round(e.jitter * 1e3, 3), round(e.delay * 1e3, 3), e.blocks, e.fitted,
                            self.clock_skipped)
