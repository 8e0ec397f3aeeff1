"""What a run counts, as typed records: a stream's, the fusion's and the run's summary.

:meth:`Graph.summary <supramodal.node.runtime.graph.Graph.summary>` makes a :class:`RunSummary` of the
:class:`StreamSummary` of each stream and the :class:`FusionSummary` of the fusion block; the sinks read
their fields, and write :meth:`~supramodal.records.JsonRecord.to_dict` where they write JSON. Each record
also reads as that dict, read-only (:class:`~supramodal.records.JsonRecord`). The leaves that are open
sets of counts (a driver's own statistics, the ring's, a sink's, frame fates) stay mappings of name to
count: their keys belong to the part that counts them, documented there.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from supramodal.decisions import DecisionCounts
from supramodal.records import JsonRecord, JsonValue

__all__ = ["Accuracy", "ClockSummary", "FusionHealth", "FusionSummary", "Health", "RunSummary", "StreamHealth",
           "StreamSummary"]

#: Counts by name (frame fates, driver events per kind, late windows per stream, ...).
Counts = Mapping[str, int]
#: A latency histogram's ``{"p50", "p99", "max", "count"}`` in ms, or None with none recorded.
Latency = Mapping[str, float] | None
#: A part's own statistics, as that part documents them (a driver's, the ring's, a sink's, a tap's).
Stats = Mapping[str, JsonValue]


@dataclass(frozen=True, eq=False)
class Accuracy(JsonRecord):
    """Decisions against the truth, where a driver knows it (a stream's or the fusion's).

    Attributes
    ----------
    window_accuracy : float or None
        Of the labelled windows, the share decided right; None with no truth.
    labelled_windows : int
        Windows with a truth label.
    accumulated_accuracy : float or None
        Of the labelled windows with a pooled decision, the share whose pooled decision was right.
    """

    window_accuracy: float | None
    labelled_windows: int
    accumulated_accuracy: float | None

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the accuracy as the summary's JSON has it."""
        return {"window_accuracy": self.window_accuracy, "labelled_windows": self.labelled_windows,
                "accumulated_accuracy": self.accumulated_accuracy}


@dataclass(frozen=True, eq=False)
class ClockSummary(JsonRecord):
    """A source's clock, as the run's summary and the graph's health say it (a source with a host timebase).

    Attributes
    ----------
    ppm : float
        The source's rate error, parts per million (3 decimals).
    jitter_ms, delay_ms : float
        The spread and the median of the recent blocks' delays above the fitted line, ms (3 decimals).
    blocks : int
        Blocks the clock has taken.
    fitted : bool
        Whether the rate comes from a fit rather than the nominal rate.
    skipped : int
        Block stamps out of order (a driver's fill), not taken as measurements.
    """

    ppm: float
    jitter_ms: float
    delay_ms: float
    blocks: int
    fitted: bool
    skipped: int

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the clock's estimate as the summary's JSON has it."""
        return {"ppm": self.ppm, "jitter_ms": self.jitter_ms, "delay_ms": self.delay_ms, "blocks": self.blocks,
                "fitted": self.fitted, "skipped": self.skipped}


@dataclass(frozen=True, eq=False)
class StreamSummary(JsonRecord):
    """One stream's part of a run's summary: what it windowed, decided and lost.

    Attributes
    ----------
    source : str
        The name of the source the stream reads (not written: the run's ``clocks`` are by source).
    windows : int
        Windows emitted.
    stream_seconds : float
        Seconds of signal the stream was offered.
    accuracy : Accuracy
        Decisions against the truth.
    decisions : DecisionCounts or None
        What its decider counted; None for a stream without a model (feature windows).
    frames : mapping of str to int
        Every frame's fate (:meth:`Source.frame_fates <supramodal.node.runtime.sources.Source.frame_fates>`).
    nonfinite_replaced, out_of_range_replaced : int
        Samples the filterbank replaced (NaN/inf; beyond the rails).
    partial_window_samples : int
        Samples of an unfinished last window, never decided.
    latency_ms : mapping of str to float, or None
        From the block that completed a window to its event.
    real_time_factor : float
        Processing CPU seconds per second of signal.
    driver, ring : mapping
        The driver's own statistics; the ring's numeric ones.
    """

    source: str
    windows: int
    stream_seconds: float
    accuracy: Accuracy
    decisions: DecisionCounts | None
    frames: Counts
    nonfinite_replaced: int
    out_of_range_replaced: int
    partial_window_samples: int
    latency_ms: Latency
    real_time_factor: float
    driver: Stats
    ring: Stats

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the stream's counts as the summary's JSON has them (accuracy and decisions flat)."""
        return {"windows": self.windows, "stream_seconds": self.stream_seconds, **self.accuracy.to_dict(),
                **(self.decisions.to_dict() if self.decisions is not None else {}),
                "frames": dict(self.frames), "nonfinite_replaced": self.nonfinite_replaced,
                "out_of_range_replaced": self.out_of_range_replaced,
                "partial_window_samples": self.partial_window_samples,
                "latency_ms": None if self.latency_ms is None else dict(self.latency_ms),
                "real_time_factor": self.real_time_factor, "driver": dict(self.driver), "ring": dict(self.ring)}


@dataclass(frozen=True, eq=False)
class FusionSummary(JsonRecord):
    """The fusion block's part of a run's summary.

    Attributes
    ----------
    inputs : tuple of str
        The fused streams, in the model's order.
    method : str
        ``"late"`` or ``"early"``.
    weight, sharpness : float or None
        The late fusion's learned weight and sharpness; None for an early fusion.
    windows : int
        Fused decisions: ``paired`` from both senses, ``alone`` from one.
    paired, alone : int
        See ``windows``.
    late : mapping of str to int
        Windows per stream whose partner was already decided alone (left out).
    dropouts : mapping of str to int
        Times each stream stopped coming in time (each said as a ``sense_lost`` event).
    accuracy : Accuracy
        Fused decisions against the truth.
    decisions : DecisionCounts
        What the fusion's decider counted.
    latency_ms : mapping of str to float, or None
        From the later window's last block to the fused decision.
    """

    inputs: tuple[str, ...]
    method: str
    weight: float | None
    sharpness: float | None
    windows: int
    paired: int
    alone: int
    late: Counts
    dropouts: Counts
    accuracy: Accuracy
    decisions: DecisionCounts
    latency_ms: Latency

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the fusion's counts as the summary's JSON has them (accuracy and decisions flat)."""
        return {"inputs": list(self.inputs), "method": self.method, "weight": self.weight,
                "sharpness": self.sharpness, "windows": self.windows, "paired": self.paired, "alone": self.alone,
                "late": dict(self.late), "dropouts": dict(self.dropouts), **self.accuracy.to_dict(),
                **self.decisions.to_dict(), "latency_ms": None if self.latency_ms is None else dict(self.latency_ms)}


@dataclass(frozen=True, eq=False)
class RunSummary(JsonRecord):
    """A run's summary: each stream's, the fusion's, and the graph's own counts (:meth:`Graph.summary`).

    The fields are the same whatever the graph; the JSON form (:meth:`to_dict`) keeps the shape a reader of
    a one-stream node knows: with one stream and no fusion, that stream's counts are at the top level and
    its source's clock under ``clock``; otherwise ``windows`` (all streams'), ``stream_seconds`` (the
    longest), the streams under ``streams``, the sources' clocks under ``clocks``, the fusion's counts
    under ``fusion``.

    Attributes
    ----------
    streams : mapping of str to StreamSummary
        By stream name (``"main"`` for a one-source scene); empty for a relay (taps only).
    fusion : FusionSummary or None
        The fusion block's; None without one.
    clocks : mapping of str to ClockSummary
        Per source with a host timebase, its clock's estimate (:meth:`Source.clock_summary`).
    windows : int
        All streams' windows.
    stream_seconds : float
        The longest stream's seconds (a relay's: its longest source's).
    wall_seconds : float
        The run's wall time.
    recorded : tuple of str, or None
        The files the recorders wrote; None when none did.
    stopped_by : str or None
        What stopped the run before its sources ended (a signal, ``max_seconds``, a stop).
    events : mapping
        Driver events: ``counts`` and ``dropped`` per kind (``source/kind`` with several sources).
    sinks : tuple of mapping
        What each queued sink wrote, dropped and raised (the sinks whose ``stats()`` is not None).
    contacts : tuple of mapping, or None
        Per contact signal its timeline's and listener's counts; None without one.
    taps : mapping of str to mapping, or None
        Per tap its own counts and ``frames``, every frame's fate as its reader saw it; None without taps.
    """

    streams: Mapping[str, StreamSummary]
    fusion: FusionSummary | None
    clocks: Mapping[str, ClockSummary]
    windows: int
    stream_seconds: float
    wall_seconds: float
    recorded: tuple[str, ...] | None
    stopped_by: str | None
    events: Mapping[str, Counts]
    sinks: tuple[Stats, ...]
    contacts: tuple[Stats, ...] | None = None
    taps: Mapping[str, Stats] | None = None

    @property
    def one_stream(self) -> StreamSummary | None:
        """Return the stream of a one-stream node (one stream, no fusion), else None."""
        if len(self.streams) == 1 and self.fusion is None:
            return next(iter(self.streams.values()))
        return None

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the summary as it is written: a one-stream node's counts flat, several streams' by name."""
        common: dict[str, JsonValue] = {
            "wall_seconds": self.wall_seconds, "recorded": None if self.recorded is None else list(self.recorded),
            "stopped_by": self.stopped_by, "events": {k: dict(v) for k, v in self.events.items()},
            "sinks": [dict(s) for s in self.sinks]}
        if self.contacts is not None:
            common["contacts"] = [dict(c) for c in self.contacts]
        if self.taps is not None:
            common["taps"] = {name: dict(t) for name, t in self.taps.items()}
        one = self.one_stream
        if one is not None:
            clock = self.clocks.get(one.source)
            return {**one.to_dict(), **({"clock": dict(clock)} if clock else {}), **common}
        return {"windows": self.windows, "stream_seconds": self.stream_seconds,
                "streams": {name: s.to_dict() for name, s in self.streams.items()},
                "clocks": {name: dict(c) for name, c in self.clocks.items()},
                "fusion": None if self.fusion is None else self.fusion.to_dict(), **common}


@dataclass(frozen=True, eq=False)
class StreamHealth(JsonRecord):
    """One stream's counters while the graph runs (:class:`Health`).

    Attributes
    ----------
    windows : int
        Windows emitted so far.
    frames : mapping of str to int
        Every frame's fate so far (:meth:`Source.frame_fates <supramodal.node.runtime.sources.Source.frame_fates>`).
    latency_ms : mapping of str to float, or None
        From the block that completed a window to its event.
    source : str
        The source the stream reads.
    """

    windows: int
    frames: Counts
    latency_ms: Latency
    source: str

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the counters as the view's and ROS 2's health messages have them."""
        return {"windows": self.windows, "frames": dict(self.frames),
                "latency_ms": None if self.latency_ms is None else dict(self.latency_ms), "source": self.source}


@dataclass(frozen=True, eq=False)
class FusionHealth(JsonRecord):
    """The fusion block's pairing counters while the graph runs (:class:`Health`; as :class:`FusionSummary`)."""

    windows: int
    paired: int
    alone: int
    late: Counts
    dropouts: Counts
    latency_ms: Latency

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the counters as the view's and ROS 2's health messages have them."""
        return {"windows": self.windows, "paired": self.paired, "alone": self.alone, "late": dict(self.late),
                "dropouts": dict(self.dropouts),
                "latency_ms": None if self.latency_ms is None else dict(self.latency_ms)}


@dataclass(frozen=True, eq=False)
class Health(JsonRecord):
    """What the graph counts, read while it runs (:meth:`Graph.health`): what its summary says at the end.

    Attributes
    ----------
    streams : mapping of str to StreamHealth
        By stream name.
    clocks : mapping of str to ClockSummary
        Per source with a host timebase, its clock's estimate.
    fusion : FusionHealth or None
        The fusion block's pairing counters; None without one.
    sinks : tuple of mapping
        Each counting sink's stats (``written``, ``dropped_windows``, ``dropped_events``, ``errors``, ...).
    """

    streams: Mapping[str, StreamHealth]
    clocks: Mapping[str, ClockSummary]
    fusion: FusionHealth | None
    sinks: tuple[Stats, ...]

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the counters as the view's and ROS 2's health messages have them."""
        return {"streams": {name: s.to_dict() for name, s in self.streams.items()},
                "clocks": {name: dict(c) for name, c in self.clocks.items()},
                "fusion": None if self.fusion is None else self.fusion.to_dict(),
                "sinks": [dict(s) for s in self.sinks]}
