"""A graph recording made from files a lab already has: ``supramodal import-recording``.

``supramodal record`` writes a graph's recording as one session per source (``NAME.SOURCE.wav`` +
``.json``, the sidecar keeping every block's time on the graph's common time, ``arrivals``) and
``NAME.toml``, the scene that replays the sources in step (``timing = "recorded"``). This module
writes the same layout from files made elsewhere, so that ``supramodal run``, ``train --fusion``
and ``evaluate --scene`` take them as they take a recording of the node's own:

* **WAV + timestamps (CSV)**, one pair per source, all timestamps on one clock (the lab's
  recorder's, a host clock, a DAQ's): a CSV with the header ``end_frame,seconds`` gives one row
  per delivered block, the frame after its last (frames delivered so far) and when it was
  complete, the last block ending at the WAV's end; a CSV with the header ``seconds`` gives
  one row per frame of the WAV, the time that sample was taken (per-sample timestamps, as LSL
  stamps them). Per-sample times are cut into blocks of about 10 ms, each at the time of its last
  sample, a step of more than a period plus the tolerance filled with zeros and marked, as an XDF
  stream's (:mod:`supramodal.replay.xdf`).
* **XDF streams** (LabRecorder's files; the ``lsl`` extra): each named stream of the file, read by
  :func:`supramodal.replay.xdf.xdf_session` (its recorded times, gaps filled and marked, a
  marker stream's strings as labels).
* **rosbag2 topics** (a robot's recording, MCAP or sqlite3; the ``ros2`` extra): each named sensor
  topic, read by :func:`supramodal.replay.rosbag.bag_streams` at its bank's rate and then by the XDF
  reader's rules (its stamps, gaps filled and marked), a ``std_msgs/String`` topic's messages as labels.

The times of all sources are put on one common time whose zero is the earliest first sample.
Every file is data: WAVs through :func:`~supramodal.replay.wavio.read_wav`, CSVs through
:mod:`csv` with each field parsed as a number and checked (finite, ascending, one per block or
frame), banks through :func:`~supramodal.bankfile.load_bank`, models through
:meth:`~supramodal.model.TextureModel.load`; nothing is executed. Every refusal is an
:class:`ImportRecordingError` naming the file, the line and the fix; nothing is written until
every input is read and checked. The recording is written into a folder of its own beside it and its
scene built there; only then does each file take its place, and an existing one is replaced only with
``overwrite``: a refused or interrupted import leaves every file as it was. An input is never an output.
"""

from __future__ import annotations

import contextlib
import csv
import math
import os
import shutil
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from supramodal.bankfile import load_bank
from supramodal.checks import NAME_HELP, is_name
from supramodal.csvdata import bounded_lines
from supramodal.errors import InputError
from supramodal.node.runtime.outputs import check_new_file
from supramodal.node.workflows.labels import replace_all
from supramodal.replay.errors import ReplayError
from supramodal.replay.session import Session, save_session, session_paths, validate_arrivals
from supramodal.replay.wavio import read_wav

__all__ = ["ImportRecordingError", "SourceFiles", "BANK_KINDS", "BLOCK_COLUMNS", "SAMPLE_COLUMNS", "import_recording",
           "read_times", "recording_files", "sources_from_options"]

#: ``[stream.bank] kind`` a source may be given by name (else a bank file's path).
BANK_KINDS = ("whisker", "cochlea")
#: The header of a CSV of per-block timestamps.
BLOCK_COLUMNS = ("end_frame", "seconds")
#: The header of a CSV of per-sample timestamps.
SAMPLE_COLUMNS = ("seconds",)
#: Longest timestamp accepted, seconds (epoch seconds reach 1.8e9 in 2027; 1e10 is year 2286): a
#: larger one is a unit mistake (ms or ns) or a damaged file.
MAX_TIME = 1e10


class ImportRecordingError(InputError):
    """A file to import, or an option of the import, is refused.

    The message names the file (and line), what is wrong and the fix.
    """


@dataclass(frozen=True)
class SourceFiles:
    """One source of the recording to make.

    Attributes
    ----------
    name : str
        The source's (and its stream's) name in the replay scene.
    bank : str
        ``"whisker"``, ``"cochlea"`` or a bank file's path (its stream's ``[stream.bank]``).
    wav, times : path or None
        The WAV file and its timestamps (CSV), for a source read from WAV + CSV.
    xdf_stream : str or None
        The name of a stream of the XDF file, for a source read from XDF.
    topic : str or None
        A sensor topic of the bag, for a source read from a rosbag2.
    model : path or None
        A model file for the stream (copied beside the sessions); None: the stream gives feature
        windows.
    mapping : str or int
        How its channels feed its bank (its ``[[stream]]`` mapping; default ``"auto"``).
    """

    name: str
    bank: str
    wav: Path | None = None
    times: Path | None = None
    xdf_stream: str | None = None
    model: Path | None = None
    topic: str | None = None
    mapping: str | int = "auto"

    @property
    def origins(self) -> int:
        """How many of a WAV, an XDF stream and a bag topic the source is read from (one is right)."""
        return (self.wav is not None) + (self.xdf_stream is not None) + (self.topic is not None)


def sources_from_options(wav=(), times=(), xdf_streams=(), banks=(), models=(), topics=(),
                         mappings=()) -> list[SourceFiles]:
    """Return the sources the command line's ``SOURCE=VALUE`` options describe.

    In the order the WAVs, XDF streams or bag topics are given (``wav``, ``times``, ``xdf_streams``,
    ``banks``, ``models``, ``topics``, ``mappings``: lists of ``(source, value)``). Refused, naming the
    option: a source given twice in one option, a ``--times``, ``--bank``, ``--model`` or ``--mapping`` for no
    source, a mapping the scene would refuse, a source without its bank or (a WAV) its timestamps.
    """
    def by_source(option: str, pairs) -> dict[str, str]:
        out: dict[str, str] = {}
        for name, value in pairs:
            if name in out:
                raise ImportRecordingError(f"{option}: source {name!r} is given twice; one {option} per source")
            out[name] = value
        return out

    wavs, stamps = by_source("--wav", wav), by_source("--times", times)
    streams, bank = by_source("--xdf-stream", xdf_streams), by_source("--bank", banks)
    model, topic = by_source("--model", models), by_source("--topic", topics)
    mapping = {n: _mapping(n, v) for n, v in by_source("--mapping", mappings).items()}
    names = list(wavs) + [n for n in streams if n not in wavs]
    names += [n for n in topic if n not in names]
    for option, given in (("--times", stamps), ("--bank", bank), ("--model", model), ("--mapping", mapping)):
        stray = sorted(set(given) - set(names))
        if stray:
            raise ImportRecordingError(f"{option}: no source {stray[0]!r} (the sources: {names}); name a source "
                                       "given by --wav, --xdf-stream or --topic")
    for n in names:
        if (n in wavs) + (n in streams) + (n in topic) > 1:
            raise ImportRecordingError(f"source {n!r} is given more than one of a WAV, an XDF stream and a bag topic; "
                                       "one of them")
        if n in wavs and n not in stamps:
            raise ImportRecordingError(f"source {n!r}: its WAV needs its timestamps: --times {n}=TIMES.csv "
                                       f"(a CSV with the header '{','.join(BLOCK_COLUMNS)}' or "
                                       f"'{','.join(SAMPLE_COLUMNS)}')")
        if n not in bank:
            raise ImportRecordingError(f"source {n!r} has no bank: --bank {n}=whisker, cochlea or a bank file")
    return [SourceFiles(n, bank[n], wav=Path(wavs[n]) if n in wavs else None,
                        times=Path(stamps[n]) if n in wavs else None, xdf_stream=streams.get(n),
                        model=Path(model[n]) if n in model else None, topic=topic.get(n),
                        mapping=mapping.get(n, "auto")) for n in names]


def _mapping(source: str, value: str) -> str | int:
    """Return ``--mapping``'s value as the scene takes it (a channel index as an integer), or refuse it, naming it."""
    from supramodal.node.scene.schema import MAPPING

    taken: str | int = int(value) if value.strip().isdigit() else value.strip()
    if not MAPPING.check(taken):
        raise ImportRecordingError(f"--mapping {source}={value}: expected {MAPPING.expected}")
    return taken


def _number(text: str, where: str, column: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ImportRecordingError(f"{where}: {column} {text.strip()!r} is not a number; write seconds as a "
                                   "decimal number (e.g. 12.345678)") from None
    if not math.isfinite(v) or abs(v) > MAX_TIME:
        raise ImportRecordingError(f"{where}: {column} {text.strip()!r} is not a finite time within +-{MAX_TIME:g} s "
                                   "(MAX_TIME); write seconds (not ms or ns), every row a time")
    return v


def _frame(text: str, where: str, frames: int) -> int:
    try:
        v = int(text.strip())
    except ValueError:
        raise ImportRecordingError(f"{where}: end_frame {text.strip()!r} is not a whole number of frames; write the "
                                   "count of frames delivered by the end of the block") from None
    if not 0 < v <= frames:
        raise ImportRecordingError(f"{where}: end_frame {v} is outside 1..{frames} (the WAV's frames); each block "
                                   "ends within the WAV")
    return v


def read_times(path, frames: int) -> tuple[str, np.ndarray, np.ndarray]:
    """Read a CSV of timestamps for a WAV of ``frames`` frames.

    Parameters
    ----------
    path : path
        A CSV with the header ``end_frame,seconds`` (per block) or ``seconds`` (per sample, one
        row per frame); seconds on the clock all the recording's sources share.
    frames : int
        The WAV's frame count.

    Returns
    -------
    (kind, end_frames, seconds)
        ``kind`` ``"block"`` or ``"sample"``; per block, each block's end frame (ascending, the
        last ``frames``) and time (non-decreasing), seconds; per sample, ``end_frames`` is empty
        and ``seconds`` holds one time per frame.

    Raises
    ------
    ImportRecordingError
        Naming the file and line: a header that is neither form, a field that is not a finite
        number, frames not ascending or past the WAV, times going back, rows missing or too many.
    """
    path = Path(path)
    try:
        fh = open(path, newline="", encoding="utf-8-sig")
    except OSError as exc:
        raise ImportRecordingError(f"{path}: cannot read the timestamps ({exc.strerror or exc})") from None
    with fh:
        rows = csv.reader(bounded_lines(fh, str(path), ImportRecordingError))
        try:
            header = tuple(c.strip() for c in next(rows, ()))
            if header not in (BLOCK_COLUMNS, SAMPLE_COLUMNS):
                raise ImportRecordingError(
                    f"{path}: line 1 is {','.join(header) or 'empty'}; the first line names the columns: "
                    f"'{','.join(BLOCK_COLUMNS)}' (one row per block: the frames delivered by its end and when it "
                    f"was complete) or '{','.join(SAMPLE_COLUMNS)}' (one row per frame: when it was taken)")
            per_block = header == BLOCK_COLUMNS
            ends: list[int] = []
            times: list[float] = []
            for line, row in enumerate(rows, start=2):
                where = f"{path}: line {line}"
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) != len(header):
                    raise ImportRecordingError(f"{where}: {len(row)} fields, the header names {len(header)} "
                                               f"({','.join(header)}); one value per column")
                if len(times) >= frames:
                    raise ImportRecordingError(f"{where}: more rows than the WAV's {frames} frames; these "
                                               "timestamps belong to another (longer) WAV")
                if per_block:
                    end = _frame(row[0], where, frames)
                    if ends and end <= ends[-1]:
                        raise ImportRecordingError(f"{where}: end_frame {end} is not after the block before it "
                                                   f"({ends[-1]}); block ends ascend")
                    ends.append(end)
                t = _number(row[-1], where, "seconds")
                if per_block and times and t < times[-1]:
                    raise ImportRecordingError(f"{where}: seconds {t!r} comes before the block before it "
                                               f"({times[-1]!r}); a block is complete no earlier than the one before")
                times.append(t)
        except csv.Error as exc:
            raise ImportRecordingError(f"{path}: line {rows.line_num}: not CSV ({exc})") from None
        except UnicodeDecodeError:
            raise ImportRecordingError(f"{path}: not a text file (UTF-8); give the timestamps as CSV") from None
    if not times:
        raise ImportRecordingError(f"{path}: no timestamp after the header; one row per block or per frame")
    if per_block and ends[-1] != frames:
        raise ImportRecordingError(f"{path}: the last block ends at frame {ends[-1]}, the WAV has {frames} frames; "
                                   "the blocks cover the whole WAV (cut the WAV, or give the missing blocks)")
    if not per_block and len(times) != frames:
        raise ImportRecordingError(f"{path}: {len(times)} per-sample timestamps for a WAV of {frames} frames; one "
                                   "row per frame")
    return ("block" if per_block else "sample"), np.array(ends, dtype=np.int64), np.array(times, dtype=np.float64)


def _wav_session(src: SourceFiles) -> tuple[Session, float]:
    """Return a source's WAV and timestamps as a session, and the time of its first sample on the file's clock.

    The session's arrivals are on the file's clock (zero not yet moved).
    """
    from supramodal.replay.xdf import MAX_XDF_TIME, xdf_session

    assert src.wav is not None and src.times is not None
    try:
        data, rate = read_wav(src.wav)
    except FileNotFoundError:
        raise ImportRecordingError(f"{src.wav}: no such WAV file (source {src.name!r})") from None
    except ReplayError as exc:
        raise ImportRecordingError(f"source {src.name!r}: {exc}") from None
    kind, ends, seconds = read_times(src.times, data.shape[0])
    what = f"{src.wav.name} with {src.times.name} ({'per-block' if kind == 'block' else 'per-sample'} timestamps)"
    if kind == "block":
        # a block is complete when its last sample is taken: the first sample, that many periods before
        first = float(seconds[0] - (ends[0] - 1) / rate)
        return Session(data, rate, what, arrivals=(ends, seconds, float(rate))), first
    # Times in another unit than seconds (milliseconds: every step 1000 times too long) would be read as
    # gaps to fill: 2 s of 8 kHz became 16 M frames. The steps' median says the unit.
    if seconds.size > 1:
        step = float(np.median(np.diff(seconds)))
        if not 0.5 / rate <= step <= 2.0 / rate:
            raise ImportRecordingError(
                f"{src.times}: its times step by {step:.6g} s (the median), where samples at the WAV's {rate} Hz come "
                f"every {1 / rate:.6g} s: {'milliseconds? ' if 500 / rate <= step <= 2000 / rate else ''}give each "
                "frame's time in seconds, or the WAV at its real rate")
    # A jump far beyond any recording's length (a damaged row, another clock pasted in) would otherwise be
    # refused in an XDF file's words; say it in the CSV's, with its row.
    span = seconds - seconds[0]
    if np.max(np.abs(span)) > MAX_XDF_TIME:
        row = int(np.argmax(np.abs(span) > MAX_XDF_TIME))
        raise ImportRecordingError(
            f"{src.times}: line {row + 2} (frame {row}) is {span[row]:.6g} s from the first frame's time, beyond the "
            f"{MAX_XDF_TIME:g} s any recording spans: a damaged line or another clock; correct that line's time")
    # Per-sample times follow an XDF stream's rules (blocks of about 10 ms at their last sample's
    # time, gaps filled and marked, the rate the times show): read as the one stream of a file.
    stream = {"info": {"name": [src.name], "type": ["imported"], "source_id": [""], "nominal_srate": [str(rate)],
                       "channel_count": [str(data.shape[1])]},
              "time_series": data, "time_stamps": seconds - seconds[0]}     # from 0: epoch seconds too
    try:
        session = xdf_session(src.times, name=src.name, streams=[stream])
    except ReplayError as exc:
        raise ImportRecordingError(f"source {src.name!r}: {exc}") from None
    assert session.arrivals is not None
    ends, times, shown = session.arrivals            # from the first sample: put back on the file's clock
    return replace(session, source=what, path=None, arrivals=(ends, times + seconds[0], shown)), float(seconds[0])


def _xdf_sessions(path: Path, sources: list[SourceFiles], markers: str | None) -> dict[str, Session]:
    from supramodal.replay.xdf import load_xdf_streams, xdf_session

    try:
        streams = load_xdf_streams(path)
        return {s.name: xdf_session(path, s.xdf_stream, streams=streams, labels=markers) for s in sources}
    except FileNotFoundError:
        raise ImportRecordingError(f"{path}: no such XDF file") from None
    except ReplayError as exc:
        raise ImportRecordingError(str(exc)) from None


def _bag_sessions(path: Path, sources: list[SourceFiles], labels: str | None) -> dict[str, Session]:
    """Each source's topic of the bag as a session, read at its bank's rate."""
    from supramodal.replay.rosbag import bag_streams
    from supramodal.replay.xdf import xdf_session

    rates = {}
    for s in sources:
        assert s.topic is not None
        rates[s.topic] = _bank_rate(s)
    try:
        streams = bag_streams(path, rates, labels)
        out = {}
        for s in sources:
            session = xdf_session(path, s.topic, streams=streams, labels=labels)
            out[s.name] = replace(session, source=f"rosbag2 {path.name}: topic {s.topic}")
        return out
    except ReplayError as exc:
        raise ImportRecordingError(str(exc)) from None


def _bank_rate(source: SourceFiles) -> float:
    """Return the rate, Hz, the source's bank reads: a bag's samples carry none of their own."""
    from supramodal.banks import cochlea_bank, whisker_bank

    if source.bank == "whisker":
        return float(whisker_bank().fs)
    if source.bank == "cochlea":
        return float(cochlea_bank().fs)
    return float(load_bank(source.bank).fs)


def _check_times(name: str, session: Session, where: str) -> None:
    """Refuse times that do not follow the frames as a device's clock does (the rule replays are held to)."""
    assert session.arrivals is not None
    ends, seconds, rate = session.arrivals
    try:
        validate_arrivals({"frames": ends.tolist(), "seconds": seconds.tolist(), "rate": rate}, session.frames,
                          where, marks=session.marks)
    except ReplayError as exc:
        raise ImportRecordingError(f"source {name!r}: its timestamps do not follow its samples at {session.rate} Hz: "
                                   f"{exc} (arrivals are the blocks' ends and times, in the CSV's order)") from None


def _check_overlap(sessions: Mapping[str, Session], where: Mapping[str, str]) -> None:
    """Refuse sources two of which share no time: sources recorded in step share some.

    Two that never do (another day's file, a clock of another origin) would make the replay wait out the
    gap between them, for as long as it is.
    """
    spans = {}
    for n, session in sessions.items():
        assert session.arrivals is not None
        ends, seconds, rate = session.arrivals
        spans[n] = (float(seconds[0] - (ends[0] - 1) / rate), float(seconds[-1]))
    last_start = max(spans, key=lambda n: spans[n][0])
    first_end = min(spans, key=lambda n: spans[n][1])
    if spans[last_start][0] >= spans[first_end][1]:
        said = "; ".join(f"{n} ({where[n]}) {a:.6g} to {b:.6g} s" for n, (a, b) in spans.items())
        raise ImportRecordingError(
            f"the sources never overlap in time: {said} on the common clock; {last_start} starts "
            f"{spans[last_start][0] - spans[first_end][1]:.6g} s after {first_end} ends. Give times on one clock, "
            "of one session (or import each source alone)")


def recording_files(folder, name: str, sources) -> list[Path]:
    """Every file :func:`import_recording` writes into ``folder`` for ``sources``."""
    folder = Path(folder)
    out = [p for s in sources for p in session_paths(folder / f"{name}.{s.name}")]
    out += [folder / f"{name}.{s.name}.npz" for s in sources if s.model is not None]
    out += [folder / f"{name}.{s.name}.bank.json" for s in sources if s.bank not in BANK_KINDS]
    return out + [folder / f"{name}.toml"]


def import_recording(folder, name: str, sources: list[SourceFiles], xdf=None, markers: str | None = None,
                     fusion: bool = False, overwrite: bool = False, bag=None) -> Path:
    """Write a replayable graph recording of ``sources`` into ``folder``; returns its scene's path.

    Parameters
    ----------
    folder : path
        Created if missing.
    name : str
        The recording's name: ``NAME.SOURCE.wav/.json`` per source, ``NAME.toml``.
    sources : list of SourceFiles
        One or more, each from a WAV and its timestamps, or (all of them) from streams of ``xdf``.
    xdf : path, optional
        The XDF file the sources' ``xdf_stream`` name.
    markers : str, optional
        With ``xdf``: a marker stream of the file whose strings label every source (each marker
        starts a label that runs to the next; an empty one ends it); with ``bag``: a ``std_msgs/String``
        topic of the bag, read the same way.
    fusion : bool
        Write ``[fusion]`` (late fusion of the two streams, default weight; learn it with
        ``supramodal train --fusion late``): needs exactly two sources, each with a model.
    overwrite : bool
        Replace files of an earlier import of that name (default: refuse).
    bag : path, optional
        The rosbag2 (folder, or its ``.mcap`` / ``.db3`` file) the sources' ``topic`` name.

    Raises
    ------
    ImportRecordingError
        For any input that does not fit (see the module notes); nothing is then written.
    """
    from supramodal.model import ModelError, TextureModel
    from supramodal.node.scene.schema import scene_from_dict, scene_to_toml

    folder = Path(folder)
    if not is_name(name):
        raise ImportRecordingError(f"the recording's name {name!r} is not {NAME_HELP}")
    if not sources:
        raise ImportRecordingError("no source to import: give each source's WAV and timestamps, or XDF streams")
    names = [s.name for s in sources]
    for s in sources:
        if not is_name(s.name):
            raise ImportRecordingError(f"the source name {s.name!r} is not {NAME_HELP}")
        if s.name == "fused":
            raise ImportRecordingError("'fused' is the fusion block's stream: name the source otherwise")
        if (s.wav is None) != (s.times is None) or s.origins != 1:
            raise ImportRecordingError(f"source {s.name!r}: give its WAV and its timestamps (CSV), an XDF stream or a "
                                       "bag topic")
        if s.bank not in BANK_KINDS and not Path(s.bank).is_file():
            raise ImportRecordingError(f"source {s.name!r}: the bank is {list(BANK_KINDS)} or a bank file; no file "
                                       f"at {s.bank}")
    if len(set(names)) != len(names):
        raise ImportRecordingError(f"source names repeat: {names}; give each source its own name")
    from_xdf = [s for s in sources if s.xdf_stream is not None]
    if from_xdf and xdf is None:
        raise ImportRecordingError("XDF streams were named but no XDF file given")
    if xdf is not None and len(from_xdf) != len(sources):
        raise ImportRecordingError("a recording is imported from WAV files or from one XDF file, not both: their "
                                   "timestamps would not share a clock")
    from_bag = [s for s in sources if s.topic is not None]
    if from_bag and bag is None:
        raise ImportRecordingError("bag topics were named (--topic) but no bag given (--bag)")
    if bag is not None and (len(from_bag) != len(sources) or xdf is not None):
        raise ImportRecordingError("a recording is imported from WAV files, one XDF file or one bag, not several: "
                                   "their timestamps would not share a clock")
    if markers is not None and xdf is None and bag is None:
        raise ImportRecordingError("marker labels are read from an XDF file or a bag; with WAV files label the "
                                   "recording after the import")
    if fusion and (len(sources) != 2 or any(s.model is None for s in sources)):
        raise ImportRecordingError("a fusion fuses two streams' decisions: give exactly two sources, each with a "
                                   "model")
    if folder.exists() and not folder.is_dir():
        raise ImportRecordingError(f"{folder} is a file; give a folder for the recording")
    outputs = recording_files(folder, name, sources)
    if folder.is_dir():
        for path in outputs:
            check_new_file(path, overwrite, "the recording's file")
    # An input is never replaced (nor deleted by a failed import): an output of the same path is refused.
    inputs = [p for s in sources for p in (s.wav, s.times, s.model, None if s.bank in BANK_KINDS else s.bank)
              if p is not None] + [Path(p) for p in (xdf, bag) if p is not None]
    same = sorted({str(o) for o in outputs for i in inputs if Path(o).resolve() == Path(i).resolve()})
    if same:
        raise ImportRecordingError(f"{same[0]} is an input of the import and would be one of its outputs; give "
                                   "another --name or --out (the import never writes over its inputs)")
    # Read and check everything before anything is written.
    models = {}
    for s in sources:
        if s.model is not None:
            try:
                models[s.name] = TextureModel.load(s.model)
            except (ModelError, OSError) as exc:
                raise ImportRecordingError(f"source {s.name!r}: model {s.model}: {exc}") from None
        if s.bank not in BANK_KINDS:
            try:
                load_bank(s.bank)
            except InputError as exc:
                raise ImportRecordingError(f"source {s.name!r}: {exc}") from None
    if xdf is not None:
        sessions = _xdf_sessions(Path(xdf), sources, markers)
        where = {s.name: f"{xdf} stream {s.xdf_stream!r}" for s in sources}
    elif bag is not None:
        sessions = _bag_sessions(Path(bag), sources, markers)
        where = {s.name: f"{bag} topic {s.topic}" for s in sources}
    else:
        read = {s.name: _wav_session(s) for s in sources}
        zero = min(first for _, first in read.values())
        sessions = {}
        for n, (session, _) in read.items():
            assert session.arrivals is not None
            ends, seconds, rate = session.arrivals
            sessions[n] = Session(session.data, session.rate, session.source, filled=session.filled,
                                  marks=session.marks, arrivals=(ends, seconds - zero, rate))
        where = {s.name: str(s.times) for s in sources}
    for n, session in sessions.items():
        _check_times(n, session, where[n])
    _check_overlap(sessions, where)
    scene = folder / f"{name}.toml"
    d = {"source": [{"name": n, "type": "replay", "path": f"{name}.{n}.wav", "timing": "recorded", "speed": "max"}
                    for n in names],
         "stream": [{"name": s.name, "source": s.name, **({"mapping": s.mapping} if s.mapping != "auto" else {}),
                     "bank": {"kind": s.bank} if s.bank in BANK_KINDS else {"file": f"{name}.{s.name}.bank.json"},
                     **({"model": {"path": f"{name}.{s.name}.npz"}} if s.model is not None else {})}
                    for s in sources]}
    if fusion:
        d["fusion"] = {"streams": names}
    text = scene_to_toml(scene_from_dict(d, str(scene), folder))
    made = not folder.exists()
    # Everything is written into a folder of its own beside the recording and checked there (the scene built);
    # only then does each file take its place, replacing an earlier import's (with overwrite), all of them with
    # Ctrl-C and SIGTERM held till the last. A refusal or an interruption before that leaves every file that was
    # there as it was. The folder is named before it is made: an interruption at any moment knows what to remove.
    staging = folder / f".{name}.import-{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        staging.mkdir(exist_ok=True)
        for s in sources:
            session = sessions[s.name]
            exact32 = np.array_equal(session.data.astype(np.float32).astype(np.float64), session.data)
            save_session(staging / f"{name}.{s.name}", session.data, session.rate, session.source,
                         labels=session.labels, filled=list(session.filled),
                         dtype="float32" if exact32 else "float64", marks=session.marks, arrivals=session.arrivals)
            if s.model is not None:
                shutil.copyfile(s.model, staging / f"{name}.{s.name}.npz")
            if s.bank not in BANK_KINDS:
                shutil.copyfile(s.bank, staging / f"{name}.{s.name}.bank.json")
        (staging / scene.name).write_text(f"# Replays the recording {name}, imported by supramodal import-recording "
                                          f"from {xdf or bag or ', '.join(str(s.wav) for s in sources)}.\n" + text)
        _check_scene(staging / scene.name)
        # the scene last: a recording is there when its scene is (a signal between two files left some new)
        replace_all([(staging / Path(path).name, Path(path)) for path in outputs])
    except BaseException:
        if made:
            shutil.rmtree(staging, ignore_errors=True)
            with contextlib.suppress(OSError):
                folder.rmdir()                  # a folder made for nothing is not left behind (only if empty)
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return scene


def _check_scene(path: Path) -> None:
    """Build (not run) the written scene, so that what would fail at the first run is refused now.

    A model that does not fit its stream's bank or features, or two streams that cannot be fused, is
    refused now, not at the first run.
    """
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import load_scene

    try:
        build_node(load_scene(path), speed="max", sinks_override=[])
    except InputError as exc:
        hint = (" (here: --mapping SOURCE=mean, or a channel index)" if "mapping" in str(exc) else "")
        raise ImportRecordingError(f"the imported recording does not run: {exc}{hint}") from None
