"""The ``jsonl`` sink: one JSON object per window, driver event and summary, to stdout or a file.

A :class:`~supramodal.node.runtime.sinks.FileSink`, behind its own queue in a scene.
"""

from __future__ import annotations

import json

from supramodal.drivers.base import DriverEvent
from supramodal.node.runtime.events import WindowEvent
from supramodal.node.runtime.sinks import PATH_KEY, FileSink, file_sink
from supramodal.node.runtime.sinks.spec import SinkSpec
from supramodal.node.runtime.summaries import RunSummary

__all__ = ["SPEC", "JsonLinesSink"]


class JsonLinesSink(FileSink):
    """One JSON object per window, driver event and summary, in one stream of lines.

    A window as :meth:`WindowEvent.as_dict`; a driver event as ``{"event": kind, "message": ..., "time": ...,
    "stream_index": ..., "count": ...}`` in the same stream; the summary as a last object with
    ``"summary": true``.
    """

    def emit(self, event: WindowEvent) -> None:
        """Write a window's event as one JSON line (under the sink's lock)."""
        line = json.dumps(event.as_dict()) + "\n"
        with self._lock:
            self._fh.write(line)

    def event(self, ev: DriverEvent) -> None:
        """Write a driver event as one JSON line (under the sink's lock)."""
        line = json.dumps(ev.as_dict()) + "\n"
        with self._lock:
            self._fh.write(line)

    def summary(self, summary: RunSummary) -> None:
        """Write the run's summary as a last JSON line, with ``"summary": true``."""
        self._fh.write(json.dumps({"summary": True, **summary.to_dict()}) + "\n")


SPEC = SinkSpec(type="jsonl", keys={"path": PATH_KEY}, build=file_sink(JsonLinesSink),
                summary="one JSON object per window, driver event and summary (stdout or a file)")
