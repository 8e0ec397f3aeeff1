"""Sessions: a WAV file plus a strict JSON sidecar.

A session named ``NAME`` is two files side by side:

``NAME.wav``
    The samples (any layout :func:`replay.wavio.read_wav` accepts).
``NAME.json``
    The sidecar, a JSON object with exactly these keys::

        {
          "format": "supramodal-session",   # required, this exact string
          "version": 1,                     # required, integer; only 1 exists
          "rate": 5000,                     # required, Hz; equals the WAV header's rate
          "channels": 20,                   # required; equals the WAV's channel count
          "source": "serial_whisker port=/dev/ttyACM0 baud=2000000",  # required, free text
          "labels": [                       # required, may be empty; seconds from the
            {"start": 0.0, "end": 2.5, "label": "sandpaper"},       # start of the WAV,
            {"start": 2.5, "end": 5.0, "label": "felt"}             # in time order,
          ],                                                        # not overlapping
          "filled": [[1200, 1250], [9000, 9001]]  # optional: [start_frame, end_frame)
          "marks": [[4800, "restart"], [7000, "overrun"]]  # optional: [frame, kind]
          "arrivals": {"frames": [50, 100, ...],   # optional: each block's end frame and
                       "seconds": [0.0103, 0.0201, ...],  # when it was complete, on the
                       "rate": 5000.0}            # recording node's common time, and the
        }                                         # nominal rate its clock model assumed

``filled`` lists the frame ranges the recording driver synthesised. ``arrivals`` is written
when a node of several sources records: with it, the sessions of the sources replay with their
original relative timing, drift and jitter included (the replay driver's ``timing="recorded"``).
Its times must tell the same story as its frames (:func:`validate_arrivals`): between two blocks
with no mark between them, the seconds that passed differ from the seconds their frames last at
``arrivals.rate`` by at most :data:`ARRIVALS_CLOCK_ERROR` of the latter (a device's crystal or
resonator) plus :data:`ARRIVALS_LATENCY` (a block delivered late); at a ``restart`` or
``overrun`` mark the time may jump forward.

The sidecar is data, never code: it is read with :func:`json.loads` only
(duplicate keys, ``NaN`` and ``Infinity`` refused; files over
:data:`MAX_SIDECAR_BYTES` or nested deeper than :data:`MAX_SIDECAR_DEPTH` refused
before parsing), and validated strictly:
an unknown key, a wrong type, a rate or channel count that disagrees with the
WAV, a label outside the recording or overlapping another, each raise a
:class:`~replay.errors.SessionError` naming the file, the key and the fix.

Threading: the functions keep no state and may be called from any thread.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn, TypeGuard

import numpy as np
from numpy.typing import ArrayLike

from supramodal.checks import NAME_HELP, is_name
from supramodal.errors import InputError
from supramodal.jsondata import read_json_file
from supramodal.replay.errors import MissingSidecarError, SessionError
from supramodal.replay.wavio import as_frames, read_wav, wav_info, write_wav

__all__ = ["FORMAT", "VERSION", "MAX_SIDECAR_BYTES", "MAX_SIDECAR_DEPTH", "Label", "Session", "session_paths",
           "load_session", "save_session",
           "validate_sidecar", "validate_arrivals", "sidecar_text", "mask_to_ranges", "missing_sidecar",
           "ARRIVALS_CLOCK_ERROR", "ARRIVALS_LATENCY"]

#: Value of the sidecar's ``"format"`` key.
FORMAT = "supramodal-session"
#: The only sidecar version this code reads and writes.
VERSION = 1

#: Largest sidecar read, bytes (checked before reading): an hour of labels and filled
#: ranges takes well under 1 MiB.
MAX_SIDECAR_BYTES = 16 * 2**20
#: Deepest nesting of arrays and objects read: the format nests 3 levels (object,
#: ``labels`` array, label object); deeper text is refused before it is parsed.
MAX_SIDECAR_DEPTH = 8

#: Largest clock error a recording's block times may show against ``arrivals.rate``, a fraction
#: (1 %): crystals are within about 100 ppm, the ceramic resonators of cheap boards within 0.5 %.
ARRIVALS_CLOCK_ERROR = 0.01
#: Longest a block's time may lag (or, after a late block, lead) the line its frames put it on,
#: seconds: a block delivered late by a stalled host, USB or network link. Delivery delays of real
#: devices are milliseconds to a fraction of a second.
ARRIVALS_LATENCY = 5.0

_REQUIRED = ("format", "version", "rate", "channels", "source", "labels")
_OPTIONAL = ("filled", "marks", "arrivals")
#: What a mark says happened at its frame (drivers.base.Block's ``restarts`` and ``overruns``).
MARK_KINDS = ("restart", "overrun")
_LABEL_KEYS = ("start", "end", "label")


@dataclass(frozen=True)
class Label:
    """A labelled time range of a recording.

    Attributes
    ----------
    start, end : float
        Seconds from the start of the recording (or of the replayed stream,
        for :attr:`replay.driver.ReplayDriver.labels`); ``start < end``, the
        range is ``[start, end)``.
    label : str
        What was under the whiskers / microphone, e.g. a texture name.
    """

    start: float
    end: float
    label: str

    def shifted(self, seconds: float) -> Label:
        """Return the same label moved later by ``seconds``."""
        return Label(self.start + seconds, self.end + seconds, self.label)


@dataclass(frozen=True, eq=False)
class Session:
    """A loaded session.

    Attributes
    ----------
    data : ndarray of float64, shape (frames, channels)
        Samples scaled to +-1 full scale.
    rate : int
        Frames per second, Hz.
    source : str
        Free text saying what recorded it (driver name and options).
    labels : tuple of Label
        In time order, not overlapping, within ``[0, frames / rate]``.
    filled : tuple of (int, int)
        ``[start_frame, end_frame)`` ranges the recording driver synthesised,
        ascending and not overlapping.
    marks : tuple of (int, str)
        ``(frame, kind)``, ascending: where the recording driver reported a board restart
        (``"restart"``: the source's time may jump there) or samples the board lost itself
        (``"overrun"``), so that a replay flags the same windows as the live run.
    path : pathlib.Path or None
        The WAV file it was loaded from, if any.
    arrivals : (ndarray of int64, ndarray of float64, float) or None
        Each recorded block's end frame (ascending, the last at most ``frames``), the time it
        was complete on the recording node's common time, seconds (non-decreasing), and the
        nominal rate of the recording node's clock model for the source (samples per second of
        common time); None when the session was not recorded by a node of several sources.
    """

    data: np.ndarray
    rate: int
    source: str
    labels: tuple[Label, ...] = ()
    filled: tuple[tuple[int, int], ...] = ()
    marks: tuple[tuple[int, str], ...] = ()
    path: Path | None = field(default=None)
    arrivals: tuple[np.ndarray, np.ndarray, float] | None = None

    @property
    def frames(self) -> int:
        """Frames in the session (rows of ``data``)."""
        return int(self.data.shape[0])

    @property
    def channels(self) -> int:
        """Channels per frame (columns of ``data``)."""
        return int(self.data.shape[1])

    @property
    def duration(self) -> float:
        """Length in seconds, ``frames / rate``."""
        return self.frames / self.rate

    def filled_mask(self) -> np.ndarray:
        """Per-frame filled flags, bool array of shape (frames,)."""
        mask = np.zeros(self.frames, dtype=bool)
        for s, e in self.filled:
            mask[s:e] = True
        return mask


def session_paths(path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Return the ``(NAME.wav, NAME.json)`` pair for ``NAME``, ``NAME.wav`` or ``NAME.json``."""
    p = Path(path)
    if p.suffix.lower() in (".wav", ".json"):
        p = p.with_suffix("")
    return p.with_name(p.name + ".wav"), p.with_name(p.name + ".json")


# --- strict JSON ------------------------------------------------------------

def _no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    seen: dict[str, Any] = {}
    for k, v in pairs:
        if k in seen:
            raise _StrictJson(f"key {k!r} appears twice in one object; keep one")
        seen[k] = v
    return seen


def _no_constants(name: str) -> NoReturn:
    raise _StrictJson(f"{name} is not a number JSON allows; use a finite number")


class _StrictJson(SessionError):
    """Raised by the parser hooks, which do not know the file; :func:`_load_json` names it."""


def _load_json(path: Path) -> Any:
    try:
        return read_json_file(path, max_bytes=MAX_SIDECAR_BYTES, max_depth=MAX_SIDECAR_DEPTH, error=SessionError,
                              limits=("supramodal.replay.session.MAX_SIDECAR_BYTES",
                                      "supramodal.replay.session.MAX_SIDECAR_DEPTH"),
                              object_pairs_hook=_no_duplicate_keys, parse_constant=_no_constants)
    except _StrictJson as e:
        raise SessionError(f"{path}: {e}") from None


# --- validation ---------------------------------------------------------------

def _is_int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: object) -> bool:
    return (_is_int(v) or isinstance(v, float)) and math.isfinite(v)


def _type_name(v: object) -> str:
    return {dict: "object", list: "array", str: "string", bool: "boolean", type(None): "null",
            int: "integer", float: "number"}.get(type(v), type(v).__name__)


#: ``bad(key, problem, fix)``: a SessionError naming the file, the key, the problem and the fix.
_Complaint = Callable[[str, str, str], SessionError]


def _complaint(where: str) -> _Complaint:
    """``bad(key, problem, fix)``: the SessionError that names the file, the key, the problem and the fix."""
    def bad(key: str, problem: str, fix: str) -> SessionError:
        return SessionError(f"{where}: {key}: {problem}; {fix}")
    return bad


def validate_sidecar(meta: Any, *, rate: int, channels: int, frames: int,
                     where: str = "sidecar") -> tuple[str, tuple[Label, ...], tuple[tuple[int, int], ...],
                                                      tuple[tuple[int, str], ...]]:
    """Check a parsed sidecar against the WAV it describes.

    Parameters
    ----------
    meta : object
        What :func:`json.load` returned.
    rate : int
        The WAV header's rate, Hz.
    channels : int
        The WAV's channel count.
    frames : int
        The WAV's length in frames (labels and filled ranges must lie within).
    where : str
        Prefix of error messages, normally the sidecar's path.

    Returns
    -------
    source : str
    labels : tuple of Label
    filled : tuple of (int, int)
    marks : tuple of (int, str)

    Raises
    ------
    SessionError
        Naming the key, the problem and the fix.
    """
    bad = _complaint(where)

    if not isinstance(meta, dict):
        raise SessionError(f"{where}: the sidecar must be a JSON object, got {_type_name(meta)}")
    unknown = sorted(set(meta) - set(_REQUIRED) - set(_OPTIONAL))
    if unknown:
        raise bad(", ".join(repr(k) for k in unknown), "unknown key",
                  f"remove it or fix its spelling (allowed keys: {', '.join(_REQUIRED + _OPTIONAL)})")
    missing = [k for k in _REQUIRED if k not in meta]
    if missing:
        raise bad(", ".join(repr(k) for k in missing), "missing", f"add it (required keys: {', '.join(_REQUIRED)})")

    if meta["format"] != FORMAT:
        raise bad("format", f"is {meta['format']!r}", f"it must be {FORMAT!r}; this is not a supramodal session")
    v = meta["version"]
    if not _is_int(v):
        raise bad("version", f"must be an integer, got {_type_name(v)} {v!r}", f"set it to {VERSION}")
    if v != VERSION:
        raise bad("version", f"is {v}, this code reads version {VERSION} only",
                  "use the supramodal version that wrote it, or convert the sidecar")

    r = meta["rate"]
    if not _is_number(r) or r <= 0:
        raise bad("rate", f"must be a positive number of Hz, got {_type_name(r)} {r!r}", f"set it to {rate}")
    if r != rate:
        raise bad("rate", f"is {r} Hz but the WAV header says {rate} Hz",
                  "correct the sidecar's rate or re-save the session; replay never guesses which is right")
    c = meta["channels"]
    if not _is_int(c) or c < 1:
        raise bad("channels", f"must be a positive integer, got {_type_name(c)} {c!r}", f"set it to {channels}")
    if c != channels:
        raise bad("channels", f"is {c} but the WAV has {channels}",
                  "correct the sidecar or pair it with the right WAV")
    source = meta["source"]
    if not isinstance(source, str):
        raise bad("source", f"must be a string, got {_type_name(source)}",
                  "describe the recording driver and its options as text")

    labels = _validate_labels(meta["labels"], frames / rate, 0.5 / rate, bad)
    filled = _validate_filled(meta.get("filled", []), frames, bad)
    marks = _validate_marks(meta.get("marks", []), frames, bad)
    return source, labels, filled, marks


def validate_arrivals(raw: Any, frames: int, where: str = "sidecar", marks: Iterable[tuple[int, str]] = (),
                      times: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
    """Check a sidecar's ``arrivals``: ``{"frames": [...], "seconds": [...], "rate": r}``.

    The arrays must be of equal length >= 1, frames integers ascending in ``(0, frames]``,
    seconds finite and non-decreasing, the rate a positive number.

    With ``times`` (the default; :func:`load_session`), the times must also agree with the frames
    and the rate: for any two blocks ``j < k`` with no mark (``marks``: the sidecar's restarts
    and overruns, where a source's time may jump) between their ends,

        ``|(seconds[k] - seconds[j]) - (frames[k] - frames[j]) / rate|``
        ``<= ARRIVALS_CLOCK_ERROR (frames[k] - frames[j]) / rate + ARRIVALS_LATENCY``

    that is, the source's clock within 1 % of the rate the sidecar names, each block late by at
    most 5 s. Times that break it (a jump, times that stand still, a rate far from the one the
    seconds show) would put the source's windows at the wrong times and pair them with the wrong
    windows of the other sources, silently; they are refused, naming both blocks. (The check is
    O(blocks): a running minimum and maximum per stretch between marks.) :func:`save_session`
    checks only the form, so that a live recording with a long stall is still saved.

    Returns
    -------
    (ndarray of int64, ndarray of float64, float)

    Raises
    ------
    SessionError
        Naming the key, the problem and the fix.
    """
    bad = _complaint(where)

    if not (isinstance(raw, dict) and sorted(raw) == ["frames", "rate", "seconds"]):
        raise bad("arrivals", f"must be an object with exactly the keys 'frames', 'seconds' and 'rate', got "
                  f"{str(raw)[:80]}", "write each recorded block's end frame and its time, or omit the key")
    if not (_is_number(raw["rate"]) and raw["rate"] > 0):
        raise bad("arrivals.rate", f"must be a positive number of Hz, got {raw['rate']!r}",
                  "write the nominal rate of the recording node's clock for this source")
    f, t = raw["frames"], raw["seconds"]
    if not (isinstance(f, list) and isinstance(t, list) and 1 <= len(f) == len(t)):
        raise bad("arrivals", "'frames' and 'seconds' must be arrays of one length >= 1",
                  "give one time per block end")
    for i, v in enumerate(f):
        if not _is_int(v):
            raise bad(f"arrivals.frames[{i}]", f"must be an integer, got {_type_name(v)} {v!r}", "write frame counts")
        if not 0 < v <= frames:
            raise bad(f"arrivals.frames[{i}]", f"{v} is outside (0, {frames}]",
                      "block ends must lie within the recording")
    for i, v in enumerate(t):
        if not _is_number(v):
            raise bad(f"arrivals.seconds[{i}]", f"must be a finite number, got {_type_name(v)} {v!r}",
                      "write seconds of the recording node's common time")
    fa, ta = np.array(f, dtype=np.int64), np.array(t, dtype=np.float64)
    step = np.flatnonzero(np.diff(fa) <= 0)
    if step.size:
        i = int(step[0]) + 1
        raise bad(f"arrivals.frames[{i}]", f"{int(fa[i])} is not after the block before it ({int(fa[i - 1])})",
                  "block ends must ascend")
    back = np.flatnonzero(np.diff(ta) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise bad(f"arrivals.seconds[{i}]", f"{t[i]!r} comes before the block before it ({t[i - 1]!r})",
                  "arrival times never go back")
    if times:
        _check_arrival_times(fa, ta, float(raw["rate"]), marks, bad)
    return fa, ta, float(raw["rate"])


def _check_arrival_times(fa: np.ndarray, ta: np.ndarray, rate: float, marks: Iterable[tuple[int, str]],
                         bad: _Complaint) -> None:
    """Check the consistency rule of :func:`validate_arrivals`, in O(blocks)."""
    with np.errstate(over="ignore", invalid="ignore"):
        nominal = fa / rate                     # when each block ends by its frames, seconds
    if not np.all(np.isfinite(nominal)):
        raise bad("arrivals.rate", f"{rate!r} Hz puts the block ends at non-finite times",
                  "write the nominal rate of the recording node's clock for this source")
    late = ta - (1.0 + ARRIVALS_CLOCK_ERROR) * nominal      # lag of block k behind block j: late[k] - late[j]
    early = ta - (1.0 - ARRIVALS_CLOCK_ERROR) * nominal     # lead of block k on block j: early[j] - early[k]
    # A stretch: the blocks whose ends have the same number of marks before them.
    cut = np.sort(np.fromiter((m[0] for m in marks), dtype=np.int64, count=-1))
    stretch = np.searchsorted(cut, fa, side="left")
    starts = np.flatnonzero(np.r_[True, np.diff(stretch) != 0])
    for a, b in zip(starts, np.r_[starts[1:], fa.size]):
        if b - a < 2:
            continue
        for name, worst in (("after", late[a:b] - np.minimum.accumulate(late[a:b])),
                            ("before", np.maximum.accumulate(early[a:b]) - early[a:b])):
            over = np.flatnonzero(~(worst <= ARRIVALS_LATENCY))
            if not over.size:
                continue
            k = a + int(over[0])
            j = a + int(np.argmin(late[a:k]) if name == "after" else np.argmax(early[a:k]))
            passed, lasts = float(ta[k] - ta[j]), float(nominal[k] - nominal[j])
            raise bad(f"arrivals.seconds[{k}]",
                      f"{float(ta[k])!r} s is {passed:.6g} s after arrivals.seconds[{j}] ({float(ta[j])!r} s), "
                      f"but the {int(fa[k] - fa[j])} frames between those blocks' ends last {lasts:.6g} s at "
                      f"arrivals.rate {rate!r} Hz: block times must follow the frames to within "
                      f"{ARRIVALS_CLOCK_ERROR:.0%} of that plus {ARRIVALS_LATENCY:g} s of delivery delay "
                      "(a real device's drift and latency), or jump only at a restart or overrun mark",
                      "these are not the recording's times: write the recorded ones back (a copy from where the "
                      "recording was made), or delete the sidecar's 'arrivals' and replay the session with "
                      "timing = 'nominal' (then not in step with the other sources)")


def _validate_labels(raw: Any, duration: float, slack: float, bad: _Complaint) -> tuple[Label, ...]:
    if not isinstance(raw, list):
        raise bad("labels", f"must be an array, got {_type_name(raw)}", "use [] when nothing is labelled")
    out: list[Label] = []
    for i, item in enumerate(raw):
        key = f"labels[{i}]"
        if not isinstance(item, dict):
            raise bad(key, f"must be an object, got {_type_name(item)}",
                      'write {"start": s, "end": s, "label": "name"}')
        extra = sorted(set(item) - set(_LABEL_KEYS))
        missing = [k for k in _LABEL_KEYS if k not in item]
        if extra or missing:
            raise bad(key, f"has keys {sorted(item)}", f"use exactly {list(_LABEL_KEYS)}")
        s, e, name = item["start"], item["end"], item["label"]
        for k, val in (("start", s), ("end", e)):
            if not _is_number(val):
                raise bad(f"{key}.{k}", f"must be a finite number of seconds, got {_type_name(val)} {val!r}",
                          "write seconds from the start of the recording")
        if not is_name(name):
            raise bad(f"{key}.label", f"must be {NAME_HELP}, got {str(name)[:80]!r}",
                      "name the texture (supramodal label --replace relabels a recording)")
        if not 0 <= s < e:
            raise bad(key, f"range [{s}, {e}) is empty, reversed or negative", "need 0 <= start < end")
        # Half a frame of slack: "end = duration" computed in float must pass.
        if e > duration + slack:
            raise bad(key, f"ends at {e} s, after the recording's end at {duration} s",
                      "clip it to the recording or pair the sidecar with the right WAV")
        if out and s < out[-1].end:
            prev = out[-1]
            problem = f"starts before labels[{i - 1}] ([{prev.start}, {prev.end}) {prev.label!r})"
            fix = ("put labels in time order" if s < prev.start else
                   "labels must not overlap; end the earlier one where this one starts")
            raise bad(key, f"[{s}, {e}) {problem}", fix)
        out.append(Label(float(s), float(e), name))
    return tuple(out)


def _validate_filled(raw: Any, frames: int, bad: _Complaint) -> tuple[tuple[int, int], ...]:
    if not isinstance(raw, list):
        raise bad("filled", f"must be an array of [start_frame, end_frame] pairs, got {_type_name(raw)}",
                  "omit the key when no frame was filled")
    out: list[tuple[int, int]] = []
    for i, item in enumerate(raw):
        key = f"filled[{i}]"
        if not (isinstance(item, list) and len(item) == 2 and all(_is_int(v) for v in item)):
            raise bad(key, f"must be a pair of integer frame indices, got {item!r}",
                      "write [start_frame, end_frame] (end excluded)")
        s, e = item
        if not 0 <= s < e <= frames:
            raise bad(key, f"range [{s}, {e}) is empty or outside the recording's {frames} frames",
                      "need 0 <= start < end <= frames")
        if out and s < out[-1][1]:
            raise bad(key, f"[{s}, {e}) starts before the end of filled[{i - 1}] {list(out[-1])}",
                      "list ranges in order without overlap (merge overlapping ones)")
        out.append((s, e))
    return tuple(out)


def _validate_marks(raw: Any, frames: int, bad: _Complaint) -> tuple[tuple[int, str], ...]:
    if not isinstance(raw, list):
        raise bad("marks", f"must be an array of [frame, kind] pairs, got {_type_name(raw)}",
                  "omit the key when the board never restarted or overran")
    out: list[tuple[int, str]] = []
    for i, item in enumerate(raw):
        key = f"marks[{i}]"
        if not (isinstance(item, list) and len(item) == 2 and _is_int(item[0]) and isinstance(item[1], str)):
            raise bad(key, f"must be a [frame, kind] pair, got {item!r}", f"write [frame, one of {list(MARK_KINDS)}]")
        frame, kind = item
        if kind not in MARK_KINDS:
            raise bad(key, f"kind {kind!r} is unknown", f"use one of {list(MARK_KINDS)}")
        if not 0 <= frame < frames:
            raise bad(key, f"frame {frame} is outside the recording's {frames} frames", "need 0 <= frame < frames")
        if out and frame < out[-1][0]:
            raise bad(key, f"frame {frame} comes before marks[{i - 1}] at {out[-1][0]}", "list marks in frame order")
        out.append((frame, kind))
    return tuple(out)


# --- load / save ----------------------------------------------------------------

def load_session(path: str | os.PathLike[str]) -> Session:
    """Load and validate a session.

    Parameters
    ----------
    path : str or path-like
        ``NAME``, ``NAME.wav`` or ``NAME.json``; both files must exist.

    Returns
    -------
    Session

    Raises
    ------
    MissingSidecarError
        If the sidecar is missing (:func:`missing_sidecar`; also a FileNotFoundError).
    FileNotFoundError
        If the WAV file is missing.
    SessionError
        If the sidecar is not valid JSON or fails validation (see
        :func:`validate_sidecar`); checked before the samples are read.
    WavFormatError
        If the WAV file is unsupported, truncated or corrupt.
    """
    wav, js = session_paths(path)
    if not js.exists():
        raise missing_sidecar(path)
    meta = _load_json(js)
    info = wav_info(wav)
    source, labels, filled, marks = validate_sidecar(meta, rate=info.rate, channels=info.channels,
                                                     frames=info.frames, where=str(js))
    arrivals = validate_arrivals(meta["arrivals"], info.frames, str(js), marks) if "arrivals" in meta else None
    data, rate = read_wav(wav)
    return Session(data=data, rate=rate, source=source, labels=labels, filled=filled, marks=marks, path=wav,
                   arrivals=arrivals)


def missing_sidecar(path: str | os.PathLike[str]) -> MissingSidecarError:
    """Return the error for a session whose sidecar ``NAME.json`` is not there.

    It names the file, what is lost without it and how to get it back (a caller that needs a
    session, such as a replay with ``timing = "recorded"``, raises it rather than playing the
    bare WAV).
    """
    wav, js = session_paths(path)
    have = f"beside {wav.name}" if wav.exists() else f"and so is {wav.name}"
    return MissingSidecarError(
        f"{js}: no sidecar: the session's sidecar file is missing ({have}); it holds the session's rate and channel "
        "checks, its labels, its filled ranges and marks, and its blocks' recorded times ('arrivals', which "
        "replay it in step with the other sources of its recording); copy it back from where the "
        f"recording was made (supramodal record writes {js.name} beside {wav.name}), or record again; "
        "without it the WAV is only samples: it replays with timing = 'nominal' alone, unlabelled and out "
        "of step with any other source")


def mask_to_ranges(mask: ArrayLike) -> list[tuple[int, int]]:
    """``[start, end)`` ranges of the True runs of a 1-D bool array."""
    m = np.asarray(mask, dtype=bool).ravel()
    edges = np.diff(np.concatenate(([False], m, [False])).astype(np.int8))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1)
    return [(int(s), int(e)) for s, e in zip(starts, ends)]


def _label_dict(item: Label | Mapping[str, Any] | tuple[float, float, str]) -> dict[str, Any]:
    if isinstance(item, Label):
        return {"start": item.start, "end": item.end, "label": item.label}
    if isinstance(item, Mapping):
        return dict(item)
    s, e, name = item  # (start, end, label) tuple
    return {"start": s, "end": e, "label": name}


def sidecar_text(meta: dict[str, Any]) -> str:
    """Return the sidecar as written: indented JSON, with the block ``arrivals`` on one compact line each.

    One number per line would double their size.
    """
    head = {k: v for k, v in meta.items() if k != "arrivals"}
    text = json.dumps(head, indent=1, allow_nan=False)
    if "arrivals" in meta:
        compact = json.dumps(meta["arrivals"], separators=(",", ":"), allow_nan=False)
        text = text[:-2] + f',\n "arrivals": {compact}\n}}'
    return text + "\n"


def save_session(path: str | os.PathLike[str], data: ArrayLike, rate: int, source: str,
                 labels: Iterable[Label | Mapping[str, Any] | tuple[float, float, str]] = (),
                 filled: np.ndarray | Iterable[tuple[int, int]] | None = None,
                 dtype: str = "float32", marks: Iterable[tuple[int, str]] = (),
                 arrivals: tuple[Iterable[int], Iterable[float], float] | None = None) -> tuple[Path, Path]:
    """Write a session: ``NAME.wav`` and its sidecar ``NAME.json``.

    The sidecar is validated exactly as :func:`load_session` would before
    anything is written, except that the block times in ``arrivals`` are checked
    for form only (a live recording whose times :func:`load_session` would refuse
    is still saved, rather than lost; see :func:`validate_arrivals`). An
    existing sidecar is removed first and the new one written last, so an
    interrupted save leaves a WAV without a sidecar (not loadable as a session)
    rather than a sidecar describing the wrong WAV.

    Parameters
    ----------
    path : str or path-like
        ``NAME``, ``NAME.wav`` or ``NAME.json``.
    data : array_like of float, shape (frames, channels) or (frames,)
        Samples, full scale +-1.
    rate : int
        Frames per second, Hz (a whole number: WAV stores integers).
    source : str
        Free text: the recording driver and its options.
    labels : iterable of Label, dict or (start, end, label) tuple, optional
        Seconds from the start of ``data``; sorted by start here, then
        checked for overlap and range.
    filled : sequence of (start_frame, end_frame), or bool array of shape (frames,), optional
        Frames the recording driver synthesised (e.g. the concatenated
        :attr:`supramodal.drivers.base.Block.filled` masks).
    dtype : {'float32', 'float64', 'int16', 'int32', 'uint8'}, default 'float32'
        Sample type of the WAV (see :func:`replay.wavio.write_wav`).
    marks : iterable of (frame, kind), optional
        Board restarts and overruns the recording driver reported (kind ``"restart"`` or
        ``"overrun"``, see :attr:`Session.marks`); sorted by frame here.
    arrivals : (frames, seconds, rate), optional
        Each block's end frame, when it was complete on the recording node's common time, and
        its clock model's nominal rate (see :attr:`Session.arrivals`); seconds are written to
        the microsecond.

    Returns
    -------
    (pathlib.Path, pathlib.Path)
        The WAV and sidecar written.

    Raises
    ------
    SessionError
        If the metadata would not validate.
    ValueError
        For bad samples, rate or dtype.
    """
    wav, js = session_paths(path)
    x = as_frames(data)
    if isinstance(rate, bool) or not _is_number(rate) or not float(rate).is_integer() or rate < 1:
        raise InputError(f"rate must be a positive whole number of Hz (WAV stores integers), got {rate!r}")
    rate = int(rate)
    # Sort only what sorts; anything malformed stays in place for validation to name.
    label_list = sorted((_label_dict(item) for item in labels),
                        key=lambda d: d["start"] if _is_number(d.get("start")) else -math.inf)
    ranges: list[tuple[int, int]]
    if filled is None:
        ranges = []
    else:
        arr = np.asarray(filled)
        if arr.dtype == bool:
            if arr.shape != (x.shape[0],):
                raise InputError(f"filled mask must have shape ({x.shape[0]},), got {arr.shape}")
            ranges = mask_to_ranges(arr)
        else:
            ranges = [(int(s), int(e)) for s, e in filled]
    meta: dict[str, Any] = {"format": FORMAT, "version": VERSION, "rate": rate, "channels": int(x.shape[1]),
                            "source": source, "labels": label_list}
    if ranges:
        meta["filled"] = [list(r) for r in ranges]
    mark_list: list[list[Any]] = sorted(([m[0], m[1]] for m in marks), key=lambda m: m[0] if _is_int(m[0]) else -1)
    if mark_list:
        meta["marks"] = mark_list
    validate_sidecar(meta, rate=rate, channels=int(x.shape[1]), frames=int(x.shape[0]), where=str(js))
    if arrivals is not None:
        frames_at, seconds_at, clock_rate = arrivals
        meta["arrivals"] = {"frames": [int(v) for v in frames_at],
                            "seconds": [round(float(v), 6) for v in seconds_at], "rate": float(clock_rate)}
        validate_arrivals(meta["arrivals"], int(x.shape[0]), str(js), times=False)   # a live recording is kept
    text = sidecar_text(meta)
    if len(text.encode("utf-8")) > MAX_SIDECAR_BYTES:
        raise SessionError(f"{js}: the sidecar would take {len(text.encode('utf-8'))} bytes, more than the "
                           f"{MAX_SIDECAR_BYTES} a session's sidecar may have (MAX_SIDECAR_BYTES): it could not be "
                           "loaded; record shorter sessions")

    js.unlink(missing_ok=True)
    write_wav(wav, x, rate, dtype=dtype)
    fd, tmp = tempfile.mkstemp(prefix=f".{js.name}.", suffix=".tmp", dir=js.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, js)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return wav, js
