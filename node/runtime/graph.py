"""The running node: sources -> streams -> (fusion) -> sinks, on their own threads.

A graph is built from a scene (node/scene/build.py): each ``[[source]]`` a driver with its ring and
thread (:mod:`supramodal.node.runtime.sources`), each ``[[stream]]`` one source's samples through a bank,
features and model to window events (:mod:`supramodal.node.runtime.streams`), an optional ``[fusion]``
block pairing two streams' windows on common time (:mod:`supramodal.node.runtime.fusion`), and sinks,
each listening to the streams it names. A one-driver scene is the one-source case
(:class:`Node`).

Threads and real-time rules
---------------------------
* Each *source thread* only moves blocks from its driver to its ring, and never waits on
  processing (see :mod:`supramodal.node.runtime.sources`).
* Each *processing thread* runs one stream's model blocks over its ring reader and hands each
  window's :class:`~supramodal.node.runtime.events.WindowEvent` to the router, which never blocks: a
  scene's sinks run behind their own bounded queues (:class:`~supramodal.node.runtime.sinks.QueuedSink`),
  the fusion block behind its queue.
* The *event thread* hands the sources' driver events to the sinks, at most one per kind per
  second per source (:class:`node.runtime.events.EventLimiter`: repeats are folded into the next one's
  ``count``), so neither a source nor a stream ever waits on a sink for an event.
* The *fusion thread*, with a ``[fusion]`` block, pairs the streams' windows and emits the fused
  decisions (stream ``"fused"``).
* Each *tap thread* (:class:`~supramodal.node.runtime.taps.Tap`: the recorder, the LSL signal outlet)
  reads one source's raw frames from its own ring reader.
* Every frame of every source has one fate in the summary's ``frames``: delivered, filled or
  dropped (see :meth:`Source.frame_fates`).
* The caller's thread (:meth:`Graph.run`) starts them all, waits, and handles the stop request
  (Ctrl-C, SIGTERM, :meth:`Graph.stop`): the drivers stop, what is already buffered is
  processed, the summary is written, nothing is left running.

The graph calls sinks and taps only through their bases' methods (:class:`~supramodal.node.runtime.sinks.Sink`,
:class:`~supramodal.node.runtime.taps.Tap`), every one of which a subclass may leave as it is; it never
probes them for a method.
"""

from __future__ import annotations

import contextlib
import functools
import math
import queue
import threading
import time
from collections.abc import Callable, Collection, Iterable
from dataclasses import replace
from typing import TYPE_CHECKING

from supramodal.decisions import DEFAULT_DECISION, DecisionRules
from supramodal.drivers.base import Driver, DriverEvent
from supramodal.errors import InputError, SupramodalError
from supramodal.model import TextureModel
from supramodal.node.runtime.events import FUSED_STREAM, MAIN_STREAM, EventLimiter, WindowEvent
from supramodal.node.runtime.labels import Labels
from supramodal.node.runtime.sinks import Sink
from supramodal.node.runtime.sources import EventItem, Feed, Source
from supramodal.node.runtime.streams import Stream, channel_mapper
from supramodal.node.runtime.summaries import FusionHealth, Health, RunSummary, StreamHealth
from supramodal.node.runtime.taps import Tap
from supramodal.node.runtime.taps.recorder import SessionRecorder
from supramodal.pipeline import FeaturePipeline

if TYPE_CHECKING:   # for annotations only: a graph of one stream does not load the fusion block
    from supramodal.drivers.contact import ContactListener
    from supramodal.node.runtime.contacts import ContactTimeline
    from supramodal.node.runtime.fusion import LateFusion

__all__ = ["Graph", "Node", "NodeError", "Labels", "channel_mapper"]


#: Least wall seconds beyond its stream's time that a run waits for a source that delivers nothing.
SILENT_SOURCE_GRACE = 5.0


def silent_source_limit(max_seconds: float, sources: Iterable[Source]) -> float:
    """Return the wall seconds, from the drivers' opening, after which a run with a silent live device ends.

    A run asked for ``max_seconds`` of stream ends at that limit if a live device has delivered nothing by then (a
    board whose every frame is refused, a sound card that never starts; :func:`silent_sources`). The limit is twice
    the time the stream takes at the slowest source's pace (a replay's ``speed``; real time for a device), and at
    least 5 s more than it.
    """
    pace = min((float(s.driver.speed) for s in sources), default=1.0)
    wall = max_seconds / pace if pace > 0 else 0.0
    return wall + max(SILENT_SOURCE_GRACE, wall)


def silent_sources(sources: Iterable[Source]) -> list[str]:
    """Return the names of the live devices that have delivered no sample.

    Live devices are sources whose ring drops rather than waits (a serial board, a microphone). A replay, and a
    network source that waits for its peer (LSL, ROS 2: its ring blocks), may rightly begin late (a stream that
    starts late in a recording, a robot started after the node), so they are never called silent.
    """
    return [s.name for s in sources if s.ring.overrun != "block" and not s.delivered_any]


class NodeError(SupramodalError, RuntimeError):
    """A thread of the node failed; the message says which and why."""


class Graph:
    """Sources, streams, an optional fusion block and sinks, run on their own threads.

    Parameters
    ----------
    sources : list of node.runtime.sources.Source
    streams : list of node.runtime.streams.Stream
        Each reads one of ``sources``; names are unique.
    sinks : list of node.runtime.sinks.Sink
        Called on the graph's threads: a scene's sinks are each behind a
        :class:`~supramodal.node.runtime.sinks.QueuedSink`, so that processing never waits on them.
    routes : list of (set of str or None), optional
        Per sink, the stream names it listens to (``"fused"`` for the fusion block's
        decisions); None (the default for every sink) listens to all. Driver events and the
        summary go to every sink.
    fusion : node.runtime.fusion.LateFusion, optional
    recorder : node.runtime.taps.recorder.SessionRecorder or dict, optional
        Records the raw frames of a source (a tap, run as the others are): one recorder for a
        graph of one source, or ``{source name: recorder}`` for several (each keeps its blocks'
        times on common time, so that the sessions replay in step). What they wrote is in the
        summary's ``recorded``, not under ``taps``.
    taps : list of (str, node.runtime.taps.Tap), optional
        Readers of a source's raw frames, each on a thread of its own, by source name (e.g.
        :class:`~supramodal.node.runtime.taps.lsl_signal.LSLSignalOutlet`); see
        :class:`~supramodal.node.runtime.taps.Tap` for the calls and their threads. A source that
        only taps read needs no stream: a graph may have none (a relay).
    """

    def __init__(self, sources: Iterable[Source], streams: Iterable[Stream], sinks: Iterable[Sink],
                 routes: Iterable[Collection[str] | None] | None = None, fusion: LateFusion | None = None,
                 recorder: SessionRecorder | dict[str, SessionRecorder] | None = None,
                 taps: Iterable[tuple[str, Tap]] = (),
                 contacts: Iterable[tuple[ContactListener, ContactTimeline]] = ()) -> None:
        self.sources = list(sources)
        if not self.sources:
            raise InputError("a graph needs at least one source")
        self.streams = list(streams)
        names = [s.name for s in self.streams]
        if len(set(names)) != len(names):
            raise InputError(f"stream names must be unique, got {names}")
        self.sinks = list(sinks)
        odd = [type(s).__name__ for s in self.sinks if not isinstance(s, Sink)]
        if odd:
            raise InputError(f"a graph's sinks derive from supramodal.node.runtime.sinks.Sink; {odd} do not")
        self.routes: list[Collection[str] | None] = list(routes) if routes is not None else [None] * len(self.sinks)
        if len(self.routes) != len(self.sinks):
            raise InputError(f"{len(self.routes)} routes for {len(self.sinks)} sinks")
        for s in self.sinks:
            s.on_reader_left = self._sink_reader_left     # a queued sink's reader may leave (`| head`)
            s.watch(self.health)                          # the graph's counters, for a sink that reports them
        self.fusion = fusion
        self.recorder = recorder
        recorders: dict[str, SessionRecorder]
        if recorder is None:
            recorders = {}
        elif isinstance(recorder, dict):
            unknown = sorted(set(recorder) - {s.name for s in self.sources})
            if unknown:
                raise InputError(f"recorders for unknown sources {unknown}")
            recorders = dict(recorder)
        elif len(self.sources) == 1:
            recorders = {self.sources[0].name: recorder}
        else:
            raise InputError("a graph of several sources records each one: give {source name: recorder}")
        for source in self.sources:     # a source's truth labels: those of the first stream reading it
            stream = next((st for st in self.streams if st.source is source), None)
            source.labels = stream.labels if stream is not None else None
        # Taps: the recorders (their own thread named "recorder"), then the others, each with the
        # source it reads, its feed and its thread's name.
        self._recorders: list[tuple[SessionRecorder, Source, Feed, str]] = []
        for source in self.sources:
            rec = recorders.get(source.name)
            if rec is None:
                continue
            if not isinstance(rec, SessionRecorder):
                raise InputError("a recorder is a supramodal.node.runtime.taps.recorder.SessionRecorder, "
                                 f"got {type(rec).__name__}")
            self._recorders.append((rec, source, source.add_feed("recorder", track=rec.track), "recorder"))
        self._taps: list[tuple[Tap, Source, Feed, str]] = []
        by_name = {s.name: s for s in self.sources}
        for name, tap in taps:
            if name not in by_name:
                raise InputError(f"a tap of unknown source {name!r}; the sources are {list(by_name)}")
            if not isinstance(tap, Tap):
                raise InputError("a graph's taps derive from supramodal.node.runtime.taps.Tap; "
                                 f"{type(tap).__name__} does not")
            source = by_name[name]
            self._taps.append((tap, source, source.add_feed(f"tap {tap.name}", track=tap.track), f"tap {tap.name}"))
        self.contacts = list(contacts)
        # source threads -> event thread: (source name, events, dropped); None from each source at its end
        self._event_queue: queue.SimpleQueue[EventItem | None] = queue.SimpleQueue()
        for source in self.sources:
            source.event_queue = self._event_queue
        self._limiter = EventLimiter()
        self._stop = threading.Event()
        self._errors: list[tuple[str, BaseException]] = []
        self._stopped_by: str | None = None

    # -- control -----------------------------------------------------------------------------

    def stop(self, reason: str = "stop requested") -> None:
        """Ask the node to stop (thread-safe, also from a signal handler)."""
        if self._stopped_by is None:
            self._stopped_by = reason
        self._stop.set()

    def run(self, max_seconds: float | None = None, on_running: Callable[[], None] | None = None) -> RunSummary:
        """Run until every source's stream ends, ``max_seconds`` of stream have passed, or :meth:`stop`.

        ``on_running``: called on the caller's thread once the taps are prepared (a wait for an
        outlet's consumer is over), just before time starts: e.g. to make Ctrl-C stop the run
        rather than interrupt the start-up. Returns the summary (also sent to the sinks).
        """
        if max_seconds is not None and not max_seconds > 0:
            raise InputError(f"max_seconds must be > 0 (or None or inf: no limit), got {max_seconds!r}")
        if max_seconds is not None and math.isinf(max_seconds):
            max_seconds = None
        try:
            return self._run(max_seconds, on_running)
        finally:
            for tap, _, _, _ in self._all_taps():  # an outlet is not left open, whatever happened
                tap.close()

    def _all_taps(self) -> list[tuple[Tap, Source, Feed, str]]:
        """Return the recorders and the other taps: ``(tap, source, feed, thread name)``."""
        return [*self._recorders, *self._taps]

    def _run(self, max_seconds: float | None, on_running: Callable[[], None] | None) -> RunSummary:
        for s in self.sinks:
            s.prepare()                           # may wait (e.g. for a consumer), before time starts
        for tap, _, _, _ in self._all_taps():
            tap.prepare()
        if on_running is not None:
            on_running()
        t0 = time.monotonic()
        for source in self.sources:
            source.max_frames = None if max_seconds is None else int(round(max_seconds * source.rate))
            source.epoch = t0
        for s in self.sinks:
            s.start(t0)                           # e.g. a sink that puts common time on another clock (LSL)
        threads = [self._thread(f"source {s.name}", self._drive, s) for s in self.sources]
        threads += [self._thread(f"processing {s.name}" if len(self.streams) > 1 else "processing", self._process, s)
                    for s in self.streams]
        threads.append(self._thread("event", self._deliver_events))
        for stream in self.streams:
            stream.on_event = functools.partial(self._stream_event, stream.name)
        if self.fusion is not None:
            self.fusion.on_event = functools.partial(self._stream_event, FUSED_STREAM)
            threads.append(self._thread("fusion", self._fuse, self.fusion))
        for tap, source, feed, where in self._all_taps():
            tap.start(source, t0)
            threads.append(self._thread(where, tap.run, feed))
        threads += [self._thread(f"contacts {listener.name}", self._listen, listener, timeline, t0)
                    for listener, timeline in self.contacts]
        with contextlib.ExitStack() as opened:
            for source in self.sources:
                opened.enter_context(source.driver)
            for t in threads:
                t.start()
            opened_at = time.monotonic()        # a slow open (an LSL resolve, a ROS node) spends none of it
            deadline = None if max_seconds is None else opened_at + silent_source_limit(max_seconds, self.sources)
            # Join with a timeout so that the main thread stays responsive to signals.
            while any(t.is_alive() for t in threads):
                for t in threads:
                    t.join(0.1)
                if deadline is not None and time.monotonic() > deadline:
                    deadline = None
                    silent = silent_sources(self.sources)
                    if silent:
                        self.stop(f"the stream length: source(s) {', '.join(silent)} delivered no sample in "
                                  f"{time.monotonic() - opened_at:.0f} s (see their events), so the length asked "
                                  f"({max_seconds:g} s of stream) could never be reached")
        for s in self.sinks:
            s.drain()                             # a queued sink: let it take what it holds
        for tap, _, _, _ in self._all_taps():
            tap.close()                           # its last chunk goes before the summary says so
        summary = self.summary(time.monotonic() - t0)
        for s in self.sinks:
            s.summary(summary)
        for s in self.sinks:                      # every summary out before any close: a close may linger
            s.close()                             # (an LSL outlet's, up to 1 s, for its consumers)
        if self._errors:
            where, exc = self._errors[0]
            raise NodeError(f"the {where} thread failed: {type(exc).__name__}: {exc}") from exc
        return summary

    def _thread(self, where: str, target: Callable[..., object], *args: object) -> threading.Thread:
        return threading.Thread(target=self._guard, args=(where, target, *args), daemon=True,
                                name="node-" + where.replace(" ", "-"))

    def _sink_reader_left(self, exc: BrokenPipeError) -> None:
        """Handle a sink's reader leaving: the stream has no one to go to; stop, and say why at the end."""
        self._errors.append(("sink", exc))
        self.stop("the reader of the output left")

    def _guard(self, where: str, target: Callable[..., object], *args: object) -> None:
        try:
            target(*args)
        except BaseException as exc:  # surfaced by run(); never lost in a thread
            self._errors.append((where, exc))
            self.stop(f"{where} error")
            for source in self.sources:
                source.ring.close()

    # -- threads ------------------------------------------------------------------------------

    def _drive(self, source: Source) -> None:
        try:
            source.drive(self._stop, self._source_ended)
        finally:
            self._event_queue.put(None)

    def _source_ended(self, reason: str) -> None:
        """Handle a source reaching the stream length: stop when every source has."""
        if all(s.ring.closed or s.reached_length for s in self.sources):
            self.stop(reason)

    def _listen(self, listener: ContactListener, timeline: ContactTimeline, t0: float) -> None:
        """Put a contact signal's states onto its timeline, on common time, until the node stops."""
        try:
            with listener:
                while not self._stop.is_set() and not all(s.ring.closed for s in self.sources):
                    states = listener.poll(0.05)
                    if states:
                        timeline.add((t - t0, state) for t, state in states)
                    events, dropped = listener.take_events()
                    if events or dropped:
                        self._event_queue.put(("contacts", events, dropped))
        finally:
            self._event_queue.put(None)

    def _fuse(self, fusion: LateFusion) -> None:
        try:
            fusion.run(self._route)
        finally:
            self._event_queue.put(None)

    def _stream_event(self, name: str, ev: DriverEvent) -> None:
        """Pass an event a stream or the fusion said (a texture ``change``, a ``sense_lost``) to the event thread."""
        self._event_queue.put((name, [ev], {}))

    def _process(self, stream: Stream) -> None:
        try:
            stream.process(self._route)
        finally:
            self._event_queue.put(None)         # the stream says no more (its last change event is before)
            if self.fusion is not None and stream.name in self.fusion.inputs:
                self.fusion.end(stream.name)

    def _route(self, event: WindowEvent) -> None:
        """Route a window event to the fusion block (if it takes this stream) and to its stream's sinks.

        Every sink that listens to the event's stream gets it. Never blocks.
        """
        if self.fusion is not None and event.stream in self.fusion.inputs:
            self.fusion.put(event)
        for sink, route in zip(self.sinks, self.routes):
            if route is None or event.stream in route:
                sink.emit(event)

    def _deliver_events(self) -> None:
        """Driver events to the sinks, rate-limited; ends after every source thread's end."""
        lim = self._limiter
        # each source, stream, the fusion and each contact listener ends with a None
        running = len(self.sources) + len(self.streams) + (self.fusion is not None) + len(self.contacts)
        tag = len(self.sources) > 1           # name the source when there are several
        while running:
            item: EventItem | tuple[()] | None
            try:
                item = self._event_queue.get(timeout=0.1)
            except queue.Empty:
                item = ()
            if item is None:
                running -= 1
            elif item:
                name, events, dropped = item
                source = name if tag else None
                lim.add_dropped(dropped, source)
                self._show([lim.add(replace(ev, source=source) if tag else ev) for ev in events])
            self._show(lim.due())
        self._show(lim.flush())

    def _show(self, events: Iterable[DriverEvent | None]) -> None:
        for ev in events:
            if ev is not None:
                for s in self.sinks:
                    s.event(ev)

    # -- summary ------------------------------------------------------------------------------

    def health(self) -> Health:
        """Return what the graph counts, read while it runs (what its summary says at the end, in the same units).

        Per stream ``frames`` (delivered, filled, dropped, :meth:`Source.frame_fates`), ``windows``,
        ``latency_ms`` (p50, p99, max) and ``source``; per source with a host timebase its clock
        (``ppm``, ``jitter_ms``, ``delay_ms``: :meth:`Source.clock_summary`); the fusion's pairing counts
        (``windows``, ``paired``, ``alone``, ``late``, ``dropouts``, ``latency_ms``) or None; each sink's
        stats (those that count: ``written``, ``dropped_windows``, ``dropped_events``, ``errors`` for a
        queued sink). Any thread: every count is a snapshot, read without stopping the graph.
        """
        streams = {st.name: StreamHealth(st.windows, st.source.frame_fates(st.feed), st.latencies.summary(),
                                         st.source.name) for st in self.streams}
        clocks = {s.name: summary for s in self.sources if s.clock is not None
                  and (summary := s.clock_summary()) is not None}
        f = self.fusion
        fusion = None if f is None else FusionHealth(f.windows, f.paired, f.alone, dict(f.late), dict(f.dropouts),
                                                     f.latencies.summary())
        sinks = tuple(s for s in (k.stats() for k in self.sinks) if s is not None)
        return Health(streams, clocks, fusion, sinks)

    def summary(self, wall: float) -> RunSummary:
        """Return the run's summary (:class:`~supramodal.node.runtime.summaries.RunSummary`).

        Each stream's counts, the fusion's, the sources' clocks, and the graph's own: ``wall`` seconds,
        driver events per kind, what each queued sink wrote, dropped and raised, what stopped the run,
        the recorders' files, the contact signals' and the taps' counts. The caller's thread, after the run.
        """
        streams = {s.name: s.summary() for s in self.streams}
        recorded = tuple(str(p) for rec, _, _, _ in self._recorders for p in (rec.paths or ()))
        if streams:
            stream_seconds = max(s.stream_seconds for s in streams.values())
        else:                                               # a relay: its sources' frames are under taps
            stream_seconds = max(s.ring.stats()["written"] / s.rate for s in self.sources)
        return RunSummary(
            streams=streams, fusion=self.fusion.summary() if self.fusion is not None else None,
            clocks={s.name: summary for s in self.sources if (summary := s.clock_summary()) is not None},
            windows=sum(s.windows for s in streams.values()), stream_seconds=stream_seconds, wall_seconds=wall,
            recorded=recorded or None, stopped_by=self._stopped_by, events=self._limiter.summary(),
            sinks=tuple(stats for stats in (s.stats() for s in self.sinks) if stats is not None),
            contacts=(tuple({**timeline.summary(), **listener.stats()} for listener, timeline in self.contacts)
                      if self.contacts else None),
            taps=({tap.name: {**tap.summary(), "frames": source.frame_fates(feed)}
                   for tap, source, feed, _ in self._taps} if self._taps else None))


class Node(Graph):
    """One stream: a driver, the model blocks and the sinks (the one-source graph).

    Parameters
    ----------
    driver : drivers.base.Driver
    pipeline : supramodal.pipeline.FeaturePipeline
        Its bank's rate must equal the driver's rate.
    sinks : list of node.runtime.sinks.Sink
    model : TextureModel, optional
        Without it the node emits feature windows.
    decision : supramodal.decisions.DecisionRules, optional
        How it decides (default: each window alone).
    mapping : str or int
        Driver channels to filter inputs, see :func:`channel_mapper`.
    labels : Labels, optional
        Truth labels; by default those the driver carries (a replayed session's).
    buffer_seconds : float
        Ring capacity.
    recorder : node.runtime.taps.recorder.SessionRecorder, optional
        Records the raw driver frames (a second ring reader, on its own thread).
    overrun : {"drop-oldest", "drop-newest", "block"}
        "block" makes the driver thread wait for space: right for replay, where
        no sample need be lost; live drivers drop and count instead.
    timebase : {"stream", "host", "recorded"}
        How window events are put on common time (see :mod:`supramodal.node.runtime.sources`), with
        ``time_offset`` and ``time_rate`` as :class:`~supramodal.node.runtime.sources.Source` takes them.
    taps : sequence of tap, optional
        Readers of the driver's raw frames (see :class:`Graph`).
    """

    def __init__(self, driver: Driver, pipeline: FeaturePipeline, sinks: Iterable[Sink],
                 model: TextureModel | None = None, decision: DecisionRules = DEFAULT_DECISION,
                 mapping: str | int = "auto", labels: Labels | None = None, buffer_seconds: float = 2.0,
                 overrun: str = "drop-oldest", recorder: SessionRecorder | None = None,
                 timebase: str = "stream", time_offset: float = 0.0, time_rate: float | None = None,
                 taps: Iterable[Tap] = ()) -> None:
        source = Source(MAIN_STREAM, driver, buffer_seconds, overrun, timebase, time_offset, time_rate)
        stream = Stream(MAIN_STREAM, source, pipeline, model, decision, mapping, labels)
        super().__init__([source], [stream], sinks, recorder=recorder, taps=[(MAIN_STREAM, tap) for tap in taps])

    @property
    def driver(self) -> Driver:
        """The driver of the node's one source."""
        return self.sources[0].driver

    @property
    def labels(self) -> Labels:
        """The truth labels of the node's one stream."""
        return self.streams[0].labels

    @property
    def pipeline(self) -> FeaturePipeline:
        """The feature pipeline of the node's one stream."""
        return self.streams[0].pipeline
