"""Where the node's window events go: text lines or JSON Lines, to stdout or a file.

A sink is called from the processing thread only; it must not block for long
(a file or a terminal is fine; a network peer would need its own thread).
"""

from __future__ import annotations

import json
import sys
from typing import TextIO

from supramodal.errors import InputError


class Sink:
    """Base sink: ``emit(event)`` per window, ``summary(summary)`` once, ``close()`` at the end."""

    def __init__(self, path: str = "-") -> None:
        self.path = path
        self._fh: TextIO = sys.stdout if path == "-" else open(path, "w", buffering=1)

    def emit(self, event: dict) -> None:
        raise NotImplementedError

    def summary(self, summary: dict) -> None:
        raise NotImplementedError

    def close(self) -> None:
        if self._fh is not sys.stdout:
            self._fh.close()
        else:
            self._fh.flush()


class JsonLinesSink(Sink):
    """One JSON object per window; the summary as a last object with ``"summary": true``."""

    def emit(self, event: dict) -> None:
        self._fh.write(json.dumps(event) + "\n")

    def summary(self, summary: dict) -> None:
        self._fh.write(json.dumps({"summary": True, **summary}) + "\n")


class TextSink(Sink):
    """One human-readable line per window and a summary block."""

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
        lines.append(frames_line(s["frames"]))
        lines.append(f"  samples replaced   nonfinite replaced {s['nonfinite_replaced']}, out of range replaced "
                     f"{s.get('out_of_range_replaced', 0)}")
        lat = s.get("latency_ms")
        if lat:
            lines.append(f"  decision latency   p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms, max {lat['max']:.2f} ms "
                         "after window close")
        lines.append(f"  real-time factor   {s['real_time_factor']:.4f} (processing CPU s per s of stream)")
        if s.get("stopped_by"):
            lines.append(f"  stopped by         {s['stopped_by']}")
        self._fh.write("\n".join(lines) + "\n")


def frames_line(f: dict) -> str:
    """The summary line of frame fates: ``stream = delivered + filled + dropped``, with where the
    dropped ones went (docs/node.md, "Every frame has one fate")."""
    total = f["delivered"] + f["filled"] + f["dropped"]
    line = (f"  frames             {f['stream']} = delivered {f['delivered']} + filled {f['filled']} + "
            f"dropped {f['dropped']} (in ring {f['dropped_in_ring']}, by driver {f['dropped_by_driver']})")
    if total != f["stream"]:
        # Only when the processing thread stopped before draining the ring (it failed): say so
        # rather than print an identity that does not hold.
        line = line.replace(" = ", " != ", 1) + f"; {f['stream'] - total} not processed"
    return line


class ListSink(Sink):
    """Keeps events and the summary in memory: for a node embedded in a Python program, and tests."""

    def __init__(self) -> None:
        self.path = None
        self.events: list[dict] = []
        self.final: dict | None = None

    def emit(self, event: dict) -> None:
        self.events.append(event)

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
