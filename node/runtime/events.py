"""What the node tells its sinks: window results and driver events on their way to the sinks.

Window results are :class:`WindowEvent`, one typed event per window and stream; driver events are
rate-limited per kind and counted exactly.

Threading rules
---------------
An :class:`EventLimiter` is used by one thread (the node's event thread); it
holds no lock and calls nothing.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

from supramodal.decisions import PooledDecision, TextureChange
from supramodal.drivers.base import DriverEvent
from supramodal.errors import InputError
from supramodal.node.runtime.summaries import Accuracy
from supramodal.records import JsonValue

#: Event kinds that are decisions, not a device's health: a texture ``change`` within a contact
#: (:func:`change_event`). Each is passed on (never folded by :class:`EventLimiter`) and is no
#: source's state.
DECISION_EVENTS = frozenset({"change"})


#: How grave each kind of driver event is, said here once: the page colours an event's banner and its
#: line in the event list by it, and says nothing of its own about kinds. ``"alarm"`` (red): samples
#: were lost, filled or made up, or a source is gone; ``"warning"`` (amber): the stream goes on, but
#: something wants a look (a setting, a sense decided alone); ``"info"`` (blue): news, nothing lost (a
#: port opened, a source back, a texture change). The kinds are those the drivers document
#: (:class:`~supramodal.drivers.base.DriverEvent`), the fusion's and the decisions' (:data:`DECISION_EVENTS`).
SEVERITY: dict[str, str] = {
    **dict.fromkeys(("unplug", "gap", "overrun", "overflow", "dropped", "restart", "channels", "version", "silence",
                     "error", "nan"), "alarm"),
    **dict.fromkeys(("sense_lost", "backlog", "baudrate", "level", "underflow", "block", "reopen", "contact"),
                    "warning"),
    **dict.fromkeys(("open", "close", "reconnect", "waiting", "notice", "sense_back", "sense_ended", "change"),
                    "info"),
}
#: The severity of a kind :data:`SEVERITY` does not name (a new driver's): shown in amber, so that it is
#: neither an alarm that cries wolf nor news that hides a fault.
UNKNOWN_SEVERITY = "warning"


def severity(kind: str) -> str:
    """How grave a driver event of ``kind`` is: ``"alarm"``, ``"warning"`` or ``"info"`` (:data:`SEVERITY`)."""
    return SEVERITY.get(kind, UNKNOWN_SEVERITY)


class EventLimiter:
    """At most ``burst`` events per kind per ``interval`` seconds; repeats folded into counts.

    Events of a kind pass at once while fewer than ``burst`` of that kind passed
    in the last ``interval`` (so rare events, such as two unplugs a second
    apart, are each shown as they happen). Beyond that they are held back and
    counted; the next one passed (an event once there is room again, :meth:`due`
    once there is, or :meth:`flush` at the end) carries them: its ``count`` is 1
    + those held back, its message the latest. A board spewing errors gives at
    most ``burst`` lines per kind per interval, and nothing is lost:
    :attr:`counts` holds every occurrence per kind. A kind of :data:`DECISION_EVENTS` always passes:
    it is a decision (at most one per window), not a device's noise.

    Parameters
    ----------
    interval : float, default 1.0
        Seconds.
    burst : int, default 3
    clock : callable, default time.monotonic
    """

    def __init__(self, interval: float = 1.0, burst: int = 3, clock: Callable[[], float] = time.monotonic) -> None:
        self.interval = float(interval)
        self.burst = int(burst)
        self._clock = clock
        # keys: kind, or source/kind for events that name their source
        self._passed: dict[str, deque[float]] = {}  # key -> when its last (up to burst) events passed
        self._held: dict[str, DriverEvent] = {}  # key -> latest held event, count = occurrences held
        self.counts: Counter[str] = Counter()  # key -> occurrences seen (dropped ones included)
        self.dropped: Counter[str] = Counter()  # key -> occurrences a driver dropped before we saw them

    def add(self, ev: DriverEvent) -> DriverEvent | None:
        """Take one event; return what to show now (it, carrying any held back), or None."""
        key = _key(ev.source, ev.kind)
        self.counts[key] += ev.count
        if ev.kind in DECISION_EVENTS:
            return ev
        now = self._clock()
        held = self._held.pop(key, None)
        if held is not None:
            ev = replace(ev, count=ev.count + held.count)
        if self._room(key, now):
            return ev
        self._held[key] = ev
        return None

    def _room(self, key: str, now: float) -> bool:
        """May an event of ``key`` pass now? If so, note that it does."""
        passed = self._passed.setdefault(key, deque())
        while passed and now - passed[0] >= self.interval:
            passed.popleft()
        if len(passed) >= self.burst:
            return False
        passed.append(now)
        return True

    def add_dropped(self, dropped: dict[str, int], source: str | None = None) -> None:
        """Count events a driver's bounded log dropped (per kind) before they were taken."""
        for kind, n in dropped.items():
            self.counts[_key(source, kind)] += n
            self.dropped[_key(source, kind)] += n

    def due(self) -> list[DriverEvent]:
        """Held events whose kind's interval is over: show them now."""
        now = self._clock()
        keys = [key for key in self._held if self._room(key, now)]
        return [self._held.pop(key) for key in keys]

    def flush(self) -> list[DriverEvent]:
        """Every held event, whatever the time (the stream has ended)."""
        out = list(self._held.values())
        self._held.clear()
        return out

    def summary(self) -> dict[str, dict[str, int]]:
        """Return ``{"counts": {kind: occurrences}, "dropped": {kind: n}}`` for the node's summary.

        Kinds are named ``source/kind`` for events that name their source.
        """
        return {"counts": dict(sorted(self.counts.items())), "dropped": dict(sorted(self.dropped.items()))}


#: The name of a one-source scene's stream (events carry it in ``stream``).
MAIN_STREAM = "main"
#: The name of the fusion block's stream.
FUSED_STREAM = "fused"


def _key(source: str | None, kind: str) -> str:
    """Events are limited and counted per source and kind."""
    return kind if source is None else f"{source}/{kind}"


@dataclass(frozen=True)
class WindowEvent:
    """One window's result on one stream: what every sink receives per window.

    Attributes
    ----------
    stream : str
        The stream's name (a scene's ``[[stream]] name``; ``"main"`` for a one-source scene,
        ``"fused"`` for the fusion block's decisions).
    window : int
        Window number on that stream, from 0.
    start, end : float
        The window's first sample and the sample after its last, seconds on the graph's common
        clock (see :mod:`supramodal.node.runtime.sources`; for a one-source scene, stream time).
    t : float
        End of the window in the stream's own time, seconds (``(window + 1) * W / fs``).
    features : mapping of str to array_like, or None
        Per feature, the window's values over the channels (a stream's: a row of its windows' array); None
        on a fused event.
    posteriors : ndarray or None
        Normalised class posteriors (a model's, or the fused ones); None without a model.
    classes : tuple of str
        The class names in the order of ``posteriors`` (``()`` without a model).
    decision : str or None
        The winning class (winner-take-all over ``posteriors``).
    confidence : float or None
        Its posterior.
    pooled : supramodal.decisions.PooledDecision or None
        The decision pooled over windows, with a ``[decision] scope`` other than ``"window"``
        (JSON ``"accumulated"``).
    truth : str or None
        The texture really there, where the source carries labels.
    flags : frozenset of str
        ``"gap"`` (frames filled or lost), ``"restart"``, ``"overrun"`` (the driver's marks);
        on a fused event also ``"alone"`` (one sense decided: the other's window did not come
        in time or its source is down).
    latency_ms : float or None
        Host time from the arrival of the block that completed the window to the event, ms.
    senses : tuple of str
        The streams a fused decision used; ``()`` on a stream's own event.
    in_contact : bool
        Whether the contact detector saw a touch in the window (True without one); a fused
        event is in contact when either sense is.
    log_posteriors : ndarray or None
        The log of ``posteriors``, computed without underflow (what fusion and pooling use).
    guess : str or None
        The winner when ``decision`` is ``"unknown"`` (None on a tie or otherwise).
    unknown : str or None
        Why the decision is ``"unknown"``: ``"novel"`` (unlike every training texture),
        ``"unsure"`` (below ``[decision] unknown_below``) or ``"tie"``; None otherwise.
    novelty : float or None
        The window's novelty score, where ``[decision] unknown`` asks for it.
    """

    stream: str
    window: int
    start: float
    end: float
    t: float
    features: Mapping[str, ArrayLike] | None = None
    posteriors: np.ndarray | None = None
    decision: str | None = None
    confidence: float | None = None
    pooled: PooledDecision | None = None
    truth: str | None = None
    flags: frozenset[str] = frozenset()
    latency_ms: float | None = None
    senses: tuple[str, ...] = ()
    in_contact: bool = True
    classes: tuple[str, ...] = ()
    log_posteriors: np.ndarray | None = None
    guess: str | None = None
    unknown: str | None = None
    novelty: float | None = None

    def as_dict(self) -> dict[str, JsonValue]:
        """Return the event as a JSON-ready dict.

        Its keys: ``{"stream", "t", "window", "start", "end"}``, then ``predicted`` and ``confidence``
        (and, where set, ``unknown`` and ``guess``, ``novelty``, and ``accumulated``, the pooled decision)
        with a model, else ``features``; ``senses`` where set; ``truth``, each flag as ``true``,
        ``latency_ms``.
        """
        out: dict[str, JsonValue] = {"stream": self.stream, "t": round(self.t, 6), "window": self.window,
                                     "start": round(self.start, 6), "end": round(self.end, 6)}
        if self.decision is not None:
            # a decision comes with its confidence (the streams and the fusion set both)
            out.update(predicted=self.decision, confidence=round(cast(float, self.confidence), 4))
            if self.unknown is not None:
                out.update(unknown=self.unknown, guess=self.guess)
            if self.novelty is not None:
                out["novelty"] = self.novelty
            if self.pooled is not None:
                out["accumulated"] = self.pooled.to_dict()
        elif self.features is not None:
            out["features"] = {name: np.asarray(v).tolist() for name, v in self.features.items()}
        if self.senses:
            out["senses"] = list(self.senses)
        out["truth"] = self.truth
        for flag in sorted(self.flags):
            out[flag] = True
        out["latency_ms"] = self.latency_ms
        return out


def change_event(stream: str, window: int, change: TextureChange, window_samples: int | None = None) -> DriverEvent:
    """Return the event a stream (or the fusion) says when its decider re-decides within a contact.

    This is ``[decision] change``'s event: kind ``"change"``, its source the stream, so that every sink takes it
    as it takes a driver's event (a line on stderr, a JSON line, the ROS 2 events topic, the view's banner).

    Parameters
    ----------
    stream : str
        The stream whose decision changed (``"fused"``: the fusion's).
    window : int
        The window in which the change was signalled.
    change : supramodal.decisions.TextureChange
        The pooled decision's change (``after``: the windows since the change began, the signalling
        window counted).
    window_samples : int, optional
        Samples per window: the event's ``stream_index`` is then the sample at which the change began
        (None: the fusion, which has no samples of its own).
    """
    began = window + 1 - change.after
    stream_index = None if window_samples is None else began * window_samples
    return DriverEvent("change", f"{stream}: the texture changed from {change.from_} to {change.to} at window "
                                 f"{began} (said at window {window}): a new decision starts there",
                       time.time(), stream_index=stream_index, source=stream)


def log_posteriors_of(event: WindowEvent) -> np.ndarray:
    """Return a window event's log-posteriors.

    Those it carries (a stream's and the fusion's events do: never clipped), else the log of its
    posteriors, refused where one is exactly 0 (an event made elsewhere, e.g. by hand: its log would be
    -inf and poison every sum it enters).
    """
    if event.log_posteriors is not None:
        return np.asarray(event.log_posteriors, dtype=np.float64)
    with np.errstate(divide="ignore"):
        lp = np.log(np.asarray(event.posteriors, dtype=np.float64))
    if not np.isfinite(lp).all():
        raise InputError(f"a window of {event.stream!r} carries posteriors of exactly 0 and no log-posteriors: "
                         "its log-posteriors are needed (a stream's events carry them)")
    return lp


class TruthTally:
    """Decisions against the truth, where a driver knows it: per window, and of the pooled decision.

    The pooled decision is a stream's or a fusion's. One processing thread writes, the summary reads it
    after.
    """

    def __init__(self) -> None:
        self.correct = self.labelled = self.pooled_correct = self.pooled_labelled = 0

    def add(self, decision: str | None, pooled_label: str | None, truth: str | None) -> None:
        """One window's decision and its pooled decision's label (None: no pooled decision)."""
        if truth is None:
            return
        self.labelled += 1
        self.correct += decision == truth
        if pooled_label is not None:
            self.pooled_labelled += 1
            self.pooled_correct += pooled_label == truth

    def summary(self) -> Accuracy:
        """Return the accuracy so far (None where nothing was labelled)."""
        return Accuracy(self.correct / self.labelled if self.labelled else None, self.labelled,
                        self.pooled_correct / self.pooled_labelled if self.pooled_labelled else None)
