"""The fusion block: two streams' windows paired on common time, their decisions fused.

Each stream emits its windows in order, on its own clock. Windows are paired when their
centres on the graph's common time lie within half a window of each other (two 100 ms windows
on crystals a few ppm and tens of ms apart overlap by at least half). A window whose partner has
not come within ``max_wait`` seconds of host time (the other source is late, stalled or
unplugged) is decided by its own sense alone and flagged ``"alone"`` (two file sources wait for
each other without a deadline: their decisions do not depend on the host's timing); a partner that comes
after that is *late*: counted, and left out of fusion (its own stream's sinks still get it).
When both streams have ended, what is still waiting is decided alone.

A sense that drops out is said as it happens: the first window decided alone because the other
stream's did not come in time gives a ``sense_lost`` event, the first pair after it a
``sense_back`` event (with the count of windows decided alone meanwhile), and a stream that ends
while the other goes on a ``sense_ended`` event. They go to the sinks as driver events do,
from source ``"fused"``, and are counted in the summary (``dropouts``).

Late fusion: ``log_softmax(s (w log p_a + (1 - w) log p_b))`` (:func:`supramodal.fusion.fuse_late`)
of the streams' log-posteriors, winner-take-all; pooling over windows and the "unknown" rules as
for one stream (:class:`supramodal.decisions.Decider`). A fused window is unknown as novel when either
sense's window is: an honest "not sure" beats a confident wrong name.

Threading rules
---------------
:meth:`LateFusion.put` and :meth:`LateFusion.end` are called from the streams' processing
threads and never block; :meth:`LateFusion.run` is the fusion thread; :meth:`summary` is called
once it has ended.
"""

from __future__ import annotations

import collections
import math
import queue
import time
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from supramodal.decisions import DEFAULT_DECISION, Decider, DecisionRules, fitted_change_threshold
from supramodal.drivers.base import DriverEvent
from supramodal.errors import InputError
from supramodal.features import DEFAULT_WINDOW
from supramodal.fusion import fuse_late
from supramodal.node.runtime.events import FUSED_STREAM, TruthTally, WindowEvent, change_event, log_posteriors_of
from supramodal.node.runtime.latency import LatencyHistogram
from supramodal.node.runtime.summaries import FusionSummary

if TYPE_CHECKING:   # for annotations only: the runtime does not load the early-fusion model
    from supramodal.fused_model import EarlyFusionModel
    from supramodal.node.runtime.contacts import ContactTimeline

#: Host seconds a window waits for its partner from the other stream before it is decided alone.
DEFAULT_MAX_WAIT = 0.5
#: Late-fusion weight of the first stream when a scene gives none.
DEFAULT_WEIGHT = 0.5


class _End:
    """The type of :data:`_END`."""


#: On the fusion queue, ``(_END, stream)``: that stream has emitted its last window.
_END = _End()

#: What the fusion queue holds: ``(window event, host time it was put)`` or ``(_END, stream name)``.
_Item = tuple[WindowEvent, float] | tuple[_End, str]
#: A window waiting for its partner: (event, when it was put, when its last block arrived or None).
_Pending = tuple[WindowEvent, float, float | None]


class LateFusion:
    """Pairs the windows of two streams and fuses their posteriors.

    Subclasses decide a pair otherwise (:meth:`_fused_posteriors`; :class:`EarlyFusion`).

    Parameters
    ----------
    inputs : (str, str)
        The two streams' names.
    classes : (sequence of str, sequence of str)
        Each stream's model classes; the two must name the same textures (in any order).
    weight : float
        Weight of the first stream's log-posteriors, in [0, 1] (default :data:`DEFAULT_WEIGHT`).
    sharpness : float
        Tempering of the fused log-posteriors, > 0 (default 1; learned with the weight by
        :func:`supramodal.fusion.learn_late_fusion`).
    correlation : float
        Window correlation of the fused decisions' pooling (default 0: summed log-posteriors).
    caps : array-like (classes, classes) or None
        The pooling's caps per pair of classes, in the order of ``classes[0]`` (None: uncapped).
    max_wait : float or None
        Host seconds a window waits for its partner (default :data:`DEFAULT_MAX_WAIT`). None:
        until the other stream has passed it or ended, however long that takes (two files replayed
        at any speed: their timing is their own, and the decisions do not depend on the host's).
    decision : supramodal.decisions.DecisionRules, optional
        Pooling and rules of the fused decisions, as for a stream (default: each window alone).
    change_threshold : float or None
        With ``decision.change``: the change detector's threshold fitted for that rate on held-out
        windows (an early fusion's model carries them); None (default): the detector's bound, which a
        late fusion keeps (no held-out windows of its fused posteriors are kept).

    Attributes
    ----------
    on_event : callable or None
        Called from the fusion thread with each ``DriverEvent`` it says (a sense lost, back or
        ended); must not block. The graph sets it to its event queue.
    """

    method = "late"

    def __init__(self, inputs: Sequence[str], classes: Sequence[Sequence[str]], weight: float = DEFAULT_WEIGHT,
                 max_wait: float | None = DEFAULT_MAX_WAIT,
                 decision: DecisionRules = DEFAULT_DECISION, *, sharpness: float = 1.0, correlation: float = 0.0,
                 caps: ArrayLike | None = None, window_seconds: float = DEFAULT_WINDOW,
                 change_threshold: float | None = None) -> None:
        a, b = inputs
        if a == b:
            raise InputError(f"fusion needs two different streams, got {a!r} twice")
        ca, cb = (list(c) for c in classes)
        if sorted(ca) != sorted(cb) or len(set(ca)) != len(ca):
            raise InputError(f"the fused streams' models must know the same textures: {a!r} has {ca}, {b!r} has {cb}; "
                             "train both on one texture set")
        if not (isinstance(weight, (int, float)) and 0.0 <= weight <= 1.0):
            raise InputError(f"the fusion weight must lie in [0, 1], got {weight!r}")
        if not (isinstance(sharpness, (int, float)) and math.isfinite(sharpness) and sharpness > 0):
            raise InputError(f"the fusion sharpness must be a finite number > 0, got {sharpness!r}")
        if max_wait is not None and not (isinstance(max_wait, (int, float)) and math.isfinite(max_wait)
                                         and max_wait > 0):
            raise InputError(f"the fusion's max_wait must be a positive number of seconds, got {max_wait!r}")
        self.inputs = (a, b)
        self.classes = tuple(ca)
        self._order_b = np.array([cb.index(name) for name in ca])   # b's outputs in a's class order
        # The weight the pairs are fused with; `weight`, what the summary says (None: early fusion).
        self._weight = float(weight)
        self.weight: float | None = self._weight
        self.sharpness = float(sharpness)
        self.correlation = float(correlation)
        self.max_wait = math.inf if max_wait is None else float(max_wait)
        self.decider = Decider(ca, decision, correlation, caps=caps, window_seconds=window_seconds,
                               change_threshold=change_threshold)
        #: The robot's own contact signal (``[fusion.decision] contact_from``): the fused windows'
        #: touches; None: a fused window is in contact when either sense's is.
        self.touches: ContactTimeline | None = None
        self._queue: queue.SimpleQueue[_Item] = queue.SimpleQueue()
        # per stream: (event, when it was put, when its last block arrived or None) of the windows
        # awaiting a partner
        self._pending: dict[str, collections.deque[_Pending]] = {
            a: collections.deque(), b: collections.deque()}
        self._ended: set[str] = set()
        # per stream: the centre of the last window of the *other* stream decided alone because
        # this one's did not come in time; this stream's windows up to there are late
        self._alone_until = {a: -math.inf, b: -math.inf}
        self.windows = self.paired = self.alone = 0
        self.late = {a: 0, b: 0}
        self.on_event: Callable[[DriverEvent], None] | None = None
        #: A list to which each fused pair of window events is appended (training a fusion on
        #: recorded sessions); None: pairs are not kept.
        self.kept_pairs: list[tuple[WindowEvent, WindowEvent]] | None = None
        # per stream: missing since its partner window did not come in time (windows decided
        # alone since then), or None while present
        self._missing: dict[str, int | None] = {a: None, b: None}
        self._said_ended: set[str] = set()
        self._after_end = {a: 0, b: 0}          # windows of a stream decided alone after the other's end
        self.dropouts = {a: 0, b: 0}
        self.tally = TruthTally()
        self.latencies = LatencyHistogram()

    # -- processing threads -----------------------------------------------------------------

    def put(self, event: WindowEvent) -> None:
        """Take a window of one of the inputs (never blocks)."""
        self._queue.put((event, time.monotonic()))

    def end(self, stream: str) -> None:
        """Mark that the stream ``stream`` has emitted its last window."""
        self._queue.put((_END, stream))

    # -- fusion thread ----------------------------------------------------------------------

    def run(self, emit: Callable[[WindowEvent], None]) -> None:
        """Pair and fuse until both inputs have ended; ``emit`` each fused WindowEvent."""
        while len(self._ended) < 2:
            item: _Item | None
            try:
                item = self._queue.get(timeout=0.01)
            except queue.Empty:
                item = None
            if item is None:
                pass
            elif isinstance(item[0], _End):     # (_END, stream)
                self._ended.add(item[1])
            else:
                self._take(*item)
            self._pair(time.monotonic(), emit)
        while not self._queue.empty():          # nothing comes after both ends, but be exact
            item = self._queue.get()
            if not isinstance(item[0], _End):
                self._take(*item)
        self._pair(math.inf, emit)

    def _take(self, event: WindowEvent, put_at: float) -> None:
        s = event.stream
        if _centre(event) <= self._alone_until[s]:
            self.late[s] += 1                   # its partner was already decided alone
            return
        # when the window's last block arrived (its stream measured the latency at emit time)
        closed = put_at - event.latency_ms / 1e3 if event.latency_ms is not None else None
        self._pending[s].append((event, put_at, closed))

    def _pair(self, now: float, emit: Callable[[WindowEvent], None]) -> None:
        a, b = self.inputs
        pa, pb = self._pending[a], self._pending[b]
        while pa and pb:
            ea, eb = pa[0][0], pb[0][0]
            tol = 0.5 * min(ea.end - ea.start, eb.end - eb.start)
            if abs(_centre(ea) - _centre(eb)) <= tol:
                for s in self.inputs:
                    if self._missing[s] is not None:
                        self._say("sense_back", f"fusion: '{s}' is back: fused decisions resume "
                                                f"({self._missing[s]} windows decided alone meanwhile)")
                        self._missing[s] = None
                emit(self._fuse(pa.popleft(), pb.popleft()))
            elif _centre(ea) < _centre(eb):
                emit(self._single(pa.popleft()))    # b has moved past it: a's window has no partner
            else:
                emit(self._single(pb.popleft()))
        for s, other in ((a, b), (b, a)):
            waiting = self._pending[s]
            while waiting and (other in self._ended or now - waiting[0][1] > self.max_wait):
                item = waiting.popleft()
                if other in self._ended:
                    # Said at the second window decided alone after the other's end: two files
                    # a few ms apart leave one lone window at their ends, which says nothing.
                    self._after_end[s] += s not in self._ended
                    if other not in self._said_ended and self._after_end[s] == 2:
                        self._said_ended.add(other)
                        self._say("sense_ended", f"fusion: '{other}' has ended; deciding on '{s}' alone")
                else:
                    self._alone_until[other] = _centre(item[0]) + 0.5 * (item[0].end - item[0].start)
                    missing = self._missing[other]
                    if missing is None:
                        missing = 0
                        self.dropouts[other] += 1
                        self._say("sense_lost", f"fusion: no window from '{other}' within {self.max_wait:g} s; "
                                                f"deciding on '{s}' alone until it comes back")
                    self._missing[other] = missing + 1
                emit(self._single(item))

    def _say(self, kind: str, message: str) -> None:
        if self.on_event is not None:
            self.on_event(DriverEvent(kind, message, time.time(), source=FUSED_STREAM))

    def _fused_log_posteriors(self, ea: WindowEvent, eb: WindowEvent) -> np.ndarray:
        """Log-posteriors of a pair, in :attr:`classes` order (:func:`~supramodal.fusion.fuse_late`)."""
        fused = fuse_late(log_posteriors_of(ea)[None, :], log_posteriors_of(eb)[self._order_b][None, :], self._weight,
                          self.sharpness)
        post: np.ndarray = fused[0]     # (an ndarray's row is typed Any)
        return post

    def _fuse(self, item_a: _Pending, item_b: _Pending) -> WindowEvent:
        (ea, _, closed_a), (eb, _, closed_b) = item_a, item_b
        post = self._fused_log_posteriors(ea, eb)
        if self.kept_pairs is not None:
            self.kept_pairs.append((ea, eb))
        self.paired += 1
        closed = None if closed_a is None or closed_b is None else max(closed_a, closed_b)
        return self._event(post, (ea, eb), closed, frozenset((ea.flags | eb.flags) - {"alone"}))

    def _single(self, item: _Pending) -> WindowEvent:
        event, _, closed = item
        lp = log_posteriors_of(event)
        post = lp if event.stream == self.inputs[0] else lp[self._order_b]
        self.alone += 1
        return self._event(post, (event,), closed, event.flags | {"alone"})

    def _event(self, log_post: np.ndarray, events: Sequence[WindowEvent], closed: float | None,
               flags: Iterable[str]) -> WindowEvent:
        truth = next((e.truth for e in events if e.truth is not None), None)
        start, end = min(e.start for e in events), max(e.end for e in events)
        # the robot's own contact signal where the fusion has one, else either sense's touch
        in_contact = (self.touches.in_window(start, end) if self.touches is not None
                      else any(e.in_contact for e in events))
        said = self.decider.decide(log_post, in_contact, novel=any(e.unknown == "novel" for e in events))
        decision, pooled = said.decision, said.pooled
        self.tally.add(decision, None if pooled is None else pooled.label, truth)
        if pooled is not None and pooled.change is not None and self.on_event is not None:
            self.on_event(change_event(FUSED_STREAM, self.windows, pooled.change))
        latency = None
        if closed is not None:
            latency = (time.monotonic() - closed) * 1e3
            self.latencies.add(latency)
            latency = round(latency, 3)
        event = WindowEvent(FUSED_STREAM, self.windows, start, end, end, posteriors=np.exp(log_post),
                            decision=decision, confidence=said.confidence, pooled=pooled, truth=truth,
                            flags=frozenset(flags), latency_ms=latency, senses=tuple(e.stream for e in events),
                            in_contact=in_contact, classes=self.classes, log_posteriors=log_post,
                            guess=said.guess, unknown=said.reason)
        self.windows += 1
        return event

    # -- summary ----------------------------------------------------------------------------

    def summary(self) -> FusionSummary:
        """Return the fusion's part of the node's summary (a :class:`~.summaries.FusionSummary`)."""
        return FusionSummary(tuple(self.inputs), self.method, self.weight,
                             None if self.weight is None else self.sharpness, self.windows, self.paired, self.alone,
                             dict(self.late), dict(self.dropouts), self.tally.summary(), self.decider.summary(),
                             self.latencies.summary())


def _centre(event: WindowEvent) -> float:
    return 0.5 * (event.start + event.end)


class EarlyFusion(LateFusion):
    """Pairs two streams' windows as :class:`LateFusion` does, and decides each pair with one network.

    The network, on both windows' features, is the supramodal network,
    :class:`supramodal.fused_model.EarlyFusionModel`. A window decided alone (its partner did
    not come in time, or its stream runs alone) keeps its own stream's posteriors.

    Parameters
    ----------
    inputs, classes, max_wait, decision
        As :class:`LateFusion`; ``inputs[k]`` feeds the model's sense ``k``.
    model : EarlyFusionModel
        Knows the streams' textures (in any order); its senses' features are read from the
        window events by name. The fused decisions are pooled by its calibration's contact
        pooling (uncapped summed log-posteriors for an uncalibrated model), and their change
        threshold (``decision.change``) is fitted on its calibration's held-out windows, as a
        stream's is (:func:`~supramodal.decisions.fitted_change_threshold`; the detector's
        bound for a model file without them).
    window_seconds : float
        Seconds between windows (what a change rate per minute is per window).
    """

    method = "early"

    def __init__(self, inputs: Sequence[str], classes: Sequence[Sequence[str]], model: EarlyFusionModel,
                 max_wait: float | None = DEFAULT_MAX_WAIT,
                 decision: DecisionRules = DEFAULT_DECISION, window_seconds: float = DEFAULT_WINDOW) -> None:
        if sorted(model.classes) != sorted(classes[0]):
            raise InputError(f"the early-fusion model knows {list(model.classes)}, the streams {list(classes[0])}: "
                             "train it on the streams' textures")
        correlation, model_caps = (0.0, None) if model.calibration is None else model.calibration.contact_pooling
        caps = None
        if model_caps is not None:          # the model's class order -> the streams'
            order = [list(model.classes).index(name) for name in classes[0]]
            caps = np.asarray(model_caps)[np.ix_(order, order)]
        super().__init__(inputs, classes, DEFAULT_WEIGHT, max_wait, decision, correlation=correlation, caps=caps,
                         window_seconds=window_seconds,
                         change_threshold=fitted_change_threshold(model.calibration, decision, window_seconds))
        self.model = model
        self.weight = None
        self._order_model = np.array([list(model.classes).index(name) for name in self.classes])

    def _fused_log_posteriors(self, ea: WindowEvent, eb: WindowEvent) -> np.ndarray:
        a, b = self.model.senses
        assert ea.features is not None and eb.features is not None, "an early fusion's streams emit their features"
        va = np.stack([ea.features[f] for f in a.features])[None]
        vb = np.stack([eb.features[f] for f in b.features])[None]
        post: np.ndarray = self.model.log_posteriors(va, vb)[0][self._order_model]   # (indexed: typed Any)
        return post
