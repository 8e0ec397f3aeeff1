"""XDF recordings (LabRecorder's files) as sessions that replay with their recorded timing.

Needs pyxdf (the optional extra ``lsl``: ``pip install "supramodal[lsl]"``); :func:`import_pyxdf`
is the one place that imports it.

A stream of an XDF file becomes a :class:`~supramodal.replay.session.Session` whose ``arrivals``
are the recorded timestamps: blocks of about 10 ms, each with the time of its last sample, in
seconds from the file's earliest timestamp (of any regularly sampled stream in it, so that every
stream of one file shares that zero). Replayed with ``timing = "recorded"``, the node's clock model
is fitted to those times, and two streams of one file (a whisker array at 5 kHz and a microphone at
44.1 kHz, each on its own crystal) are put on one time line as they were recorded, at any speed.

The timestamps are those the file holds, put on the recorder's clock by the file's clock offsets
(pyxdf's ``synchronize_clocks``), not dejittered: the node's clock model rejects the jitter itself.
A timestamp earlier than the one before it (jitter across a chunk boundary) is raised to it, so
that block times never go backwards.

Samples the file does not have (a sender that dropped out; a node's signal outlet, which sends
no sample it did not measure) show as a step in the timestamps. As the LSL inlet does live
(:mod:`supramodal.drivers.lsl`, the same tolerance and longest gap), a step of more than one
sample period plus ``gap_tolerance`` is filled with zeros, marked filled (the node counts them,
the windows are flagged ``gap``), so that stream time stays the recording's. How many are
missing is read on the sample clock each side of the gap (the median of ``t - i / rate`` over
:data:`CLOCK_FIT_SECONDS` of stamps), not from the two jittered stamps at its edges. A gap longer than
``max_gap`` is not filled but marked as a restart (the clock model starts again after it). Files
are data: a stream that is not numeric, not regularly sampled, or holds non-finite samples or
timestamps is refused with a message naming it; so is one whose ``nominal_srate`` is not a whole
number of Hz from 1 to :data:`MAX_XDF_RATE`, or whose
``channel_count`` is 0, or that would take more than :data:`MAX_XDF_SAMPLES` samples once its
gaps are filled (checked before anything is filled). pyxdf's own log (tracebacks of the chunks it
skips, notes on clock segments) is kept off the terminal: a file it cannot read is refused with
its first complaint, and one it read only by skipping damaged chunks gives an
:class:`~supramodal.replay.errors.XdfDamageWarning`.
"""

from __future__ import annotations

import logging
import math
import os
import re
import threading
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

from supramodal.checks import NAME_HELP, Key, is_name, text
from supramodal.drivers.base import DeviceUnavailable
from supramodal.drivers.lsl import DEFAULT_GAP_TOLERANCE, DEFAULT_MAX_GAP
from supramodal.drivers.spec import BuildContext, Built, DriverSpec, OptionError
from supramodal.drivers.timestamps import TimestampSteps
from supramodal.interrupts import held_interrupts
from supramodal.replay.errors import ReplayError, XdfDamageWarning
from supramodal.replay.session import Label, Session

#: Seconds per replayed block of an XDF stream.
XDF_BLOCK_SECONDS = 0.01
#: Highest ``nominal_srate`` replayed, Hz: above any sensor the node serves (audio interfaces
#: reach 768 kHz); a rate beyond it is a damaged or foreign header.
MAX_XDF_RATE = 1_000_000
#: How far the rate a stream's timestamps show may be from its ``nominal_srate``, a factor either way.
RATE_MISMATCH = 2.0
#: Seconds of filled frames always allowed, however few the stream's own: one pause as long as the longest gap
#: filled (a short stream with a pause replays); beyond it, and beyond the stream's own frames, a stream is
#: more made up than recorded.
MIN_FILL_SECONDS_REFUSED = DEFAULT_MAX_GAP
#: Most samples (frames x channels) one replayed stream may hold once its gaps are filled: 2**29,
#: 4 GiB as float64 (an hour of 20 channels at 5 kHz, or three of 44.1 kHz audio).
MAX_XDF_SAMPLES = 2**29


#: Largest timestamp an XDF stream may carry, seconds: LSL's clock counts from the machine's boot
#: (30 years is 9.5e8 s); beyond it the file's clock offsets are damaged.
MAX_XDF_TIME = 1e9

#: One stream of an XDF file as pyxdf reads it: ``info`` (the header, each value a list of strings),
#: ``time_series``, ``time_stamps``, ...
XdfStream = dict[str, Any]


def import_pyxdf() -> ModuleType:
    """Return the pyxdf module, or raise :class:`DeviceUnavailable` saying what to install."""
    try:
        with held_interrupts():
            import pyxdf
    except ImportError:
        raise DeviceUnavailable('reading XDF files needs pyxdf: pip install "supramodal[lsl]"') from None
    module: ModuleType = pyxdf      # a module, untyped (Any) to mypy
    return module


def _describe(info: dict[str, Any]) -> str:
    def first(key: str) -> Any:
        v = info.get(key)
        return v[0] if isinstance(v, list) and v else v

    return (f"name={first('name')!r} type={first('type')!r} source_id={first('source_id')!r} "
            f"{first('channel_count')} ch at {first('nominal_srate')} Hz")


def _matches(info: dict[str, Any], want: dict[str, str]) -> bool:
    return all((info.get(k) or [None])[0] == v for k, v in want.items())


class _Kept(logging.Handler):
    """Keeps pyxdf's log records (while a file is read) instead of letting them reach stderr."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


_PYXDF_LOG = threading.Lock()       # one read at a time swaps pyxdf's logger

#: Most channels a stream of an XDF file may declare (a WAV's most: every replayed stream becomes one).
MAX_XDF_CHANNELS = 65535
#: Longest stream header read by :func:`check_xdf_headers`, bytes.
_MAX_HEADER_BYTES = 1 << 20
_CHANNEL_COUNT = re.compile(rb"<channel_count>\s*([^<]*?)\s*</channel_count>")


def check_xdf_headers(path: Path) -> None:
    """Refuse, before pyxdf reads it, a file whose headers declare channel or sample counts out of bounds.

    That is a file whose stream headers declare more than :data:`MAX_XDF_CHANNELS` channels, or
    a count that is no whole number, or one of whose Samples chunks declares more samples than
    its bytes can hold: pyxdf sizes its buffers from those counts (a 306-byte file declaring 1e9
    channels took 12.7 GB). Walks the chunks' lengths only (seeking past the samples); a chunk
    structure it cannot follow is left for pyxdf to refuse.
    """
    size = path.stat().st_size
    channels: dict[int, int] = {}                               # by StreamId, as their headers declare
    with path.open("rb") as f:
        if f.read(4) != b"XDF:":
            return
        while f.tell() < size:
            n = f.read(1)
            if len(n) != 1 or n[0] not in (1, 4, 8):
                return
            raw = f.read(n[0])
            if len(raw) != n[0]:
                return
            length = int.from_bytes(raw, "little")
            start = f.tell()
            if length < 2 or start + length > size:
                return
            tag = int.from_bytes(f.read(2), "little")
            if tag == 2 and length <= _MAX_HEADER_BYTES:        # a StreamHeader: StreamId + its XML
                content = f.read(length - 2)
                for found in _CHANNEL_COUNT.findall(content[4:]):
                    text = found.decode("ascii", "replace")
                    # the length first: int() refuses more than 4300 digits with a ValueError of its own
                    if not text.isdigit() or len(text.lstrip("0")) > 5 or int(text) > MAX_XDF_CHANNELS:
                        raise ReplayError(f"{path}: a stream header declares channel_count {text[:20]!r}; a stream "
                                          f"has 1 to {MAX_XDF_CHANNELS} channels (MAX_XDF_CHANNELS): the header is "
                                          "damaged, or the stream is no sensor's")
                    channels[int.from_bytes(content[:4], "little")] = int(text)
            elif tag == 3:                                      # Samples: StreamId, then NumSamples (varlen)
                head = f.read(min(length - 2, 13))
                width = head[4] if len(head) > 4 else 0
                if width in (1, 4, 8) and len(head) >= 5 + width:
                    # pyxdf allocates every declared sample and channel before reading one, a marker stream's as
                    # Python lists (16 M samples declared in 5 bytes took 12 s and 1.5 GB; 3000 samples of 65535
                    # channels in a 9 kB file, 1.6 GB); in the file each takes a byte (its stamp flag) and each
                    # value a byte at least
                    count = int.from_bytes(head[5:5 + width], "little")
                    room = length - 2 - 5 - width
                    each = 1 + channels.get(int.from_bytes(head[:4], "little"), 0)
                    if count * each > room:
                        raise ReplayError(f"{path}: the Samples chunk at byte {start} declares {count} samples of "
                                          f"{each - 1} channel(s) in {room} bytes, room for {room // each} at most: "
                                          "the file is damaged there; record it again, or give the file LabRecorder "
                                          "wrote")
            f.seek(start + length)


def load_xdf_streams(path: str | os.PathLike[str]) -> list[XdfStream]:
    """Every stream of an XDF file, timestamps on the recorder's clock: a list of pyxdf's stream dicts.

    :class:`DeviceUnavailable` if the file is missing; :class:`ReplayError` if it cannot be
    read as XDF (also when pyxdf found nothing but damage). pyxdf's log stays off the terminal; a
    file read only by skipping damaged chunks gives an :class:`XdfDamageWarning`.
    """
    pyxdf = import_pyxdf()
    path = Path(path)
    if not path.is_file():
        raise DeviceUnavailable(f"{path}: no such XDF file")
    check_xdf_headers(path)
    log = logging.getLogger("pyxdf")
    kept = _Kept()
    streams: list[XdfStream]
    with _PYXDF_LOG:
        propagate, level = log.propagate, log.level
        log.addHandler(kept)
        log.propagate = False
        log.setLevel(logging.WARNING)
        try:
            streams, _ = pyxdf.load_xdf(str(path), synchronize_clocks=True, dejitter_timestamps=False, verbose=False)
        except Exception as exc:  # pyxdf's errors on a damaged or foreign file, one place
            raise ReplayError(f"{path}: not a readable XDF file ({type(exc).__name__}: {exc})") from None
        finally:
            log.removeHandler(kept)
            log.propagate = propagate
            log.setLevel(level)
    damage = [r for r in kept.records if r.levelno >= logging.ERROR]
    if damage:
        first = _said(damage[0])
        if not streams:
            raise ReplayError(f"{path}: not a readable XDF file: no stream could be read (pyxdf: {first}); it is "
                              "damaged or not XDF: record it again, or give the file LabRecorder wrote")
        warnings.warn(f"{path}: damaged: pyxdf skipped {len(damage)} damaged part(s) of the file ({first}); their "
                      "samples are missing (filled as gaps where the timestamps show them)", XdfDamageWarning,
                      stacklevel=2)
    return streams


def _said(record: logging.LogRecord) -> str:
    """Return a pyxdf log record in one line, with the exception it carries."""
    text = record.getMessage().strip()
    if record.exc_info and record.exc_info[1] is not None:
        text += f" ({type(record.exc_info[1]).__name__}: {record.exc_info[1]})"
    return " ".join(text.split())


def _regular(s: XdfStream) -> bool:
    info = s.get("info", {})
    try:
        rate = float(info.get("nominal_srate", ["0"])[0])
    except (TypeError, ValueError):
        return False
    return rate > 0 and isinstance(s.get("time_series"), np.ndarray) and len(s.get("time_stamps", ())) > 0


def xdf_session(path: str | os.PathLike[str], name: str | None = None, stream_type: str | None = None,
                source_id: str | None = None, streams: list[XdfStream] | None = None,
                labels: str | None = None) -> Session:
    """One stream of an XDF file as a session with its recorded timing (see the module notes).

    Parameters
    ----------
    path : path-like
    name, stream_type, source_id : str, optional
        What the stream must match (at least one; all that are given). Exactly one stream of the
        file must match.
    streams : list, optional
        :func:`load_xdf_streams` of the file, when the caller has it already (one read for
        several sources).
    labels : str, optional
        The name of a marker stream of the same file whose strings are the truth labels
        (:func:`marker_labels`).
    """
    want = {k: v for k, v in (("name", name), ("type", stream_type), ("source_id", source_id)) if v is not None}
    if not want:
        raise ReplayError("an XDF source needs the stream's name, type or source_id")
    path = Path(path)
    streams = load_xdf_streams(path) if streams is None else streams
    found = [s for s in streams if _matches(s.get("info", {}), want)]
    asked = ", ".join(f"{k}={v!r}" for k, v in want.items())
    if len(found) != 1:
        have = "; ".join(_describe(s.get("info", {})) for s in streams) or "no stream"
        what = "no stream" if not found else f"{len(found)} streams"
        raise ReplayError(f"{path}: {what} with {asked}; the file has {have}")
    s = found[0]
    where = f"{path}: stream {_describe(s['info'])}"
    if not _regular(s):
        raise ReplayError(f"{where}: not a regularly sampled numeric stream (markers cannot be replayed as a signal)")
    data = np.asarray(s["time_series"])
    if data.ndim == 2 and data.shape[1] == 0:
        raise ReplayError(f"{where}: channel_count is {(s['info'].get('channel_count') or ['0'])[0]} in the file: the "
                          "stream has no channel to replay; name a stream that has samples")
    if data.dtype.kind not in "fiu" or data.ndim != 2 or data.shape[0] == 0:
        raise ReplayError(f"{where}: expected numeric samples of shape (samples, channels), got {data.dtype} "
                          f"{data.shape}")
    stamps = np.asarray(s["time_stamps"], dtype=np.float64)
    if stamps.shape != (data.shape[0],) or not np.all(np.isfinite(stamps)):
        raise ReplayError(f"{where}: its timestamps are not one finite number per sample")
    if np.max(np.abs(stamps)) > MAX_XDF_TIME:
        raise ReplayError(f"{where}: its timestamps, with the file's clock offsets applied, reach "
                          f"{np.max(np.abs(stamps)):.3g} s, beyond the {MAX_XDF_TIME:g} s (MAX_XDF_TIME) any LSL clock "
                          "shows: the file's clock offset chunks are damaged; record it again, or remove them")
    if data.dtype.kind in "iu":
        data = data.astype(np.float64) / _full_scale(data.dtype)
    else:
        data = data.astype(np.float64)
    if not np.all(np.isfinite(data)):
        raise ReplayError(f"{where}: it holds NaN or infinite samples")
    rate = float(s["info"]["nominal_srate"][0])
    whole = _session_rate(rate, where)          # before anything is filled at that rate
    _check_stamps_fit_rate(stamps, rate, where)
    made_up = sum(missing for _, kind, missing in _steps(stamps, rate) if kind == "gap")
    frames = data.shape[0] + made_up
    if frames * data.shape[1] > MAX_XDF_SAMPLES:
        raise ReplayError(f"{where}: its timestamps span {float(stamps[-1] - stamps[0]):.6g} s: with the gaps in them "
                          f"filled at nominal_srate {rate:g} Hz it would be {frames} frames x {data.shape[1]} "
                          f"channel(s), more than the {MAX_XDF_SAMPLES} samples a replayed stream may hold "
                          "(MAX_XDF_SAMPLES, 4 GiB); check the stream's nominal_srate and timestamps, or cut the "
                          "recording into shorter files")
    if made_up > max(data.shape[0], rate * MIN_FILL_SECONDS_REFUSED):
        raise ReplayError(f"{where}: its timestamps leave room for {made_up} missing frames at nominal_srate "
                          f"{rate:g} Hz, more than the {data.shape[0]} it holds: filled with zeros, the replay would "
                          "be more made up than recorded (a stream that sends now and then, or a wrong "
                          "nominal_srate); name a regularly sampled stream, or correct its nominal_srate where it "
                          "was recorded")
    zero = min(float(np.min(x["time_stamps"])) for x in streams if _regular(x))
    data, stamps, filled, marks = fill_gaps(data, stamps, rate)
    truth = () if labels is None else marker_labels(_marker_stream(streams, labels, path), stamps, rate,
                                                    f"{path}: labels {labels!r}")
    return Session(data, whole, f"XDF {path.name}: {_describe(s['info'])}", path=path,
                   arrivals=_arrivals(stamps - zero, rate, [at for at, _ in marks]), filled=filled, marks=marks,
                   labels=truth)


def _marker_stream(streams: list[XdfStream], name: str, path: Path) -> XdfStream:
    """Return the one marker stream called ``name``: irregular, one string channel."""
    found = [s for s in streams if _matches(s.get("info", {}), {"name": name})]
    if len(found) != 1:
        have = "; ".join(_describe(s.get("info", {})) for s in streams) or "no stream"
        raise ReplayError(f"{path}: labels: {'no' if not found else len(found)} stream(s) named {name!r}; the file "
                          f"has {have}")
    info = found[0]["info"]
    if (info.get("channel_format") or [None])[0] != "string" or (info.get("channel_count") or ["0"])[0] != "1":
        raise ReplayError(f"{path}: labels: stream {_describe(info)} is not a marker stream (one string channel); "
                          "name the stream whose markers say which texture is there")
    return found[0]


def marker_labels(markers: XdfStream, stamps: np.ndarray, rate: float, where: str = "labels") -> tuple[Label, ...]:
    """Truth labels from a marker stream, in the seconds of the stream whose samples are stamped ``stamps``.

    The stamps are those after :func:`fill_gaps`.

    Each marker's text starts a label at the first sample stamped at or after the marker, which
    runs until the next marker (or the end of the stream); a marker whose text is empty ends the
    current label. A label that would cover no sample is left out. A marker is data: a text that is no
    name (:data:`~supramodal.checks.NAME_HELP`: a label becomes a model's class, a file name's part, a
    line on a terminal) is refused, a :class:`ReplayError` naming ``where``.
    """
    times = np.asarray(markers.get("time_stamps", ()), dtype=np.float64)
    texts = [str(m[0]).strip() if len(m) else "" for m in markers.get("time_series", ())]
    for i, t in enumerate(texts):
        if t and not is_name(t):
            raise ReplayError(f"{where}: marker {i} says {t[:80]!r}, which is no label ({NAME_HELP}); relabel the "
                              "recording after the import (supramodal label), or fix the markers")
    order = np.argsort(times, kind="stable")
    starts = np.searchsorted(stamps, times[order]) / rate
    ends = np.r_[starts[1:], stamps.size / rate]
    return tuple(Label(float(a), float(b), texts[k]) for a, b, k in zip(starts, ends, order.tolist())
                 if texts[k] and b > a)


def fill_gaps(data: np.ndarray, stamps: np.ndarray, rate: float, tolerance: float = DEFAULT_GAP_TOLERANCE,
              max_gap: float = DEFAULT_MAX_GAP) -> tuple[np.ndarray, np.ndarray, tuple[tuple[int, int], ...],
                                                         tuple[tuple[int, str], ...]]:
    """Put back the samples a recorded stream's timestamps say are missing (see the module notes).

    Parameters
    ----------
    data : ndarray, shape (samples, channels)
    stamps : ndarray, shape (samples,)
        Seconds, one per sample.
    rate : float
        The nominal rate, Hz.
    tolerance : float
        Seconds of timestamp jitter beyond one sample period before a step counts as missing
        samples (default the LSL inlet's ``DEFAULT_GAP_TOLERANCE``).
    max_gap : float
        Longest gap filled, seconds (default the LSL inlet's ``DEFAULT_MAX_GAP``); a longer one,
        or a step back beyond the tolerance, is marked as a restart instead (the inlet's rules:
        :class:`~supramodal.drivers.timestamps.TimestampSteps`).

    Returns
    -------
    data, stamps : ndarray
        With the missing samples as zeros, their times evenly spread over the gap.
    filled : tuple of (int, int)
        The filled ranges, ``[start, end)`` frames of the returned data.
    marks : tuple of (int, str)
        ``(frame, "restart")`` where a gap too long to fill ends.
    """
    steps = np.diff(stamps)
    parts: list[np.ndarray] = []
    times: list[np.ndarray] = []
    filled: list[tuple[int, int]] = []
    marks: list[tuple[int, str]] = []
    taken = added = 0
    for i, kind, missing in _steps(stamps, rate, tolerance, max_gap):   # between sample i and i + 1
        parts.append(data[taken:i + 1])
        times.append(stamps[taken:i + 1])
        at = i + 1 + added
        if kind == "gap":
            parts.append(np.zeros((missing, data.shape[1]), dtype=data.dtype))
            times.append(stamps[i] + steps[i] * np.arange(1, missing + 1) / (missing + 1))
            filled.append((at, at + missing))
            added += missing
        else:                             # too long to fill, or back in time: stream time jumps
            marks.append((at, "restart"))
        taken = i + 1
    if not parts:
        return data, stamps, (), ()
    parts.append(data[taken:])
    times.append(stamps[taken:])
    return np.concatenate(parts), np.concatenate(times), tuple(filled), tuple(marks)


def _steps(stamps: np.ndarray, rate: float, tolerance: float = DEFAULT_GAP_TOLERANCE,
           max_gap: float = DEFAULT_MAX_GAP) -> list[tuple[int, str, int]]:
    """Return the steps of ``stamps`` that :func:`fill_gaps` acts on, judged as the live inlet judges them.

    Each is ``(i, kind, missing)`` for the step between sample ``i`` and ``i + 1``, ``kind``
    ``"gap"`` (``missing`` samples to fill) or a restart (``"long"``, ``"back"``; ``missing`` 0).
    """
    steps = np.diff(stamps)
    # The live inlet's judge, on each step that is not within the tolerance of one period.
    judge = TimestampSteps(rate, tolerance, max_gap)
    at = np.flatnonzero(np.abs(steps - 1.0 / rate) > tolerance).tolist()
    out: list[tuple[int, str, int]] = []
    for k, i in enumerate(at):
        judge.last = float(stamps[i])
        step = judge.step(float(stamps[i + 1]), float(stamps[i + 1]))
        if step.kind not in ("gap", "long", "back"):
            continue
        missing = 0
        if step.kind == "gap":
            # Sized on the sample clock each side, not from the two jittered stamps at its edges.
            lo = at[k - 1] + 1 if k else 0
            hi = at[k + 1] + 1 if k + 1 < len(at) else stamps.size
            after = _clock_offset(stamps, i + 1, hi, rate, near_start=True)
            missing = int(round((after - _clock_offset(stamps, lo, i + 1, rate, near_start=False)) * rate))
            if missing < 1:
                continue
        out.append((i, step.kind, missing))
    return out


#: Seconds of samples each side of a gap whose stamps place the sender's sample clock there.
CLOCK_FIT_SECONDS = 1.0


def _clock_offset(stamps: np.ndarray, a: int, b: int, rate: float, near_start: bool) -> float:
    """Return the sender's sample clock over samples ``a .. b`` (no gap between them), as ``t - i / rate`` at ``i = 0``.

    It is the median over the :data:`CLOCK_FIT_SECONDS` of them nearest the gap (the first ones
    when ``near_start``, else the last), robust to the stamps' jitter (a rate 100 ppm off moves
    it 0.1 ms over that second).
    """
    n = max(1, int(CLOCK_FIT_SECONDS * rate))
    idx = np.arange(a, min(b, a + n)) if near_start else np.arange(max(a, b - n), b)
    return float(np.median(stamps[idx] - idx / rate))


def _full_scale(dtype: DTypeLike) -> float:
    """Integer samples are scaled so that the type's range is +-1."""
    return float(2 ** (np.dtype(dtype).itemsize * 8 - 1))


def _check_stamps_fit_rate(stamps: np.ndarray, rate: float, where: str) -> None:
    """Refuse timestamps that say another rate than ``rate`` (the header's ``nominal_srate``).

    Refused by more than :data:`RATE_MISMATCH` either way: faster over the whole stream (its
    samples per second of stamps; gaps only make that slower), or slower step by step (the
    median step; gaps leave it alone). Read at a wrong rate, every step is a restart or a filled
    gap.
    """
    if stamps.size < 3:
        return
    span = float(stamps[-1] - stamps[0])
    faster = span > 0 and (stamps.size - 1) / span > RATE_MISMATCH * rate
    step = float(np.median(np.diff(stamps)))
    slower = step > RATE_MISMATCH / rate
    if faster or slower:
        shown, how = (((stamps.size - 1) / span, "over the whole stream") if faster
                      else (1.0 / step, "by its median step"))
        raise ReplayError(f"{where}: its timestamps show {shown:.6g} samples a second ({how}), where its "
                          f"nominal_srate says {rate:g} Hz: the header or the stamps are wrong; correct the stream's "
                          "nominal_srate where it was recorded, or name another stream")


def _session_rate(rate: float, where: str) -> int:
    """Return a stream's nominal rate as a session's: whole Hz from 1 to :data:`MAX_XDF_RATE`; any other is refused."""
    if not (math.isfinite(rate) and 1 <= rate <= MAX_XDF_RATE):
        raise ReplayError(f"{where}: nominal_srate {rate:g} Hz is out of range: the node replays streams of 1 to "
                          f"{MAX_XDF_RATE} Hz (MAX_XDF_RATE); this header is damaged or the stream is not a sensor's "
                          "signal: name another stream, or correct the stream's nominal_srate where it was recorded")
    if abs(rate - round(rate)) >= 1e-9 * rate:
        raise ReplayError(f"{where}: nominal_srate {rate} Hz is not a whole number of Hz; the node replays "
                          "streams at whole rates")
    return int(round(rate))


def _arrivals(seconds: np.ndarray, rate: float, cuts: Iterable[int] = ()) -> tuple[np.ndarray, np.ndarray, float]:
    """Cut the stream into blocks of :data:`XDF_BLOCK_SECONDS`, also at ``cuts``, and time them.

    ``cuts`` are restart frames: no block spans one, so none of its frames is timed by the line
    after it. Returns each block's end frame and the time of its last sample (never earlier
    than the block's before), and the rate the timestamps show over the whole stream (a
    least-squares line; the nominal rate for a stream too short to show one). The node's
    clock model starts from that rate, so the first windows are on time too, before the model
    has seen enough blocks to find a drift of tens of ppm itself.
    """
    n = seconds.size
    step = max(1, int(round(XDF_BLOCK_SECONDS * rate)))
    ends = np.unique(np.r_[np.arange(step, n, step), [c for c in cuts if 0 < c < n], n]).astype(np.int64)
    times = np.maximum.accumulate(seconds[ends - 1])
    shown = float(rate)
    if n >= 2 and seconds[-1] > seconds[0]:
        # Fitted on the first sample and each block's last (a few per XDF_BLOCK_SECONDS, not every
        # sample: an hour at 1 MHz would take minutes): the same line where the stamps are regular.
        at = np.r_[0, ends - 1]
        index, times_at = at.astype(np.float64), seconds[at]
        slope = np.polyfit(index - index.mean(), times_at - times_at.mean(), 1)[0]
        # A rate far from nominal is a broken file or a clock reset: keep the nominal one.
        if slope > 0 and abs(1.0 / slope - rate) < 0.01 * rate:
            shown = 1.0 / slope
    return ends, times, shown


# -- as a scene names it ---------------------------------------------------------------------------

#: Keys that name the recorded stream: a scene gives at least one.
WHICH = ("stream", "stream_type", "source_id")


def _check(options: Mapping[str, Any]) -> None:
    if all(options[k] is None for k in WHICH):
        raise OptionError('type "xdf" needs the recorded stream\'s name (stream = ...), stream_type or source_id')


def _build(options: Mapping[str, Any], context: BuildContext) -> Built:
    from supramodal.replay.driver import ReplayDriver, pacing

    path = context.resolve(options["path"])
    if not path.exists():
        raise OptionError(f"path: no XDF file at {path} (a relative path is taken from the scene file's folder)")
    files = context.shared.setdefault("xdf", {})        # one file read once for all its sources
    try:
        if path not in files:
            files[path] = load_xdf_streams(path)
        session = xdf_session(path, options["stream"], options["stream_type"], options["source_id"],
                              streams=files[path], labels=options["labels"])
        driver = ReplayDriver(session, rate=context.rate, timing="recorded", on_notice=None,
                              **pacing({"speed": options["speed"]}, context))
    except ReplayError as exc:
        raise OptionError(str(exc)) from None
    return Built(driver, source_rate=driver.source_rate)   # its labels (the marker stream's) are the driver's


def _spec() -> DriverSpec:
    from supramodal.replay.driver import speed_key

    return DriverSpec(
        type="xdf",
        summary="a stream of an XDF recording (LabRecorder's files; the lsl extra), at its recorded times",
        keys={
            "path": Key(text, "an XDF file path", path=True),
            "stream": Key(text, "the recorded stream's name", None),
            "stream_type": Key(text, 'the recorded stream\'s type, e.g. "Whiskers"', None),
            "source_id": Key(text, "the recorded stream's source_id", None),
            "labels": Key(text, "the name of a marker stream in the file whose strings are the truth labels (each "
                                "marker starts a label, which runs until the next; an empty marker ends it)", None),
            "speed": speed_key(),
        },
        build=_build, live=False, check=_check,
        timebase=lambda options, driver: ("recorded", 0.0, float(driver.recorded_rate)))


SPEC = _spec()
