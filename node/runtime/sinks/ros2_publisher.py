"""Window events, driver events and the node's health on ROS 2 topics, in stock message types.

So that a robot's planner, ``ros2 topic echo``, rqt and Foxglove take them with no interface package:
:class:`Ros2Publisher`, the ROS side of the ``ros2`` sink. The node runs it in a process of its own
(:mod:`supramodal.node.runtime.sinks.ros2`), so that rclpy and DDS never hold the node's interpreter; in a process
with no stream of its own (a test, a tool) it is used as it is.

Needs the optional extra ``ros2`` or a sourced ROS 2 (:func:`supramodal.drivers.ros2.import_rclpy`
says what to install when rclpy is missing).

Topics
------
The sink is one ROS 2 node, ``node_name`` (default ``supramodal``) in ``namespace`` (default the
root), both remappable as for any node (``--ros-args -r __ns:=/robot -r __node:=texture``). Per node
stream it listens to (``[[sink]] from``; default every stream, the fused one included), its topics
are private names of that node, ``~/STREAM/OUTPUT`` (``/supramodal/main/decision``), made when
the node is built, before any model is trained, so that subscribers match while the node trains:

``~/STREAM/decision`` (``std_msgs/String``; reliable, transient local, keep last ``history``, default
    10: a subscriber that comes later gets the last ones, oldest first, the newest the current one)
    The window's JSON object, the ``jsonl`` sink's line with one key more, ``stamp``: the ROS time of
    the window's end, ``{"sec", "nanosec"}``.
``~/STREAM/posteriors`` (``sensor_msgs/JointState``; reliable, volatile, keep last ``history``)
    ``name``: the classes, ``position``: their posteriors (``velocity`` and ``effort`` empty).
``~/STREAM/features`` (``sensor_msgs/JointState``; best effort, volatile, keep last 5: sensor data)
    ``name``: ``FEATURE/FILTER``, ``position``: the window's values.
``~/events`` (``std_msgs/String``; reliable, transient local, keep last 20)
    A driver event's JSON object (unplug, reconnect, gap, overrun, ...), as the ``jsonl`` sink writes it;
    also each texture ``change`` within a contact (``[decision] change``; its ``source`` the stream, its
    message from which texture to which, at which window), which is in no diagnostics.
``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``; reliable, volatile, keep last 10)
    Per stream, source, the fusion and the sinks: a level, a line and the counts (below).

A message with a header (``JointState``) is stamped with its window's end on the ROS clock; the
decision's ``stamp`` is that same time, so a subscriber can join a decision to its posteriors. The
node's common time is put on the ROS clock by an offset measured once when the node starts (system
time), or, where the node runs with ``use_sim_time`` (a bag played with ``--clock``), as the ROS
clock's now less the window's age (:class:`~supramodal.drivers.ros2.RosClock`). A best-effort topic
(features) needs a best-effort subscriber (``qos_profile_sensor_data``); the others take a
default one.

Diagnostics
-----------
Each time it is given the graph's counters (the ``ros2`` sink does every ``diagnostics_period``
seconds, default 1, the ROS convention) and at once on a driver event, one ``DiagnosticArray`` whose
statuses are named ``NODE: stream NAME``, ``NODE: source NAME``, ``NODE: fusion`` and ``NODE: sinks``
(a diagnostic aggregator groups them by that prefix): :func:`diagnostic_report` says what each carries
and when it is OK, WARN or ERROR. While the node starts up (a model trained on the spot) a single status says so.

Threading: ``emit``, ``publish_window`` and ``event`` publish on the caller's thread and never wait
for a subscriber (DDS keeps what a topic's history allows and drops the rest for a slow reader); the
ROS node's executor spins on a thread of its own (the ``/clock`` of ``use_sim_time``, parameter
services); a lock keeps two threads from publishing diagnostics at once.
"""

from __future__ import annotations

import array
import functools
import json
import threading
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from supramodal.drivers.base import DriverEvent
from supramodal.drivers.ros2 import RosClock, RosNode, check_token
from supramodal.errors import InputError
from supramodal.node.runtime.events import DECISION_EVENTS, FUSED_STREAM, MAIN_STREAM, WindowEvent, severity
from supramodal.node.runtime.sinks.spec import stream_outputs
from supramodal.records import JsonValue

__all__ = ["OUTPUTS", "Ros2Publisher", "SourceState", "Status", "TopicStream", "diagnostic_report"]

#: What a ros2 sink can publish per stream, in order.
OUTPUTS = ("decision", "posteriors", "features")
DEFAULT_NODE_NAME = "supramodal"
#: The ROS standard topic of diagnostics (absolute: every node publishes there; remappable).
DIAGNOSTICS_TOPIC = "/diagnostics"
EVENTS_TOPIC = "~/events"
#: Messages a decision or posteriors topic keeps for a slow or late subscriber: one second of windows. With a
#: history of 1, a subscriber started before the node missed decisions in a suite run under load: one whose
#: side of the match completes after the first windows gets only what the history holds (transient local),
#: and one held up gets only what the publisher has not yet overwritten.
DEFAULT_HISTORY = 10
MAX_HISTORY = 1000
#: Driver events the events topic keeps for a late subscriber.
EVENTS_HISTORY = 20
#: Seconds to wait for subscribers before the node starts: none (a live sensor cannot wait).
DEFAULT_WAIT_FOR_SUBSCRIBERS = 0.0
MAX_WAIT_FOR_SUBSCRIBERS = 3600.0
#: Seconds after every decision topic has a subscriber before the node starts: the subscriber's side
#: of the match may still be on its way.
MATCH_SETTLE_SECONDS = 0.2
#: Longest wait at the end for the subscribers' acknowledgements of the last messages, seconds (a stopped
#: subscriber never acknowledges: the node ends anyway).
ACK_WAIT_SECONDS = 1.0
#: Seconds of one sleep in the wait: the main thread sees SIGINT and SIGTERM between two.
WAIT_STEP_SECONDS = 0.05

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR = 0, 1, 2


@dataclass(frozen=True)
class TopicStream:
    """What the topics of one node stream say about it.

    Attributes
    ----------
    name : str
        The node's stream name (``"main"`` in a one-source scene, ``"fused"`` for fusion); a ROS
        name token (:func:`~supramodal.drivers.ros2.check_token`).
    classes : tuple of str
        The model's classes, in the order of the posteriors (empty without a model).
    features : tuple of str
        The features, in the order their values are concatenated (empty for the fused stream).
    filters : tuple of str
        The bank's filter names, in channel order.
    """

    name: str
    classes: tuple[str, ...]
    features: tuple[str, ...] = ()
    filters: tuple[str, ...] = ()

    @functools.cached_property
    def feature_labels(self) -> tuple[str, ...]:
        """``FEATURE/FILTER`` per value of a window's features, in order.

        Made once: each window's features message names them.
        """
        return tuple(f"{f}/{name}" for f in self.features for name in self.filters)


@dataclass(frozen=True)
class Status:
    """One ``diagnostic_msgs/DiagnosticStatus``, before it is a message.

    Attributes
    ----------
    level : {0, 1, 2}
        OK, WARN, ERROR.
    name, message, hardware_id : str
    values : tuple of (str, str)
    """

    level: int
    name: str
    message: str
    hardware_id: str = ""
    values: tuple[tuple[str, str], ...] = ()


@dataclass
class SourceState:
    """What the driver events of one source said: the last one, counts per kind, and whether it is unplugged.

    Unplugged now: an ``unplug`` not yet followed by a ``reconnect``.
    """

    last: DriverEvent | None = None
    counts: Counter[str] = field(default_factory=Counter)
    unplugged: bool = False




def _count(value: object) -> int:
    """Return one of the graph's counts as an int (0 where there is none)."""
    return int(value) if isinstance(value, int | float | str) and value else 0


def _grew(now: Mapping[str, object], before: Mapping[str, object], key: str) -> int:
    """How much ``now[key]`` grew since ``before`` (all of it without a ``before``: empty)."""
    return _count(now.get(key)) - _count(before.get(key, 0))


def _fields(value: object) -> Mapping[str, object]:
    """Return a JSON object of the counters, or an empty one where there is none (None, absent)."""
    return value if isinstance(value, Mapping) else {}


def _items(value: object) -> list[object]:
    """Return a JSON list of the counters, or an empty one where there is none (None, absent)."""
    return value if isinstance(value, list) else []


def _fmt(value: object) -> str:
    return "" if value is None else f"{value:g}" if isinstance(value, float) else str(value)


def diagnostic_report(node: str, health: Mapping[str, JsonValue] | None, sources: Mapping[str, SourceState],
                      before: Mapping[str, JsonValue] | None, now: float) -> list[Status]:
    """Return the statuses of one diagnostics message.

    Parameters
    ----------
    node : str
        The ROS node's name: each status is named ``NODE: ...``.
    health : dict or None
        What the graph counts (:meth:`Graph.health <supramodal.node.runtime.graph.Graph.health>`:
        ``streams``, ``clocks``, ``fusion``, ``sinks``); None while the node starts up.
    sources : dict of str to SourceState
        The driver events seen per source since the start.
    before : dict or None
        The ``health`` of the last report, to say what changed since (None: the first).
    now : float
        ``time.time()`` of the report: a source's lossy event of the last 2 s makes it WARN.

    Returns
    -------
    list of Status
        ``NODE: stream NAME`` per stream: windows, frame fates (``frames_delivered``, ``_filled``,
        ``_dropped``, ``_stream``), latency (``latency_p50_ms``, ``_p99_ms``, ``_max_ms``) and its
        source's clock (``clock_ppm``, ``clock_jitter_ms``, ``clock_delay_ms``); ERROR while its
        source is unplugged, WARN when frames were filled or dropped since the last report, else OK.
        ``NODE: source NAME`` per source with events: the last event, counts per kind; ERROR while
        unplugged, WARN after an event that lost or made up samples, else OK. ``NODE: fusion``
        (``paired``, ``alone``, ``late``): WARN when windows were decided alone since the last
        report. ``NODE: sinks``: per sink its written, dropped and failed items; WARN when a sink
        dropped or failed since the last report. Without ``health`` (start-up), ``NODE: node`` saying
        so, and the sources' statuses.
    """
    out = []
    if health is None:
        out.append(Status(OK, f"{node}: node", "starting up (building the scene, training its model)"))
        health = {}
    before = before or {}
    before_streams = _fields(before.get("streams"))
    clocks = _fields(health.get("clocks"))
    for name, stream in _fields(health.get("streams")).items():
        st = _fields(stream)
        frames, latency = _fields(st.get("frames")), _fields(st.get("latency_ms"))
        was = _fields(_fields(before_streams.get(name)).get("frames"))
        source = str(st.get("source") or "")
        values = [("windows", _fmt(st.get("windows")))]
        values += [(f"frames_{k}", _fmt(frames.get(k))) for k in ("delivered", "filled", "dropped", "stream")]
        values += [(f"latency_{k}_ms", _fmt(latency.get(k))) for k in ("p50", "p99", "max")]
        clock = _fields(clocks.get(source))
        values += [(f"clock_{k}", _fmt(clock.get(k))) for k in ("ppm", "jitter_ms", "delay_ms") if k in clock]
        state = sources.get(source)
        filled, dropped = _grew(frames, was, "filled"), _grew(frames, was, "dropped")
        if state is not None and state.unplugged:
            level, message = ERROR, f"source {source} unplugged: {state.last.message if state.last else ''}"
        elif filled or dropped:
            level, message = WARN, f"{filled} frames filled and {dropped} dropped since the last report"
        else:
            p99 = latency.get("p99")
            level, message = OK, f"{st.get('windows', 0)} windows" + (f", latency p99 {p99:.1f} ms" if p99 else "")
        out.append(Status(level, f"{node}: stream {name}", message, source, tuple(values)))
    for name, state in sources.items():
        last = state.last
        values = [("last_event", last.kind if last else ""), ("last_message", last.message if last else "")]
        values += [(f"events_{kind}", str(n)) for kind, n in sorted(state.counts.items())]
        if state.unplugged:
            level, message = ERROR, f"unplugged: {last.message if last else ''}"
        elif last is not None and severity(last.kind) == "alarm" and now - last.time < 2.0:   # samples lost, made up
            level, message = WARN, f"{last.kind}: {last.message}"
        else:
            level, message = OK, f"last event: {last.kind}" if last else "no event"
        out.append(Status(level, f"{node}: source {name}", message, name, tuple(values)))
    fusion = _fields(health.get("fusion"))
    if fusion:
        alone = _grew(fusion, _fields(before.get("fusion")), "alone")
        values = [("windows", _fmt(fusion.get("windows"))), ("paired", _fmt(fusion.get("paired"))),
                  ("alone", _fmt(fusion.get("alone"))), ("late", json.dumps(fusion.get("late") or {}))]
        out.append(Status(WARN if alone else OK, f"{node}: fusion",
                          f"{alone} windows decided by one sense since the last report" if alone
                          else f"{fusion.get('paired', 0)} windows paired", FUSED_STREAM, tuple(values)))
    sinks = [_fields(s) for s in _items(health.get("sinks"))]
    if sinks:
        values, grew = [], 0
        was_sinks = {s.get("sink"): s for s in map(_fields, _items(before.get("sinks")))}
        for s in sinks:
            label = str(s.get("sink"))
            for key in ("written", "dropped_windows", "dropped_events", "errors", "publisher_errors"):
                if key in s:
                    values.append((f"{label} {key}", _fmt(s[key])))
            grew += sum(_grew(s, was_sinks.get(s.get("sink"), {}), k) for k in ("dropped_windows", "dropped_events",
                                                                             "errors", "publisher_errors") if k in s)
        out.append(Status(WARN if grew else OK, f"{node}: sinks",
                          f"{grew} items dropped or failed since the last report" if grew else f"{len(sinks)} sinks",
                          "", tuple(values)))
    return out


class _Publisher(Protocol):
    """What the node uses of an ``rclpy`` publisher (rclpy is not type-checked here: the ros2 extra)."""

    @property
    def topic_name(self) -> str:
        """The topic's full name."""
        ...

    def publish(self, msg: object) -> None:
        """Publish one message of the publisher's type."""
        ...

    def get_subscription_count(self) -> int:
        """Return the subscriptions matched now."""
        ...

    def wait_for_all_acked(self, timeout: object) -> bool:
        """Wait up to ``timeout`` (an ``rclpy.duration.Duration``) for every reliable subscriber's acknowledgements."""
        ...


class Ros2Publisher:
    """The node's window events, driver events and health on ROS 2 topics (see the module notes).

    Parameters
    ----------
    streams : sequence of TopicStream
        The streams this sink publishes (events of other streams are ignored).
    outputs : sequence of {"decision", "posteriors", "features"}
        Default all three; decision and posteriors only for a stream with classes, features only for
        a stream with features.
    node_name : str
        Default ``"supramodal"``.
    namespace : str
        Default ``""``: the root (or what ``--ros-args -r __ns:=...`` says).
    frame_id : str
        The ``header.frame_id`` of the stamped messages (the sensor's TF frame), default ``""``.
    wait_for_subscribers : float
        Seconds :meth:`prepare` waits, before the node starts, until every decision topic (or, for a
        stream without classes, its features topic) has a subscriber (default 0: start at once).
    history : int
        Messages each decision and posteriors topic keeps for a slow or late subscriber (default
        :data:`DEFAULT_HISTORY`); a subscriber held up longer than that many windows misses some.

    Raises
    ------
    Ros2Unavailable
        No rclpy here.
    InputError
        A bad option, or rclpy refused the node's name.
    """

    def __init__(self, streams: Sequence[TopicStream], outputs: Sequence[str] = OUTPUTS,
                 node_name: str = DEFAULT_NODE_NAME, namespace: str = "", frame_id: str = "",
                 wait_for_subscribers: float = DEFAULT_WAIT_FOR_SUBSCRIBERS,
                 history: int = DEFAULT_HISTORY) -> None:
        unknown = sorted(set(outputs) - set(OUTPUTS))
        if unknown or not outputs:
            raise InputError(f"a ros2 sink publishes some of {list(OUTPUTS)}, got {list(outputs)}")
        bad = [s.name for s in streams if not check_token(s.name)]
        if bad:
            raise InputError(f"streams {bad} cannot be part of a ROS topic name; rename them with letters, digits "
                             "and '_' (no '__', not starting with a digit)")
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        self._ros = RosNode(node_name, namespace)
        node = self._ros.node
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(history),
                             reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        kinds: dict[str, tuple[type[object], object]] = {          # message class, QoS profile
            "decision": (String, latched),
            "posteriors": (JointState, QoSProfile(depth=int(history))),
            "features": (JointState, qos_profile_sensor_data),
        }
        self._streams = {s.name: s for s in streams}
        self._publishers: dict[tuple[str, str], _Publisher] = {}
        self._messages: dict[tuple[str, str], Any] = {}       # (stream, output) -> its JointState, refilled
        self._names: dict[tuple[str, str], tuple[str, ...]] = {}     # ... -> the names its message carries
        self._one_source: str | None = None                   # the graph's one source, once known
        for s in streams:
            for output in stream_outputs(outputs, bool(s.features), bool(s.classes)):
                kind, qos = kinds[output]
                self._publishers[(s.name, output)] = node.create_publisher(kind, f"~/{s.name}/{output}", qos)
        self._events = node.create_publisher(String, EVENTS_TOPIC, QoSProfile(
            depth=EVENTS_HISTORY, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._diagnostics = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, QoSProfile(depth=10))
        self._String, self._JointState, self._DiagnosticArray = String, JointState, DiagnosticArray
        self.frame_id = frame_id
        self.wait_for_subscribers = float(wait_for_subscribers)
        self.waited_s: float | None = None
        self.subscribed: list[str] | None = None
        self.published: Counter[str] = Counter()
        self._sources: dict[str, SourceState] = {}
        self._health: dict[str, JsonValue] | None = None      # the graph's counters last given
        self._before: dict[str, JsonValue] | None = None      # ... as the last report said them
        self._lock = threading.Lock()
        self._clock = RosClock(node.get_clock(), time.monotonic())
        self._ros.start()

    @property
    def node_name(self) -> str:
        """The ROS node's fully qualified name (``/supramodal``; after any remapping)."""
        return self._ros.name

    @property
    def outputs(self) -> tuple[tuple[str, str], ...]:
        """What it publishes: ``(stream, output)`` per topic of a stream, in order."""
        return tuple(self._publishers)

    def topic(self, stream: str, output: str) -> str:
        """Return the full name of one of the sink's topics (after any remapping)."""
        name: str = self._publishers[(stream, output)].topic_name
        return name

    # -- the node's calls ---------------------------------------------------------------------

    def prepare(self) -> None:
        """Wait up to ``wait_for_subscribers`` seconds until every decision topic has a subscriber.

        For a stream without classes, its features topic. The caller's thread, before the
        graph's start; made of short sleeps, so that SIGINT and SIGTERM interrupt it.
        """
        if self.wait_for_subscribers <= 0:
            return
        waited = {key: pub for key, pub in self._publishers.items()
                  if key[1] == "decision" or key[1] == "features" and not self._streams[key[0]].classes}
        t = time.monotonic()
        found = {key: False for key in waited}
        while not all(found.values()) and time.monotonic() - t < self.wait_for_subscribers:
            found = {key: pub.get_subscription_count() > 0 for key, pub in waited.items()}
            if not all(found.values()):
                time.sleep(WAIT_STEP_SECONDS)
        if any(found.values()):
            time.sleep(MATCH_SETTLE_SECONDS)
        self.waited_s = round(time.monotonic() - t, 3)
        self.subscribed = [f"{stream}/{output}" for (stream, output), ok in found.items() if ok]

    def start(self, epoch: float) -> None:
        """Take the graph's start, on ``time.monotonic()``: common time 0.

        The caller's thread, before any event.
        """
        self._clock = RosClock(self._ros.node.get_clock(), epoch)

    def emit(self, event: WindowEvent) -> None:
        """Publish one window event on its stream's topics.

        An event of a stream this publisher does not publish is ignored.
        """
        s = self._streams.get(event.stream)
        if s is None:
            return
        self.publish_window(s.name, event.end, features_of(event, s), event.posteriors,
                            tuple(event.classes or s.classes),
                            event.as_dict() if event.decision is not None else None)

    def publish_window(self, stream: str, end: float, features: np.ndarray | None, posteriors: np.ndarray | None,
                       classes: tuple[str, ...] | None, decision: Mapping[str, JsonValue] | None) -> None:
        """Publish one window, by its parts.

        Its ``end`` (common time, s), its ``features`` (the stream's features' values concatenated in order,
        :func:`features_of`), ``posteriors`` in the order of ``classes`` (None: the stream's), and the ``decision``
        (the event's :meth:`~WindowEvent.as_dict`); None: not published. A stream this publisher does not publish is
        ignored.
        """
        s = self._streams.get(stream)
        if s is None:
            return
        ns = self._clock.stamp_ns(end)
        sec, nanosec = divmod(ns, 1_000_000_000)
        publisher = self._publishers.get((s.name, "features"))
        if publisher is not None and features is not None and len(features):
            publisher.publish(self._joint_state(s.name, "features", sec, nanosec, s.feature_labels,
                                                np.asarray(features, dtype=np.float64)))
            self.published["features"] += 1
        publisher = self._publishers.get((s.name, "posteriors"))
        if publisher is not None and posteriors is not None:
            publisher.publish(self._joint_state(s.name, "posteriors", sec, nanosec, classes or s.classes,
                                                np.asarray(posteriors, dtype=np.float64)))
            self.published["posteriors"] += 1
        publisher = self._publishers.get((s.name, "decision"))
        if publisher is not None and decision is not None:
            stamp = {"sec": sec, "nanosec": nanosec}
            publisher.publish(self._String(data=json.dumps({**decision, "stamp": stamp})))
            self.published["decision"] += 1

    def _joint_state(self, stream: str, output: str, sec: int, nanosec: int, names: tuple[str, ...],
                     values: np.ndarray) -> object:
        """Return the stream's ``JointState`` of ``output``, its stamp and values set.

        One message per topic, kept and refilled: a new one costs its field checks (about a third of a window's
        publishing); its names are set again only when they change (compared with the tuple last set, not the
        message's list). The sink's thread only.
        """
        key = (stream, output)
        msg = self._messages.get(key)
        if msg is None:
            msg = self._messages[key] = self._JointState()
            msg.header.frame_id = self.frame_id
        if self._names.get(key) != names:
            msg.name = list(names)
            self._names[key] = names
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        msg.position = array.array("d", values.tobytes())   # an array of doubles: rclpy takes it unchecked
        return msg

    def event(self, ev: DriverEvent, source: str | None = None,
              health: Mapping[str, JsonValue] | None = None) -> None:
        """Publish a driver event: on ``~/events`` at once (as the ``jsonl`` sink writes it), and in the diagnostics.

        The diagnostics are published at once too, of ``health`` (None: the counters last given). ``source``:
        the source it is filed under when the event names none (default: the graph's one source).
        """
        if ev.kind in DECISION_EVENTS:          # a texture change: the planner's to act on, not the health's
            self._events.publish(self._String(data=json.dumps(ev.as_dict())))
            self.published["events"] += 1
            return
        name = ev.source or source or self._only_source()
        with self._lock:
            state = self._sources.setdefault(name, SourceState())
            state.last = ev
            state.counts[ev.kind] += ev.count
            if ev.kind == "unplug":
                state.unplugged = True
            elif ev.kind in ("reconnect", "restart"):
                state.unplugged = False
        self._events.publish(self._String(data=json.dumps(ev.as_dict())))
        self.published["events"] += 1
        self.publish_diagnostics(health)

    def _only_source(self) -> str:
        """Return the name of the graph's one source (a one-source graph's events name none).

        What its stream's status is keyed by; ``main`` outside a graph (no counters given yet).
        """
        if self._one_source is None:
            if self._health is None:
                return MAIN_STREAM
            self._one_source = only_source(self._health)
        return self._one_source

    def publish_diagnostics(self, health: Mapping[str, JsonValue] | None = None) -> None:
        """Publish one ``DiagnosticArray`` of :func:`diagnostic_report` now, of ``health``.

        ``health``: the graph's counters, :meth:`Graph.health <supramodal.node.runtime.graph.Graph.health>`;
        None: those last given, or "starting up" before any. Any thread.
        """
        from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

        with self._lock:
            if health is not None:
                self._health = dict(health)
            health = self._health
            statuses = diagnostic_report(self._ros.node.get_name(), health, self._sources, self._before, time.time())
            self._before = health
            msg = self._DiagnosticArray()
            msg.header.stamp = self._ros.node.get_clock().now().to_msg()
            msg.status = [DiagnosticStatus(level=bytes([s.level]), name=s.name, message=s.message,
                                           hardware_id=s.hardware_id,
                                           values=[KeyValue(key=k, value=v) for k, v in s.values])
                          for s in statuses]
            self._diagnostics.publish(msg)
            self.published["diagnostics"] += 1

    def stats(self) -> dict[str, JsonValue]:
        """Return the node's name, what was published per output, and the wait for subscribers.

        With a wait for subscribers, ``waited_s`` and ``subscribed`` (the topics that had one, ``STREAM/OUTPUT``).
        """
        out: dict[str, JsonValue] = {"node": self.node_name, "published": dict(self.published)}
        if self.waited_s is not None:
            out.update(waited_s=self.waited_s, subscribed=None if self.subscribed is None else list(self.subscribed))
        return out

    def drain(self, timeout: float = 5.0) -> None:
        """Wait, after the last window, until every subscriber has acknowledged the reliable topics' last messages.

        At most ``timeout`` s, and at most :data:`ACK_WAIT_SECONDS`; so that closing the node does not cut the last
        windows off on their way (a subscriber missed the last window of two streams so, in a suite run under load).
        The caller's thread.
        """
        from rclpy.duration import Duration

        deadline = time.monotonic() + min(timeout, ACK_WAIT_SECONDS)
        for (_, output), pub in self._publishers.items():
            left = deadline - time.monotonic()
            if output != "features" and left > 0:
                pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))

    def close(self) -> None:
        """Destroy the ROS node (idempotent)."""
        self._ros.close()


def features_of(event: WindowEvent, stream: TopicStream) -> np.ndarray | None:
    """Return a window event's features, its stream's features' values concatenated in their order.

    float64; None without features.
    """
    if not event.features:
        return None
    return np.concatenate([np.asarray(event.features[f], dtype=np.float64) for f in stream.features])


def only_source(health: Mapping[str, JsonValue]) -> str:
    """Return the name of a graph's one source, from its counters (``main`` where there is not exactly one).

    The source a driver event that names none came from.
    """
    sources = {_fields(st).get("source") for st in _fields(health.get("streams")).values()} - {None}
    return str(sources.pop()) if len(sources) == 1 else MAIN_STREAM
