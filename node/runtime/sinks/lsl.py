"""Window events out as Lab Streaming Layer streams: features, decisions and posteriors.

So that another machine (a recorder such as LabRecorder, a controller, a second classifier) takes them.

Needs the optional extra ``lsl`` (:func:`supramodal.drivers.lsl.import_pylsl` says what to
install when it is missing).

Streams
-------
Per node stream it listens to (``[[sink]] from``; default every stream, the fused one included),
the sink opens up to three outlets, made when the node is built, before any model is trained (from
the streams' plans: bank, features, classes), so that consumers resolve them during the start-up.
A consumer started before the node gets window 0 however soon the node starts: by default each
outlet keeps its windows, from the node's start, until its first consumer has connected (then sends
them, stamped as they were) or :data:`HOLD_FOR_CONSUMER_SECONDS` have passed, and the node itself
waits for nothing; ``wait_for_consumer`` (seconds) makes the node wait for consumers before it
starts instead, and ``wait_for_consumer = 0`` sends every window at once (a consumer gets what
comes after it has connected). Their names, types and source ids are fixed by the node's stream
name (``NAME``) and the sink's ``prefix`` (default ``"supramodal"``), so that a restarted node is
picked up again by consumers that recover by source id:

============  ======================  ============  =========================================================
output        name                    type          samples
============  ======================  ============  =========================================================
features      ``PREFIX-NAME-features``  ``Features``    float32, one channel per (feature, filter), labelled
                                                    ``FEATURE/FILTER`` with the feature's unit; 1 / window Hz
decisions     ``PREFIX-NAME-decisions`` ``Markers``     one JSON string per window: stream, window, start, end,
                                                    decision, confidence, pooled, truth, flags; irregular
posteriors    ``PREFIX-NAME-posteriors`` ``Posteriors`` float32, one channel per class, labelled with its name
============  ======================  ============  =========================================================

The source id is ``PREFIX@HOST/NAME/OUTPUT`` (HOST: this machine's name). Every stream's
description carries ``channels`` (``label``, ``unit``, ``type``, per the XDF meta-data
conventions) where it has channels, and a ``supramodal`` element: the node's stream, the bank
(kind, rate, filters with their centre frequencies), the features, the window (seconds) and the
classes.

Time: each sample is stamped with its window's end on the node's common clock, put on LSL's
clock (``pylsl.local_clock()``) by the offset between the two measured when the node starts. A
window event's ``end`` counts seconds from the graph's start (:meth:`start` gives that instant);
so for a live source it is the host time its last sample was taken, for a file it is the file's
own time from the start of the run.

Threading: the node runs this sink behind its own queue (:class:`~supramodal.node.runtime.sinks.QueuedSink`);
``emit`` pushes (or keeps, above) on that thread and never waits for consumers (liblsl buffers and
drops for a slow one, its outlets' ``max_buffered``).
"""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Protocol

import numpy as np

from supramodal import __version__
from supramodal.checks import NAME_HELP, Key, is_name, non_negative
from supramodal.drivers.base import DriverEvent
from supramodal.drivers.lsl import import_pylsl, lsl_clock_offset
from supramodal.drivers.spec import OptionError
from supramodal.errors import InputError
from supramodal.features import FEATURE_TABLE
from supramodal.node.runtime.events import FUSED_STREAM, WindowEvent
from supramodal.node.runtime.fields import optional_float_of, str_of, strs_of
from supramodal.node.runtime.sinks import QueuedSink, Sink
from supramodal.node.runtime.sinks.spec import Options, SinkContext, SinkSpec, listened, option_from, stream_outputs
from supramodal.node.runtime.summaries import RunSummary
from supramodal.records import JsonValue

if TYPE_CHECKING:   # for the annotations only: the sink needs no model code to run
    from supramodal.pipeline import FeaturePipeline

#: What an LSL sink can send, in order.
OUTPUTS = ("features", "decisions", "posteriors")
#: Prefix of the outlets' names and source ids.
DEFAULT_PREFIX = "supramodal"
_TYPES = {"features": "Features", "decisions": "Markers", "posteriors": "Posteriors"}
#: Seconds of samples an outlet keeps for a slow consumer before it drops the oldest.
OUTLET_BUFFER_SECONDS = 60
#: Seconds to wait for consumers before the node starts; None (the key absent): no wait, each
#: outlet keeps its first windows for its first consumer instead (:data:`HOLD_FOR_CONSUMER_SECONDS`).
DEFAULT_WAIT_FOR_CONSUMER = None
#: Seconds after the node's start that an outlet with no consumer yet keeps its windows for the first
#: one (the default, no ``wait_for_consumer``). liblsl sends a new consumer nothing pushed before it
#: connected, and a consumer started before the node connects 0.1-0.7 s after the outlets are up (a plain
#: pylsl resolve on one machine, measured), 1-3 s later if it waits for a duplicate as the node's own
#: inlet does (resolve_stream), longer across a network: up to 2.6 s of windows were lost. Nothing waits
#: on the hold, so it is several times that.
HOLD_FOR_CONSUMER_SECONDS = 10.0
#: Seconds after the last consumer has connected before the node starts: a consumer's data
#: connection is set up after ``wait_for_consumers`` returns, and a sample pushed before can miss it.
CONNECT_SETTLE_SECONDS = 0.2
#: Seconds of one wait in liblsl: the main thread sees SIGINT and SIGTERM between two.
WAIT_STEP_SECONDS = 0.1
#: Seconds the sink keeps its outlets open at the end of a run while they have consumers: liblsl sends
#: from threads of its own, and an outlet released drops what it has not yet sent (a consumer on a busy
#: machine missed a run's last windows, its connection "broke off" as the node exited).
CLOSE_LINGER_SECONDS = 1.0


#: One sample of an outlet: a float32 row of its channels, or a string outlet's one string in a list.
Sample = np.ndarray | list[str]


class Outlet(Protocol):
    """What the node uses of a ``pylsl.StreamOutlet`` (pylsl ships no type information)."""

    def push_sample(self, x: Sample, timestamp: float = ...) -> None:
        """Push one sample (a row of channels), stamped ``timestamp`` on LSL's clock."""
        ...

    def push_chunk(self, x: np.ndarray, timestamp: float = ...) -> None:
        """Push several samples (the rows of a float32 array), the last stamped ``timestamp`` on LSL's clock."""
        ...

    def wait_for_consumers(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for a consumer; return whether one has connected."""
        ...

    def have_consumers(self) -> bool:
        """Return whether a consumer is connected now."""
        ...


@dataclass(frozen=True)
class OutletStream:
    """What the outlets of one node stream say about it.

    Attributes
    ----------
    name : str
        The node's stream name (``"main"`` in a one-source scene, ``"fused"`` for fusion).
    bank_kind : str
    rate : float
        The bank's sample rate, Hz.
    filters : tuple of str
        Filter names, in channel order (empty for the fused stream: it has no features).
    centre_hz : tuple of float
    features : tuple of str
    window : float
        Seconds.
    classes : tuple of str
        The model's classes (empty without a model).
    """

    name: str
    bank_kind: str
    rate: float
    filters: tuple[str, ...]
    centre_hz: tuple[float, ...]
    features: tuple[str, ...]
    window: float
    classes: tuple[str, ...]


class LSLClock:
    """The node's common time on LSL's clock (``pylsl.local_clock()``).

    Parameters
    ----------
    pylsl : module
    epoch : float
        The graph's start on ``time.monotonic()``: common time 0.

    The offset between the host's monotonic clock and LSL's is measured once, here
    (:func:`~supramodal.drivers.lsl.lsl_clock_offset`).
    """

    def __init__(self, pylsl: ModuleType, epoch: float) -> None:
        self.epoch = epoch
        self.offset = lsl_clock_offset(pylsl)

    def lsl_time(self, common: float) -> float:
        """Return a time on the node's common clock, seconds, on LSL's clock."""
        return self.epoch + common - self.offset


def wait_for_consumers(outlets: Sequence[Outlet], seconds: float) -> tuple[float, list[bool]]:
    """Wait up to ``seconds`` until each of ``outlets`` (pylsl ``StreamOutlet``) has a consumer.

    Then wait :data:`CONNECT_SETTLE_SECONDS` more. Start-up work: the wait is made of liblsl waits of at most
    :data:`WAIT_STEP_SECONDS`, so that SIGINT and SIGTERM, whose handlers run on the main thread between two,
    interrupt it.

    Returns
    -------
    waited_s : float
        Seconds waited, rounded to the millisecond.
    found : list of bool
        Per outlet, whether it had a consumer.
    """
    t = time.monotonic()
    found = [False] * len(outlets)
    while not all(found):
        left = seconds - (time.monotonic() - t)
        if left <= 0:
            break
        i = found.index(False)
        found[i] = bool(outlets[i].wait_for_consumers(min(WAIT_STEP_SECONDS, left)))
        found = [ok or bool(o.have_consumers()) for ok, o in zip(found, outlets)]
    if any(found):
        time.sleep(CONNECT_SETTLE_SECONDS)
    return round(time.monotonic() - t, 3), found


def outlet_name(prefix: str, stream: str, output: str) -> str:
    """Return the LSL name of one outlet: ``PREFIX-STREAM-OUTPUT``."""
    return f"{prefix}-{stream}-{output}"


def outlet_source_id(prefix: str, stream: str, output: str, host: str | None = None) -> str:
    """Return the LSL source id of one outlet: ``PREFIX@HOST/STREAM/OUTPUT``."""
    return f"{prefix}@{host or socket.gethostname()}/{stream}/{output}"


class LSLOutletSink(Sink):
    """The node's window events as LSL outlets (see the module notes): a :class:`~supramodal.node.runtime.sinks.Sink`.

    Parameters
    ----------
    streams : sequence of OutletStream
        The streams this sink sends (events of other streams are ignored).
    outputs : sequence of {"features", "decisions", "posteriors"}
        Default all three; posteriors and decisions only for a stream with classes, features
        only for a stream with filters.
    prefix : str
        Default :data:`DEFAULT_PREFIX`.
    wait_for_consumer : float or None
        Seconds :meth:`prepare` waits, before the node starts, until each outlet has a consumer;
        the node starts anyway when one has none by then (:meth:`stats`: ``waited_s`` and
        ``consumers``). 0: no wait, every window sent at once. None (the default): no wait, and each
        outlet keeps its windows until its first consumer connects, for at most
        :data:`HOLD_FOR_CONSUMER_SECONDS` after the start (:meth:`stats`: ``held_s`` and ``consumers``).

    The outlets are made here, when the node is built and before any model is trained, so that
    a consumer started before the node resolves them during the start-up and gets window 0.
    """

    def __init__(self, streams: Sequence[OutletStream], outputs: Sequence[str] = OUTPUTS, prefix: str = DEFAULT_PREFIX,
                 wait_for_consumer: float | None = DEFAULT_WAIT_FOR_CONSUMER) -> None:
        unknown = sorted(set(outputs) - set(OUTPUTS))
        if unknown or not outputs:
            raise InputError(f"an LSL sink sends some of {list(OUTPUTS)}, got {list(outputs)}")
        pylsl = self._pylsl = import_pylsl()
        self.prefix = prefix
        self.wait_for_consumer = None if wait_for_consumer is None else float(wait_for_consumer)
        self.waited_s: float | None = None
        self.consumers: list[str] | None = None
        self._outlets: dict[tuple[str, str], Outlet] = {}
        # The default's hold: per outlet with no consumer yet, the samples kept for its first one,
        # until _hold_end (time.monotonic()); an outlet leaves it for good on its first consumer.
        self._held: dict[tuple[str, str], list[tuple[Sample, float]]] = {}
        self._hold_end = 0.0
        self._pushed = False                 # whether any sample went to an outlet (close lingers only then)
        self._streams = {s.name: s for s in streams}
        self._clock = LSLClock(pylsl, time.monotonic())
        for s in streams:
            for output in stream_outputs(outputs, bool(s.filters), bool(s.classes)):
                info = self._info(s, output)
                self._outlets[(s.name, output)] = pylsl.StreamOutlet(info, chunk_size=1,
                                                                     max_buffered=OUTLET_BUFFER_SECONDS)

    def _info(self, s: OutletStream, output: str) -> object:
        """Return the outlet's ``pylsl.StreamInfo`` (an object to the type checker: pylsl ships no types)."""
        pylsl = self._pylsl
        if output == "features":
            labels = [f"{f}/{name}" for f in s.features for name in s.filters]
            units = [FEATURE_TABLE[f].unit for f in s.features for _ in s.filters]
            kinds = [f"supramodal-{f}" for f in s.features for _ in s.filters]
            info = pylsl.StreamInfo(outlet_name(self.prefix, s.name, output), _TYPES[output], len(labels),
                                    1.0 / s.window, "float32", outlet_source_id(self.prefix, s.name, output))
        elif output == "posteriors":
            labels, units, kinds = list(s.classes), ["probability"] * len(s.classes), ["posterior"] * len(s.classes)
            # The fused stream's windows are stamped when a pair of windows of two sources is
            # complete, on common time: not a regular rate (irregular, as LSL says it).
            rate = pylsl.IRREGULAR_RATE if s.name == FUSED_STREAM else 1.0 / s.window
            info = pylsl.StreamInfo(outlet_name(self.prefix, s.name, output), _TYPES[output], len(labels),
                                    rate, "float32", outlet_source_id(self.prefix, s.name, output))
        else:
            labels, units, kinds = ["decision"], ["json"], ["marker"]
            info = pylsl.StreamInfo(outlet_name(self.prefix, s.name, output), _TYPES[output], 1, pylsl.IRREGULAR_RATE,
                                    "string", outlet_source_id(self.prefix, s.name, output))
        desc = info.desc()
        if labels:
            channels = desc.append_child("channels")
            for label, unit, kind in zip(labels, units, kinds):
                ch = channels.append_child("channel")
                ch.append_child_value("label", label)
                ch.append_child_value("unit", unit)
                ch.append_child_value("type", kind)
        meta = desc.append_child("supramodal")
        meta.append_child_value("version", __version__)
        meta.append_child_value("stream", s.name)
        meta.append_child_value("window", repr(s.window))
        meta.append_child_value("features", ",".join(s.features))
        meta.append_child_value("classes", json.dumps(list(s.classes)))
        bank = meta.append_child("bank")
        bank.append_child_value("kind", s.bank_kind)
        bank.append_child_value("rate", repr(s.rate))
        filters = bank.append_child("filters")
        for name, cf in zip(s.filters, s.centre_hz):
            f = filters.append_child("filter")
            f.append_child_value("name", name)
            f.append_child_value("centre_hz", repr(float(cf)))
        return info

    # -- the node's calls ---------------------------------------------------------------------

    def prepare(self) -> None:
        """Wait up to ``wait_for_consumer`` seconds until every outlet has a consumer.

        See :func:`wait_for_consumers`. The caller's thread, before the graph's start.
        """
        if self.wait_for_consumer is not None and self.wait_for_consumer > 0:
            self.waited_s, found = wait_for_consumers(list(self._outlets.values()), self.wait_for_consumer)
            self.consumers = [f"{name}-{output}" for (name, output), ok in zip(self._outlets, found) if ok]

    def stats(self) -> dict[str, JsonValue] | None:
        """Return how the outlets found their consumers, or None.

        With a wait for consumers: ``waited_s`` and ``consumers`` (the outlets that had one,
        ``STREAM-OUTPUT``); with the default's hold: ``held_s`` and ``consumers`` (the outlets whose
        first consumer came in time for window 0); else None.
        """
        if self.waited_s is not None:
            return {"sink": "LSLOutletSink", "waited_s": self.waited_s,
                    "consumers": None if self.consumers is None else list(self.consumers)}
        if self.wait_for_consumer is None:
            return {"sink": "LSLOutletSink", "held_s": HOLD_FOR_CONSUMER_SECONDS,
                    "consumers": list(self.consumers or [])}
        return None

    def start(self, epoch: float) -> None:
        """Take the graph's start, on ``time.monotonic()``: common time 0; start the hold, by default.

        The caller's thread, before any event.
        """
        self._clock = LSLClock(self._pylsl, epoch)
        if self.wait_for_consumer is None:
            self._held = {key: [] for key in self._outlets}
            self._hold_end = epoch + HOLD_FOR_CONSUMER_SECONDS
            self.consumers = []

    def emit(self, event: WindowEvent) -> None:
        """Push a window's features, posteriors and decision marker on its stream's outlets.

        Each stamped with the window's end on LSL's clock, or kept for the outlet's first consumer
        during the hold. A window of a stream the sink does not listen to is ignored. The sink's thread;
        never waits for consumers.
        """
        if event.stream not in self._streams:
            return
        stamp = self._clock.lsl_time(event.end)
        name = event.stream
        if (name, "features") in self._outlets and event.features:
            s = self._streams[name]
            row = np.concatenate([np.asarray(event.features[f], dtype=np.float32) for f in s.features])
            self._push((name, "features"), row, stamp)
        if (name, "posteriors") in self._outlets and event.posteriors is not None:
            self._push((name, "posteriors"), np.asarray(event.posteriors, dtype=np.float32), stamp)
        if (name, "decisions") in self._outlets and event.decision is not None:
            self._push((name, "decisions"), [json.dumps(_marker(event))], stamp)

    def _push(self, key: tuple[str, str], sample: Sample, stamp: float) -> None:
        """Push one sample on an outlet, or keep it for the outlet's first consumer (the hold)."""
        outlet = self._outlets[key]
        held = self._held.get(key)
        if held is not None and not self._release(key):
            if time.monotonic() < self._hold_end:
                held.append((sample, stamp))
                return
            del self._held[key]                     # none in time: sent as they come, as with 0
        outlet.push_sample(sample, stamp)
        self._pushed = True

    def _release(self, key: tuple[str, str]) -> bool:
        """Return whether the held outlet ``key`` has its first consumer.

        If it has, what it kept is sent, in order, and it holds no more.
        """
        outlet = self._outlets[key]
        if not outlet.have_consumers():
            return False
        for x, t in self._held.pop(key):
            outlet.push_sample(x, t)
            self._pushed = True
        if self.consumers is not None:
            self.consumers.append("-".join(key))
        return True

    def event(self, ev: DriverEvent) -> None:
        """Driver events are not sent (they are in the node's own sinks)."""

    def drain(self, timeout: float = 5.0) -> None:
        """Send what an outlet kept to the consumer that connected after its last window.

        No wait: a run that ends before its consumer connects needs ``wait_for_consumer``.
        """
        for key in list(self._held):
            self._release(key)

    def summary(self, summary: RunSummary) -> None:
        """Nothing to write (the node's summary counts what the sink's queue passed on)."""

    def close(self) -> None:
        """Drop a hold no consumer came for and release the outlets (liblsl closes them).

        Where samples were pushed and an outlet has a consumer, up to :data:`CLOSE_LINGER_SECONDS`
        first, in steps of :data:`WAIT_STEP_SECONDS` (less once no outlet has one), so that what was
        pushed last reaches it.
        """
        self._held.clear()                  # a hold no consumer came for: nobody to send it to
        end = time.monotonic() + CLOSE_LINGER_SECONDS
        while (self._pushed and time.monotonic() < end
               and any(o.have_consumers() for o in self._outlets.values())):
            time.sleep(WAIT_STEP_SECONDS)
        self._outlets.clear()               # liblsl closes an outlet when it is released


def _marker(event: WindowEvent) -> dict[str, JsonValue]:
    """Return the decision marker of one window: what a consumer needs to act on it."""
    return {"stream": event.stream, "window": event.window, "start": round(event.start, 6),
            "end": round(event.end, 6), "decision": event.decision,
            "confidence": None if event.confidence is None else round(event.confidence, 4),
            "pooled": None if event.pooled is None else event.pooled.to_dict(), "truth": event.truth,
            "flags": list(sorted(event.flags)),   # a list of JSON values (sorted's own is a list of str)
            **({"unknown": event.unknown, "guess": event.guess} if event.unknown is not None else {})}


# -- as a scene names it ---------------------------------------------------------------------------

def describe(name: str, pipeline: FeaturePipeline, classes: Sequence[str]) -> OutletStream:
    """Return a stream's outlets' description from its pipeline and its model's classes.

    With no classes (empty), the stream has the features outlet only.
    """
    bank = pipeline.bank
    return OutletStream(name, bank.kind, bank.fs, tuple(bank.names), tuple(float(c) for c in bank.cf),
                        pipeline.features, pipeline.window_samples / bank.fs, tuple(classes))


def _build(options: Options, context: SinkContext) -> Sink:
    # Made from the streams' plans, before any model is trained: consumers resolve the outlets
    # while the node trains (seconds), and get window 0.
    described = {name: describe(name, p.pipeline, p.classes) for name, p in context.plans.items()}
    if context.fused_classes is not None and described:
        window = next(iter(described.values())).window
        described[FUSED_STREAM] = OutletStream(FUSED_STREAM, "fused", 0.0, (), (), (), window,
                                               tuple(context.fused_classes))
    names = listened(option_from(options), described)
    try:
        sink = LSLOutletSink([described[n] for n in names], strs_of(options, "outputs"),
                             str_of(options, "prefix"), optional_float_of(options, "wait_for_consumer"))
    except InputError as exc:
        raise OptionError(str(exc)) from None
    return QueuedSink(sink)


#: Longest wait for consumers a scene may ask for, seconds.
MAX_WAIT_FOR_CONSUMER = 3600.0


SPEC = SinkSpec(
    type="lsl",
    summary="window events as Lab Streaming Layer outlets: features, decisions, posteriors (the lsl extra)",
    keys={"outputs": Key(lambda v: isinstance(v, list) and bool(v) and len(set(v)) == len(v) and set(v) <= set(OUTPUTS),
                         'a list drawn from "features", "decisions" and "posteriors"', list(OUTPUTS)),
          "prefix": Key(is_name, "the outlets' name prefix: " + NAME_HELP[len("a name: "):], DEFAULT_PREFIX),
          "wait_for_consumer": Key(non_negative(MAX_WAIT_FOR_CONSUMER),
                                   "seconds to wait, before the node starts, for a consumer on each of the sink's "
                                   f"outlets, 0 to {MAX_WAIT_FOR_CONSUMER:g} (0: start at once and send every window "
                                   "as it comes; absent: start at once, each outlet keeping its windows of the first "
                                   f"{HOLD_FOR_CONSUMER_SECONDS:g} s for its first consumer)",
                                   DEFAULT_WAIT_FOR_CONSUMER)},
    build=_build, needs="plans")
