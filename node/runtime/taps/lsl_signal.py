"""A source's samples out as a Lab Streaming Layer stream, so that another machine records or classifies them.

E.g. the robot's computer sends the whisker array, a workstation runs the model.

Needs the optional extra ``lsl`` (:func:`supramodal.drivers.lsl.import_pylsl` says what to
install when it is missing). A scene asks for it with ``[[sink]] type = "lsl-signal"``; a scene
whose sources feed no ``[[stream]]`` (a relay) runs no bank, features or model at all.

Stream
------
============  ==============================================================================
name          ``PREFIX-SOURCE-signal`` (SOURCE: the scene's source name; ``main`` in a
              one-source scene; PREFIX: default ``"supramodal"``)
type          ``stream_type``; default ``"Whiskers"`` for a whisker array (a source read by a
              whisker bank, or a serial or whisker two-sense driver), ``"Audio"`` for a
              microphone (or a source read by a cochlea bank), ``"Signal"`` otherwise
source_id     ``PREFIX@HOST/SOURCE/signal``: stable across restarts, so consumers that recover
              by source id pick up a restarted node
format        float32, one channel per driver channel, at the source's nominal rate; samples as
              the node reads them (full scale +-1)
description   ``channels`` (``label``, ``unit``, ``type`` per channel, the XDF meta-data
              conventions) and ``supramodal`` (version, source, driver, rate, chunk seconds, holes)
============  ==============================================================================

Chunks and time
---------------
The samples are cut at fixed stream indices, every ``chunk`` seconds of samples (frames
``k * C``), whatever block sizes the driver delivers, and at the driver's restart marks (where
the source's time jumps: no chunk reaches across one), and each chunk is pushed as soon as its last
sample is in (``push_chunk``, which stamps the chunk's last sample; liblsl dates the others back by
the nominal rate); after :data:`SILENCE_FLUSH_SECONDS` without a frame the frames of the chunk
begun are pushed without waiting for the rest. The stamp is that sample's time on the node's common clock (the source's
clock model, the line of the block that brought it), put on LSL's clock: for a live source, the
host time the sample was taken; for a file, its own time from the start of the run.

Holes
-----
Samples the node never measured are not sent: frames the driver filled (lost on the line, a
microphone overflow) and frames this outlet's ring reader lost (it fell behind a live source's
ring). The chunk before a hole is pushed at once; the next starts after it. A consumer sees the
hole in the timestamps (the node's own LSL inlet fills and counts it; LabRecorder keeps the
timestamps), and the node's summary counts every frame's fate under ``taps``.

Threading
---------
The outlet is a *tap* (:class:`supramodal.node.runtime.taps.Tap`): another reader of the source's ring
on a thread of its own, run by :class:`supramodal.node.runtime.graph.Graph`, as the recorder is.
``push_chunk`` copies into liblsl's buffer and never waits for a consumer (liblsl drops the
oldest for one slower than ``OUTLET_BUFFER_SECONDS``). A file source's ring (policy "block")
waits for this reader as for every other; a live source's ring drops frames for a reader that
falls behind, counted.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from supramodal import __version__
from supramodal.checks import NAME_HELP, Key, is_name, non_negative, number, text
from supramodal.drivers.lsl import import_pylsl
from supramodal.drivers.spec import OptionError
from supramodal.errors import InputError
from supramodal.node.runtime.fields import float_of, optional_str_of, str_of
from supramodal.node.runtime.ringbuffer import RingClosed, flag_runs
from supramodal.node.runtime.sinks.lsl import (
    DEFAULT_PREFIX,
    OUTLET_BUFFER_SECONDS,
    LSLClock,
    Outlet,
    outlet_name,
    outlet_source_id,
    wait_for_consumers,
)
from supramodal.node.runtime.sinks.spec import Options, SinkContext, SinkSpec, SourcePlan
from supramodal.node.runtime.taps import Tap
from supramodal.records import JsonValue

if TYPE_CHECKING:   # the annotations' names only (the sources import the taps)
    from supramodal.node.runtime.sources import Feed, Source

#: Seconds of samples per push: LSL's usual 5-30 ms; 10 ms matches the node's own chunks.
DEFAULT_SIGNAL_CHUNK = 0.01
#: Seconds to wait for a consumer before the node starts: none, as a live sensor cannot wait.
DEFAULT_WAIT_FOR_CONSUMER = 0.0
#: The LSL content type of a source that is neither a whisker array nor a microphone.
DEFAULT_SIGNAL_TYPE = "Signal"
#: The range of ``chunk`` a scene may ask for, seconds.
SIGNAL_CHUNK_RANGE = (0.001, 0.1)
#: The output name in the stream's name and source id.
SIGNAL = "signal"
#: Seconds without a frame from the source after which the frames of a chunk begun are pushed
#: without waiting for the rest of the chunk.
SILENCE_FLUSH_SECONDS = 0.1
#: Seconds :meth:`LSLSignalOutlet.close` waits, when a consumer is connected, for liblsl to send
#: the last chunk before the outlet goes.
LINGER_SECONDS = 0.5


class LSLSignalOutlet(Tap):
    """One source's samples as an LSL stream (see the module notes): a :class:`~supramodal.node.runtime.taps.Tap`.

    Parameters
    ----------
    source : str
        The source's name in the scene.
    rate : float
        The source's nominal rate, Hz.
    channels : int
    chunk : float
        Seconds of samples per push (default :data:`DEFAULT_SIGNAL_CHUNK`).
    prefix : str
        Default :data:`~supramodal.node.runtime.sinks.lsl.DEFAULT_PREFIX`.
    stream_type : str
        The LSL content type (default :data:`DEFAULT_SIGNAL_TYPE`; a scene's ``lsl-signal`` sink
        passes what the source is: :func:`signal_type`).
    labels : sequence of str, optional
        Channel labels (default ``ch1`` ... ``chN``).
    driver : str
        What the source is (the scene's driver type), for the stream's description.
    wait_for_consumer : float
        Seconds the node waits, before it starts, for a consumer of this outlet (default 0: it
        starts at once). Sending a file to another machine needs it: an LSL consumer gets only
        what is pushed once it is connected. The node starts anyway when none comes
        (``waited_s`` and ``consumer`` in the summary say so).

    The outlet is made here, so that consumers can resolve it before the node starts.
    """

    def __init__(self, source: str, rate: float, channels: int, chunk: float = DEFAULT_SIGNAL_CHUNK,
                 prefix: str = DEFAULT_PREFIX, stream_type: str = DEFAULT_SIGNAL_TYPE,
                 labels: Sequence[str] | None = None, driver: str = "",
                 wait_for_consumer: float = DEFAULT_WAIT_FOR_CONSUMER) -> None:
        lo, hi = SIGNAL_CHUNK_RANGE
        if not lo <= chunk <= hi:
            raise InputError(f"an LSL signal outlet's chunk is {lo:g} to {hi:g} s, got {chunk!r}")
        labels = [f"ch{i + 1}" for i in range(channels)] if labels is None else list(labels)
        if len(labels) != channels:
            raise InputError(f"{len(labels)} channel labels for {channels} channels")
        self._pylsl = pylsl = import_pylsl()
        self.source = source
        self.rate = float(rate)
        self.frames_per_chunk = max(1, int(round(chunk * self.rate)))
        self.name = outlet_name(prefix, source, SIGNAL)
        self.source_id = outlet_source_id(prefix, source, SIGNAL)
        info = pylsl.StreamInfo(self.name, stream_type, channels, self.rate, "float32", self.source_id)
        desc = info.desc()
        chans = desc.append_child("channels")
        for label in labels:
            ch = chans.append_child("channel")
            ch.append_child_value("label", label)
            ch.append_child_value("unit", "fullscale")
            ch.append_child_value("type", stream_type)
        meta = desc.append_child("supramodal")
        meta.append_child_value("version", __version__)
        meta.append_child_value("source", source)
        meta.append_child_value("driver", driver)
        meta.append_child_value("rate", repr(self.rate))
        meta.append_child_value("chunk", repr(self.frames_per_chunk / self.rate))
        meta.append_child_value("holes", "samples the node never measured are not sent; the timestamps show where")
        self._outlet: Outlet | None = pylsl.StreamOutlet(info, chunk_size=self.frames_per_chunk,
                                          max_buffered=OUTLET_BUFFER_SECONDS)
        self.wait_for_consumer = float(wait_for_consumer)
        self.waited_s: float | None = None
        self.consumer: bool | None = None
        self._clock: LSLClock | None = None
        self._feed: Feed | None = None
        self._source: Source | None = None
        self._pending: list[np.ndarray] = []
        self._restarts: collections.deque[int] = collections.deque()    # stream indices, ascending
        self._pending_end = 0              # stream index one past the last pending frame
        self.chunks = 0
        self.samples_sent = 0
        #: Pushes cut short by a hole (a filled or lost run) rather than at a chunk's end or a
        #: restart (a hole that begins on a chunk's end cuts nothing short, and is not counted
        #: here; every frame not sent is, in the summary's ``frames``).
        self.holes = 0

    # -- the graph's calls --------------------------------------------------------------------

    def prepare(self) -> None:
        """Wait up to ``wait_for_consumer`` seconds for a consumer.

        The caller's thread, before the graph's start (a graph prepares its taps in turn: waits without
        a consumer add up).
        """
        if self.wait_for_consumer > 0:
            assert self._outlet is not None, "prepare before close (the graph's order of calls)"
            self.waited_s, (self.consumer,) = wait_for_consumers([self._outlet], self.wait_for_consumer)

    def start(self, source: Source, epoch: float) -> None:
        """Take the source this outlet taps and the graph's start (``time.monotonic()``): common time 0.

        The caller's thread, before the tap's thread starts.
        """
        self._clock = LSLClock(self._pylsl, epoch)
        self._source = source

    def run(self, feed: Feed) -> None:
        """Read ``feed`` until the ring closes, pushing each chunk as it completes.

        ``feed``: a :class:`~supramodal.node.runtime.sources.Feed` of the source's ring. The tap's thread.
        """
        reader, expected = feed.reader, 0
        self._feed = feed
        heard = time.monotonic()
        while True:
            try:
                got = reader.read(timeout=0.05)
            except RingClosed:
                break
            if got is None:
                # A source gone silent (a sensor unplugged, a sender paused): the frames of the
                # chunk begun go now, not when (if ever) the chunk completes.
                if self._pending and time.monotonic() - heard >= SILENCE_FLUSH_SECONDS:
                    self._flush()
                continue
            heard = time.monotonic()
            start, data, filled = got
            self._take_restarts(feed.marks, start + data.shape[0])
            if start > expected:
                self._flush(hole=True)     # frames this reader lost: not sent, the stamps show it
            if filled is None or not filled.any():
                self._add(data, start)
            else:
                for a, b in flag_runs(~filled):                 # the measured runs
                    self._add(data[a:b], start + a)
                if filled[-1]:
                    self._flush(hole=True)
            expected = start + data.shape[0]
        self._flush()

    def summary(self) -> dict[str, JsonValue]:
        """Return what the outlet sent (the graph adds every frame's fate as its reader saw it)."""
        return {"outlet": self.name, "source_id": self.source_id, "chunks": self.chunks,
                "samples_sent": self.samples_sent, "holes": self.holes, "waited_s": self.waited_s,
                "consumer": self.consumer}

    def close(self) -> None:
        """Release the outlet (again: a no-op)."""
        if self._outlet is not None and self.samples_sent and self._outlet.have_consumers():
            time.sleep(LINGER_SECONDS)     # liblsl sends from its own thread: let the last chunk go
        self._outlet = None                # liblsl closes an outlet when it is released

    # -- chunks -------------------------------------------------------------------------------

    def _take_restarts(self, marks: collections.deque[tuple[int, str]], end: int) -> None:
        """Keep the driver's restart marks before stream index ``end``.

        The source thread notes a block's marks before it writes the block, so all of them are there.
        """
        while marks and marks[0][0] < end:
            index, kind = marks.popleft()
            if kind == "restart":
                self._restarts.append(index)

    def _add(self, frames: np.ndarray, index: int) -> None:
        """Add frames from stream ``index`` on, measured and contiguous: pushed at each cut, and before a restart.

        Before a restart, because liblsl dates a chunk's samples back from its last one at the nominal
        rate, which must not reach across a jump in the source's time.
        """
        if self._pending and index != self._pending_end:
            self._flush(hole=True)
        C, n, i = self.frames_per_chunk, frames.shape[0], 0
        while i < n:
            while self._restarts and self._restarts[0] <= index + i:
                self._restarts.popleft()
                self._flush()
            cut = ((index + i) // C + 1) * C
            if self._restarts:
                cut = min(cut, self._restarts[0])
            j = min(n, cut - index)
            self._pending.append(frames[i:j])
            self._pending_end = index + j
            if self._pending_end == cut:
                self._flush()
            i = j

    def _flush(self, hole: bool = False) -> None:
        if not self._pending:
            return
        x = np.concatenate(self._pending, axis=0).astype(np.float32)
        self._pending = []
        outlet, clock = self._outlet, self._clock
        assert outlet is not None and clock is not None, "pushed between start and close (the tap's thread)"
        outlet.push_chunk(x, clock.lsl_time(self._stamp(self._pending_end - 1)))
        self.chunks += 1
        self.samples_sent += x.shape[0]
        self.holes += hole

    def _stamp(self, index: int) -> float:
        """Return sample ``index`` on common time, by the line of the block that brought it.

        That line is the one a window ending there is dated by.
        """
        feed, source = self._feed, self._source
        assert feed is not None and source is not None, "start and run set them before any frame"
        block = feed.block_of(index)
        offset, slope = source.line() if block is None else block[2]
        return offset + index * slope


# -- as a scene names it ---------------------------------------------------------------------------

def signal_type(source: SourcePlan) -> str:
    """Return what ``source`` is, as an LSL content type: by the banks that read it, else by its driver's spec.

    The driver's spec says it in :attr:`~supramodal.node.runtime.sinks.spec.SourcePlan.signal_type`.
    """
    kinds = {bank.kind for bank, _ in source.read_by}
    if kinds == {"whisker"}:
        return "Whiskers"
    if kinds == {"cochlea"}:
        return "Audio"
    return source.signal_type or DEFAULT_SIGNAL_TYPE


def _build(options: Options, context: SinkContext) -> Tap:
    name = str_of(options, "source")
    source = context.sources[name]
    driver = source.driver
    channels = driver.channels
    # Channel labels: the filters' names where a bank takes the channels one to one.
    labels = next((bank.names for bank, mapping in source.read_by
                   if mapping in ("auto", "per-channel") and bank.channels == channels), None)
    try:
        return LSLSignalOutlet(name, driver.rate, channels, float_of(options, "chunk"),
                               str_of(options, "prefix"), optional_str_of(options, "stream_type")
                               or signal_type(source), labels, source.type, float_of(options, "wait_for_consumer"))
    except InputError as exc:
        raise OptionError(str(exc)) from None


#: Longest wait for a consumer a scene may ask for, seconds.
MAX_WAIT_FOR_CONSUMER = 3600.0

SPEC = SinkSpec(
    type="lsl-signal",
    summary="a source's samples as a Lab Streaming Layer outlet, to classify them on another machine (the lsl extra)",
    keys={
        "chunk": Key(number(*SIGNAL_CHUNK_RANGE),
                     f"seconds of samples per push, {SIGNAL_CHUNK_RANGE[0]:g} to {SIGNAL_CHUNK_RANGE[1]:g}",
                     DEFAULT_SIGNAL_CHUNK),
        "prefix": Key(is_name, "the outlet's name prefix: " + NAME_HELP[len("a name: "):], DEFAULT_PREFIX),
        # None: what the source is (its banks' kind, else its driver's signal type).
        "stream_type": Key(text, 'the LSL stream\'s type, e.g. "Whiskers" (default: what the source is)', None),
        "wait_for_consumer": Key(non_negative(MAX_WAIT_FOR_CONSUMER),
                                 "seconds to wait for a consumer before the node starts, 0 to "
                                 f"{MAX_WAIT_FOR_CONSUMER:g} (0: start at once; a file sent to another machine "
                                 "needs a wait)", DEFAULT_WAIT_FOR_CONSUMER),
    },
    build=_build, listens="samples", needs="sources", unique=("source", "prefix"))
