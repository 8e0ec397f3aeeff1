"""Reads and validates a training manifest: the CSV file that lists labelled recordings.

A manifest is UTF-8 text (a byte-order mark, as spreadsheets write for "CSV UTF-8",
is accepted) in CSV form: a header line naming the columns ``path,label`` and,
optionally, ``start,end``, then one line per recording::

    path,label,start,end
    carpet.wav,carpet,0,3.3
    "felt, wet.wav","felt, wet",,

* ``path``: a WAV file or a session (``NAME.wav`` / ``NAME.json``); a relative path
  is taken from the manifest's folder, not from the working directory.
* ``label``: the class name. A label or path holding a comma must be quoted, as
  above: an unquoted comma adds a field, and a line with more fields than the
  header is refused (never cut silently).
* ``start``, ``end``: seconds, the part of the recording to use; empty means the
  start and the end of the file. They must be finite with
  ``0 <= start < end <= duration`` (``end`` may exceed the duration by less than
  one frame, for rounding).

Blank lines (or lines of empty fields) are skipped. Every refusal is a
:class:`ManifestError` naming the manifest, the line (physical line of the file,
the header being line 1), the cause and the fix; :func:`read_manifest` checks
every row, every file's existence and every span against the file's duration
before anything is trained.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

from supramodal.checks import CLASS_NAME_HELP, is_class_name
from supramodal.csvdata import bounded_lines
from supramodal.errors import InputError
from supramodal.replay.errors import ReplayError
from supramodal.replay.session import session_paths
from supramodal.replay.wavio import WavInfo, wav_info

__all__ = ["COLUMNS", "REQUIRED_COLUMNS", "ManifestError", "Recording", "read_manifest"]

#: Every column a manifest may have, in the documented order.
COLUMNS = ("path", "label", "start", "end")
#: Columns every manifest must have.
REQUIRED_COLUMNS = ("path", "label")

_QUOTE_HINT = 'quote labels (and paths) containing commas, e.g. "rough, wet"'


class ManifestError(InputError):
    """A training manifest, or a recording it lists, is refused; the message names the manifest's line."""


@dataclass(frozen=True)
class Recording:
    """One manifest row.

    Attributes
    ----------
    path : pathlib.Path
        The recording, resolved against the manifest's folder.
    label : str
        Its class name.
    start : float
        Seconds from the start of the file where the used part begins.
    end : float or None
        Seconds where it ends; None = the end of the file.
    line : int
        The manifest line it came from (1 = the header); 0 when built by hand.
    manifest : pathlib.Path or None
        The manifest it came from.
    """

    path: Path
    label: str
    start: float = 0.0
    end: float | None = None
    line: int = 0
    manifest: Path | None = None

    @property
    def where(self) -> str:
        """``"MANIFEST, line N"`` for messages (the file's path for a row built by hand)."""
        return f"{self.manifest}, line {self.line}" if self.manifest is not None else str(self.path)


def _rows(path: Path):
    """Yield ``(line, fields)`` for every non-blank CSV record, ``line`` being the record's first line."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(bounded_lines(f, str(path), ManifestError), strict=True)
            first = 1
            for fields in reader:
                if any(v.strip() for v in fields):
                    yield first, [v.strip() for v in fields]
                first = reader.line_num + 1
    except FileNotFoundError:
        raise ManifestError(f"no manifest at {path}: give the path of a CSV file") from None
    except IsADirectoryError:
        raise ManifestError(f"{path} is a folder, not a manifest: give the path of a CSV file") from None
    except UnicodeDecodeError as e:
        raise ManifestError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start}); save it as "
                            '"CSV UTF-8" or plain UTF-8') from None
    except csv.Error as e:
        raise ManifestError(f"{path}, line {reader.line_num}: not valid CSV ({e}); {_QUOTE_HINT}, "
                            'and double a quote inside a quoted field ("")') from None


def _seconds(text: str, key: str, where: str) -> float | None:
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise ManifestError(f"{where}: {key} {text!r} is not a number; write seconds (e.g. 2.5) or leave "
                            "it empty") from None
    if not math.isfinite(value):
        raise ManifestError(f"{where}: {key} is {text!r}; write a finite number of seconds (or leave it empty "
                            f"for the {'start' if key == 'start' else 'end'} of the file)")
    return value


def _parse(path: Path) -> list[Recording]:
    rows = _rows(path)
    try:
        _, header = next(rows)
    except StopIteration:
        raise ManifestError(f"{path}, line 1: the manifest is empty; write a header line 'path,label' (optionally "
                            "',start,end') and one line per recording") from None
    columns = [c.lower() for c in header]
    unknown = [c for c in columns if c not in COLUMNS]
    missing = [c for c in REQUIRED_COLUMNS if c not in columns]
    if unknown or missing or len(set(columns)) != len(columns):
        raise ManifestError(f"{path}, line 1: the header is {','.join(header)!r}; columns must be "
                            "path,label[,start,end], each named once (is the header line missing?)")
    recs = []
    for line, fields in rows:
        where = f"{path}, line {line}"
        if len(fields) > len(columns):
            raise ManifestError(f"{where}: the line has {len(fields)} fields but the header names "
                                f"{len(columns)} ({','.join(columns)}); {_QUOTE_HINT}")
        row = dict(zip(columns, fields))             # missing trailing fields: empty
        name, label = row.get("path", ""), row.get("label", "")
        if not name or not label:
            raise ManifestError(f"{where}: {'path' if not name else 'label'} is empty; every line needs "
                                "a recording and its label")
        if not is_class_name(label):
            raise ManifestError(f"{where}: label {label[:80]!r} is not {CLASS_NAME_HELP}; it becomes a model's "
                                "class, printed and published as it is: write it as plain text")
        start = _seconds(row.get("start", ""), "start", where)
        end = _seconds(row.get("end", ""), "end", where)
        start = 0.0 if start is None else start
        if start < 0 or (end is not None and end <= start):
            raise ManifestError(f"{where}: need 0 <= start < end, got start={start:g}, end={end:g} s"
                                if end is not None else f"{where}: start {start:g} s is negative")
        p = Path(name)
        recs.append(Recording(p if p.is_absolute() else path.parent / p, label, start, end, line, path))
    if not recs:
        raise ManifestError(f"{path}, line 2: the manifest lists no recording after its header; add one line "
                            "per file under the header")
    return recs


def recording_info(rec: Recording) -> WavInfo:
    """Return the header of ``rec``'s WAV file (for a session, its ``NAME.wav``); no sample is read.

    Raises
    ------
    ManifestError
        Naming the manifest's line, if the file is missing or not a readable WAV.
    """
    wav = session_paths(rec.path)[0] if rec.path.suffix.lower() in (".wav", ".json") else rec.path
    if not rec.path.is_file() or not wav.is_file():
        raise ManifestError(f"{rec.where}: no recording at {rec.path} (a relative path is taken from the "
                            "manifest's folder); fix the path or move the file")
    try:
        return wav_info(wav)
    except ReplayError as e:
        raise ManifestError(f"{rec.where}: {e}") from e


def check_span(rec: Recording, info: WavInfo) -> None:
    """Refuse a row whose ``[start, end)`` does not lie inside its file (``info``: the file's header)."""
    duration = info.duration
    slack = 1.0 / info.rate                              # end = duration computed in float must pass
    if rec.start >= duration:
        raise ManifestError(f"{rec.where}: start {rec.start:g} s lies past the end of {rec.path.name}, "
                            f"which is {duration:g} s long; start inside the recording or drop the line")
    if rec.end is not None and rec.end > duration + slack:
        raise ManifestError(f"{rec.where}: end {rec.end:g} s lies past the end of {rec.path.name}, "
                            f"which is {duration:g} s long; lower it, or leave it empty for the end of the file")


def read_manifest(path) -> list[Recording]:
    """Read a manifest and check it against the files it lists.

    Parameters
    ----------
    path : str or path-like
        The CSV file (format in this module's docstring).

    Returns
    -------
    list of Recording
        In file order; paths resolved against the manifest's folder.

    Raises
    ------
    ManifestError
        For the first problem found, naming the manifest's line, the cause and the fix:
        not UTF-8, bad CSV, a bad header, a line with more fields than the header (an
        unquoted comma), an empty path or label, a start or end that is not a finite
        number, ``start >= end``, a missing or unreadable file, or a span outside the file.
    """
    path = Path(path)
    recs = _parse(path)
    for rec in recs:
        check_span(rec, recording_info(rec))
    return recs


def manifest_classes(recs: list[Recording], manifest) -> tuple[str, ...]:
    """Return the labels of a manifest's recordings, sorted; a :class:`ManifestError` with fewer than two.

    A model that tells one texture from nothing learns nothing: ``train`` and ``fit`` refuse it alike.
    """
    classes = tuple(sorted({r.label for r in recs}))
    if len(classes) < 2:
        raise ManifestError(f"{manifest}: training needs at least two labels, found {list(classes)}; "
                            "add recordings of another texture")
    return classes
