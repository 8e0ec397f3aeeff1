"""Labels of a recorded graph: spans on the node's common time, kept in each source's session.

Two clocks, one rule. A person labels what happened when (a line typed while recording, a video
annotation afterwards): those times are on the node's **common time**, seconds since the
recording started, the time line every window's ``start`` and ``end`` are printed on. A
session's sidecar keeps its labels in **seconds of the device's own stream**: ``frame / rate``,
the sample index over the sidecar's nominal rate, which names one sample exactly whatever the
device's crystal did, needs no clock model to be read back (a one-source session has no common
time at all), and is what a replay, ``train`` and a manifest's ``start``/``end`` read. A device
90 ppm fast has taken 21.6 ms more samples than its nominal rate says after 4 minutes: a label
put at ``t x rate`` would land 108 samples (at 5 kHz) early. So a span on common time is mapped
to each source's stream through that source's clock: the clock model fed the blocks' recorded
times (the sidecar's ``arrivals``), exactly as the node and its replay feed it, the line as it
stood after the block that completed the sample (:func:`~supramodal.node.runtime.clock.frames_at`,
beside the clock model: a recorder maps its marks on common time with it too).

* :func:`read_spans` reads a spans file (CSV ``start,end,label``, seconds of common time),
  validated: finite times, ``0 <= start < end``, names of :data:`supramodal.checks.NAME_HELP`,
  in order, not overlapping.
* :func:`label_recording` (``supramodal label REC.toml SPANS.csv``) writes them into every
  session of a recorded graph, refusing sessions that already hold labels unless told to replace
  them.

Files here are data: read with :mod:`csv` and strict JSON, validated, never executed.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from supramodal.checks import NAME_HELP, is_name
from supramodal.csvdata import bounded_lines
from supramodal.errors import InputError
from supramodal.node.runtime.clock import frames_at
from supramodal.replay.session import (
    MAX_SIDECAR_BYTES,
    load_session,
    session_paths,
    sidecar_text,
    validate_sidecar,
)

__all__ = ["SPAN_COLUMNS", "LabelError", "Span", "check_label_name", "frames_at", "label_recording", "read_spans",
           "replace_all", "spans_to_stream"]

#: The columns of a spans file, in order.
SPAN_COLUMNS = ("start", "end", "label")


class LabelError(InputError):
    """A spans file, a label or a recording to label is refused; the message names the problem and the fix."""


@dataclass(frozen=True)
class Span:
    """A label on common time.

    Attributes
    ----------
    start, end : float
        Seconds of the node's common time since the recording started; ``start < end``, the span is
        ``[start, end)``.
    label : str
        A name (:data:`supramodal.checks.NAME_HELP`).
    """

    start: float
    end: float
    label: str


def check_label_name(name: object, where: str) -> str:
    """Return ``name`` if it is a valid label (a name: letters, digits, '-' or '_'), else raise a :class:`LabelError`.

    The error names ``where`` and the fix (class names become outlet channels, file name parts and columns).
    """
    if not is_name(name):
        raise LabelError(f"{where}: the label {name!r} is not {NAME_HELP}; rename it (e.g. 'rough_wood')")
    return str(name)


def _seconds(text: str, key: str, where: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value < 0:
        raise LabelError(f"{where}: {key} {text!r} is not a finite number of seconds >= 0; write seconds of the "
                         "recording's common time (e.g. 12.5)")
    return value


def read_spans(path) -> list[Span]:
    """Read a spans file: CSV with the header ``start,end,label``, one span a line.

    Parameters
    ----------
    path : str or path-like
        UTF-8 CSV (a byte-order mark is accepted). ``start``, ``end``: seconds of the node's common
        time since the recording started (what the replay prints as a window's ``start``/``end``);
        ``label``: a name.

    Returns
    -------
    list of Span
        In time order.

    Raises
    ------
    LabelError
        Naming the file and line: not UTF-8 or not CSV, a wrong header, a missing field, a time that
        is not a finite number >= 0, ``end <= start``, a bad name, spans out of order or overlapping,
        or no span at all.
    """
    path = Path(path)
    spans: list[tuple[int, Span]] = []
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(bounded_lines(f, str(path), LabelError), strict=True)
            header = None
            for fields in reader:
                where = f"{path}, line {reader.line_num}"
                fields = [v.strip() for v in fields]
                if not any(fields):
                    continue
                if header is None:
                    header = [c.lower() for c in fields]
                    if tuple(header) != SPAN_COLUMNS:
                        raise LabelError(f"{where}: the header is {','.join(fields)!r}; write "
                                         f"{','.join(SPAN_COLUMNS)!r} (seconds of common time, and the label)")
                    continue
                if len(fields) != len(SPAN_COLUMNS):
                    raise LabelError(f"{where}: {len(fields)} fields, expected {len(SPAN_COLUMNS)} (start,end,label)")
                start, end = _seconds(fields[0], "start", where), _seconds(fields[1], "end", where)
                if end <= start:
                    raise LabelError(f"{where}: end {end:g} s is not after start {start:g} s; a span is [start, end)")
                spans.append((reader.line_num, Span(start, end, check_label_name(fields[2], where))))
    except FileNotFoundError:
        raise LabelError(f"no spans file at {path}: give a CSV file with the header start,end,label") from None
    except IsADirectoryError:
        raise LabelError(f"{path} is a folder: give a CSV file with the header start,end,label") from None
    except UnicodeDecodeError as e:
        raise LabelError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start}); save it as UTF-8") from None
    except csv.Error as e:
        raise LabelError(f"{path}: not valid CSV ({e}); quote a field holding a comma") from None
    if not spans:
        raise LabelError(f"{path}: no span; write the header start,end,label and one line per span")
    for (_, a), (line, b) in zip(spans, spans[1:]):
        if b.start < a.end:
            raise LabelError(f"{path}, line {line}: [{b.start:g}, {b.end:g}) {b.label!r} "
                             + ("starts before the span above it" if b.start < a.start else
                                f"overlaps [{a.start:g}, {a.end:g}) {a.label!r}")
                             + "; put spans in time order, each ending before the next starts")
    return [s for _, s in spans]


def spans_to_stream(spans: Iterable[Span], arrivals, marks, frames: int, rate: float) -> list[tuple[float, float, str]]:
    """Return spans on common time as labels of one session: ``(start_s, end_s, name)``.

    In seconds of the device's own stream (frame / ``rate``), each end clipped to the ``frames`` recorded; a
    span the source did not record (all before its first sample or after its last) is left out.
    """
    spans = list(spans)
    if not spans:
        return []
    edges = frames_at(arrivals, [v for s in spans for v in (s.start, s.end)], marks)
    out = []
    for k, span in enumerate(spans):
        a = min(max(edges[2 * k], 0.0), frames)
        b = min(max(edges[2 * k + 1], 0.0), frames)
        if b > a:
            out.append((round(a / rate, 6), round(b / rate, 6), span.label))
    # Neighbouring spans may meet inside one rounding step: never let them overlap.
    for i in range(1, len(out)):
        if out[i][0] < out[i - 1][1]:
            out[i - 1] = (out[i - 1][0], out[i][0], out[i - 1][2])
    return [s for s in out if s[1] > s[0]]


def _sessions(scene_path) -> list[tuple[str, Path]]:
    """``(source name, session path)`` of every source of a recorded graph's replay scene."""
    from supramodal.node.scene.registry import driver_spec
    from supramodal.node.scene.schema import load_scene

    scene = load_scene(scene_path)
    sessions = []
    for src in scene.sources:
        session = driver_spec(src.type).replays(src.options)
        if session is None or not session.in_step:
            raise LabelError(f"{scene.source}: source {src.name!r} is not a recorded session (type = "
                             f"{src.type!r}); give the scene `supramodal record` wrote for a graph (DIR/NAME.toml)")
        sessions.append((src.name, scene.resolve(session.path)))
    return sessions


def _staged(path: Path) -> Path:
    """Return the temporary name beside ``path`` its new text is written under.

    It is then put in place by :func:`replace_all`. The name is known before the file is made, so that an
    interruption at any moment knows what to remove (a signal right after ``mkstemp`` made one left it
    behind).
    """
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def replace_all(staged: list[tuple[Path, Path]]) -> None:
    """Put every staged file in place, ``(temporary, final)``: all or none.

    Every command that writes several files puts them so: a label's sidecars; the files of an import, a
    recorded graph, a report. Each replace is atomic (a crash leaves a sidecar old or new, never half of one), and a
    Ctrl-C or SIGTERM that comes meanwhile is held until all are done, then given to the handler it was for (a
    signal in between left one session labelled and the other not). Signals are held only on the main thread
    (the only one Python's handlers run on); elsewhere the replaces are microseconds apart.
    """
    from supramodal.interrupts import held_interrupts

    try:
        with held_interrupts():
            for tmp, path in staged:
                os.replace(tmp, path)
    finally:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)


def label_recording(scene_path, spans_path, replace: bool = False) -> dict[str, list[tuple[float, float, str]]]:
    """Label every session of a recorded graph with the spans of a spans file (``supramodal label``).

    Parameters
    ----------
    scene_path : path
        The replay scene ``supramodal record`` wrote for a graph (``DIR/NAME.toml``).
    spans_path : path
        Spans on common time (:func:`read_spans`).
    replace : bool
        Replace labels a session already holds (default False: refused, naming the sessions).

    Returns
    -------
    dict
        Per source, the labels written: ``(start_s, end_s, name)`` in seconds of its own stream.

    Raises
    ------
    LabelError
        A bad spans file; a span starting after the recording's end (no source recorded it); a
        session that already holds labels, without ``replace``; a session without its blocks'
        times (``arrivals``), which cannot be put on common time. Every session is checked before
        any is written.
    """
    spans = read_spans(spans_path)
    plans = []
    latest = 0.0
    for name, path in _sessions(scene_path):
        session = load_session(path)
        if session.arrivals is None:
            raise LabelError(f"{path}: the session keeps no block times ('arrivals'), so common time cannot be "
                             "mapped to its samples; label it by hand in its sidecar (seconds of its own stream)")
        if session.labels and not replace:
            raise LabelError(f"{path}: the session already holds {len(session.labels)} label(s) (e.g. "
                             f"{session.labels[0].label!r} from {session.labels[0].start:g} s); pass --replace to "
                             "replace them all, or leave them")
        latest = max(latest, float(session.arrivals[1][-1]))
        frames = session.data.shape[0]
        plans.append((name, path, spans_to_stream(spans, session.arrivals, session.marks, frames, session.rate),
                      frames, session))
    late = [s for s in spans if s.start >= latest]
    if late:
        raise LabelError(f"{spans_path}: the span [{late[0].start:g}, {late[0].end:g}) {late[0].label!r} starts "
                         f"after the recording ends ({latest:.3f} s of common time); give times since the recording "
                         "started, as its replay prints them")
    written, texts = {}, []
    for name, path, labels, frames, session in plans:            # every sidecar made and checked first
        js = session_paths(path)[1]
        meta = json.loads(js.read_text(encoding="utf-8"))        # validated whole by load_session above
        meta["labels"] = [{"start": a, "end": b, "label": n} for a, b, n in labels]
        validate_sidecar(meta, rate=session.rate, channels=session.data.shape[1], frames=frames, where=str(js))
        text = sidecar_text(meta)
        size = len(text.encode("utf-8"))
        if size > MAX_SIDECAR_BYTES:
            raise LabelError(f"{spans_path}: {len(spans)} spans would make {js.name} {size} bytes, more than the "
                             f"{MAX_SIDECAR_BYTES} a sidecar may have (MAX_SIDECAR_BYTES), and the recording would "
                             "no longer load; nothing was written. Merge neighbouring spans of one label, or label "
                             "a shorter recording")
        texts.append((js, text))
        written[name] = labels
    staged: list[tuple[Path, Path]] = []
    try:
        for js, text in texts:
            staged.append((_staged(js), js))
            staged[-1][0].write_text(text, encoding="utf-8")
    except BaseException:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        raise
    replace_all(staged)
    return written
