"""Where the node's window events go: text lines or JSON Lines, to stdout or a file.

Threading rules
---------------
``emit`` is called from the node's processing thread, ``event`` (driver events)
from its event thread, ``summary`` and ``close`` from the caller's thread once
both have ended. A sink must not block for long (a file or a terminal is fine; a
network peer would need its own thread); one writing ``emit`` and ``event`` to
the same stream serialises them with its lock, held for one write.
"""

from __future__ import annotations

import json
import sys
import threading
from typing import TextIO

from drivers.base import DriverEvent

from supramodal.errors import InputError


class Sink:
    """Base sink: ``emit(event)`` per window, ``event(ev)`` per driver event (default: ignored),
    ``summary(summary)`` once, ``close()`` at the end."""

    def __init__(self, path: str = "-") -> None:
        self.path = path
        self._fh: TextIO = sys.stdout if path == "-" else open(path, "w", buffering=1)
        self._lock = threading.Lock()

    def emit(self, event: dict) -> None:
        raise NotImplementedError

    def event(self, ev: DriverEvent) -> None:
        """A driver event (rate-limited by the node: ``ev.count`` > 1 stands for repeats)."""

    def summary(self, summary: dict) -> None:
        raise NotImplementedError

    def close(self) -> None:
        if self._fh is not sys.stdout:
            self._fh.close()
        else:
            self._fh.flush()


class JsonLinesSink(Sink):
    """One JSON object per window; a driver event as ``{"event": kind, "message": ..., "time": ...,
    "stream_index": ..., "count": ...}`` in the same stream; the summary as a last object with
    ``"summary": true``."""

    def emit(self, event: dict) -> None:
        line = json.dumps(event) + "\n"
        with self._lock:
            self._fh.write(line)

    def event(self, ev: DriverEvent) -> None:
        line = json.dumps(ev.as_dict()) + "\n"
        with self._lock:
            self._fh.write(line)

    def summary(self, summary: dict) -> None:
        self._fh.write(json.dumps({"summary": True, **summary}) + "\n")


class TextSink(Sink):
    """One human-readable line per window and a summary block; driver events on stderr,
    ``supramodal: MESSAGE`` and, for repeats folded in, ``(N more since)``."""

    def event(self, ev: DriverEvent) -> None:
        more = f" ({ev.count - 1} more since)" if ev.count > 1 else ""
        sys.stderr.write(f"supramodal: {ev.message}{more}\n")
        sys.stderr.flush()

    def emit(self, event: dict) -> None:
        head = f"{event['t']:9.3f} s"
        if "predicted" in event:
            line = f"{head}  {event['predicted']:<12} conf {event['confidence']:.2f}"
            acc = event.get("accumulated")
            if acc:
                shown = acc["label"] if acc["label"] is not None else "(no contact)"
                line += f"  | over {acc['windows']:>3} win: {shown:<12} conf {acc['confidence']:.2f}"
            if event.get("truth") is not None:
                mark = "ok" if event["truth"] == event["predicted"] else "--"
                line += f"  truth {event['truth']:<12} {mark}"
        else:
            parts = [f"{name} sum {sum(vals):.4g}" for name, vals in event["features"].items()]
            line = f"{head}  " + "  ".join(parts)
        if event.get("gap"):
            line += "  [gap]"
        self._fh.write(line + "\n")

    def summary(self, s: dict) -> None:
        lines = ["", "summary",
                 f"  windows            {s['windows']}",
                 f"  stream             {s['stream_seconds']:.2f} s in {s['wall_seconds']:.2f} s wall time"]
        if s.get("window_accuracy") is not None:
            lines.append(f"  window accuracy    {s['window_accuracy']:.3f} over {s['labelled_windows']} labelled windows")
        if s.get("accumulated_accuracy") is not None:
            lines.append(f"  accumulated acc.   {s['accumulated_accuracy']:.3f}")
        lines.append(f"  samples dropped    {s['samples_dropped']}  (filled {s['samples_filled']}, "
                     f"nonfinite replaced {s['nonfinite_replaced']}, out of range replaced "
                     f"{s.get('out_of_range_replaced', 0)})")
        lat = s.get("latency_ms")
        if lat:
            lines.append(f"  decision latency   p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms, max {lat['max']:.2f} ms "
                         "after window close")
        lines.append(f"  real-time factor   {s['real_time_factor']:.4f} (processing CPU s per s of stream)")
        counts = (s.get("events") or {}).get("counts")
        if counts:
            dropped = sum(s["events"].get("dropped", {}).values())
            lines.append("  driver events      " + ", ".join(f"{k} {n}" for k, n in counts.items())
                         + (f" ({dropped} not shown: dropped before the node took them)" if dropped else ""))
        if s.get("stopped_by"):
            lines.append(f"  stopped by         {s['stopped_by']}")
        self._fh.write("\n".join(lines) + "\n")


class ListSink(Sink):
    """Keeps window events (``events``), driver events (``driver_events``) and the summary in
    memory: for a node embedded in a Python program, and tests."""

    def __init__(self) -> None:
        self.path = None
        self.events: list[dict] = []
        self.driver_events: list[DriverEvent] = []
        self.final: dict | None = None

    def emit(self, event: dict) -> None:
        self.events.append(event)

    def event(self, ev: DriverEvent) -> None:
        self.driver_events.append(ev)

    def summary(self, summary: dict) -> None:
        self.final = summary

    def close(self) -> None:
        pass


SINKS = {"text": TextSink, "jsonl": JsonLinesSink}


def make_sink(kind: str, path: str = "-") -> Sink:
    try:
        return SINKS[kind](path)
    except KeyError:
        raise InputError(f"unknown sink {kind!r}; sinks are {sorted(SINKS)}") from None
