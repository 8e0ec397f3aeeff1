"""A stream: from one source's ring reader to one window event per window.

Ring reader -> channel mapping -> filterbank -> peaks -> windows -> classifier -> decisions -> one
:class:`~supramodal.node.runtime.events.WindowEvent` per window.

Threading rules
---------------
:meth:`Stream.process` runs on the stream's own processing thread and is the only code that
touches the pipeline, the model and the stream's counters. Frames the ring lost are replaced by
zeros, so stream time stays exact, and the windows they touch are flagged ``gap``. The events
go to ``emit`` (the graph's router: sinks behind their queues, and the fusion block's queue),
which never blocks.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from supramodal.decisions import (
    DEFAULT_DECISION,
    ContactDetector,
    Decider,
    DecisionRules,
    fitted_change_threshold,
)
from supramodal.drivers.base import DriverEvent
from supramodal.errors import InputError
from supramodal.model import TextureModel
from supramodal.node.runtime.events import TruthTally, WindowEvent, change_event
from supramodal.node.runtime.labels import Labels
from supramodal.node.runtime.latency import LatencyHistogram
from supramodal.node.runtime.ringbuffer import RingClosed
from supramodal.node.runtime.summaries import StreamSummary
from supramodal.pipeline import FeaturePipeline

if TYPE_CHECKING:   # for annotations only
    from supramodal.features import Windows
    from supramodal.fused_model import EarlyFusionModel
    from supramodal.node.runtime.contacts import ContactTimeline
    from supramodal.node.runtime.sources import Source

#: A window event's way out of a stream (the graph's router).
Emit = Callable[[WindowEvent], None]


def channel_mapper(mapping: str | int, driver_channels: int, bank_channels: int,
                   setting: str = "the scene's [driver] mapping") -> Callable[[np.ndarray], np.ndarray]:
    """Return ``f(frames (L, driver_channels)) -> model input`` for a scene's ``mapping``.

    ``"mono"`` (one channel, fanned out to every filter), ``"per-channel"`` (each
    physical channel through its own filter), ``"mean"`` (their mean, fanned
    out), an integer (that channel, fanned out), or ``"auto"`` (mono for one
    channel, per-channel when the counts match). ``setting`` names where the user sets
    the mapping, for the advice of a refusal (``"--mapping"`` on the command line).
    """
    if mapping == "auto":
        if driver_channels == 1:
            mapping = "mono"
        elif driver_channels == bank_channels:
            mapping = "per-channel"
        else:
            raise InputError(
                f"the source has {driver_channels} channels and the bank {bank_channels}: set {setting} to "
                "\"mean\" or a channel index (e.g. 0), or use a bank with as many channels")
    if mapping == "mono":
        if driver_channels != 1:
            raise InputError(f"mapping \"mono\" needs a one-channel source; this one has {driver_channels}: "
                             f"set {setting} to \"mean\" or a channel index")
        return lambda frames: frames[:, 0]
    if mapping == "per-channel":
        if driver_channels != bank_channels:
            raise InputError(f"mapping \"per-channel\" needs as many driver channels ({driver_channels}) "
                             f"as filters ({bank_channels})")
        return lambda frames: frames.T
    if mapping == "mean":
        return lambda frames: frames.mean(axis=1)
    if isinstance(mapping, int):
        if not 0 <= mapping < driver_channels:
            raise InputError(f"mapping channel {mapping} does not exist: "
                             f"the driver has channels 0..{driver_channels - 1}")
        return lambda frames: frames[:, mapping]
    raise InputError(f"unknown channel mapping {mapping!r}")


def refuse_uncalibrated(rules: DecisionRules, models: Sequence[TextureModel | EarlyFusionModel], where: str) -> None:
    """Refuse ``[decision]`` rules that need calibrated posteriors when one of ``models`` has none, naming the fix.

    Such rules: a confidence threshold, "unknown". ``models``: a stream's, or a fusion's.
    """
    asks = rules.calibrated_rules
    old = [m for m in models if not m.calibrated]
    if asks and old:
        whose = "the model is" if len(models) == 1 else f"{len(old)} of the {len(models)} models are"
        raise InputError(f"{where} {', '.join(asks)} needs calibrated posteriors, but {whose} uncalibrated (a "
                         "version 1 model file): retrain with `supramodal train`")


def decider_for(model: TextureModel, rules: DecisionRules, where: str = "[decision]",
                window_seconds: float | None = None) -> Decider:
    """Return the :class:`~supramodal.decisions.Decider` of a stream of ``model`` with the scene's decision rules.

    ``rules`` are the scene's ``[decision]``. Refuse rules the model cannot follow (a confidence threshold or
    "unknown" without a calibration, "unknown" without a novelty score), naming the fix.
    """
    refuse_uncalibrated(rules, (model,), where)
    threshold = None
    if rules.unknown:
        if model.novelty is None:
            raise InputError(f"{where} unknown needs a model with a novelty score: retrain it with `supramodal train`")
        threshold = model.novelty.threshold(rules.unknown)
    correlation, caps = model.calibration.contact_pooling if model.calibration is not None else (0.0, None)
    if window_seconds is None:
        window_seconds = model.window_samples / model.bank.fs
    return Decider(model.classes, rules, correlation, threshold, caps=caps, window_seconds=window_seconds,
                   change_threshold=fitted_change_threshold(model.calibration, rules, window_seconds))


class Stream:
    """One source's samples through the model, to window events.

    Parameters
    ----------
    name : str
        The stream's name (``[[stream]] name``; events carry it).
    source : node.runtime.sources.Source
        Its bank's rate must equal the source's rate.
    pipeline : supramodal.pipeline.FeaturePipeline
    model : TextureModel, optional
        Without it the stream emits feature windows.
    decision : supramodal.decisions.DecisionRules, optional
        How it decides (default: :data:`~supramodal.decisions.DEFAULT_DECISION`, each window alone).
    mapping : str or int
        Source channels to filter inputs, see :func:`channel_mapper`.
    labels : Labels, optional
        Truth labels; by default those the driver carries (a replayed session's).
    mapping_setting : str
        Where the scene sets ``mapping``, for the advice of a refusal (default ``"the scene's [driver]
        mapping"``, a one-source scene's).
    """

    def __init__(self, name: str, source: Source, pipeline: FeaturePipeline, model: TextureModel | None = None,
                 decision: DecisionRules = DEFAULT_DECISION, mapping: str | int = "auto",
                 labels: Labels | None = None, mapping_setting: str = "the scene's [driver] mapping") -> None:
        bank = pipeline.bank
        if abs(source.rate - bank.fs) > 1e-9 * bank.fs:
            raise InputError(f"the driver delivers {source.rate:g} Hz but the {bank.kind} bank runs at {bank.fs:g} Hz")
        if model is not None:
            model.check_pipeline(pipeline)
        self.name = name
        self.source = source
        self.pipeline = pipeline
        self.model = model
        self.labels = labels if labels is not None else Labels.of(source.driver)
        self.map = channel_mapper(mapping, source.driver.channels, bank.channels, mapping_setting)
        self.decision = decision
        self.decider = None
        self.contact = None
        #: The robot's own contact signal (``[decision] contact_from``), in place of :attr:`contact`.
        self.touches: ContactTimeline | None = None
        if model is not None:
            self.decider = decider_for(model, decision, f"stream {name!r}: [decision]")
            if decision.scope == "contact":
                self.contact = ContactDetector(pipeline.window_samples, decision.contact_threshold)
        self.feed = source.add_feed(f"stream {name}")
        self._window_marks: dict[int, set[str]] = {}
        self._expected = 0
        self._gap_windows: set[int] = set()
        self.latencies = LatencyHistogram()
        self.cpu = 0.0
        self.windows = 0
        self.tally = TruthTally()
        #: Told a texture ``change`` within a contact as an event (the graph puts it on its event thread).
        self.on_event: Callable[[DriverEvent], None] | None = None

    # -- processing thread --------------------------------------------------------------------

    def process(self, emit: Emit) -> None:
        """Read the source's ring until it closes, and ``emit`` a WindowEvent per window."""
        W = self.pipeline.window_samples
        reader = self.feed.reader
        while True:
            try:
                chunk = reader.read(timeout=0.05)
            except RingClosed:
                break
            if chunk is None:
                continue
            c0 = time.thread_time()
            start, data, filled = chunk
            if start > self._expected:
                # Frames lost in the ring: zeros keep stream time exact; the windows are flagged.
                # The ring counts them (lost, lost_filled), so that each keeps one fate: these
                # zeros are the stream's stand-in, not another count (see Source.frame_fates).
                gap = start - self._expected
                self._gap_windows.update(range(self._expected // W, (start - 1) // W + 1))
                self._step(np.zeros((gap, data.shape[1])), self._expected, emit)
            if filled is not None and filled.any():
                idx = np.flatnonzero(filled) + start
                self._gap_windows.update(np.unique(idx // W).tolist())
            self._step(data, start, emit)
            self._expected = start + data.shape[0]
            self.cpu += time.thread_time() - c0
        c0 = time.thread_time()
        self._emit(self.pipeline.finish(), None, emit)
        self.cpu += time.thread_time() - c0

    def _step(self, frames: np.ndarray, start: int, emit: Emit) -> None:
        # Cut the stream at each window end, wherever the ring read happened to end: the
        # pipeline then filters exactly one window's samples per pass, so the output does not
        # depend on thread timing, not even in its last bit (a pass over several windows rounds
        # differently). No latency is added: a window still runs when its last sample is in.
        W = self.pipeline.window_samples
        n = frames.shape[0]
        cut = 0
        while cut < n:
            end = min(n, ((start + cut) // W + 1) * W - start)
            x = self.map(frames[cut:end])
            windows = self.pipeline.process(x)
            flags = self.contact.process(x) if self.contact is not None and self.touches is None else None
            self._emit(windows, flags, emit)
            cut = end

    def _emit(self, windows: Windows, contact_flags: np.ndarray | None, emit: Emit) -> None:
        if not len(windows):
            return
        W, fs = self.pipeline.window_samples, self.pipeline.bank.fs
        log_post = novelty = None
        decider = self.decider
        if self.model is not None:
            assert decider is not None, "a stream with a model has its decider (made in __init__)"
            log_post = self.model.log_posteriors(windows.values)
            if decider.novelty_threshold is not None:
                novelty = self.model.novelty_score(windows.values)
        for i, w in enumerate(windows.numbers.tolist()):
            end = (w + 1) * W
            truth = self.labels.at((w + 0.5) * W / fs)
            block = self.feed.block_of(end - 1)     # the block that completed the window
            offset, slope = self.source.line() if block is None else block[2]
            start_t, end_t = offset + w * W * slope, offset + end * slope       # on common time
            if self.touches is not None:
                in_contact = self.touches.in_window(start_t, end_t)
            else:
                in_contact = bool(contact_flags[i]) if contact_flags is not None and i < len(contact_flags) else True
            post = decision = confidence = pooled = guess = reason = None
            if log_post is not None and decider is not None:
                post = np.exp(log_post[i])
                novel = novelty is not None and bool(novelty[i] > decider.novelty_threshold)
                said = decider.decide(log_post[i], in_contact, novel)
                decision, confidence, guess, reason, pooled = (said.decision, said.confidence, said.guess,
                                                               said.reason, said.pooled)
                self.tally.add(decision, None if pooled is None else pooled.label, truth)
                if pooled is not None and pooled.change is not None and self.on_event is not None:
                    self.on_event(change_event(self.name, w, pooled.change, W))
            flags = set(self._marks_of(w, W))
            if w in self._gap_windows:
                flags.add("gap")
                self._gap_windows.discard(w)
            features = {f: windows.values[i, k] for k, f in enumerate(windows.features)}
            latency = None if block is None else self._latency_ms(block[1])
            event = WindowEvent(self.name, w, start_t, end_t, end / fs,
                                features=features, posteriors=post, decision=decision, confidence=confidence,
                                pooled=pooled, truth=truth, log_posteriors=None if log_post is None else log_post[i],
                                guess=guess, unknown=reason,
                                novelty=None if novelty is None else round(float(novelty[i]), 4),
                                flags=frozenset(flags), latency_ms=latency,
                                in_contact=in_contact, classes=self.model.classes if self.model is not None else ())
            self.windows += 1
            emit(event)

    def _marks_of(self, w: int, W: int) -> list[str]:
        """Return the driver's marks ("restart", "overrun") in window ``w``."""
        end = (w + 1) * W
        marks = self.feed.marks
        while marks and marks[0][0] < end:
            index, kind = marks.popleft()
            self._window_marks.setdefault(index // W, set()).add(kind)
        for old in [k for k in self._window_marks if k < w]:  # windows never emitted (end of stream)
            del self._window_marks[old]
        return sorted(self._window_marks.pop(w, ()))

    def _latency_ms(self, arrival: float) -> float:
        """Now minus the arrival of the block that completed the window."""
        lat = (time.monotonic() - arrival) * 1e3
        self.latencies.add(lat)
        return round(lat, 3)

    # -- summary ------------------------------------------------------------------------------

    def summary(self) -> StreamSummary:
        """Return this stream's part of the node's summary (see :meth:`Graph.summary`)."""
        stream = self._expected / self.pipeline.bank.fs
        source = self.source
        return StreamSummary(
            source=source.name, windows=self.windows, stream_seconds=stream, accuracy=self.tally.summary(),
            decisions=self.decider.summary() if self.decider is not None else None,
            frames=source.frame_fates(self.feed),
            nonfinite_replaced=self.pipeline.filterbank.nonfinite_count,
            out_of_range_replaced=self.pipeline.filterbank.out_of_range_count,
            partial_window_samples=self.pipeline.partial_samples,
            latency_ms=self.latencies.summary(),
            real_time_factor=self.cpu / stream if stream else 0.0,
            driver=dict(source.driver.stats()),
            ring={k: v for k, v in source.ring.stats().items() if isinstance(v, (int, float))})
