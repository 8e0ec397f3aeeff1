"""Sinks: where the node's window events go.

This package holds the base and the machinery every sink shares; each sink a scene can name is one module beside it,
with its spec (``SPEC``, a :class:`~supramodal.node.runtime.sinks.spec.SinkSpec`: :mod:`.spec`), registered in
:data:`supramodal.node.scene.registry.SINK_MODULES`: :mod:`.text` (text lines), :mod:`.jsonl` (JSON Lines),
:mod:`.lsl` (Lab Streaming Layer outlets), :mod:`.view` (a page in the browser). The taps (a source's raw frames)
are in :mod:`supramodal.node.runtime.taps`.

:class:`Sink` is the interface the graph calls (every call but ``emit`` a documented no-op by
default): ``start``, ``emit``, ``event``, ``drain``, ``stats``, ``summary``, ``close``, and the
:attr:`Sink.on_reader_left` and :meth:`Sink.watch` hooks. A new sink derives from it and overrides what it needs; the
graph calls the rest as they are (it never probes a sink for a method).

A file sink (:class:`FileSink`: text, JSON Lines) checks its path when it is made (an existing
file is refused unless ``overwrite``) but creates the file only when it first writes: a node
that fails to start (a port that does not open) leaves no empty file behind.

Threading rules
---------------
``start`` is called from the caller's thread before any event; ``emit`` from the node's
processing thread (or the fusion thread), ``event`` (driver events) from its event thread;
``drain``, ``stats``, ``summary`` and ``close`` from the caller's thread once those have ended.
One writing ``emit`` and ``event`` to the same stream serialises them with its lock, held for
one write. A scene's sinks (and ``run --json``'s) run behind a :class:`QueuedSink`: on their
own thread, behind a bounded queue, so that processing never waits on a sink; what a sink
cannot take is dropped and counted in the summary (``sinks``).
"""

from __future__ import annotations

import abc
import errno
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

from supramodal.checks import Key
from supramodal.checks import text as is_text  # not `text`: that is the text sink's module here
from supramodal.drivers.base import DriverEvent
from supramodal.drivers.spec import OptionError
from supramodal.errors import InputError
from supramodal.node.runtime.events import WindowEvent
from supramodal.node.runtime.fields import str_of
from supramodal.node.runtime.outputs import check_new_file
from supramodal.node.runtime.sinks.spec import Options, SinkContext
from supramodal.node.runtime.summaries import Health, RunSummary
from supramodal.records import JsonValue


class Sink(abc.ABC):
    """The base of every sink: the calls the graph makes, in order, all no-ops but :meth:`emit`.

    :meth:`start` once, then :meth:`emit` per window and :meth:`event` per driver event (in any
    interleaving, from two threads), then :meth:`drain`, :meth:`stats`, :meth:`summary` and
    :meth:`close` once each.

    Attributes
    ----------
    path : str or None
        Where the sink writes (``"-"``: standard output), for the summary; None by default.
    on_reader_left : callable or None
        Set by the graph before the run: a sink that runs on its own thread (:class:`QueuedSink`)
        calls it, with the ``BrokenPipeError``, when the reader of its output has left (``|
        head``), and the graph stops. A sink called on the graph's threads need not: its error
        stops the graph anyway. Default None.
    health : callable or None
        ``health() -> Health``: what the graph counts, read while it runs (``Graph.health``), given by
        :meth:`watch` when the graph is made; None before (and for a sink outside a graph). A
        sink that reports the node's health (the view's page, ROS 2 diagnostics) calls it from
        its own thread.
    """

    path: str | None = None
    on_reader_left: Callable[[BrokenPipeError], None] | None = None
    health: Callable[[], Health] | None = None

    def watch(self, health: Callable[[], Health]) -> None:
        """Take the graph's counters (:attr:`health`); the graph calls it once, when it is made.

        Default: keep it.
        """
        self.health = health

    def prepare(self) -> None:
        """Prepare before the graph's start, still start-up (SIGINT and SIGTERM interrupt it).

        E.g. wait for a consumer of an outlet. The caller's (main) thread. Default: nothing.
        """

    def start(self, epoch: float) -> None:
        """Take the graph's start on ``time.monotonic()`` (common time 0), before any event.

        For a sink that puts common time on another clock (LSL). The caller's thread. Default: nothing.
        """

    @abc.abstractmethod
    def emit(self, event: WindowEvent) -> None:
        """Take one window's event (of the streams the sink listens to). The processing or fusion thread."""

    def event(self, ev: DriverEvent) -> None:
        """Take a driver event (rate-limited by the node: ``ev.count`` > 1 stands for repeats).

        The event thread. Default: ignored.
        """

    def drain(self, timeout: float = 5.0) -> None:
        """Take what is still held, for at most ``timeout`` seconds, after the last ``emit`` and ``event``.

        E.g. a queued sink's queue. The caller's thread. Default: nothing.
        """

    def stats(self) -> dict[str, JsonValue] | None:
        """Return what the sink wrote, dropped and raised, for the summary's ``sinks``.

        None (the default) for a sink that counts nothing (one called on the graph's own threads), which
        the summary leaves out. The caller's thread, after :meth:`drain`.
        """
        return None

    def summary(self, summary: RunSummary) -> None:
        """Take the run's summary, once, after :meth:`drain`. The caller's thread. Default: nothing."""

    def close(self) -> None:
        """Release what the sink holds, last. The caller's thread. Default: nothing."""


class NoReader(OSError):
    """A FIFO sink's file has no reader yet: opening it would block.

    The item is kept and the open tried again (:class:`QueuedSink`); nothing waits on it.
    """


class FileSink(Sink):
    """A sink that writes lines to standard output or a file (the base of text and JSON Lines).

    Parameters
    ----------
    path : str
        ``"-"`` for standard output, else a file, created at the first write. A named pipe
        (FIFO) is opened without waiting for its reader: until one comes, a write raises
        :class:`NoReader` (a queued sink keeps the items and tries again).
    overwrite : bool
        Whether an existing file may be replaced (default False: refused with an InputError
        that says how to allow it).
    """

    path: str

    def __init__(self, path: str = "-", overwrite: bool = False) -> None:
        self.path = path
        self._file: TextIO | None = sys.stdout if path == "-" else None
        if path != "-":
            check_new_file(Path(path), overwrite, "a sink file")
        self._lock = threading.Lock()

    @property
    def _fh(self) -> TextIO:
        if self._file is None:
            path = Path(self.path)
            if path.is_fifo():
                # open() of a FIFO waits for a reader, in a system call no signal ends: open it
                # without waiting, then write as to any file.
                try:
                    fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
                except OSError as exc:
                    if exc.errno == errno.ENXIO:
                        raise NoReader(errno.ENXIO, f"no reader of the named pipe {path} yet") from None
                    raise
                os.set_blocking(fd, True)
                self._file = open(fd, "w", buffering=1)
            else:
                self._file = open(self.path, "w", buffering=1)
        return self._file

    def close(self) -> None:
        """Flush standard output, or close the file (if it was ever opened)."""
        if self._file is sys.stdout:
            self._file.flush()
        elif self._file is not None:
            self._file.close()


class ListSink(Sink):
    """Keeps window events, driver events and the summary in memory, for a node in a Python program and tests.

    Window events are in ``windows`` (:class:`WindowEvent`) and, as the dicts a JSON Lines sink writes,
    ``events``; driver events in ``driver_events``; the summary in ``final``.
    """

    def __init__(self) -> None:
        self.path = None
        self.windows: list[WindowEvent] = []
        self.driver_events: list[DriverEvent] = []
        self.final: RunSummary | None = None

    @property
    def events(self) -> list[dict[str, JsonValue]]:
        """The window events kept, as the dicts a JSON Lines sink writes (:meth:`WindowEvent.as_dict`)."""
        return [w.as_dict() for w in self.windows]

    def emit(self, event: WindowEvent) -> None:
        """Keep a window's event in ``windows``."""
        self.windows.append(event)

    def event(self, ev: DriverEvent) -> None:
        """Keep a driver event in ``driver_events``."""
        self.driver_events.append(ev)

    def summary(self, summary: RunSummary) -> None:
        """Keep the run's summary in ``final``."""
        self.final = summary

    def close(self) -> None:
        """Do nothing: what the sink kept stays readable."""
        pass


#: Items a sink's queue holds (:class:`QueuedSink`): 6.8 minutes of 100 ms windows.
DEFAULT_SINK_QUEUE_ITEMS = 4096
#: Seconds between two tries to open a named pipe that has no reader yet.
NO_READER_RETRY = 0.05


class QueuedSink(Sink):
    """Runs a sink on its own thread, behind a bounded queue, so that processing never waits on it.

    ``emit`` and ``event`` only put the item in the queue; when the queue is full (the sink is
    slower than the stream: a slow disk, a stalled terminal, a network peer), the item is dropped
    and counted. An exception from the sink is counted and the first one kept; the sink gets the
    next items all the same. A ``BrokenPipeError`` (the reader of stdout left) ends the sink and
    calls :attr:`on_reader_left`, which the node sets to stop the stream. :meth:`drain` waits
    (bounded) for the queue to empty at the end; ``summary`` and ``close`` then run on the
    caller's thread, as for any sink; ``start`` is passed on, on the caller's thread, before
    any event.

    Parameters
    ----------
    sink : Sink
        The sink to run.
    capacity : int
        Items (window events and driver events) the queue holds (default
        :data:`DEFAULT_SINK_QUEUE_ITEMS`).

    Threading rules: ``emit`` and ``event`` may be called from any thread and never block;
    :meth:`stats` is a snapshot, safe at any time.
    """

    def __init__(self, sink: Sink, capacity: int = DEFAULT_SINK_QUEUE_ITEMS) -> None:
        if not isinstance(sink, Sink):
            raise InputError("a queued sink runs a Sink (supramodal.node.runtime.sinks.Sink), "
                             f"got {type(sink).__name__}")
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise InputError(f"a sink queue holds at least 1 item, got capacity {capacity!r}")
        self.sink = sink
        self.path = sink.path
        # (method, item), or None: the end
        self._queue: queue.Queue[tuple[str, WindowEvent | DriverEvent] | None] = queue.Queue(maxsize=capacity)
        self._dropped = {"windows": 0, "events": 0}
        self._errors = 0
        self._first_error: str | None = None
        self._written = 0
        self._lock = threading.Lock()
        #: The BrokenPipeError that ended the sink (its reader left), else None.
        self.reader_left: BrokenPipeError | None = None
        #: Called (on the sink's thread) with that error; the node sets it to stop.
        self.on_reader_left: Callable[[BrokenPipeError], None] | None = None
        self._pending: tuple[str, WindowEvent | DriverEvent] | None = None   # held back while a FIFO has no reader
        self._closing = threading.Event()  # drain's time is up: stop waiting for a reader
        self._thread = threading.Thread(target=self._run, name=f"sink-{type(sink).__name__}", daemon=True)
        self._thread.start()

    def emit(self, event: WindowEvent) -> None:
        """Queue a window's event for the sink (never blocks: dropped and counted when the queue is full)."""
        self._put("emit", event, "windows")

    def event(self, ev: DriverEvent) -> None:
        """Queue a driver event for the sink (never blocks: dropped and counted when the queue is full)."""
        self._put("event", ev, "events")

    def _put(self, method: str, item: WindowEvent | DriverEvent, kind: str) -> None:
        try:
            self._queue.put_nowait((method, item))
        except queue.Full:
            with self._lock:
                self._dropped[kind] += 1

    def _run(self) -> None:
        while True:
            item = self._pending if self._pending is not None else self._queue.get()
            self._pending = None
            if item is None:
                return
            method, payload = item            # ("emit", a window) or ("event", a driver event)
            try:
                if isinstance(payload, WindowEvent):
                    self.sink.emit(payload)
                else:
                    self.sink.event(payload)
                with self._lock:
                    self._written += 1
            except NoReader:               # a FIFO with no reader yet: keep the item, try again
                if self._closing.is_set():
                    with self._lock:
                        self._dropped["windows" if method == "emit" else "events"] += 1
                    return
                self._pending = item
                self._closing.wait(NO_READER_RETRY)
            except BrokenPipeError as exc:  # the reader of stdout left (`| head`): nothing more to write
                self.reader_left = exc
                if self.on_reader_left is not None:
                    self.on_reader_left(exc)
                return
            except Exception as exc:       # the sink's failure is counted, never the stream's
                with self._lock:
                    self._errors += 1
                    if self._first_error is None:
                        self._first_error = f"{type(exc).__name__}: {exc}"

    def drain(self, timeout: float = 5.0) -> None:
        """Let the sink take what is queued, for at most ``timeout`` seconds.

        What it has not taken by then is dropped and counted. Call once, after the last ``emit`` and
        ``event``; the wrapped sink's own ``drain`` follows, in what is left of ``timeout``.
        """
        deadline = time.monotonic() + timeout
        while self._thread.is_alive():
            try:
                self._queue.put(None, timeout=max(0.0, deadline - time.monotonic()))
                break
            except queue.Full:
                break
        self._thread.join(max(0.0, deadline - time.monotonic()))
        self._closing.set()                # a sink still waiting for a reader gives up
        self._thread.join(2 * NO_READER_RETRY)
        while True:                        # what the sink did not take in time
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item is not None:
                with self._lock:
                    self._dropped["windows" if item[0] == "emit" else "events"] += 1
        if not self._thread.is_alive():    # never while the worker may still call the sink
            self.sink.drain(max(0.0, deadline - time.monotonic()))

    def stats(self) -> dict[str, JsonValue]:
        """Return ``{"sink", "written", "dropped_windows", "dropped_events", "errors", "first_error"}``.

        And what the sink's own ``stats`` adds.
        """
        own = self.sink.stats() or {}
        with self._lock:
            return {"sink": type(self.sink).__name__ + (f" {self.path}" if self.path not in (None, "-") else ""),
                    "written": self._written, "dropped_windows": self._dropped["windows"],
                    "dropped_events": self._dropped["events"], "errors": self._errors,
                    "first_error": self._first_error, **{k: v for k, v in own.items() if k != "sink"}}

    def prepare(self) -> None:
        """Pass the call on to the sink (on the caller's thread)."""
        self.sink.prepare()

    def watch(self, health: Callable[[], Health]) -> None:
        """Pass the graph's counters on to the sink (and keep them)."""
        self.health = health
        self.sink.watch(health)

    def start(self, epoch: float) -> None:
        """Pass the graph's start on to the sink (before any event, on the caller's thread)."""
        self.sink.start(epoch)

    def summary(self, summary: RunSummary) -> None:
        """Pass the run's summary on to the sink, on the caller's thread.

        A named pipe with no reader (:class:`NoReader`) is not waited for: the summary is not written,
        and that is counted as an error.
        """
        try:
            self.sink.summary(summary)
        except NoReader as exc:            # the summary cannot wait for a reader either
            with self._lock:
                self._errors += 1
                if self._first_error is None:
                    self._first_error = f"the summary was not written: {exc.strerror}"

    def close(self) -> None:
        """End the sink's thread (unless the sink is stuck for good: its daemon thread is left), then close the sink."""
        self._closing.set()
        if self._thread.is_alive():
            try:
                self._queue.put_nowait(None)     # end the worker (it ends at once if drained)
            except queue.Full:
                pass                             # a sink stuck for good: its daemon thread is left
        self.sink.close()


# -- the file sinks as a scene names them (text, jsonl) -----------------------------------------------

#: The ``path`` key of a file sink (:mod:`.text`, :mod:`.jsonl`).
PATH_KEY = Key(is_text, '"-" (stdout) or a file path', "-", path=True, words=("-",))


def file_sink(kind: type[FileSink]) -> Callable[[Options, SinkContext], Sink]:
    """Return the ``build`` of a file sink's spec: ``kind`` at the scene's ``path``, behind its own queue.

    The ``path`` is relative to the scene; the queue a :class:`QueuedSink`.
    """
    def build(options: Options, context: SinkContext) -> Sink:
        path = str_of(options, "path")
        path = path if path == "-" else str(context.resolve(path))
        try:
            sink = kind(path, context.overwrite)
        except InputError as exc:
            raise OptionError(f"path: {exc}") from None
        # Behind its own queue: processing never waits on a slow disk or a stalled terminal.
        return QueuedSink(sink)
    return build
