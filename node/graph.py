"""The running node: driver thread -> ring buffer -> processing thread -> sinks.

Threads and real-time rules
---------------------------
* The *driver thread* only moves blocks: ``driver.read()`` -> ``ring.write()``,
  noting each block's arrival time and its restart/overrun marks. It never waits
  on processing: when the
  processing thread lags by more than the ring's capacity, the ring's overrun
  policy drops frames, and every dropped frame is counted. After every read (a
  block or a timeout, at most 50 ms apart) it takes the driver's new events
  (``take_events()``) and queues them, without waiting.
* The *event thread* hands the queued driver events to the sinks
  (``sink.event(ev)``), at most one per kind per second (:class:`node.events.EventLimiter`:
  repeats are folded into the next one's ``count``), so neither the driver nor
  the processing thread ever waits on a sink for an event.
* The *processing thread* reads the ring, runs the model blocks (mapping ->
  filterbank -> peaks -> windows -> classifier -> decisions) and calls the
  sinks. Frames lost in the ring are replaced by zeros, so stream time stays
  exact and the windows they touch are flagged ``gap``.
* Every frame of the stream has one fate in the summary's ``frames``:
  delivered, filled or dropped (see :meth:`Node._frame_fates`).
* The caller's thread (:meth:`Node.run`) starts both, waits, and handles the
  stop request (Ctrl-C, SIGTERM, :meth:`Node.stop`): the driver stops, what is
  already buffered is processed, the summary is written, nothing is left running.
"""

from __future__ import annotations

import collections
import math
import queue
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from supramodal.drivers.base import Block, DriverClosed
from supramodal.node.events import EventLimiter
from supramodal.node.latency import LatencyHistogram
from supramodal.node.ringbuffer import RingBuffer, RingClosed
from supramodal.decisions import ContactDetector, DecisionAccumulator, window_decision
from supramodal.errors import InputError, SupramodalError
from supramodal.model import TextureModel
from supramodal.pipeline import FeaturePipeline


class NodeError(SupramodalError, RuntimeError):
    """A thread of the node failed; the message says which and why."""


def channel_mapper(mapping, driver_channels: int, bank_channels: int, setting: str = "the scene's [driver] mapping"):
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
            raise InputError(f"mapping channel {mapping} does not exist: the driver has channels 0..{driver_channels - 1}")
        return lambda frames: frames[:, mapping]
    raise InputError(f"unknown channel mapping {mapping!r}")


@dataclass
class Labels:
    """Truth labels as time ranges ``(start_s, end_s, name)``, for accuracy where they are known."""

    ranges: list[tuple[float, float, str]] = field(default_factory=list)

    @classmethod
    def of(cls, driver) -> "Labels":
        """The labels a driver carries (a replayed session's), or none."""
        return cls([(lab.start, lab.end, lab.label) for lab in getattr(driver, "labels", ())])

    def at(self, t: float) -> str | None:
        for start, end, name in self.ranges:
            if start <= t < end:
                return name
        return None


def _head(block: Block, n: int) -> Block:
    """The first ``n`` frames of a block."""
    n = max(n, 0)
    filled = None if block.filled is None else block.filled[:n]
    return Block(block.data[:n], block.start, block.arrival, filled,
                 tuple(i for i in block.restarts if i < n), tuple(i for i in block.overruns if i < n))


class Node:
    """One stream: a driver, the model blocks and the sinks, run on two threads.

    Parameters
    ----------
    driver : drivers.base.Driver
    pipeline : supramodal.pipeline.FeaturePipeline
        Its bank's rate must equal the driver's rate.
    sinks : list of node.sinks.Sink
    model : TextureModel, optional
        Without it the node emits feature windows.
    decision : dict, optional
        ``scope``, ``n``, ``method``, ``contact_threshold`` (see supramodal.decisions).
    mapping : str or int
        Driver channels to filter inputs, see :func:`channel_mapper`.
    labels : Labels, optional
        Truth labels; by default those the driver carries (a replayed session's).
    buffer_seconds : float
        Ring capacity.
    recorder : node.recorder.SessionRecorder, optional
        Records the raw driver frames (a second ring reader, on its own thread).
    overrun : {"drop-oldest", "drop-newest", "block"}
        "block" makes the driver thread wait for space: right for replay, where
        no sample need be lost; live drivers drop and count instead.
    """

    def __init__(self, driver, pipeline: FeaturePipeline, sinks, model: TextureModel | None = None,
                 decision: dict | None = None, mapping="auto", labels: Labels | None = None,
                 buffer_seconds: float = 2.0, overrun: str = "drop-oldest", recorder=None) -> None:
        bank = pipeline.bank
        if abs(driver.rate - bank.fs) > 1e-9 * bank.fs:
            raise InputError(f"the driver delivers {driver.rate:g} Hz but the {bank.kind} bank runs at {bank.fs:g} Hz")
        if model is not None:
            model.check_pipeline(pipeline)
        self.driver = driver
        self.pipeline = pipeline
        self.sinks = list(sinks)
        for s in self.sinks:
            if hasattr(s, "on_reader_left"):      # a queued sink whose reader may leave (`| head`)
                s.on_reader_left = self._sink_reader_left
        self.model = model
        self.labels = labels if labels is not None else Labels.of(driver)
        self.map = channel_mapper(mapping, driver.channels, bank.channels)
        decision = {"scope": "window", "n": 10, "method": "log", "contact_threshold": 0.01, **(decision or {})}
        self.decision = decision
        self.accumulator = None
        self.contact = None
        if model is not None and decision["scope"] != "window":
            self.accumulator = DecisionAccumulator(len(model.classes), decision["scope"], decision["n"], decision["method"])
            if decision["scope"] == "contact":
                self.contact = ContactDetector(pipeline.window_samples, decision["contact_threshold"])
        capacity = max(int(buffer_seconds * driver.rate), 1)
        self.ring = RingBuffer(capacity, driver.channels, dtype=np.float64, overrun=overrun)
        self._reader = self.ring.add_reader("processing")
        self.recorder = recorder
        if recorder is not None:
            self._recorder_reader = self.ring.add_reader("recorder")
            recorder.attach(driver.rate, driver.channels, lambda: self.ring.written, labels=self.labels.ranges)
        self._arrivals: collections.deque[tuple[int, float]] = collections.deque()
        # driver thread -> processing thread: (stream index, "restart" | "overrun"), in stream order
        self._marks: collections.deque[tuple[int, str]] = collections.deque()
        self._window_marks: dict[int, set[str]] = {}
        # driver thread -> event thread: lists of events, (None, dropped) for drops, None to end
        self._event_queue: queue.SimpleQueue = queue.SimpleQueue()
        self._limiter = EventLimiter()
        self._stop = threading.Event()
        self._errors: list[tuple[str, BaseException]] = []
        self._stopped_by = None
        self._max_frames = None
        # processing-thread state
        self._expected = 0
        self._gap_windows: set[int] = set()
        self._latencies = LatencyHistogram()
        self._cpu = 0.0
        self._n_windows = 0
        self._correct = self._labelled = self._acc_correct = self._acc_labelled = 0

    # -- control -----------------------------------------------------------------------------

    def stop(self, reason: str = "stop requested") -> None:
        """Ask the node to stop (thread-safe, also from a signal handler)."""
        if self._stopped_by is None:
            self._stopped_by = reason
        self._stop.set()

    def run(self, max_seconds: float | None = None) -> dict:
        """Run until the driver's stream ends, ``max_seconds`` of stream have passed, or :meth:`stop`.

        Returns the summary (also sent to the sinks).
        """
        if max_seconds is not None and not max_seconds > 0:
            raise InputError(f"max_seconds must be > 0 (or None or inf: no limit), got {max_seconds!r}")
        if max_seconds is not None and math.isinf(max_seconds):
            max_seconds = None
        self._max_frames = None if max_seconds is None else int(round(max_seconds * self.driver.rate))
        t0 = time.monotonic()
        threads = [threading.Thread(target=self._guard, args=("driver", self._drive), name="node-driver", daemon=True),
                   threading.Thread(target=self._guard, args=("processing", self._process), name="node-processing",
                                    daemon=True),
                   threading.Thread(target=self._guard, args=("event", self._deliver_events), name="node-events",
                                    daemon=True)]
        if self.recorder is not None:
            threads.append(threading.Thread(target=self._guard, name="node-recorder", daemon=True,
                                            args=("recorder", lambda: self.recorder.run(self._recorder_reader))))
        with self.driver:
            for t in threads:
                t.start()
            # Join with a timeout so that the main thread stays responsive to signals.
            while any(t.is_alive() for t in threads):
                for t in threads:
                    t.join(0.1)
        for s in self.sinks:
            drain = getattr(s, "drain", None)     # a queued sink: let it take what it holds
            if drain is not None:
                drain()
        summary = self._summary(time.monotonic() - t0)
        for s in self.sinks:
            s.summary(summary)
            s.close()
        if self._errors:
            where, exc = self._errors[0]
            raise NodeError(f"the {where} thread failed: {type(exc).__name__}: {exc}") from exc
        return summary

    def _sink_reader_left(self, exc: BrokenPipeError) -> None:
        """A sink's reader left: the stream has no one to go to; stop, and say why at the end."""
        self._errors.append(("sink", exc))
        self.stop("the reader of the output left")

    def _guard(self, where: str, target) -> None:
        try:
            target()
        except BaseException as exc:  # surfaced by run(); never lost in a thread
            self._errors.append((where, exc))
            self.stop(f"{where} error")
            self.ring.close()

    # -- driver thread ------------------------------------------------------------------------

    def _drive(self) -> None:
        take = getattr(self.driver, "take_events", None)
        try:
            while not self._stop.is_set():
                try:
                    block = self.driver.read(timeout=0.05)
                except DriverClosed:
                    break
                finally:
                    if take is not None:
                        self._queue_events(take)
                if block is None:
                    continue
                for kind, offsets in (("restart", block.restarts), ("overrun", block.overruns)):
                    for i in offsets:
                        self._marks.append((block.start + i, kind))
                        if self.recorder is not None:
                            self.recorder.note(block.start + i, kind)
                if self._max_frames is not None and block.start + block.frames >= self._max_frames:
                    block = _head(block, self._max_frames - block.start)
                    self._arrivals.append((block.start + block.frames, block.arrival))
                    self._write(block)
                    self.stop("stream length reached")
                    break
                self._arrivals.append((block.start + block.frames, block.arrival))
                self._write(block)
        finally:
            self.ring.close()
            self._event_queue.put(None)

    def _queue_events(self, take) -> None:
        events, dropped = take()
        if events or dropped:
            self._event_queue.put((events, dropped))

    # -- event thread -------------------------------------------------------------------------

    def _deliver_events(self) -> None:
        """Driver events to the sinks, rate-limited; ends after the driver thread's last batch."""
        lim = self._limiter
        while True:
            try:
                item = self._event_queue.get(timeout=0.1)
            except queue.Empty:
                item = ()
            if item is None:
                break
            if item:
                events, dropped = item
                lim.add_dropped(dropped)
                self._show([lim.add(ev) for ev in events])
            self._show(lim.due())
        self._show(lim.flush())

    def _show(self, events) -> None:
        for ev in events:
            if ev is not None:
                for s in self.sinks:
                    event = getattr(s, "event", None)  # a sink predating driver events has none
                    if event is not None:
                        event(ev)

    def _write(self, block) -> None:
        # Under "block" the ring takes what fits and we wait for the rest (lossless replay);
        # under the drop policies one write is final: it takes everything and counts what it
        # drops, or ("drop-newest") refuses the rest, whose stream indices are then spent.
        # Offering refused frames again would put them in the stream twice.
        kept, n = 0, block.frames
        while kept < n:
            filled = None if block.filled is None else block.filled[kept:]
            kept += self.ring.write(block.data[kept:], filled, timeout=0.1)
            if self.ring.overrun != "block" or (kept < n and self._stop.is_set() and self.ring.closed):
                return

    # -- processing thread --------------------------------------------------------------------

    def _process(self) -> None:
        W = self.pipeline.window_samples
        while True:
            try:
                chunk = self._reader.read(timeout=0.05)
            except RingClosed:
                break
            if chunk is None:
                continue
            c0 = time.thread_time()
            start, data, filled = chunk
            if start > self._expected:
                # Frames lost in the ring: zeros keep stream time exact; the windows are flagged.
                # The ring counts them (lost, lost_filled), so that each keeps one fate: these
                # zeros are the node's stand-in, not another count (see _frame_fates).
                gap = start - self._expected
                self._mark_gap(self._expected, start, W)
                self._step(np.zeros((gap, data.shape[1])), self._expected)
            if filled is not None and filled.any():
                idx = np.flatnonzero(filled) + start
                self._gap_windows.update(np.unique(idx // W).tolist())
            self._step(data, start)
            self._expected = start + data.shape[0]
            self._cpu += time.thread_time() - c0
        c0 = time.thread_time()
        self._emit(self.pipeline.finish(), flags=None)
        self._cpu += time.thread_time() - c0

    def _mark_gap(self, a: int, b: int, W: int) -> None:
        self._gap_windows.update(range(a // W, (b - 1) // W + 1))

    def _step(self, frames: np.ndarray, start: int) -> None:
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
            flags = self.contact.process(x) if self.contact is not None else None
            self._emit(windows, flags)
            cut = end

    def _emit(self, windows, flags) -> None:
        if not len(windows):
            return
        W, fs = self.pipeline.window_samples, self.pipeline.bank.fs
        outputs = self.model.outputs(windows.values) if self.model is not None else None
        for i, w in enumerate(windows.numbers.tolist()):
            end = (w + 1) * W
            event = {"t": end / fs, "window": w}
            truth = self.labels.at((w + 0.5) * W / fs)
            if outputs is not None:
                d = window_decision(outputs[i])
                name = self.model.classes[d.label]
                event.update(predicted=name, confidence=round(d.confidence, 4))
                if self.accumulator is not None:
                    in_contact = bool(flags[i]) if flags is not None and i < len(flags) else True
                    a = self.accumulator.update(outputs[i], in_contact)
                    acc_name = self.model.classes[a.label] if a.label >= 0 else None
                    event["accumulated"] = {"label": acc_name, "confidence": round(a.confidence, 4), "windows": a.windows}
                    if truth is not None and acc_name is not None:
                        self._acc_labelled += 1
                        self._acc_correct += acc_name == truth
                if truth is not None:
                    self._labelled += 1
                    self._correct += name == truth
            else:
                event["features"] = {f: windows.values[i, k].tolist() for k, f in enumerate(windows.features)}
            event["truth"] = truth
            if w in self._gap_windows:
                event["gap"] = True
                self._gap_windows.discard(w)
            for mark in self._marks_of(w, W):
                event[mark] = True
            event["latency_ms"] = self._latency_ms(end)
            self._n_windows += 1
            for s in self.sinks:
                s.emit(event)

    def _marks_of(self, w: int, W: int) -> list[str]:
        """The driver's marks ("restart", "overrun") in window ``w``, sorted."""
        end = (w + 1) * W
        while self._marks and self._marks[0][0] < end:
            index, kind = self._marks.popleft()
            self._window_marks.setdefault(index // W, set()).add(kind)
        for old in [k for k in self._window_marks if k < w]:  # windows never emitted (end of stream)
            del self._window_marks[old]
        return sorted(self._window_marks.pop(w, ()))

    def _latency_ms(self, end: int) -> float | None:
        """Now minus the arrival of the block that completed the window."""
        while self._arrivals and self._arrivals[0][0] < end:
            self._arrivals.popleft()
        if not self._arrivals:
            return None  # the window was completed by end-of-stream or filled frames
        lat = (time.monotonic() - self._arrivals[0][1]) * 1e3
        self._latencies.add(lat)
        return round(lat, 3)

    # -- summary ------------------------------------------------------------------------------

    def _frame_fates(self) -> dict[str, int]:
        """Every frame of the stream counted once: delivered, filled or dropped.

        ``delivered``: measured by the driver and processed as measured.
        ``filled``: synthesised by the driver (``Block.filled``) for samples the host never
        received (lost on the line or by the board, unplugged), whether the ring kept its zeros
        or dropped them: zeros lost are still zeros, not data lost.
        ``dropped``: samples the host received and lost: measured frames the ring lost
        (``dropped_in_ring``; the pipeline gets zeros in their place, but they count here
        only), and a driver's fills for its own losses (``dropped_by_driver``: a driver with
        ``fills_are_drops``, the microphone, fills only for overflows and a full buffer).
        ``stream``: frames offered to the ring, the stream's length; once the processing
        thread has drained the ring, ``delivered + filled + dropped == stream`` exactly.
        ``filled_lost_in_ring``: filled frames the ring dropped (counted in ``filled``, or in
        ``dropped_by_driver``), for the record.
        """
        ring = self.ring.stats()
        r = self._reader.stats()
        # The ring knows each row's flag when it drops it: the split is exact per frame,
        # whatever the timing (a fill longer than the ring loses its own head on write).
        synthesised = r["read_filled"] + r["lost_filled"]
        driver_drops = synthesised if getattr(self.driver, "fills_are_drops", False) else 0
        in_ring = r["lost"] - r["lost_filled"]
        return {"stream": ring["written"],
                "delivered": r["read"] - r["read_filled"],
                "filled": synthesised - driver_drops,
                "dropped": in_ring + driver_drops,
                "dropped_in_ring": in_ring,
                "dropped_by_driver": driver_drops,
                "filled_lost_in_ring": r["lost_filled"]}

    def _summary(self, wall: float) -> dict:
        fs = self.pipeline.bank.fs
        stream = self._expected / fs
        drv = dict(self.driver.stats())
        ring = self.ring.stats()
        return {
            "windows": self._n_windows,
            "stream_seconds": stream,
            "wall_seconds": wall,
            "window_accuracy": self._correct / self._labelled if self._labelled else None,
            "labelled_windows": self._labelled,
            "accumulated_accuracy": self._acc_correct / self._acc_labelled if self._acc_labelled else None,
            "frames": self._frame_fates(),
            "nonfinite_replaced": self.pipeline.filterbank.nonfinite_count,
            "out_of_range_replaced": self.pipeline.filterbank.out_of_range_count,
            "partial_window_samples": self.pipeline.partial_samples,
            "latency_ms": self._latencies.summary(),
            "real_time_factor": self._cpu / stream if stream else 0.0,
            "driver": drv,
            "recorded": [str(p) for p in self.recorder.paths] if self.recorder and self.recorder.paths else None,
            "ring": {k: v for k, v in ring.items() if isinstance(v, (int, float))},
            "stopped_by": self._stopped_by,
            "events": self._limiter.summary(),
            "sinks": [s.stats() for s in self.sinks if hasattr(s, "stats")],
        }
