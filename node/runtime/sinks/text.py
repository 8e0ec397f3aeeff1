"""The ``text`` sink: one human-readable line per window and a summary block, to stdout or a file.

A :class:`~supramodal.node.runtime.sinks.FileSink`, behind its own queue in a scene.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

from supramodal.drivers.base import DriverEvent
from supramodal.logs import get_logger
from supramodal.node.runtime.events import MAIN_STREAM, WindowEvent, severity
from supramodal.node.runtime.sinks import PATH_KEY, FileSink, file_sink
from supramodal.node.runtime.sinks.spec import SinkSpec
from supramodal.node.runtime.summaries import RunSummary, StreamSummary

_LOG = get_logger("events")
#: The log level of a driver event's line, by its severity (:data:`~supramodal.node.runtime.events.SEVERITY`):
#: ``supramodal -q`` (WARNING) keeps the alarms and warnings, and leaves out the news.
EVENT_LEVELS = {"alarm": logging.ERROR, "warning": logging.WARNING, "info": logging.INFO}

__all__ = ["SPEC", "TextSink", "frames_line"]


class TextSink(FileSink):
    """One human-readable line per window, under a line that names the columns, and a summary block.

    Driver events go to stderr, ``supramodal: MESSAGE`` and, for repeats folded in, ``(N more since)``, through
    the package logger (``supramodal.events``, at the event's severity: ``-q`` leaves out the news).

    Every line's time is on one basis, said in the header: the window's end (``WindowEvent.end``),
    seconds on the node's common time, for every stream's window and the fused ones alike (a
    stream's own time, ``WindowEvent.t``, would put a microphone window that ends 0.147 s into the
    graph at 0.100 s beside a fused window at 0.147 s). In a one-source scene of a file, common
    time is the stream's time.
    """

    _headed = False

    def event(self, ev: DriverEvent) -> None:
        """Log a driver event through ``supramodal.events`` at its severity, with its repeats folded in."""
        more = f" ({ev.count - 1} more since)" if ev.count > 1 else ""
        _LOG.log(EVENT_LEVELS[severity(ev.kind)], f"{ev.message}{more}")

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
        """Write a window's line (the header first, before the first window), under the sink's lock."""
        line = self._line(event)
        # Two streams' processing threads may emit at once (a sink called on the graph's own threads): the
        # lock makes the header, the file's lazy open and each line one at a time (unlocked, both threads
        # opened the file, and a line was lost under load).
        with self._lock:
            if not self._headed:
                self._fh.write(self._header(event) + "\n")
                self._headed = True
            self._fh.write(line + "\n")

    def _line(self, event: WindowEvent) -> str:
        """Return the window's line."""
        head = f"{event.end:9.3f} s"                    # common time, for every stream (TIME_BASIS)
        if event.stream != MAIN_STREAM:                 # a graph of several streams: say whose window
            head += f"  {event.stream:<8}"
        if event.decision is not None:
            line = f"{head}  {event.decision:<12} conf {event.confidence:.2f}"
            if event.unknown is not None:
                line += f" ({event.unknown}" + (f"; guess {event.guess})" if event.guess else ")")
            acc = event.pooled
            if acc is not None:
                shown = acc.label if acc.label is not None else "(no contact)"
                line += f"  | over {acc.windows:>3} win: {shown:<12} conf {acc.confidence:.2f}"
                if acc.decided:
                    line += f" decided after {acc.decided_after}"
                if acc.change is not None:              # re-decided within the contact: a new pooled decision
                    line += f"  [changed from {acc.change.from_}, {acc.change.after} win ago]"
            if event.truth is not None:
                mark = "ok" if event.truth == event.decision else "--"
                line += f"  truth {event.truth:<12} {mark}"
        else:
            features = cast(Mapping[str, ArrayLike], event.features)   # one without a decision carries features
            parts = [f"{name} sum {float(np.sum(vals)):.4g}" for name, vals in features.items()]
            line = f"{head}  " + "  ".join(parts)
        for flag in ("gap", "alone"):
            if flag in event.flags:
                line += f"  [{flag}]"
        return line

    def summary(self, s: RunSummary) -> None:
        """Write the summary block: one stream's counts, or each stream's, the clocks' and the fusion's.

        A relay's says only the seconds sent on. Then the taps' counts, the driver events', what the queued
        sinks dropped or raised, and what stopped the run.
        """
        lines = ["", "summary"]
        one = s.one_stream
        if one is not None:
            lines += _stream_lines(one, s.wall_seconds)
        elif not s.streams:                     # a relay: its sources' samples sent on, nothing decided
            lines.append(f"  stream             {s.stream_seconds:.2f} s sent on, no windows (a relay)")
        else:                                   # several streams: each one's counts, then the graph's
            lines.append(f"  windows            {s.windows} on {len(s.streams)} streams")
            for name, stream in s.streams.items():
                lines += [f"  stream {name}"] + ["  " + line for line in _stream_lines(stream)]
            for name, c in s.clocks.items():
                lines.append(f"  clock {name:<11} rate error {c['ppm']:+.1f} ppm, jitter {c['jitter_ms']:.2f} ms")
            f = s.fusion
            if f is not None:
                accuracy = f.accuracy.window_accuracy
                lines.append(f"  fused              {f.windows} windows: {f.paired} paired, {f.alone} alone"
                             f" (one sense), {sum(f.late.values())} late windows left out"
                             + "".join(f"; {name} dropped out {n} time{'s' * (n != 1)}"
                                       for name, n in f.dropouts.items() if n)
                             + (f"; window accuracy {accuracy:.3f}" if accuracy is not None else ""))
        for name, t in (s.taps or {}).items():
            fates = cast(Mapping[str, int], t["frames"])
            lines.append(f"  sent               {name}: {t['samples_sent']} samples in {t['chunks']} chunks; not sent: "
                         f"{fates['filled']} filled and {fates['dropped']} dropped frames")
        counts = s.events.get("counts")
        if counts:
            dropped = sum(s.events.get("dropped", {}).values())
            lines.append("  driver events      " + ", ".join(f"{k} {n}" for k, n in counts.items())
                         + (f" ({dropped} not shown: dropped before the node took them)" if dropped else ""))
        for q in s.sinks:
            if q["dropped_windows"] or q["dropped_events"] or q["errors"]:
                lines.append(f"  sink               {q['sink']}: dropped {q['dropped_windows']} windows and "
                             f"{q['dropped_events']} events it could not take"
                             + (f", {q['errors']} errors (first: {q['first_error']})" if q["errors"] else ""))
        if s.stopped_by:
            lines.append(f"  stopped by         {s.stopped_by}")
        self._fh.write("\n".join(lines) + "\n")


def _stream_lines(s: StreamSummary, wall_seconds: float | None = None) -> list[str]:
    """Return the summary lines of one stream's counts (with the run's wall time: a one-stream node's)."""
    lines = [f"  windows            {s.windows}",
             f"  stream             {s.stream_seconds:.2f} s"
             + (f" in {wall_seconds:.2f} s wall time" if wall_seconds is not None else "")]
    accuracy = s.accuracy
    if accuracy.window_accuracy is not None:
        lines.append(f"  window accuracy    {accuracy.window_accuracy:.3f} over {accuracy.labelled_windows} labelled "
                     "windows")
    if accuracy.accumulated_accuracy is not None:
        lines.append(f"  accumulated acc.   {accuracy.accumulated_accuracy:.3f}")
    decided = s.decisions
    if decided is not None and any(decided.unknown_windows.values()):
        unknown = decided.unknown_windows
        lines.append("  unknown windows    " + ", ".join(f"{n} {why}" for why, n in unknown.items() if n))
    if decided is not None and decided.contacts_decided is not None:
        median = decided.windows_to_decide_median
        lines.append(f"  contacts decided   {decided.contacts_decided}"
                     + (f", median {median:g} windows to decide" if median is not None else ""))
    lines.append(frames_line(s.frames))
    lines.append(f"  samples replaced   nonfinite replaced {s.nonfinite_replaced}, out of range replaced "
                 f"{s.out_of_range_replaced}")
    lat = s.latency_ms
    if lat:
        lines.append(f"  decision latency   p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms, max {lat['max']:.2f} ms "
                     "after window close")
    lines.append(f"  real-time factor   {s.real_time_factor:.4f} (processing CPU s per s of stream)")
    return lines


def frames_line(f: Mapping[str, int]) -> str:
    """Return the summary line of frame fates: ``stream = delivered + filled + dropped``.

    With where the dropped ones went (docs/node.md, "Every frame has one fate").
    """
    total = f["delivered"] + f["filled"] + f["dropped"]
    line = (f"  frames             {f['stream']} = delivered {f['delivered']} + filled {f['filled']} + "
            f"dropped {f['dropped']} (in ring {f['dropped_in_ring']}, by driver {f['dropped_by_driver']})")
    if total != f["stream"]:
        # Only when the processing thread stopped before draining the ring (it failed): say so
        # rather than print an identity that does not hold.
        line = line.replace(" = ", " != ", 1) + f"; {f['stream'] - total} not processed"
    return line


SPEC = SinkSpec(type="text", keys={"path": PATH_KEY}, build=file_sink(TextSink),
                summary="one line per window, for people (stdout or a file)")
