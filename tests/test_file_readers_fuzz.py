"""Every file reader fed random, damaged and adversarial bytes: it reads the file or refuses it naming the file;
never a traceback, a hang or a memory blow-up (issue 35).

The readers: spans CSV (:func:`read_spans`), timestamps CSV (:func:`read_times`), training manifest
(:func:`read_manifest`, with the WAV it lists), XDF (:func:`load_xdf_streams`, then :func:`xdf_session` of its
signal stream with its marker stream as labels), WAV (:func:`wav_info`, :func:`read_wav`), session (WAV and JSON
sidecar, :func:`load_session`), model file (:meth:`TextureModel.load`, an .npz) and bank file (:func:`load_bank`).

Per reader, hypothesis draws three kinds of file, each within :data:`MAX_FILE_BYTES` (256 KiB):

(a) random bytes: short, or long blocks with no line break; for the binary formats also after the format's magic,
    so that the reader gets past its first check;
(b) a valid file damaged: bytes flipped, overwritten with extreme values (0xFF.., NaN, 2**31), inserted or deleted,
    the file cut; near the start and the end (headers, a zip's directory) as well as anywhere;
(c) adversarial content in the format's own structure. CSV: fields such as 1e308, 9e9999, NaN, inf, -0, negatives,
    5000-digit numbers, NUL, control characters, terminal escapes, BOMs, stray quotes, lines up to the size bound
    without a line break, other encodings. JSON (sidecar, bank file, model header): at any key of a valid file a
    value of the wrong type, huge, non-finite, a 5000-digit integer, nesting far past the limit, a duplicate key;
    a model's arrays of the wrong dtype, shape or content, declaring a huge shape, or any bytes under a .npy header.
    WAV: RIFF headers with extreme fields and chunk sizes. XDF: stream headers with extreme fields, non-finite or
    wild samples, timestamps and clock offsets, Samples chunks declaring more samples (or channels) than they hold.

Asserted for every example: the call returns, or raises a :class:`SupramodalError` whose message holds the path of
the file (every reader prints the path it was given; a session's refusal may name its WAV or its sidecar); any
other exception fails the test, hypothesis printing the input. What a reader accepts is checked against what it
promises (finite samples, spans in order, ...). Hypothesis runs derandomized with no example database: the same
examples every run, so the test never flakes.

Bounds. Time: each example within :data:`DEADLINE_MS` (5 s; a reader takes milliseconds to tens of milliseconds on
these sizes, so only a runaway trips it, not a busy machine), and a watchdog (SIGALRM, :data:`WATCHDOG_SECONDS`)
turns a reader that never returns into a failure instead of a stuck run. Memory: the peak RSS of the process may
grow by less than :data:`MAX_RSS_GROWTH_KIB` (500 MiB) in one read and over each whole test: the largest file is
256 KiB, so a reader near that sized something from a count the file declares, not from its bytes. While a reader
runs, its address space is capped at what the process had plus :data:`ADDRESS_SPACE_MARGIN` (2 GiB), so that an
allocation bomb fails here instead of taking the machine. The example counts keep the file near 25 s on two cores;
SUPRAMODAL_FUZZ_SCALE=N runs N times as many examples (a deeper search by hand).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import resource
import signal
import struct
import threading
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from xdf_writer import XdfStream, _chunk, write_xdf

from supramodal.bankfile import load_bank
from supramodal.banks import MAX_CHANNELS, whisker_bank
from supramodal.errors import SupramodalError
from supramodal.model import TextureModel
from supramodal.node.workflows.import_recording import read_times
from supramodal.node.workflows.labels import read_spans
from supramodal.node.workflows.manifest import read_manifest
from supramodal.replay.session import load_session, save_session, session_paths
from supramodal.replay.wavio import MAX_FLOAT_MAGNITUDE, read_wav, wav_info, write_wav

pytest.importorskip("pyxdf", reason="the XDF reader needs pyxdf (the lsl extra; CI installs it)")
from supramodal.replay.xdf import load_xdf_streams, xdf_session  # noqa: E402

#: Largest file fed to a reader, bytes.
MAX_FILE_BYTES = 256 * 1024
#: Longest one example may take, milliseconds (hypothesis deadline).
DEADLINE_MS = 5000
#: A reader still running after this long is stopped and the example fails (a hang).
WATCHDOG_SECONDS = 30
#: Most the process's peak RSS may grow in one read and over one test, KiB (ru_maxrss is in KiB on Linux).
MAX_RSS_GROWTH_KIB = 500 * 1024
#: Address space a reader may take beyond what the process had, bytes.
ADDRESS_SPACE_MARGIN = 2 * 2**30

#: Sample rate of the valid recordings the damaged ones start from, Hz (small files, fast reads).
RATE = 500


#: Examples per test times this (environment variable SUPRAMODAL_FUZZ_SCALE, default 1): a deeper search by hand,
#: e.g. SUPRAMODAL_FUZZ_SCALE=20.
SCALE = float(os.environ.get("SUPRAMODAL_FUZZ_SCALE", "1"))


def fuzz(examples: int):
    """Hypothesis settings of every test here: derandomized (no flakes), no database, the deadline."""
    return settings(max_examples=max(1, round(examples * SCALE)), deadline=DEADLINE_MS, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large, HealthCheck.large_base_example])


# -- bounds and the one assertion --------------------------------------------------------------------

class ReaderHung(Exception):
    """A reader ran past :data:`WATCHDOG_SECONDS`."""


@contextlib.contextmanager
def _watchdog(seconds: float):
    """Raise :class:`ReaderHung` in the reader if it runs longer than ``seconds`` (main thread only:
    elsewhere the hypothesis deadline alone bounds it, after the fact)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise ReaderHung(f"the reader ran more than {seconds} s")

    previous = signal.signal(signal.SIGALRM, stop)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _address_space() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * resource.getpagesize()


@contextlib.contextmanager
def _address_space_limited(margin: int):
    """The process's address space capped at its present size plus ``margin`` (Linux; elsewhere no cap)."""
    try:
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        cap = _address_space() + margin
        if hard != resource.RLIM_INFINITY:
            cap = min(cap, hard)
        resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    except (OSError, ValueError):
        yield
        return
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _peak_rss_kib() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


@pytest.fixture(autouse=True)
def memory_bounded():
    """Each test (all its examples, and its fixtures' files) may raise the process's peak RSS by less than
    MAX_RSS_GROWTH_KIB."""
    before = _peak_rss_kib()
    yield
    grown = _peak_rss_kib() - before
    assert grown < MAX_RSS_GROWTH_KIB, f"peak RSS grew by {grown / 1024:.0f} MiB over the test"


def read_or_refuse(read, path: Path, *named: Path):
    """``read(path)``'s result, or None if it refused with a SupramodalError naming ``path`` (or one of
    ``named``); any other exception, a refusal that names no file, or a read that raised the peak RSS by
    MAX_RSS_GROWTH_KIB fails the example (so that hypothesis shows the input)."""
    names = [str(p) for p in (named or (path,))]
    before = _peak_rss_kib()
    try:
        with warnings.catch_warnings():
            # A damaged file may be read with a warning (XdfDamageWarning, ClippingWarning): allowed.
            warnings.simplefilter("ignore")
            with _address_space_limited(ADDRESS_SPACE_MARGIN), _watchdog(WATCHDOG_SECONDS):
                return read(path)
    except SupramodalError as exc:
        message = str(exc)
        assert any(n in message for n in names), f"the refusal names none of {names}: {message[:500]!r}"
        return None
    finally:
        grown = _peak_rss_kib() - before
        assert grown < MAX_RSS_GROWTH_KIB, f"reading {path.name} raised the peak RSS by {grown / 1024:.0f} MiB"


class Valid:
    """Valid files' bytes and parts, printed short: hypothesis prints every argument of a failing example."""

    def __init__(self, name: str, **parts):
        self.name = name
        self.__dict__.update(parts)

    def __repr__(self) -> str:
        return f"<valid {self.name}>"


# -- strategies shared by the readers ------------------------------------------------------------------

def _random_bytes(seed: int, size: int) -> bytes:
    return np.random.default_rng(seed).bytes(size)


#: Random bytes, a few or up to the size bound (drawn from a seed: hypothesis's own buffer is far smaller).
RANDOM_BYTES = st.one_of(st.binary(max_size=512),
                         st.builds(_random_bytes, st.integers(0, 2**32 - 1), st.integers(0, MAX_FILE_BYTES)))

#: Values written over a file's bytes: all ones, all zeros, sign bits, NaN, infinity, huge doubles.
EXTREMES = [b"\xff", b"\x00", b"\x80", b"\x7f", b"\xff" * 4, b"\x00" * 4, b"\xff\xff\xff\x7f", b"\x00\x00\x00\x80",
            b"\xff" * 8, struct.pack("<d", math.nan), struct.pack("<d", math.inf), struct.pack("<d", 1e308),
            struct.pack("<f", math.nan), b"\xef\xbb\xbf", b"\n", b"\r", b'"', b",", b"\x1b[2J", b"\xfe\xff"]

#: Where an edit lands: near the start (headers), near the end (a zip's directory, footers), or anywhere.
POSITION = st.one_of(st.integers(0, 96), st.integers(-96, -1), st.integers(0, 2**31))
EDIT = st.tuples(st.sampled_from(["flip", "set", "insert", "delete", "cut"]), POSITION,
                 st.one_of(st.sampled_from(EXTREMES), st.binary(min_size=1, max_size=16)))
EDITS = st.lists(EDIT, min_size=1, max_size=6)


def damaged(data: bytes, edits) -> bytes:
    """``data`` with ``edits`` applied in turn: ``(kind, position, payload)``, a negative position from the end."""
    b = bytearray(data)
    for kind, at, payload in edits:
        i = (at % (len(b) + 1)) if at >= 0 else max(len(b) + at, 0)
        if kind == "flip":
            if i < len(b):
                b[i] ^= payload[0] or 0x01
        elif kind == "set":
            b[i:i + len(payload)] = payload
        elif kind == "insert":
            b[i:i] = payload
        elif kind == "delete":
            del b[i:i + 1 + payload[0]]
        else:
            del b[i:]
    return bytes(b)


#: CSV fields that are numbers only in part, or not at all, or that are not text.
ODD_FIELDS = ["1e308", "-1e308", "9e9999", "-9e9999", "1e-320", "NaN", "nan", "-nan", "inf", "-inf", "Infinity",
              "-0", "-0.0", "0", "-1", "-5.5", "1_000", "0x10", "\uff11\uff12", "\u0663", "1e", ".", "", " ",
              "9" * 5000, "1." + "0" * 5000, "\x00", "a\x00b", "\x1b[31mred\x1b[0m", "\x1b]0;title\x07", "\x7f",
              "\u0085", "\u2028", "\u202eevil", "\ufeff", "\ufeff0", '"', '"unterminated', '""', '"a,b"', '"x\ny"',
              "\r", "rough", "smooth", "rough wood", "a.wav", "s.wav", "s.json", "bad.wav", "sub", "../a.wav",
              "/dev/zero", "/", ".", "start", "end", "label", "path", "end_frame", "seconds", "True", "[]", "None"]
FIELD = st.one_of(st.sampled_from(ODD_FIELDS), st.text(max_size=12), st.floats().map(repr),
                  st.integers(-(10**30), 10**30).map(str))


def _encode(text: str, how: str) -> bytes:
    if how == "utf-8-bom":
        return b"\xef\xbb\xbf" + text.encode("utf-8", "surrogatepass")
    if how == "latin-1":
        return text.encode("latin-1", "replace")
    if how == "utf-16":
        return text.encode("utf-16", "surrogatepass")
    return text.encode("utf-8", "surrogatepass")


@st.composite
def csv_files(draw, header: list[str]) -> bytes:
    """A CSV of adversarial fields under ``header`` (or a damaged header), or a line up to the size bound
    without a break, in UTF-8 (with or without BOM), Latin-1 or UTF-16."""
    if draw(st.integers(0, 9)) == 0:
        filler = draw(st.sampled_from(["9", "a", ",", "\x00", '"', " ", "1,", '"a\n']))
        head = ",".join(header) + "\n" if draw(st.booleans()) else ""
        text = head + filler * draw(st.integers(0, (MAX_FILE_BYTES - len(head)) // len(filler)))
        return _encode(text, "utf-8")
    columns = draw(st.one_of(st.just(header), st.lists(st.one_of(st.sampled_from(header), FIELD), max_size=5)))
    sep = draw(st.sampled_from([",", ",", ",", ";", "\t", ", "]))
    newline = draw(st.sampled_from(["\n", "\r\n", "\r", "\n\n"]))
    rows = draw(st.lists(st.lists(FIELD, min_size=0, max_size=len(header) + 1), max_size=8))
    text = newline.join(sep.join(row) for row in [columns, *rows])
    if draw(st.booleans()):
        text += newline
    return _encode(text, draw(st.sampled_from(["utf-8", "utf-8", "utf-8-bom", "latin-1", "utf-16"])))


#: Raw JSON texts put in place of a value: non-finite and huge numbers, 5000-digit integers, deep nesting.
RAW_JSON = ["NaN", "Infinity", "-Infinity", "1e400", "9e9999", "-0", "-0.0", "1e308", "-1e308", "5e-324",
            "1" * 5000, "-" + "9" * 5000, "0." + "1" * 5000, "[" * 100_000 + "]" * 100_000,
            '{"a":' * 1000 + "1" + "}" * 1000, "[" * 9 + "]" * 9, '"\\u0000"', '"\\ud800"', '"\\u001b[2J"',
            '"' + "a" * 100_000 + '"', "[" + ",".join(["1e308"] * 5000) + "]", "2147483648", "-2147483649",
            "18446744073709551616", "true", "false", "null", '""', "[]", "{}", '[[]]', '{"":null}']
JSON_LEAF = st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(allow_nan=False),
                      st.text(max_size=10), st.sampled_from(["rough", "a", "A1", "custom", "whisker", "cochlea"]))
JSON_VALUE = st.recursive(JSON_LEAF, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                              st.dictionaries(st.text(max_size=6), inner, max_size=4)),
                          max_leaves=12)
#: A JSON text put in place of a value.
JSON_TEXT = st.one_of(st.sampled_from(RAW_JSON), JSON_VALUE.map(json.dumps))


def _paths(value, prefix=()):
    """Every place in a parsed JSON value: tuples of keys and indices (at most the first 3 items of a list)."""
    yield prefix
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(value, list):
        for i, v in enumerate(value[:3]):
            yield from _paths(v, (*prefix, i))


_HOLE = "\x00fuzz-hole\x00"


def _with_hole(value, path, how):
    """A copy of ``value`` with the place ``path``: replaced by the hole marker, removed, or given a sibling."""
    if not path:
        return _HOLE
    value = json.loads(json.dumps(value))
    parent = value
    for k in path[:-1]:
        parent = parent[k]
    last = path[-1]
    if how == "drop":
        del parent[last]
    elif how == "add" and isinstance(parent, dict):
        parent["\x00extra"] = _HOLE
    elif how == "add":
        parent.insert(last, _HOLE)
    else:
        parent[last] = _HOLE
    return value


@st.composite
def json_files(draw, valid: dict) -> bytes:
    """``valid`` with one place replaced, removed or doubled by an adversarial JSON text; or another value
    altogether; or the valid text with a key written twice."""
    which = draw(st.integers(0, 9))
    if which == 0:
        text = draw(JSON_TEXT)
    elif which == 1:
        key = draw(st.sampled_from(sorted(valid)))
        text = json.dumps(valid)[:-1] + f", {json.dumps(key)}: {draw(JSON_TEXT)}}}"
    else:
        path = draw(st.sampled_from(list(_paths(valid))))
        how = draw(st.sampled_from(["set", "set", "set", "drop", "add"])) if path else "set"
        text = json.dumps(_with_hole(valid, path, how), allow_nan=True)
        text = text.replace(json.dumps(_HOLE), draw(JSON_TEXT)).replace(json.dumps("\x00extra"), '"extra"')
    return text.encode("utf-8", "surrogatepass")


# -- spans CSV -------------------------------------------------------------------------------------------

VALID_SPANS = b"start,end,label\n0,1.5,rough\n1.5,3,smooth_wood\n"


def _read_spans(path):
    spans = read_spans(path)
    # accepted: finite, in order, not overlapping (what read_spans promises)
    assert spans and all(0 <= s.start < s.end < math.inf for s in spans)
    assert all(a.end <= b.start for a, b in zip(spans, spans[1:]))
    return spans


def test_valid_spans_file_is_read(tmp_path):
    """The base the damaged files start from is itself accepted: the damage tests start past every check."""
    (tmp_path / "s.csv").write_bytes(VALID_SPANS)
    assert [s.label for s in _read_spans(tmp_path / "s.csv")] == ["rough", "smooth_wood"]


@fuzz(50)
@given(data=RANDOM_BYTES)
def test_spans_reader_refuses_random_bytes_naming_the_file(tmp_path, data):
    path = tmp_path / "spans.csv"
    path.write_bytes(data)
    read_or_refuse(_read_spans, path)


@fuzz(80)
@given(edits=EDITS)
def test_spans_reader_refuses_a_damaged_file_naming_it(tmp_path, edits):
    path = tmp_path / "spans.csv"
    path.write_bytes(damaged(VALID_SPANS, edits))
    read_or_refuse(_read_spans, path)


@fuzz(140)
@given(data=csv_files(["start", "end", "label"]))
def test_spans_reader_refuses_adversarial_fields_naming_the_file(tmp_path, data):
    path = tmp_path / "spans.csv"
    path.write_bytes(data)
    read_or_refuse(_read_spans, path)


# -- timestamps CSV ---------------------------------------------------------------------------------------

VALID_BLOCK_TIMES = b"end_frame,seconds\n50,10.1\n100,10.2\n150,10.3\n"
FRAMES = st.one_of(st.just(150), st.integers(1, 10**12))


def _reader_of_times(frames):
    def read(path):
        kind, ends, seconds = read_times(path, frames)
        # accepted: finite times, block ends ascending to the WAV's end, or one time per frame
        assert np.all(np.isfinite(seconds))
        assert (kind == "block" and ends[-1] == frames and np.all(np.diff(ends) > 0)) or \
            (kind == "sample" and seconds.size == frames)
        return kind
    return read


def test_valid_times_file_is_read(tmp_path):
    (tmp_path / "t.csv").write_bytes(VALID_BLOCK_TIMES)
    assert _reader_of_times(150)(tmp_path / "t.csv") == "block"


@fuzz(50)
@given(data=RANDOM_BYTES, frames=FRAMES)
def test_times_reader_refuses_random_bytes_naming_the_file(tmp_path, data, frames):
    path = tmp_path / "times.csv"
    path.write_bytes(data)
    read_or_refuse(_reader_of_times(frames), path)


@fuzz(80)
@given(edits=EDITS, frames=FRAMES)
def test_times_reader_refuses_a_damaged_file_naming_it(tmp_path, edits, frames):
    path = tmp_path / "times.csv"
    path.write_bytes(damaged(VALID_BLOCK_TIMES, edits))
    read_or_refuse(_reader_of_times(frames), path)


@fuzz(140)
@given(data=st.one_of(csv_files(["end_frame", "seconds"]), csv_files(["seconds"])), frames=FRAMES)
def test_times_reader_refuses_adversarial_fields_naming_the_file(tmp_path, data, frames):
    path = tmp_path / "times.csv"
    path.write_bytes(data)
    read_or_refuse(_reader_of_times(frames), path)


# -- training manifest --------------------------------------------------------------------------------------

VALID_MANIFEST = b"path,label,start,end\na.wav,rough,0,0.5\ns.wav,smooth,,\n"


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """A folder with a.wav (1 s), the session s.wav + s.json (1 s), bad.wav (text) and a subfolder."""
    folder = tmp_path_factory.mktemp("recordings")
    rng = np.random.default_rng(0)
    write_wav(folder / "a.wav", 0.1 * rng.standard_normal((RATE, 1)), RATE)
    save_session(folder / "s", 0.1 * rng.standard_normal((RATE, 2)), RATE, "fuzz", labels=[(0.0, 0.5, "rough")],
                 arrivals=(list(range(50, RATE + 1, 50)), [k * 0.1 for k in range(1, 11)], float(RATE)))
    (folder / "bad.wav").write_text("not a wav\n")
    (folder / "sub").mkdir()
    return folder


def _read_manifest(path):
    recs = read_manifest(path)
    assert recs and all(r.start >= 0 and (r.end is None or r.end > r.start) and r.path.is_file() for r in recs)
    return recs


def test_valid_manifest_is_read(recordings):
    assert [r.label for r in _read_manifest(_put(recordings / "m.csv", VALID_MANIFEST))] == ["rough", "smooth"]


def _put(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


@fuzz(50)
@given(data=RANDOM_BYTES)
def test_manifest_reader_refuses_random_bytes_naming_the_manifest(recordings, data):
    read_or_refuse(_read_manifest, _put(recordings / "m.csv", data))


@fuzz(80)
@given(edits=EDITS, wav_edits=st.one_of(st.just([]), EDITS))
def test_manifest_reader_refuses_a_damaged_manifest_or_recording_naming_the_manifest(tmp_path, recordings, edits,
                                                                                      wav_edits):
    # the manifest and the WAV it lists, both damaged: a refusal names the manifest (and its line)
    (tmp_path / "a.wav").write_bytes(damaged((recordings / "a.wav").read_bytes(), wav_edits))
    for name in ("s.wav", "s.json"):
        (tmp_path / name).write_bytes((recordings / name).read_bytes())
    read_or_refuse(_read_manifest, _put(tmp_path / "m.csv", damaged(VALID_MANIFEST, edits)))


@fuzz(140)
@given(data=csv_files(["path", "label", "start", "end"]))
def test_manifest_reader_refuses_adversarial_fields_naming_the_manifest(recordings, data):
    read_or_refuse(_read_manifest, _put(recordings / "m.csv", data))


# -- WAV -----------------------------------------------------------------------------------------------------

def _read_wav(path):
    info = wav_info(path)
    x, rate = read_wav(path)
    # accepted: the header's layout, finite samples scaled to full scale (floats up to the bound)
    assert x.dtype == np.float64 and x.shape == (info.frames, info.channels) and rate == info.rate
    assert np.all(np.isfinite(x)) and (x.size == 0 or np.max(np.abs(x)) <= MAX_FLOAT_MAGNITUDE)
    return x


@pytest.fixture(scope="module")
def wavs(tmp_path_factory):
    """Valid WAVs of every layout write_wav writes (1 to 3 channels): their bytes."""
    folder = tmp_path_factory.mktemp("wavs")
    rng = np.random.default_rng(1)
    out = []
    for dtype, channels in (("float32", 1), ("float64", 2), ("int16", 3), ("int32", 1), ("uint8", 2)):
        path = folder / f"{dtype}.wav"
        write_wav(path, np.clip(0.3 * rng.standard_normal((200, channels)), -0.99, 0.99), 5000, dtype)
        _read_wav(path)
        out.append(path.read_bytes())
    return Valid("WAVs of every layout", files=out)


RIFF_MAGIC = st.sampled_from([b"RIFF\x00\x00\x00\x00WAVE", b"RIFF\xff\xff\xff\xffWAVE", b"RIFX\x24\x00\x00\x00WAVE",
                              b"RF64\xff\xff\xff\xffWAVE", b"RIFF\x24\x00\x00\x00WAVEfmt "])


@fuzz(50)
@given(data=RANDOM_BYTES, magic=st.one_of(st.just(b""), RIFF_MAGIC))
def test_wav_reader_refuses_random_bytes_naming_the_file(tmp_path, data, magic):
    read_or_refuse(_read_wav, _put(tmp_path / "r.wav", magic + data))


@fuzz(100)
@given(which=st.integers(0, 4), edits=EDITS)
def test_wav_reader_refuses_a_damaged_file_naming_it(tmp_path, wavs, which, edits):
    read_or_refuse(_read_wav, _put(tmp_path / "r.wav", damaged(wavs.files[which], edits)))


U16 = st.one_of(st.sampled_from([0, 1, 2, 3, 8, 16, 24, 32, 64, 0xFFFE, 0xFFFF]), st.integers(0, 0xFFFF))
U32 = st.one_of(st.sampled_from([0, 1, 7, 8, 16, 5000, 44100, 1_000_000, 1_000_001, 2**31, 2**32 - 1]),
                st.integers(0, 2**32 - 1))


@st.composite
def wav_files(draw) -> bytes:
    """A RIFF/WAVE file built chunk by chunk, every header field drawn from extremes: the format tag (also
    inside WAVE_FORMAT_EXTENSIBLE), channels, rate, block align, bits, chunk sizes that lie, extra and odd-sized
    chunks, NaN, infinite and huge float samples."""
    tag, channels, bits = draw(U16), draw(U16), draw(U16)
    rate = draw(U32)
    align = draw(st.one_of(st.just((channels * bits // 8) & 0xFFFF), U16))
    fmt = struct.pack("<HHIIHH", tag, channels, rate, draw(U32), align, bits)
    if draw(st.booleans()):                                           # WAVE_FORMAT_EXTENSIBLE's tail
        fmt += struct.pack("<HHIH", 22, bits, 0, draw(U16)) + bytes.fromhex("000000001000800000aa00389b71")
    fmt = fmt[:draw(st.integers(0, len(fmt)))] if draw(st.integers(0, 5)) == 0 else fmt
    kind = draw(st.sampled_from(["random", "nan", "inf", "huge", "zeros"]))
    n = draw(st.integers(0, 4096))
    if kind == "random":
        samples = _random_bytes(draw(st.integers(0, 2**32 - 1)), n)
    else:
        value = {"nan": math.nan, "inf": -math.inf, "huge": 3e38, "zeros": 0.0}[kind]
        samples = struct.pack("<f", value) * (n // 4) if bits != 64 else struct.pack("<d", value) * (n // 8)
    chunks = []
    if draw(st.booleans()):
        chunks.append((b"LIST", draw(U32), b"odd"))
    chunks.append((b"fmt ", draw(st.one_of(st.just(len(fmt)), U32)), fmt))
    if draw(st.booleans()):
        chunks.append((b"fact", 4, b"\x00\x01\x00\x00"))
    chunks.append((b"data", draw(st.one_of(st.just(len(samples)), U32)), samples))
    if draw(st.booleans()):
        chunks.reverse()                                              # data before fmt
    body = b"".join(cid + struct.pack("<I", size) + content + b"\x00" * (len(content) & 1)
                    for cid, size, content in chunks)
    return b"RIFF" + struct.pack("<I", draw(st.one_of(st.just(len(body) + 4), U32))) + b"WAVE" + body


@fuzz(160)
@given(data=wav_files())
def test_wav_reader_refuses_adversarial_headers_naming_the_file(tmp_path, data):
    read_or_refuse(_read_wav, _put(tmp_path / "r.wav", data))


# -- session (WAV + sidecar) -----------------------------------------------------------------------------------

def _read_session(path):
    session = load_session(path)
    frames = session.data.shape[0]
    assert np.all(np.isfinite(session.data))
    assert all(0 <= lab.start < lab.end <= frames / session.rate + 1 for lab in session.labels)
    return session


@pytest.fixture(scope="module")
def session_files(recordings):
    """The valid session's WAV bytes and parsed sidecar."""
    wav, js = session_paths(recordings / "s")
    _read_session(wav)
    return Valid("session", wav=wav.read_bytes(), meta=json.loads(js.read_text()))


def _session_named(tmp_path, wav: bytes, sidecar: bytes) -> tuple[Path, Path]:
    wav_path, js_path = session_paths(tmp_path / "rec")
    wav_path.write_bytes(wav)
    js_path.write_bytes(sidecar)
    return wav_path, js_path


@fuzz(50)
@given(data=RANDOM_BYTES, which=st.sampled_from(["sidecar", "wav"]))
def test_session_reader_refuses_random_bytes_naming_the_file(tmp_path, session_files, data, which):
    wav, meta = session_files.wav, session_files.meta
    sidecar = json.dumps(meta).encode()
    wav_path, js_path = _session_named(tmp_path, data if which == "wav" else wav,
                                       data if which == "sidecar" else sidecar)
    # a WAV that disagrees with its sidecar is refused in the sidecar's words ("rate is 500 Hz but the WAV ...")
    read_or_refuse(_read_session, wav_path, wav_path, js_path)


@fuzz(100)
@given(edits=EDITS, wav_edits=st.one_of(st.just([]), EDITS))
def test_session_reader_refuses_a_damaged_session_naming_the_file(tmp_path, session_files, edits, wav_edits):
    wav, meta = session_files.wav, session_files.meta
    sidecar = json.dumps(meta, indent=1).encode()
    wav_path, js_path = _session_named(tmp_path, damaged(wav, wav_edits), damaged(sidecar, edits))
    read_or_refuse(_read_session, wav_path, wav_path, js_path)


@fuzz(160)
@given(data=st.data())
def test_session_reader_refuses_an_adversarial_sidecar_naming_it(tmp_path, session_files, data):
    wav, meta = session_files.wav, session_files.meta
    wav_path, js_path = _session_named(tmp_path, wav, data.draw(json_files(meta)))
    read_or_refuse(_read_session, wav_path, js_path)


# -- bank file ---------------------------------------------------------------------------------------------------

VALID_BANKS = [
    {"format": "supramodal-bank", "version": 1, "bank": {"kind": "whisker", "rows": "AB", "mean_B": 145, "fs": 5000}},
    {"format": "supramodal-bank", "version": 1,
     "bank": {"kind": "cochlea", "channels": 6, "f_low": 50, "f_high": 1000, "fs": 2200}},
    {"format": "supramodal-bank", "version": 1,
     "bank": {"kind": "custom", "fs": 2200, "cf": [100.0, 300.0], "b": [30.0, 40.0], "names": ["lo", "hi"]}},
]


def _read_bank(path):
    bank = load_bank(path)
    assert 1 <= bank.channels <= MAX_CHANNELS and np.all(np.isfinite(bank.cf)) and np.all(bank.cf < bank.fs / 2)
    return bank


def test_valid_bank_files_are_read(tmp_path):
    for i, valid in enumerate(VALID_BANKS):
        assert _read_bank(_put(tmp_path / f"b{i}.json", json.dumps(valid).encode())).channels in (8, 6, 2)


@fuzz(50)
@given(data=RANDOM_BYTES)
def test_bank_reader_refuses_random_bytes_naming_the_file(tmp_path, data):
    read_or_refuse(_read_bank, _put(tmp_path / "bank.json", data))


@fuzz(80)
@given(which=st.integers(0, 2), edits=EDITS)
def test_bank_reader_refuses_a_damaged_file_naming_it(tmp_path, which, edits):
    read_or_refuse(_read_bank, _put(tmp_path / "bank.json", damaged(json.dumps(VALID_BANKS[which]).encode(), edits)))


@fuzz(160)
@given(data=st.data(), which=st.integers(0, 2))
def test_bank_reader_refuses_adversarial_json_naming_the_file(tmp_path, data, which):
    read_or_refuse(_read_bank, _put(tmp_path / "bank.json", data.draw(json_files(VALID_BANKS[which]))))


# -- model file (.npz) ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def model_parts(tmp_path_factory):
    """A small calibrated model (4 channels, 3 classes, novelty score): its file's bytes, header and arrays."""
    rng = np.random.default_rng(1)
    values = rng.gamma(2.0, 1.0, (60, 1, 4))
    labels = np.repeat([0, 1, 2], 20)
    values[:, 0, 0] *= 1 + labels
    model = TextureModel.train(values, labels, ("a", "b", "c"), whisker_bank(rows="A"), ("Af",), 500, epochs=5,
                               seed=0)
    path = model.save(tmp_path_factory.mktemp("model") / "m.npz")
    TextureModel.load(path)
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files if k != "header"}
        header = json.loads(str(npz["header"]))
    return Valid("model", data=path.read_bytes(), header=header, arrays=arrays)


def _read_model(path):
    model = TextureModel.load(path)
    assert model.mlp.shape == (model.n_inputs, model.mlp.shape[1], len(model.classes))
    return model


@fuzz(50)
@given(data=RANDOM_BYTES, magic=st.sampled_from([b"", b"PK\x03\x04", b"\x93NUMPY", b"\x80\x04"]))
def test_model_reader_refuses_random_bytes_naming_the_file(tmp_path, data, magic):
    read_or_refuse(_read_model, _put(tmp_path / "m.npz", magic + data))


@fuzz(100)
@given(edits=EDITS)
def test_model_reader_refuses_a_damaged_file_naming_it(tmp_path, model_parts, edits):
    read_or_refuse(_read_model, _put(tmp_path / "m.npz", damaged(model_parts.data, edits)))


def _npy_declaring(shape, descr: str, payload: bytes = b"\x00" * 16) -> bytes:
    """A .npy member whose header declares ``shape`` of ``descr`` but holds ``payload``."""
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue() + payload


ODD_ARRAYS = st.sampled_from([
    np.zeros(0), np.zeros((0, 4)), np.float64(1.0), np.full(4, np.nan), np.full((4, 4), np.inf), np.full(4, 1e308),
    np.full(4, -0.0), np.zeros(4, np.int64), np.zeros(4, np.complex128), np.zeros(4, np.bool_), np.array(["a"] * 4),
    np.zeros(4, np.float16), np.zeros((4, 4, 4)), np.zeros((3, 4)), np.zeros(10**5), np.array([1, 2], ">f8"),
    np.zeros(4, [("a", "<f8")]),
])
HUGE_SHAPES = st.sampled_from([(2**40,), (2**31, 2**31), (10**6, 10**6), (-1,), (2**62, 4)])
DESCRS = st.sampled_from(["<f8", ">f8", "<f4", "<U4", "<U10", "|b1", "<c16", "<i8", "|V8", "|S4", "<M8[s]"])


@st.composite
def model_archives(draw, parts) -> dict[str, bytes]:
    """The members of a model .npz: the valid ones, with the header an adversarial JSON text (or not text at
    all) and any array replaced by one of the wrong dtype, shape or content, by a member declaring a huge
    shape, by any bytes under a plausible .npy header, or left out."""
    header, arrays = parts.header, parts.arrays
    members = {}
    which = draw(st.integers(0, 3))
    if which == 0:
        members["header"] = np.array(draw(ODD_ARRAYS))
    else:
        members["header"] = np.array(draw(json_files(header)).decode("utf-8", "surrogatepass"))
    for name, a in arrays.items():
        members[name] = a
    if which >= 2:
        name = draw(st.sampled_from(sorted(arrays) + ["header"]))
        how = draw(st.sampled_from(["odd", "huge", "raw", "drop"]))
        if how == "odd":
            members[name] = draw(ODD_ARRAYS)
        elif how == "huge":
            members[name] = _npy_declaring(draw(HUGE_SHAPES), draw(DESCRS))
        elif how == "raw":                        # any bytes as the data of a plausible shape (invalid text too)
            shape = draw(st.sampled_from([(), (4,), (3,), (4, 4), (4, 3), (3, 3, 3)]))
            members[name] = _npy_declaring(shape, draw(DESCRS), draw(st.binary(max_size=200)))
        else:
            del members[name]
    return members


def _write_npz(path: Path, members: dict) -> Path:
    import io

    with zipfile.ZipFile(path, "w") as z:
        for name, a in members.items():
            if isinstance(a, bytes):
                z.writestr(name + ".npy", a)
            else:
                buf = io.BytesIO()
                np.save(buf, a, allow_pickle=False)
                z.writestr(name + ".npy", buf.getvalue())
    return path


@fuzz(160)
@given(data=st.data())
def test_model_reader_refuses_adversarial_headers_and_arrays_naming_the_file(tmp_path, model_parts, data):
    read_or_refuse(_read_model, _write_npz(tmp_path / "m.npz", data.draw(model_archives(model_parts))))


# -- XDF ------------------------------------------------------------------------------------------------------------

def _xdf_streams(samples=None, stamps=None, fmt="float32", offsets=None, rate=float(RATE)):
    """A signal stream "w" (2 channels, 0.6 s) and a marker stream "m" whose markers label it."""
    rng = np.random.default_rng(2)
    n = 300
    w = XdfStream("w", "Whiskers", rate, 0.1 * rng.standard_normal((n, 2)) if samples is None else samples,
                  100.0 + np.arange(n) / RATE if stamps is None else stamps, fmt=fmt, chunk=64,
                  # one clock offset: pyxdf fits a line to two or more (50 ms a stream); the offsets case does that
                  offsets=[(100.0, 0.001)] if offsets is None else offsets)
    m = XdfStream("m", "Markers", 0.0, [["rough"], [""], ["smooth"]], np.array([100.05, 100.2, 100.3]), fmt="string",
                  offsets=[(100.0, 0.001)])
    return [w, m]


def _read_xdf(path):
    session = xdf_session(path, name="w", labels="m", streams=load_xdf_streams(path))
    assert np.all(np.isfinite(session.data)) and session.rate >= 1 and session.data.shape[1] >= 1
    return session


@pytest.fixture(scope="module")
def xdf_bytes(tmp_path_factory):
    path = tmp_path_factory.mktemp("xdf") / "r.xdf"
    write_xdf(path, _xdf_streams())
    assert [lab.label for lab in _read_xdf(path).labels] == ["rough", "smooth"]
    return Valid("XDF", data=path.read_bytes())


@fuzz(50)
@given(data=RANDOM_BYTES, magic=st.sampled_from([b"", b"XDF:", b"XDF:\x01\x05\x01\x00"]))
def test_xdf_reader_refuses_random_bytes_naming_the_file(tmp_path, data, magic):
    read_or_refuse(_read_xdf, _put(tmp_path / "r.xdf", magic + data))


@fuzz(80)
@given(edits=EDITS)
def test_xdf_reader_refuses_a_damaged_file_naming_it(tmp_path, xdf_bytes, edits):
    read_or_refuse(_read_xdf, _put(tmp_path / "r.xdf", damaged(xdf_bytes.data, edits)))


def _rechunked(data: bytes, change) -> bytes:
    """An XDF file with each chunk's content passed through ``change(tag, content, first)`` (``first``: the
    first chunk of that tag and StreamId) and its length written anew, so that only the content is wrong."""
    out, pos, seen = [data[:4]], 4, set()
    while pos < len(data):
        width = data[pos]
        length = int.from_bytes(data[pos + 1:pos + 1 + width], "little")
        start = pos + 1 + width
        tag, content = int.from_bytes(data[start:start + 2], "little"), data[start + 2:start + length]
        first = (tag, content[:4]) not in seen
        seen.add((tag, content[:4]))
        out.append(_chunk(tag, change(tag, content, first)))
        pos = start + length
    return b"".join(out)


def _with_header_field(data: bytes, field: str, value: bytes, stream: int = 1) -> bytes:
    """An XDF file with ``<field>``'s text in ``stream``'s header replaced by ``value``."""
    pattern, sid = rb"<%s>[^<]*</%s>" % (field.encode(), field.encode()), struct.pack("<I", stream)

    def change(tag, content, first):
        if tag != 2 or content[:4] != sid:
            return content
        return re.sub(pattern, lambda m: b"<%s>%s</%s>" % (field.encode(), value, field.encode()), content)
    return _rechunked(data, change)


def _with_sample_count(data: bytes, stream: int, count: int, pad: int) -> bytes:
    """An XDF file whose first Samples chunk of ``stream`` declares ``count`` samples (an 8-byte count) and has
    ``pad`` zero bytes more."""
    sid = struct.pack("<I", stream)

    def change(tag, content, first):
        if tag != 3 or content[:4] != sid or not first:
            return content
        width = content[4]
        return sid + struct.pack("<BQ", 8, count) + content[5 + width:] + b"\x00" * pad
    return _rechunked(data, change)


ODD_XML = st.one_of(st.sampled_from([b"", b"0", b"-1", b"1e308", b"9e9999", b"NaN", b"inf", b"-0", b"0.5", b"2",
                                     b"65535", b"65536", b"999999999999", b"1000001", b"1" * 5000, b"int8", b"int64",
                                     b"string", b"double64", b"\x00", b"\x1b[2J", b"<", b"&amp;", b"]]>", b"w"]),
                    st.binary(max_size=12))
ODD_FLOATS = st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0, -0.0, 1e-300, 3e38])


@st.composite
def xdf_files(draw, folder: Path) -> bytes:
    """An XDF file of the two streams with one thing made extreme: a stream header field, the samples, the
    timestamps (non-finite, huge, backwards, standing still, a jump), the clock offsets, the sample format, or
    the count of samples a chunk declares (with the channels its stream declares)."""
    path = folder / "base.xdf"
    what = draw(st.sampled_from(["header", "samples", "stamps", "offsets", "format", "count"]))
    n = 300
    stamps = 100.0 + np.arange(n) / RATE
    if what == "samples":
        samples = np.full((n, 2), 0.1)
        samples[draw(st.integers(0, n - 1)), draw(st.integers(0, 1))] = draw(ODD_FLOATS)
        with np.errstate(over="ignore"):          # 1e308 as float32 is infinite: on purpose
            write_xdf(path, _xdf_streams(samples=samples, fmt=draw(st.sampled_from(["float32", "double64"]))))
    elif what == "stamps":
        change = draw(st.sampled_from(["one", "reverse", "constant", "jump", "scale"]))
        k = draw(st.integers(0, n - 1))
        if change == "one":
            stamps[k] = draw(ODD_FLOATS)
        elif change == "reverse":
            stamps = stamps[::-1].copy()
        elif change == "constant":
            stamps[:] = 100.0
        elif change == "jump":
            stamps[k:] += draw(st.sampled_from([1e3, 1e6, 1e9, 1e12, -50.0]))
        else:
            stamps = 100.0 + np.arange(n) / RATE * draw(st.sampled_from([1e-9, 1e-3, 1e3, 1e6]))
        write_xdf(path, _xdf_streams(stamps=stamps))
    elif what == "offsets":
        write_xdf(path, _xdf_streams(offsets=[(draw(ODD_FLOATS), draw(ODD_FLOATS)), (100.2, 0.0)]))
    elif what == "format":
        fmt = draw(st.sampled_from(["int16", "int32", "double64"]))
        big = np.full((n, 2), draw(st.sampled_from([0, 1, -1, 2**15 - 1, -(2**31)])))
        write_xdf(path, _xdf_streams(samples=big, fmt=fmt))
    else:
        write_xdf(path, _xdf_streams())
    data = path.read_bytes()
    if what == "header":
        field = draw(st.sampled_from(["channel_count", "nominal_srate", "channel_format", "name", "type",
                                      "source_id"]))
        data = _with_header_field(data, field, draw(ODD_XML))
    elif what == "count":
        # a stream's declared channels and one Samples chunk's declared samples, each possibly forged
        stream = draw(st.sampled_from([1, 2]))
        if draw(st.booleans()):
            channels = draw(st.sampled_from([1, 2, 3, 1000, 65535]))
            data = _with_header_field(data, "channel_count", str(channels).encode(), stream)
        count = draw(st.sampled_from([0, 1, 2, 64, 65, 3000, 2**24, 2**31, 2**63]))
        data = _with_sample_count(data, stream, count, draw(st.integers(0, 20_000)))
    return data


@fuzz(80)
@given(data=st.data())
def test_xdf_reader_refuses_adversarial_streams_naming_the_file(tmp_path, data):
    read_or_refuse(_read_xdf, _put(tmp_path / "r.xdf", data.draw(xdf_files(tmp_path))))
