"""Where the node's window events go: text lines or JSON Lines, to stdout or a file.

:class:`Sink` is the interface the graph calls (every call but ``emit`` a documented no-op by
default): ``start``, ``emit``, ``event``, ``drain``, ``stats``, ``summary``, ``close``, and the
:attr:`Sink.on_reader_left` hook. A new sink derives from it and overrides what it needs; the
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
import json
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO, cast

import numpy as np

from supramodal.checks import Key, text
from supramodal.drivers.base import DriverEvent
from supramodal.drivers.spec import OptionError
from supramodal.errors import InputError
from supramodal.node.runtime.events import MAIN_STREAM, WindowEvent
from supramodal.node.runtime.outputs import check_new_file
from supramodal.node.scene.registry import SinkContext, SinkSpec


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
    """

    path: str | None = None
    on_reader_left: Callable[[BrokenPipeError], None] | None = None

    def prepare(self) -> None:
        """Before the graph's start, still start-up (SIGINT and SIGTERM interrupt it): e.g. wait
        for a consumer of an outlet. The caller's (main) thread. Default: nothing."""

    def start(self, epoch: float) -> None:
        """The graph's start on ``time.monotonic()`` (common time 0), before any event: for a
        sink that puts common time on another clock (LSL). The caller's thread. Default: nothing."""

    @abc.abstractmethod
    def emit(self, event: WindowEvent) -> None:
        """One window's event (of the streams the sink listens to). The processing or fusion thread."""

    def event(self, ev: DriverEvent) -> None:
        """A driver event (rate-limited by the node: ``ev.count`` > 1 stands for repeats). The
        event thread. Default: ignored."""

    def drain(self, timeout: float = 5.0) -> None:
        """After the last ``emit`` and ``event``: take what is still held, for at most
        ``timeout`` seconds (a queued sink's queue). The caller's thread. Default: nothing."""

    def stats(self) -> dict[str, Any] | None:
        """What the sink wrote, dropped and raised, for the summary's ``sinks``; None (the
        default) for a sink that counts nothing (one called on the graph's own threads), which
        the summary leaves out. The caller's thread, after :meth:`drain`."""
        return None

    def summary(self, summary: dict[str, Any]) -> None:
        """The run's summary, once, after :meth:`drain`. The caller's thread. Default: nothing."""

    def close(self) -> None:
        """Release what the sink holds, last. The caller's thread. Default: nothing."""


class NoReader(OSError):
    """A FIFO sink's file has no reader yet: opening it would block. The item is kept and the
    open tried again (:class:`QueuedSink`); nothing waits on it."""


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


class JsonLinesSink(FileSink):
    """One JSON object per window; a driver event as ``{"event": kind, "message": ..., "time": ...,
    "stream_index": ..., "count": ...}`` in the same stream; the summary as a last object with
    ``"summary": true``."""

    def emit(self, event: WindowEvent) -> None:
        line = json.dumps(event.as_dict()) + "\n"
        with self._lock:
            self._fh.write(line)

    def event(self, ev: DriverEvent) -> None:
        line = json.dumps(ev.as_dict()) + "\n"
        with self._lock:
            self._fh.write(line)

    def summary(self, summary: dict[str, Any]) -> None:
        self._fh.write(json.dumps({"summary": True, **summary}) + "\n")


class TextSink(FileSink):
    """One human-readable line per window, under a line that names the columns, and a summary block;
    driver events on stderr, ``supramodal: MESSAGE`` and, for repeats folded in, ``(N more since)``.

    Every line's time is on one basis, said in the header: the window's end (``WindowEvent.end``),
    seconds on the node's common time, for every stream's window and the fused ones alike (a
    stream's own time, ``WindowEvent.t``, would put a microphone window that ends 0.147 s into the
    graph at 0.100 s beside a fused window at 0.147 s). In a one-source scene of a file, common
    time is the stream's time.
    """

    _headed = False

    def event(self, ev: DriverEvent) -> None:
        more = f" ({ev.count - 1} more since)" if ev.count > 1 else ""
        sys.stderr.write(f"supramodal: {ev.message}{more}\n")
        sys.stderr.flush()

    #: What the first column is, said in the header.
    TIME_BASIS = "time: each window's end, s on the node's common time"

    def _header(self, event: WindowEvent) -> str:
        if event.decision is None:
            return f"{'time':>11}  feature sums over the channels, per feature  ({self.TIME_BASIS})"
        line = f"{'time':>11}  {'decision':<12} confidence  ({self.TIME_BASIS})"
        if event.pooled is not None:
            line += "  | the decision pooled over the last windows"
        if event.truth is not None:
            line += "  truth: the texture really there; ok = right, -- = wrong"
        return line

    def emit(self, event: WindowEvent) -> None:
        if not self._headed:
            self._fh.write(self._header(event) + "\n")
            self._headed = True
        head = f"{event.end:9.3f} s"                    # common time, for every stream (TIME_BASIS)
        if event.stream != MAIN_STREAM:                 # a graph of several streams: say whose window
            head += f"  {event.stream:<8}"
        if event.decision is not None:
            line = f"{head}  {event.decision:<12} conf {event.confidence:.2f}"
            if event.unknown is not None:
                line += f" ({event.unknown}" + (f"; guess {event.guess})" if event.guess else ")")
            acc = event.pooled
            if acc:
                shown = acc["label"] if acc["label"] is not None else "(no contact)"
                line += f"  | over {acc['windows']:>3} win: {shown:<12} conf {acc['confidence']:.2f}"
                if acc.get("decided"):
                    line += f" decided after {acc['decided_after']}"
            if event.truth is not None:
                mark = "ok" if event.truth == event.decision else "--"
                line += f"  truth {event.truth:<12} {mark}"
        else:
            features = cast(dict[str, Any], event.features)   # an event without a decision carries features
            parts = [f"{name} sum {float(np.sum(vals)):.4g}" for name, vals in features.items()]
            line = f"{head}  " + "  ".join(parts)
        for flag in ("gap", "alone"):
            if flag in event.flags:
                line += f"  [{flag}]"
        self._fh.write(line + "\n")

    def summary(self, s: dict[str, Any]) -> None:
        lines = ["", "summary"]
        if "streams" in s and not s["streams"]:  # a relay: its sources' samples sent on, nothing decided
            lines.append(f"  stream             {s['stream_seconds']:.2f} s sent on, no windows (a relay)")
        elif "streams" in s:                    # several streams: each one's counts, then the graph's
            lines.append(f"  windows            {s['windows']} on {len(s['streams'])} streams")
            for name, one in s["streams"].items():
                lines += [f"  stream {name}"] + ["  " + line for line in _stream_lines(one)]
            for name, c in (s.get("clocks") or {}).items():
                lines.append(f"  clock {name:<11} rate error {c['ppm']:+.1f} ppm, jitter {c['jitter_ms']:.2f} ms")
            f = s.get("fusion")
            if f:
                lines.append(f"  fused              {f['windows']} windows: {f['paired']} paired, {f['alone']} alone"
                             f" (one sense), {sum(f['late'].values())} late windows left out"
                             + "".join(f"; {name} dropped out {n} time{'s' * (n != 1)}"
                                       for name, n in f.get("dropouts", {}).items() if n)
                             + (f"; window accuracy {f['window_accuracy']:.3f}" if f.get("window_accuracy") is not None
                                else ""))
        else:
            lines += _stream_lines(s)
        for name, t in (s.get("taps") or {}).items():
            f = t["frames"]
            lines.append(f"  sent               {name}: {t['samples_sent']} samples in {t['chunks']} chunks; not sent: "
                         f"{f['filled']} filled and {f['dropped']} dropped frames")
        counts = (s.get("events") or {}).get("counts")
        if counts:
            dropped = sum(s["events"].get("dropped", {}).values())
            lines.append("  driver events      " + ", ".join(f"{k} {n}" for k, n in counts.items())
                         + (f" ({dropped} not shown: dropped before the node took them)" if dropped else ""))
        for q in s.get("sinks") or ():
            if q["dropped_windows"] or q["dropped_events"] or q["errors"]:
                lines.append(f"  sink               {q['sink']}: dropped {q['dropped_windows']} windows and "
                             f"{q['dropped_events']} events it could not take"
                             + (f", {q['errors']} errors (first: {q['first_error']})" if q["errors"] else ""))
        if s.get("stopped_by"):
            lines.append(f"  stopped by         {s['stopped_by']}")
        self._fh.write("\n".join(lines) + "\n")


def _stream_lines(s: dict[str, Any]) -> list[str]:
    """The summary lines of one stream's counts."""
    lines = [f"  windows            {s['windows']}",
             f"  stream             {s['stream_seconds']:.2f} s"
             + (f" in {s['wall_seconds']:.2f} s wall time" if "wall_seconds" in s else "")]
    if s.get("window_accuracy") is not None:
        lines.append(f"  window accuracy    {s['window_accuracy']:.3f} over {s['labelled_windows']} labelled windows")
    if s.get("accumulated_accuracy") is not None:
        lines.append(f"  accumulated acc.   {s['accumulated_accuracy']:.3f}")
    unknown = s.get("unknown_windows")
    if unknown and any(unknown.values()):
        lines.append("  unknown windows    " + ", ".join(f"{n} {why}" for why, n in unknown.items() if n))
    if "contacts_decided" in s:
        median = s["windows_to_decide_median"]
        lines.append(f"  contacts decided   {s['contacts_decided']}"
                     + (f", median {median:g} windows to decide" if median is not None else ""))
    lines.append(frames_line(s["frames"]))
    lines.append(f"  samples replaced   nonfinite replaced {s['nonfinite_replaced']}, out of range replaced "
                 f"{s.get('out_of_range_replaced', 0)}")
    lat = s.get("latency_ms")
    if lat:
        lines.append(f"  decision latency   p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms, max {lat['max']:.2f} ms "
                     "after window close")
    lines.append(f"  real-time factor   {s['real_time_factor']:.4f} (processing CPU s per s of stream)")
    return lines


def frames_line(f: dict[str, Any]) -> str:
    """The summary line of frame fates: ``stream = delivered + filled + dropped``, with where the
    dropped ones went (docs/node.md, "Every frame has one fate")."""
    total = f["delivered"] + f["filled"] + f["dropped"]
    line = (f"  frames             {f['stream']} = delivered {f['delivered']} + filled {f['filled']} + "
            f"dropped {f['dropped']} (in ring {f['dropped_in_ring']}, by driver {f['dropped_by_driver']})")
    if total != f["stream"]:
        # Only when the processing thread stopped before draining the ring (it failed): say so
        # rather than print an identity that does not hold.
        line = line.replace(" = ", " != ", 1) + f"; {f['stream'] - total} not processed"
    return line


class ListSink(Sink):
    """Keeps window events (``windows``: :class:`WindowEvent`; ``events``: the same as the dicts a
    JSON Lines sink writes), driver events (``driver_events``) and the summary in memory: for a
    node embedded in a Python program, and tests."""

    def __init__(self) -> None:
        self.path = None
        self.windows: list[WindowEvent] = []
        self.driver_events: list[DriverEvent] = []
        self.final: dict[str, Any] | None = None

    @property
    def events(self) -> list[dict[str, Any]]:
        return [w.as_dict() for w in self.windows]

    def emit(self, event: WindowEvent) -> None:
        self.windows.append(event)

    def event(self, ev: DriverEvent) -> None:
        self.driver_events.append(ev)

    def summary(self, summary: dict[str, Any]) -> None:
        self.final = summary

    def close(self) -> None:
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
        self._queue: queue.Queue[tuple[str, Any] | None] = queue.Queue(maxsize=capacity)
        self._dropped = {"windows": 0, "events": 0}
        self._errors = 0
        self._first_error: str | None = None
        self._written = 0
        self._lock = threading.Lock()
        #: The BrokenPipeError that ended the sink (its reader left), else None.
        self.reader_left: BrokenPipeError | None = None
        #: Called (on the sink's thread) with that error; the node sets it to stop.
        self.on_reader_left: Callable[[BrokenPipeError], None] | None = None
        self._pending: tuple[str, Any] | None = None   # an item held back while a FIFO has no reader
        self._closing = threading.Event()  # drain's time is up: stop waiting for a reader
        self._thread = threading.Thread(target=self._run, name=f"sink-{type(sink).__name__}", daemon=True)
        self._thread.start()

    def emit(self, event: WindowEvent) -> None:
        self._put("emit", event, "windows")

    def event(self, ev: DriverEvent) -> None:
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
            method, payload = item
            try:
                if method == "emit":
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
        """Let the sink take what is queued, for at most ``timeout`` seconds; what it has not taken
        by then is dropped and counted. Call once, after the last ``emit`` and ``event``; the
        wrapped sink's own ``drain`` follows, in what is left of ``timeout``."""
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

    def stats(self) -> dict[str, Any]:
        """``{"sink", "written", "dropped_windows", "dropped_events", "errors", "first_error"}``,
        and what the sink's own ``stats`` adds."""
        own = self.sink.stats() or {}
        with self._lock:
            return {"sink": type(self.sink).__name__ + (f" {self.path}" if self.path not in (None, "-") else ""),
                    "written": self._written, "dropped_windows": self._dropped["windows"],
                    "dropped_events": self._dropped["events"], "errors": self._errors,
                    "first_error": self._first_error, **{k: v for k, v in own.items() if k != "sink"}}

    def prepare(self) -> None:
        """Passed on to the sink (on the caller's thread)."""
        self.sink.prepare()

    def start(self, epoch: float) -> None:
        """Passed on to the sink (before any event, on the caller's thread)."""
        self.sink.start(epoch)

    def summary(self, summary: dict[str, Any]) -> None:
        try:
            self.sink.summary(summary)
        except NoReader as exc:            # the summary cannot wait for a reader either
            with self._lock:
                self._errors += 1
                if self._first_error is None:
                    self._first_error = f"the summary was not written: {exc.strerror}"

    def close(self) -> None:
        self._closing.set()
        if self._thread.is_alive():
            try:
                self._queue.put_nowait(None)     # end the worker (it ends at once if drained)
            except queue.Full:
                pass                             # a sink stuck for good: its daemon thread is left
        self.sink.close()


# -- as a scene names them ---------------------------------------------------------------------------

def _file_sink(kind: type[FileSink]) -> Callable[[dict[str, Any], SinkContext], Sink]:
    def build(options: dict[str, Any], context: SinkContext) -> Sink:
        path = options["path"] if options["path"] == "-" else str(context.resolve(options["path"]))
        try:
            sink = kind(path, context.overwrite)
        except InputError as exc:
            raise OptionError(f"path: {exc}") from None
        # Behind its own queue: processing never waits on a slow disk or a stalled terminal.
        return QueuedSink(sink)
    return build


_PATH = Key(text, '"-" (stdout) or a file path', "-")
TEXT = SinkSpec(type="text", keys={"path": _PATH}, build=_file_sink(TextSink),
                summary="one line per window, for people (stdout or a file)")
JSONL = SinkSpec(type="jsonl", keys={"path": _PATH}, build=_file_sink(JsonLinesSink),
                 summary="one JSON object per window, driver event and summary (stdout or a file)")
