"""The ``ros2`` sink: window events, driver events and the node's health on ROS 2 topics, from its own process.

What goes on which topic, in which message and with which QoS is
:class:`~supramodal.node.runtime.sinks.ros2_publisher.Ros2Publisher`'s (its module notes); this module
runs that publisher in a child process and feeds it through a pipe. In the node's own process, rclpy's
publishing took the interpreter from the streams' processing often enough to add 1.5 to 3.6 ms to the
decisions' latency p99 (``benchmarks/ros2_sink.py``); the pipe costs the node a JSON line and a write
per window.

In a fused scene the windows of the fusion's senses are held until the fused decision of the same
moment and then sent with it, fused first (:data:`HOLD_SECONDS` at most): the publisher process and its
subscribers then take the cores once per moment, after the node has decided, and not between a
sense's window and the fused decision, which waits for that sense's partner. On a 2-core machine,
publishing each window at once added 1.0 to 2.4 ms to the fused decision's latency p99; held, every
p99 was within -1.3 to +0.3 ms of the node without the sink (docs/ros2.md). A sense's messages leave a
few milliseconds later (its partner's processing and the fusion's).

The child (``python -c`` of :func:`serve`) is started when the sink is made, and answers before the
node goes on: a ROS 2 that cannot be imported, or a name rclpy refuses, is an error of the scene, as
it was in one process. It inherits the environment (``ROS_DOMAIN_ID``, a sourced ROS 2) and is given
the command line's ``--ros-args``. It ignores SIGINT and SIGTERM (Ctrl-C, systemd and ``timeout`` signal the
whole process group: the node still has its last windows to publish) and ends when the node closes the
sink, or when the pipe closes because the node is gone; a node that cannot end it in
:data:`CLOSE_TIMEOUT` kills it.

The wire, one frame per message (:class:`multiprocessing.connection.Connection`'s ``send_bytes``):
a JSON object with ``"op"``, then, for a window, a NUL and its features and posteriors as float64 bytes.
No frame is pickled. The child answers only ``open``, ``prepare`` and ``drain``, each in order, so that
the node never reads from it while it runs.

Threading: as every sink, behind a :class:`~supramodal.node.runtime.sinks.QueuedSink`; ``emit`` and
``event`` write to the pipe on that thread (a child that does not read, once the pipe's buffer is full,
blocks that thread, and the queue drops and counts, never the streams); a thread of the sink's own
sends the graph's counters every ``diagnostics_period``; a lock keeps the two writes apart.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING

import numpy as np

from supramodal.checks import Key, integer, non_negative, number
from supramodal.drivers.base import DriverEvent
from supramodal.drivers.ros2 import Ros2Unavailable, check_namespace, check_node_name, ros_arguments
from supramodal.drivers.spec import OptionError
from supramodal.errors import InputError, SupramodalError
from supramodal.logs import get_logger
from supramodal.node.runtime.events import DECISION_EVENTS, FUSED_STREAM, WindowEvent
from supramodal.node.runtime.fields import (
    float_of,
    int_mapping_of,
    int_of,
    mapping_of,
    mappings_of,
    optional_float_of,
    optional_int_of,
    optional_str_of,
    optional_strs_of,
    str_mapping_of,
    str_of,
    strs_of,
)
from supramodal.node.runtime.sinks import QueuedSink, Sink
from supramodal.node.runtime.sinks.ros2_publisher import (
    DEFAULT_HISTORY,
    DEFAULT_NODE_NAME,
    DEFAULT_WAIT_FOR_SUBSCRIBERS,
    MAX_HISTORY,
    MAX_WAIT_FOR_SUBSCRIBERS,
    OUTPUTS,
    WAIT_STEP_SECONDS,
    Ros2Publisher,
    TopicStream,
    features_of,
    only_source,
)
from supramodal.node.runtime.sinks.spec import Options, SinkContext, SinkSpec, listened, option_from, stream_outputs
from supramodal.node.runtime.summaries import RunSummary
from supramodal.records import JsonValue

_LOG = get_logger("sinks.ros2")

if TYPE_CHECKING:   # for the annotations only: the sink needs no model code to run
    from supramodal.pipeline import FeaturePipeline

__all__ = ["SPEC", "PublisherProcessError", "Ros2Sink", "serve"]

#: Seconds between two diagnostics (ROS's convention: 1 Hz).
DEFAULT_DIAGNOSTICS_PERIOD = 1.0
DIAGNOSTICS_PERIOD_RANGE = (0.1, 60.0)
#: Seconds the publisher process has to import rclpy and make its node (0.7 s on an idle 2-core machine).
OPEN_TIMEOUT = 60.0
#: Seconds more than its own wait that an answer of the publisher process may take.
ANSWER_MARGIN = 10.0
#: Seconds the publisher process has to end once told to.
CLOSE_TIMEOUT = 5.0
#: Seconds at most that a sense's window waits for the fused decision before it is sent without it
#: (twice the fusion's default wait for a partner: a fused decision that is later than this has
#: given up on a sense, or the fusion has stopped).
HOLD_SECONDS = 1.0
#: How much lower the publisher process's CPU priority is than the node's: where the cores are busy, the
#: streams' processing goes first, and a window's messages leave a little later.
PUBLISHER_NICENESS = 10
#: The publisher process: :func:`serve` on the two pipe ends it is given.
CHILD_CODE = ("import sys; from supramodal.node.runtime.sinks.ros2 import serve; "
              "serve(int(sys.argv[1]), int(sys.argv[2]))")


class PublisherProcessError(SupramodalError, RuntimeError):
    """The ros2 sink's publisher process failed, ended, or did not answer in time. Also a RuntimeError."""


# -- the wire ----------------------------------------------------------------------------------------------

def _plain(value: object) -> JsonValue:
    """JSON for what the graph's counters may hold besides JSON's own types (numpy's numbers)."""
    if isinstance(value, np.generic | np.ndarray):
        plain: JsonValue = value.tolist()      # a number (of a numpy scalar), or numbers in lists (an array's)
        return plain
    raise TypeError(f"{type(value).__name__} is not JSON")


def encode(header: Mapping[str, JsonValue], payload: bytes = b"") -> bytes:
    """Return one frame: ``header`` as JSON, then a NUL and ``payload`` if there is one.

    JSON never holds a NUL: it escapes control characters.
    """
    text = json.dumps(header, separators=(",", ":"), default=_plain).encode()
    return text + b"\0" + payload if payload else text


def decode(frame: bytes) -> tuple[dict[str, JsonValue], bytes]:
    """Return a frame's header and payload (:func:`encode`'s inverse)."""
    text, _, payload = frame.partition(b"\0")
    header: dict[str, JsonValue] = json.loads(text)     # a JSON object: what encode wrote
    return header, payload


# -- the node's side -----------------------------------------------------------------------------------------

class Ros2Sink(Sink):
    """The node's window events, driver events and health on ROS 2 topics, published by a process of its own.

    See the module notes; topics and messages: :mod:`~supramodal.node.runtime.sinks.ros2_publisher`.

    Parameters
    ----------
    streams, outputs, node_name, namespace, frame_id, wait_for_subscribers, history
        As :class:`~supramodal.node.runtime.sinks.ros2_publisher.Ros2Publisher`'s, which the process runs.
    diagnostics_period : float
        Seconds between two diagnostics (:data:`DIAGNOSTICS_PERIOD_RANGE`), default 1.
    fused_inputs : sequence of str
        The fusion's senses, whose windows wait for the fused decision (the module notes); default
        none. Only when ``streams`` has the fused stream.

    Raises
    ------
    Ros2Unavailable
        No rclpy here (the publisher process says what to install).
    InputError
        A bad option, or rclpy refused the node's name or the ROS arguments.
    PublisherProcessError
        The publisher process did not start.
    """

    def __init__(self, streams: Sequence[TopicStream], outputs: Sequence[str] = OUTPUTS,
                 node_name: str = DEFAULT_NODE_NAME, namespace: str = "", frame_id: str = "",
                 diagnostics_period: float = DEFAULT_DIAGNOSTICS_PERIOD,
                 wait_for_subscribers: float = DEFAULT_WAIT_FOR_SUBSCRIBERS,
                 history: int = DEFAULT_HISTORY, fused_inputs: Sequence[str] = ()) -> None:
        period = float(diagnostics_period)
        if not DIAGNOSTICS_PERIOD_RANGE[0] <= period <= DIAGNOSTICS_PERIOD_RANGE[1]:
            raise InputError(f"diagnostics_period is {DIAGNOSTICS_PERIOD_RANGE[0]:g} to "
                             f"{DIAGNOSTICS_PERIOD_RANGE[1]:g} s, got {diagnostics_period!r}")
        self._streams = {s.name: s for s in streams}
        self._features = {s.name for s in streams if "features" in stream_outputs(outputs, bool(s.features),
                                                                                 bool(s.classes))}
        self._held_streams = frozenset(fused_inputs) & set(self._streams) if FUSED_STREAM in self._streams \
            else frozenset()
        self._held: list[tuple[float, bytes]] = []           # (when held, frame): the senses' waiting windows
        self.wait_for_subscribers = float(wait_for_subscribers)
        self.waited_s: float | None = None
        self.subscribed: list[str] | None = None
        self._published: dict[str, int] = {}
        self._failed: tuple[int, str | None] = (0, None)     # the publisher's failures: count, first
        self._lock = threading.Lock()                        # one writer of the pipe at a time
        self._asked = 0                                      # requests sent: each answer names its own
        self._one_source: str | None = None
        into_child, self._out = os.pipe()
        self._in, from_child = os.pipe()
        try:
            self._process = subprocess.Popen([sys.executable, "-c", CHILD_CODE, str(into_child), str(from_child)],
                                             pass_fds=(into_child, from_child), stdin=subprocess.DEVNULL,
                                             stdout=subprocess.DEVNULL)
        finally:
            os.close(into_child)
            os.close(from_child)
        self._to = Connection(self._out, readable=False)
        self._from = Connection(self._in, writable=False)
        self._closed = False
        try:
            ready = self._ask({"op": "open", "streams": [asdict(s) for s in streams], "outputs": list(outputs),
                               "node_name": node_name, "namespace": namespace, "frame_id": frame_id,
                               "wait_for_subscribers": self.wait_for_subscribers, "history": int(history),
                               "ros_arguments": list(ros_arguments())}, OPEN_TIMEOUT, "start")
        except BaseException:
            self._end(now=True)
            raise
        if ready["op"] == "refused":
            self._end(now=True)
            kind = Ros2Unavailable if ready["kind"] == "unavailable" else InputError
            raise kind(str_of(ready, "message"))
        self._node = str_of(ready, "node")
        self._topics = str_mapping_of(ready, "topics")
        self._stop = threading.Event()
        self._timer = threading.Thread(target=self._diagnose, args=(period,), name="sink-ros2-diagnostics", daemon=True)
        self._timer.start()

    @property
    def node_name(self) -> str:
        """The ROS node's fully qualified name (``/supramodal``; after any remapping)."""
        return self._node

    @property
    def pid(self) -> int:
        """The publisher process's id."""
        return self._process.pid

    def topic(self, stream: str, output: str) -> str:
        """Return the full name of one of the sink's topics (after any remapping)."""
        return self._topics[f"{stream}/{output}"]

    # -- the pipe ------------------------------------------------------------------------------------------

    def _send(self, header: Mapping[str, JsonValue], payload: bytes = b"", bound: float | None = None) -> None:
        """Write one frame.

        ``bound``: seconds the caller's thread may wait, for the lock or the write (a child that stopped reading,
        its pipe full: a frozen rclpy); past them the child is killed, which ends every write waiting on it (the
        sink's thread's too). None: no bound (the sink's threads, whose waits the queue absorbs).
        """
        self._write(encode(header, payload), bound)

    def _write(self, frame: bytes, bound: float | None = None) -> None:
        """Write one encoded frame (:meth:`_send`)."""
        watchdog = None if bound is None else threading.Timer(bound, self._kill)
        if watchdog is not None:
            watchdog.daemon = True
            watchdog.start()
        try:
            with self._lock:
                self._to.send_bytes(frame)
        except OSError:   # a BrokenPipeError too: not the node's stdout, which QueuedSink would stop for
            raise PublisherProcessError(f"the ROS 2 publisher process has ended ({self._exit()}); "
                                        "what it said is above, on stderr") from None
        finally:
            if watchdog is not None:
                watchdog.cancel()

    def _kill(self, why: str | None = "stopped reading") -> None:
        """Kill the publisher process if it runs, saying ``why`` on stderr (None: silently)."""
        if self._process.poll() is None:
            if why is not None:
                _LOG.warning(f"ros2 sink: the publisher process (pid {self._process.pid}) {why}; killed")
            self._process.kill()

    def _ask(self, header: dict[str, JsonValue], timeout: float, what: str) -> dict[str, JsonValue]:
        """Send a request and wait up to ``timeout`` s for its answer, in short polls.

        SIGINT and SIGTERM reach the caller's thread between two. The caller's thread.
        """
        self._asked += 1
        self._send({**header, "ask": self._asked}, bound=ANSWER_MARGIN)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._from.poll(WAIT_STEP_SECONDS):
                try:
                    answer, _ = decode(self._from.recv_bytes())
                except (EOFError, OSError):
                    break
                if answer.get("ask") == self._asked:      # an answer that came too late for its request: skipped
                    return answer
            elif self._process.poll() is not None:
                break
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._process.wait(1.0)                      # the end of its output can come before its exit status
        if self._process.poll() is None:
            raise PublisherProcessError(f"the ROS 2 publisher process (pid {self._process.pid}) did not {what} in "
                                        f"{timeout:g} s: a machine this busy, or DDS stuck (check ROS_DOMAIN_ID, "
                                        "RMW_IMPLEMENTATION and what it said on stderr)")
        raise PublisherProcessError(f"the ROS 2 publisher process ended before it could {what} ({self._exit()}); "
                                    "what it said is above, on stderr")

    def _exit(self) -> str:
        code = self._process.poll()
        return "still running" if code is None else f"exit status {code}" if code >= 0 else f"signal {-code}"

    def _diagnose(self, period: float) -> None:
        while not self._stop.wait(period):
            try:
                self._send({"op": "diagnostics", "health": self._health()})
            except PublisherProcessError:
                return                                   # said by the next window's failure, and the summary

    # -- the node's calls ----------------------------------------------------------------------------------

    def prepare(self) -> None:
        """Wait up to ``wait_for_subscribers`` seconds until every decision topic has a subscriber.

        For a stream without classes, its features topic. The caller's thread, before the graph's start;
        SIGINT and SIGTERM interrupt it.
        """
        if self.wait_for_subscribers <= 0:
            return
        try:
            done = self._ask({"op": "prepare"}, self.wait_for_subscribers + ANSWER_MARGIN, "wait for subscribers")
        except BaseException:              # Ctrl-C, SIGTERM: the node will not start, nor close its sinks
            self._end(now=True)
            raise
        self.waited_s, self.subscribed = optional_float_of(done, "waited_s"), optional_strs_of(done, "subscribed")

    def start(self, epoch: float) -> None:
        """Take the graph's start, on ``time.monotonic()`` (one clock for every process of this machine)."""
        self._send({"op": "start", "epoch": epoch}, bound=ANSWER_MARGIN)

    def emit(self, event: WindowEvent) -> None:
        """Send one window event to the publisher process, or hold it for the fused decision.

        A window of one of the fusion's senses is held until the fused decision comes (then the fused
        decision is sent, and the held windows after it), at most :data:`HOLD_SECONDS`. A window of a
        stream the sink does not publish is ignored. The sink's thread.
        """
        s = self._streams.get(event.stream)
        if s is None:
            return
        features = features_of(event, s) if s.name in self._features else None
        posteriors = None if event.posteriors is None else np.asarray(event.posteriors, dtype=np.float64).ravel()
        classes = tuple(event.classes or s.classes)
        payload = b"".join(a.tobytes() for a in (features, posteriors) if a is not None)
        frame = encode({"op": "window", "stream": s.name, "end": event.end,
                        "features": 0 if features is None else len(features),
                        "posteriors": None if posteriors is None else len(posteriors),
                        "classes": None if classes == s.classes else list(classes),
                        "decision": event.as_dict() if event.decision is not None else None}, payload)
        now = time.monotonic()
        if s.name in self._held_streams:
            self._held.append((now, frame))
            self._release(now - HOLD_SECONDS)            # a fused decision that does not come
            return
        self._write(frame)
        if s.name == FUSED_STREAM:
            self._release()

    def _release(self, held_before: float = np.inf) -> None:
        """Send the windows held before ``held_before`` (``time.monotonic()``; default: all).

        In the order they came. The sink's thread.
        """
        while self._held and self._held[0][0] < held_before:
            self._write(self._held.pop(0)[1])

    def event(self, ev: DriverEvent) -> None:
        """Send a driver event: on ``~/events`` and in the diagnostics (of the counters now), at once.

        A texture change (:data:`~supramodal.node.runtime.events.DECISION_EVENTS`) goes on ``~/events`` only.
        """
        health = self._health() if ev.kind not in DECISION_EVENTS else None
        self._send({"op": "event", "event": asdict(ev), "source": ev.source or self._only_source(), "health": health})

    def _only_source(self) -> str:
        if self._one_source is None:
            if self.health is None:
                return only_source({})
            self._one_source = only_source(self.health())
        return self._one_source

    def drain(self, timeout: float = 5.0) -> None:
        """Have the publisher publish what it was sent and wait (bounded) for the subscribers, after the last window.

        The wait is for the subscribers' acknowledgements (:meth:`Ros2Publisher.drain`); its counts come back.
        The caller's thread, once no window comes any more.
        """
        try:
            self._release()
            done = self._ask({"op": "drain", "timeout": timeout}, timeout + ANSWER_MARGIN, "drain")
        except PublisherProcessError as exc:
            self._failed = (self._failed[0] + 1, self._failed[1] or str(exc))
            return
        self._published = int_mapping_of(done, "published")
        self._failed = (int_of(done, "errors"), optional_str_of(done, "first_error"))

    def _health(self) -> dict[str, JsonValue] | None:
        """Return the graph's counters as the publisher process takes them (JSON), or None outside a graph."""
        # dict(): a Health's JSON form; a program that watches the sink with a plain mapping of it works too
        return None if self.health is None else dict(self.health())

    def stats(self) -> dict[str, JsonValue]:
        """Return the sink's counts.

        The node's name; after :meth:`drain`, what was published per output; with a wait for
        subscribers ``waited_s`` and ``subscribed``; the publisher's failures (``publisher_errors``,
        ``publisher_first_error``, each counted in the process, which goes on) when there were any,
        ``publisher_exit`` if the process ended before it was closed, and ``unsent_windows`` if windows
        held for the fused decision were never sent (the sink's thread did not end in time).
        """
        out: dict[str, JsonValue] = {"sink": "Ros2Sink", "node": self._node, "published": dict(self._published)}
        if self.waited_s is not None:
            out.update(waited_s=self.waited_s, subscribed=None if self.subscribed is None else list(self.subscribed))
        if self._failed[0]:
            out.update(publisher_errors=self._failed[0], publisher_first_error=self._failed[1])
        if not self._closed and self._process.poll() is not None:
            out["publisher_exit"] = self._exit()
        if self._held:                                    # held for a fused decision, never sent: a sink stuck
            out["unsent_windows"] = len(self._held)
        return out

    def summary(self, summary: RunSummary) -> None:
        """Publish the last diagnostics, with the run's final counts."""
        try:
            self._send({"op": "diagnostics", "health": self._health()},
                       bound=CLOSE_TIMEOUT)
        except PublisherProcessError:
            pass                                          # the summary says so (``publisher_exit``)

    def close(self) -> None:
        """Stop the diagnostics, tell the publisher process to end, and wait for it (then kill it)."""
        self._end()

    def _end(self, now: bool = False) -> None:
        if self._closed:
            return
        self._closed = True
        stop = getattr(self, "_stop", None)
        if stop is not None:
            stop.set()
            self._timer.join(CLOSE_TIMEOUT)
        if now:
            self._kill(None)
        else:
            try:
                self._send({"op": "close"}, bound=CLOSE_TIMEOUT)
            except PublisherProcessError:
                pass
        self._to.close()                                  # the child reads the end of its input: it ends too
        try:
            self._process.wait(CLOSE_TIMEOUT)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        self._from.close()


# -- the publisher process's side ---------------------------------------------------------------------------

def serve(read_fd: int, write_fd: int) -> None:
    """Run the publisher process: make a :class:`Ros2Publisher` as the first frame says, and answer whether it could.

    Then publish what each frame says until ``close`` or the end of the input.

    Parameters
    ----------
    read_fd, write_fd : int
        The pipe ends from the node and to it.
    """
    # Ctrl-C, and a SIGTERM to the whole group (systemd, timeout), are the node's to handle: it says when to
    # end, after its last windows; a node that is gone closes the pipe, and that ends this process too.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    os.nice(PUBLISHER_NICENESS)
    source, answer = Connection(read_fd, writable=False), Connection(write_fd, readable=False)
    try:
        header, _ = decode(source.recv_bytes())
    except (EOFError, OSError):
        return
    publisher = _open(header, answer)
    if publisher is None:
        return
    errors, first = 0, None
    try:
        while True:
            try:
                header, payload = decode(source.recv_bytes())
            except (EOFError, OSError):
                return                                   # the node is gone
            op = header["op"]
            if op == "close":
                return
            try:
                if op == "window":
                    _publish_window(publisher, header, payload)
                elif op == "event":
                    publisher.event(_driver_event(mapping_of(header, "event")), str_of(header, "source"),
                                    _health_of(header))
                elif op == "diagnostics":
                    publisher.publish_diagnostics(_health_of(header))
                elif op == "start":
                    publisher.start(float_of(header, "epoch"))
                elif op == "prepare":
                    publisher.prepare()
                    answer.send_bytes(encode({"ask": header["ask"], "waited_s": publisher.waited_s,
                                              "subscribed": None if publisher.subscribed is None
                                              else list(publisher.subscribed)}))
                elif op == "drain":
                    publisher.drain(float_of(header, "timeout"))
                    answer.send_bytes(encode({"ask": header["ask"], "published": dict(publisher.published),
                                              "errors": errors, "first_error": first}))
            except Exception as exc:                     # counted, said once, and the next frame published
                errors += 1
                if first is None:
                    first = f"{type(exc).__name__}: {exc}"
                    _LOG.warning(f"ros2 sink: publishing failed ({op}): {first}")
    finally:
        publisher.close()


def _open(header: Mapping[str, JsonValue], answer: Connection) -> Ros2Publisher | None:
    """Return the publisher the ``open`` frame asks for, its node's name and topics answered.

    Or None, the refusal answered.
    """
    from supramodal.drivers.ros2 import use_ros_arguments

    use_ros_arguments(strs_of(header, "ros_arguments"))
    try:
        publisher = Ros2Publisher([TopicStream(str_of(s, "name"), tuple(strs_of(s, "classes")),
                                               tuple(strs_of(s, "features")), tuple(strs_of(s, "filters")))
                                   for s in mappings_of(header, "streams")],
                                  strs_of(header, "outputs"), str_of(header, "node_name"), str_of(header, "namespace"),
                                  str_of(header, "frame_id"), float_of(header, "wait_for_subscribers"),
                                  int_of(header, "history"))
    except Ros2Unavailable as exc:
        answer.send_bytes(encode({"ask": header["ask"], "op": "refused", "kind": "unavailable", "message": str(exc)}))
        return None
    except InputError as exc:
        answer.send_bytes(encode({"ask": header["ask"], "op": "refused", "kind": "input", "message": str(exc)}))
        return None
    topics = {f"{stream}/{output}": publisher.topic(stream, output) for stream, output in publisher.outputs}
    answer.send_bytes(encode({"ask": header["ask"], "op": "ready", "node": publisher.node_name, "topics": topics}))
    return publisher


def _publish_window(publisher: Ros2Publisher, header: Mapping[str, JsonValue], payload: bytes) -> None:
    values = np.frombuffer(payload, dtype=np.float64)
    n = int_of(header, "features")
    posteriors = optional_int_of(header, "posteriors")
    classes = optional_strs_of(header, "classes")
    publisher.publish_window(str_of(header, "stream"), float_of(header, "end"), values[:n] if n else None,
                             None if posteriors is None else values[n:n + posteriors],
                             None if classes is None else tuple(classes), _json_object(header, "decision"))


def _json_object(header: Mapping[str, JsonValue], key: str) -> Mapping[str, JsonValue] | None:
    """Return ``header[key]``, a JSON object or None (a window's decision, the graph's counters)."""
    value = header[key]
    if value is None or isinstance(value, Mapping):
        return value
    raise TypeError(f"{key!r}: {value!r} is not a JSON object")


def _health_of(header: Mapping[str, JsonValue]) -> Mapping[str, JsonValue] | None:
    """Return a frame's ``health``: the graph's counters (:meth:`Health.to_dict`), or None outside a graph."""
    return _json_object(header, "health")


def _driver_event(fields: Mapping[str, object]) -> DriverEvent:
    """Return the driver event a frame carries (as :func:`dataclasses.asdict` wrote it)."""
    return DriverEvent(str_of(fields, "kind"), str_of(fields, "message"), float_of(fields, "time"),
                       optional_int_of(fields, "stream_index"), int_of(fields, "count"),
                       optional_str_of(fields, "source"))


# -- as a scene names it ---------------------------------------------------------------------------

def describe(name: str, pipeline: FeaturePipeline, classes: Sequence[str]) -> TopicStream:
    """Return a stream's topics' description from its pipeline and its model's classes (empty: features only)."""
    return TopicStream(name, tuple(classes), tuple(pipeline.features), tuple(pipeline.bank.names))


def _build(options: Options, context: SinkContext) -> Sink:
    # Made from the streams' plans, before any model is trained: subscribers match the topics
    # while the node trains, and get window 0.
    described = {name: describe(name, p.pipeline, p.classes) for name, p in context.plans.items()}
    if context.fused_classes is not None and described:
        described[FUSED_STREAM] = TopicStream(FUSED_STREAM, tuple(context.fused_classes))
    names = listened(option_from(options), described)
    try:
        sink = Ros2Sink([described[n] for n in names], strs_of(options, "outputs"),
                        str_of(options, "node_name"), str_of(options, "namespace"),
                        str_of(options, "frame_id"), float_of(options, "diagnostics_period"),
                        float_of(options, "wait_for_subscribers"), int_of(options, "history"),
                        context.fused_inputs)
    except InputError as exc:
        raise OptionError(str(exc)) from None
    return QueuedSink(sink)


SPEC = SinkSpec(
    type="ros2",
    summary="window events, driver events and diagnostics on ROS 2 topics in stock messages (the ros2 extra)",
    keys={"outputs": Key(lambda v: isinstance(v, list) and bool(v) and len(set(v)) == len(v) and set(v) <= set(OUTPUTS),
                         'a list drawn from "decision", "posteriors" and "features"', list(OUTPUTS)),
          "node_name": Key(check_node_name, "the ROS node's name: letters, digits and '_', not starting with a digit",
                           DEFAULT_NODE_NAME),
          "namespace": Key(check_namespace, 'the ROS node\'s namespace, e.g. "/robot" ("": the root, or what '
                           "--ros-args -r __ns:=... says)", ""),
          "frame_id": Key(lambda v: isinstance(v, str) and len(v) <= 256,
                          "the header.frame_id of the stamped messages (the sensor's TF frame)", ""),
          "diagnostics_period": Key(number(*DIAGNOSTICS_PERIOD_RANGE),
                                    f"seconds between two diagnostics, {DIAGNOSTICS_PERIOD_RANGE[0]:g} to "
                                    f"{DIAGNOSTICS_PERIOD_RANGE[1]:g}", DEFAULT_DIAGNOSTICS_PERIOD),
          "wait_for_subscribers": Key(non_negative(MAX_WAIT_FOR_SUBSCRIBERS),
                                      "seconds to wait, before the node starts, for a subscriber on each decision "
                                      f"topic, 0 to {MAX_WAIT_FOR_SUBSCRIBERS:g} (0: start at once)",
                                      DEFAULT_WAIT_FOR_SUBSCRIBERS),
          "history": Key(integer(1, MAX_HISTORY), "messages each decision and posteriors topic keeps for a slow or "
                         f"late subscriber, 1 to {MAX_HISTORY} (a subscriber held up longer misses some)",
                         DEFAULT_HISTORY)},
    build=_build, needs="plans")
