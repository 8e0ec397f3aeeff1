"""Tests of the replay package: WAV I/O, sessions, and the replay driver."""

from __future__ import annotations

import json
import math
import struct
import threading
import time
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.io import wavfile

from supramodal.drivers.base import Block, DeviceUnavailable, Driver, DriverClosed, DriverError
from supramodal.replay import (ClippingWarning, Label, ReplayDriver, ReplayError, Session, SessionError,
                    WavFormatError, load_session, random_block_sizes, read_wav, release_time,
                    DeviceClock,
                    save_session, wav_info, write_wav)

RNG = np.random.default_rng(20240601)


def _noise(frames, channels, scale=0.9):
    return RNG.uniform(-scale, scale, size=(frames, channels))


def _drain(driver, timeout=None):
    blocks = []
    while True:
        try:
            b = driver.read(timeout)
        except DriverClosed:
            return blocks
        assert b is not None
        blocks.append(b)


def _riff(fmt_tag, channels, rate, bits, payload, declared=None, extensible_tag=None):
    """Hand-built WAV bytes, for formats scipy would not write."""
    block_align = channels * bits // 8
    fmt = struct.pack("<HHIIHH", fmt_tag, channels, rate, rate * block_align, block_align, bits)
    if extensible_tag is not None:
        guid_tail = b"\x00\x00\x00\x00\x10\x00\x80\x00\x00\xaa\x00\x38\x9b\x71"
        fmt += struct.pack("<HHI", 22, bits, 0) + struct.pack("<H", extensible_tag) + guid_tail
    size = len(payload) if declared is None else declared
    body = b"WAVE" + b"fmt " + struct.pack("<I", len(fmt)) + fmt + b"data" + struct.pack("<I", size) + payload
    return b"RIFF" + struct.pack("<I", len(body)) + body


# --- WAV round trips ------------------------------------------------------------------

STEP = {"int16": 1 / 32768, "int32": 1 / 2**31, "uint8": 1 / 128}


@pytest.mark.parametrize("channels", [1, 2, 20])
@pytest.mark.parametrize("dtype", ["float32", "float64", "int16", "int32", "uint8"])
def test_wav_round_trip(tmp_path, dtype, channels):
    x = _noise(257, channels)
    path = tmp_path / "x.wav"
    assert write_wav(path, x, 5000, dtype=dtype) == 0
    y, rate = read_wav(path)
    assert rate == 5000
    assert y.dtype == np.float64 and y.shape == (257, channels)
    if dtype == "float64":
        np.testing.assert_array_equal(y, x)
    elif dtype == "float32":
        np.testing.assert_array_equal(y, x.astype(np.float32).astype(np.float64))
    else:
        step = STEP[dtype]
        np.testing.assert_array_equal(y, np.rint(x / step) * step)  # exact quantisation
        assert np.max(np.abs(y - x)) <= step / 2 + 1e-12
    info = wav_info(path)
    assert (info.frames, info.channels, info.rate, info.bits) == (257, channels, 5000, np.dtype(dtype).itemsize * 8)


def test_mono_1d_input_reads_as_one_column(tmp_path):
    write_wav(tmp_path / "m.wav", np.linspace(-1, 0.5, 11), 44100)
    y, _ = read_wav(tmp_path / "m.wav")
    assert y.shape == (11, 1)


@pytest.mark.parametrize("raw, expected", [
    (np.array([-32768, 0, 16384, 32767], np.int16), [-1.0, 0.0, 0.5, 32767 / 32768]),
    (np.array([-2**31, 0, 2**30, 2**31 - 1], np.int32), [-1.0, 0.0, 0.5, (2**31 - 1) / 2**31]),
    (np.array([0, 128, 192, 255], np.uint8), [-1.0, 0.0, 0.5, 127 / 128]),
])
def test_full_scale_of_foreign_files(tmp_path, raw, expected):
    wavfile.write(tmp_path / "f.wav", 8000, raw)  # written by scipy, not by us
    y, _ = read_wav(tmp_path / "f.wav")
    np.testing.assert_array_equal(y[:, 0], expected)


def test_extensible_pcm_is_accepted(tmp_path):
    payload = np.array([[1000, -1000], [16384, -16384]], "<i2").tobytes()
    (tmp_path / "e.wav").write_bytes(_riff(0xFFFE, 2, 5000, 16, payload, extensible_tag=1))
    y, rate = read_wav(tmp_path / "e.wav")
    np.testing.assert_array_equal(y, [[1000 / 32768, -1000 / 32768], [0.5, -0.5]])


@pytest.mark.parametrize("channels", [1, 2, 5])
@pytest.mark.parametrize("extensible", [False, True])
def test_24_bit_pcm_is_read_exactly(tmp_path, channels, extensible):
    """24-bit PCM (field recorders' format), built byte by byte here: each sample v / 2**23 exactly,
    the extremes included."""
    values = np.concatenate([[-2**23, 2**23 - 1, 0, 1, -1], RNG.integers(-2**23, 2**23, 200 * channels)])
    values = values[: len(values) // channels * channels]
    payload = b"".join(int(v).to_bytes(3, "little", signed=True) for v in values)
    tag = (0xFFFE, 1) if extensible else (1, None)
    path = tmp_path / "rec24.wav"
    path.write_bytes(_riff(tag[0], channels, 48000, 24, payload, extensible_tag=tag[1]))
    y, rate = read_wav(path)
    assert rate == 48000 and y.shape == (len(values) // channels, channels)
    np.testing.assert_array_equal(y, values.reshape(-1, channels) / 2**23)
    assert wav_info(path).bits == 24


def test_int16_clipping_is_counted_and_warned(tmp_path):
    x = np.array([[0.0, 1.0], [-1.0, 1.5], [-2.0, 0.25]])
    with pytest.warns(ClippingWarning, match=r"clipped 3 of 6 samples"):
        n = write_wav(tmp_path / "c.wav", x, 5000, dtype="int16")
    assert n == 3  # +1.0 itself is one step beyond int16's largest value
    y, _ = read_wav(tmp_path / "c.wav")
    np.testing.assert_array_equal(y[:, 1], [32767 / 32768, 32767 / 32768, 0.25])
    assert y[2, 0] == -1.0


def test_float_write_keeps_values_beyond_full_scale(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert write_wav(tmp_path / "f.wav", np.array([[2.0], [-3.0]]), 5000) == 0
    assert read_wav(tmp_path / "f.wav")[0][:, 0].tolist() == [2.0, -3.0]


@pytest.mark.parametrize("kwargs, match", [
    ({"data": np.array([[np.nan]])}, "NaN"),
    ({"dtype": "int24"}, "dtype must be one of"),
    ({"rate": 44100.5}, "whole number"),
    ({"rate": 0}, "whole number"),
    ({"data": np.zeros((2, 2, 2))}, "shape"),
])
def test_write_wav_refusals(tmp_path, kwargs, match):
    args = {"data": np.zeros((4, 1)), "rate": 5000, "dtype": "float32"} | kwargs
    with pytest.raises(ValueError, match=match):
        write_wav(tmp_path / "bad.wav", **args)
    assert not (tmp_path / "bad.wav").exists()


# --- WAV refusals -----------------------------------------------------------------------

def _good_bytes(tmp_path, frames=100, channels=3, dtype="float32"):
    write_wav(tmp_path / "good.wav", _noise(frames, channels), 5000, dtype=dtype)
    return (tmp_path / "good.wav").read_bytes()


@pytest.mark.parametrize("make, match", [
    (lambda good: _riff(1, 1, 5000, 20, b"\x00" * 30), r"20-bit integer PCM samples are not supported"),
    (lambda good: _riff(0xFFFE, 2, 5000, 20, b"\x00" * 60, extensible_tag=1), r"20-bit integer PCM"),
    (lambda good: _riff(1, 2, 5000, 24, b"\x00" * 9), r"not a whole number of 6-byte frames"),
    (lambda good: _riff(1, 1, 5000, 12, b"\x00" * 10), r"12-bit integer PCM"),
    (lambda good: _riff(7, 1, 8000, 8, b"\x00" * 10), r"compressed or unknown sample format mu-law"),
    (lambda good: _riff(2, 1, 8000, 4, b"\x00" * 10), r"Microsoft ADPCM"),
    (lambda good: _riff(0x55, 2, 44100, 0, b"\x00" * 10), r"MP3"),
    (lambda good: good[:-120], r"truncated: the 'data' chunk declares 1200 bytes \(100 frames\) but the file "
                               r"holds 1080 \(90 frames\)"),
    (lambda good: good[:-5], r"truncated"),
    (lambda good: good[:50], r"truncated"),
    (lambda good: good[:20], r"too short|truncated|corrupt"),
    (lambda good: b"", r"too short to be a WAV file \(0 bytes"),
    (lambda good: b"ID3\x04" + b"\x00" * 100, r"not a WAV file"),
    (lambda good: b"RIFX" + good[4:], r"RIFX container is not supported"),
    (lambda good: _riff(1, 2, 5000, 16, b"\x00" * 7), r"not a whole number of 4-byte frames"),
    (lambda good: _riff(1, 0, 5000, 16, b""), r"0 channels"),
    (lambda good: _riff(3, 1, 5000, 32, np.array([0.5, np.nan], "<f4").tobytes()), r"NaN or infinite"),
    (lambda good: _riff(1, 1, 5000, 16, b"\x00\x00", declared=0xFFFFFFFF), r"truncated"),
])
def test_bad_wav_files_are_refused_with_their_name_and_problem(tmp_path, make, match):
    path = tmp_path / "bad_file.wav"
    path.write_bytes(make(_good_bytes(tmp_path)))
    with pytest.raises(WavFormatError, match=match) as err:
        read_wav(path)
    assert str(path) in str(err.value)
    assert isinstance(err.value, ValueError) and isinstance(err.value, ReplayError)


def test_missing_wav_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_wav(tmp_path / "nope.wav")


# --- sessions ------------------------------------------------------------------------------

def _save(tmp_path, name="s", frames=5000, channels=4, rate=5000, labels=None, filled=None, dtype="float32"):
    x = _noise(frames, channels)
    if labels is None:
        labels = [Label(0.0, 0.4, "felt"), {"start": 0.4, "end": 1.0, "label": "sandpaper"}]
    save_session(tmp_path / name, x, rate, "replay test", labels, filled=filled, dtype=dtype)
    return x


def test_session_round_trip(tmp_path):
    x = _save(tmp_path, filled=[(10, 20), (100, 101)])
    for p in ("s", "s.wav", "s.json"):
        s = load_session(tmp_path / p)
        assert isinstance(s, Session)
        assert (s.rate, s.channels, s.frames, s.source) == (5000, 4, 5000, "replay test")
        assert s.labels == (Label(0.0, 0.4, "felt"), Label(0.4, 1.0, "sandpaper"))
        assert s.filled == ((10, 20), (100, 101))
        np.testing.assert_array_equal(s.data, x.astype(np.float32))
        assert s.filled_mask().sum() == 11
    meta = json.loads((tmp_path / "s.json").read_text())
    assert meta["format"] == "supramodal-session" and meta["version"] == 1


def test_session_filled_from_mask_and_labels_sorted(tmp_path):
    mask = np.zeros(5000, bool)
    mask[3:7] = mask[4990:] = True
    _save(tmp_path, filled=mask, labels=[(0.5, 0.75, "b"), (0.0, 0.25, "a")])
    s = load_session(tmp_path / "s")
    assert s.filled == ((3, 7), (4990, 5000))
    assert [lab.label for lab in s.labels] == ["a", "b"]


def test_save_session_refuses_before_writing(tmp_path):
    with pytest.raises(SessionError, match=r"labels\[1\].*overlap"):
        _save(tmp_path, labels=[(0.0, 0.5, "a"), (0.4, 0.6, "b")])
    assert list(tmp_path.iterdir()) == []


def test_missing_sidecar(tmp_path):
    write_wav(tmp_path / "bare.wav", np.zeros((10, 1)), 5000)
    with pytest.raises(FileNotFoundError, match="no sidecar"):
        load_session(tmp_path / "bare.wav")


def _mutate(tmp_path, fn):
    _save(tmp_path)
    meta = json.loads((tmp_path / "s.json").read_text())
    fn(meta)
    (tmp_path / "s.json").write_text(json.dumps(meta))


@pytest.mark.parametrize("fn, match", [
    (lambda m: m.update(colour="red"), r"'colour': unknown key; remove it or fix its spelling"),
    (lambda m: m.pop("source"), r"'source': missing; add it"),
    (lambda m: m.update(format="something-else"), r"format: is 'something-else'"),
    (lambda m: m.update(version=2), r"version: is 2, this code reads version 1 only"),
    (lambda m: m.update(version="1"), r"version: must be an integer, got string"),
    (lambda m: m.update(version=True), r"version: must be an integer, got boolean"),
    (lambda m: m.update(rate=44100), r"rate: is 44100 Hz but the WAV header says 5000 Hz"),
    (lambda m: m.update(rate="5000"), r"rate: must be a positive number of Hz, got string"),
    (lambda m: m.update(channels=3), r"channels: is 3 but the WAV has 4"),
    (lambda m: m.update(channels=4.0), r"channels: must be a positive integer"),
    (lambda m: m.update(source=None), r"source: must be a string, got null"),
    (lambda m: m.update(labels={}), r"labels: must be an array, got object"),
    (lambda m: m["labels"].append([1.0, 2.0, "x"]), r"labels\[2\]: must be an object, got array"),
    (lambda m: m["labels"][0].pop("end"), r"labels\[0\]: has keys \['label', 'start'\]; use exactly"),
    (lambda m: m["labels"][0].update(texture="x"), r"labels\[0\]: has keys"),
    (lambda m: m["labels"][0].update(start="0"), r"labels\[0\]\.start: must be a finite number"),
    (lambda m: m["labels"][0].update(label=""), r"labels\[0\]\.label: must be a name: letters"),
    # a label is data: no terminal escapes, no line breaks, no path, no 70-character name (issue 35, item 5)
    (lambda m: m["labels"][0].update(label="felt\x1b[31mRED"), r"labels\[0\]\.label: must be a name: .*\\x1b"),
    (lambda m: m["labels"][0].update(label="x\ny"), r"labels\[0\]\.label: must be a name"),
    (lambda m: m["labels"][0].update(label="../x"), r"labels\[0\]\.label: must be a name"),
    (lambda m: m["labels"][0].update(label="a" * 70), r"labels\[0\]\.label: must be a name.*at most 64"),
    (lambda m: m["labels"][0].update(start=0.3, end=0.3), r"labels\[0\]: range \[0.3, 0.3\) is empty"),
    (lambda m: m["labels"][0].update(start=-0.1), r"labels\[0\]: range .* negative"),
    (lambda m: m["labels"][1].update(end=1.5), r"labels\[1\]: ends at 1.5 s, after the recording's end at 1.0 s"),
    (lambda m: m["labels"][1].update(start=0.3), r"labels\[1\]: .*must not overlap"),
    (lambda m: m["labels"].reverse(), r"labels\[1\]: .*put labels in time order"),
    (lambda m: m.update(filled=[[0, 10], [5, 20]]), r"filled\[1\]: .*without overlap"),
    (lambda m: m.update(filled=[[4990, 5001]]), r"filled\[0\]: range \[4990, 5001\) is empty or outside"),
    (lambda m: m.update(filled=[[0.0, 1.0]]), r"filled\[0\]: must be a pair of integer frame indices"),
    (lambda m: m.update(filled={"0": 1}), r"filled: must be an array"),
    (lambda m: m.update(marks=[[10, "reboot"]]), r"marks\[0\]: kind 'reboot' is unknown; use one of \['restart', 'overrun'\]"),
    (lambda m: m.update(marks=[[5000, "restart"]]), r"marks\[0\]: frame 5000 is outside the recording's 5000 frames"),
    (lambda m: m.update(marks=[[20, "overrun"], [10, "restart"]]), r"marks\[1\]: frame 10 comes before .*frame order"),
    (lambda m: m.update(marks=[["10", "restart"]]), r"marks\[0\]: must be a \[frame, kind\] pair"),
    (lambda m: m.update(marks={"10": "restart"}), r"marks: must be an array of \[frame, kind\] pairs"),
])
def test_sidecar_validation(tmp_path, fn, match):
    _mutate(tmp_path, fn)
    with pytest.raises(SessionError, match=match) as err:
        load_session(tmp_path / "s")
    assert str(tmp_path / "s.json") in str(err.value)


def test_label_ending_at_the_end_within_half_a_frame_passes(tmp_path):
    _mutate(tmp_path, lambda m: m["labels"][1].update(end=1.0 + 0.4 / 5000))
    assert load_session(tmp_path / "s").labels[1].end > 1.0


@pytest.mark.parametrize("text, match", [
    ('{"format": "supramodal-session", "format": "x"}', r"key 'format' appears twice"),
    ('{"rate": NaN}', r"NaN is not a number JSON allows"),
    ('{"rate": Infinity}', r"Infinity is not a number"),
    ('{"rate": 5000,', r"not valid JSON"),
    ('[1, 2]', r"must be a JSON object, got array"),
    (b'\xff\xfe{', r"not valid JSON"),
])
def test_sidecar_is_strict_json(tmp_path, text, match):
    _save(tmp_path)
    p = tmp_path / "s.json"
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(SessionError, match=match):
        load_session(tmp_path / "s")


# --- the driver: contract, tiling -----------------------------------------------------------

def test_driver_follows_the_contract():
    d = ReplayDriver((_noise(100, 2), 5000), speed="max")
    assert isinstance(d, Driver)
    with pytest.raises(DriverError, match="before open"):
        d.read()
    with d:
        b = d.read()
        assert isinstance(b, Block) and b.data.dtype == np.float64 and b.data.shape == (50, 2)
        assert b.filled is None and b.start == 0
        assert d.stats() == {"frames": 50, "filled": 0, "blocks": 1, "loops": 0}
    with pytest.raises(DriverClosed):
        d.read()


@settings(max_examples=60, deadline=None)
@given(frames=st.integers(1, 300), channels=st.integers(1, 4), size=st.integers(1, 400),
       passes=st.integers(1, 3))
def test_fixed_blocks_tile_the_source(frames, channels, size, passes):
    x = RNG.standard_normal((frames, channels)) * 0.1
    d = ReplayDriver((x, 5000), block_size=size, speed="max", loop=passes)
    with d:
        blocks = _drain(d)
    starts = [b.start for b in blocks]
    assert starts == [0] + list(np.cumsum([b.frames for b in blocks])[:-1])
    assert all(b.frames == size for b in blocks[:-1]) and 1 <= blocks[-1].frames <= size
    np.testing.assert_array_equal(np.concatenate([b.data for b in blocks]), np.tile(x, (passes, 1)))
    assert d.stats()["frames"] == frames * passes
    assert d.stats()["loops"] == passes - 1
    assert d.stats()["blocks"] == len(blocks)


@settings(max_examples=60, deadline=None)
@given(frames=st.integers(1, 500), low=st.integers(1, 40), extra=st.integers(0, 60), seed=st.integers(0, 2**32 - 1))
def test_random_blocks_tile_the_source_and_repeat_with_the_seed(frames, low, extra, seed):
    x = RNG.standard_normal((frames, 3))
    d = ReplayDriver((x, 44100), block_size=random_block_sizes(low, low + extra), seed=seed, speed="max", loop=2)
    with d:
        first = _drain(d)
    with d:  # reopening restarts the stream and the generator
        second = _drain(d)
    sizes = [b.frames for b in first]
    assert sizes == [b.frames for b in second]
    assert all(low <= s <= low + extra for s in sizes[:-1])
    assert [b.start for b in first] == [0] + list(np.cumsum(sizes)[:-1])
    np.testing.assert_array_equal(np.concatenate([b.data for b in first]), np.tile(x, (2, 1)))


def test_sequence_and_callable_block_sizes():
    x = _noise(20, 1)
    with ReplayDriver((x, 100), block_size=[3, 5], speed="max") as d:
        assert [b.frames for b in _drain(d)] == [3, 5, 3, 5, 3, 1]
    with ReplayDriver((x, 100), block_size=lambda rng: 7, speed="max") as d:
        assert [b.frames for b in _drain(d)] == [7, 7, 6]
    with ReplayDriver((x, 100), block_size=lambda rng: 0, speed="max") as d:
        with pytest.raises(ReplayError, match="must return an int >= 1"):
            d.read()


def test_default_block_is_10_ms():
    with ReplayDriver((_noise(1000, 1), 5000), speed="max") as d:
        assert d.read().frames == 50
    with ReplayDriver((_noise(1000, 1), 44100), speed="max") as d:
        assert d.read().frames == 441


def test_blocks_are_copies():
    x = _noise(10, 1)
    with ReplayDriver((x, 100), block_size=10, speed="max", loop=True) as d:
        d.read().data[:] = 5.0
        np.testing.assert_array_equal(d.read().data, x)


@pytest.mark.parametrize("kwargs, match", [
    ({"source": np.zeros((10, 1))}, r"needs its rate: pass \(array, rate\)"),
    ({"source": (np.zeros((10, 1), np.int16), 5000)}, r"must be float"),
    ({"source": (np.zeros((0, 2)), 5000)}, r"no frames"),
    ({"source": (np.full((3, 1), np.nan), 5000)}, r"NaN"),
    ({"source": (np.zeros((10, 1)), -1)}, r"source rate"),
    ({"block_size": 0}, r"block_size"),
    ({"block_size": [4, 0]}, r"block_size sequence"),
    ({"block_size": 2.5}, r"block_size"),
    ({"speed": 0}, r"speed"),
    ({"speed": "fast"}, r"speed"),
    ({"loop": 0}, r"loop"),
    ({"rate": -5}, r"rate must be"),
    ({"channels": 3}, r"has 2 channels, 3 expected"),
    ({"channels": [0, 2]}, r"channels must be indices in \[0, 2\)"),
])
def test_driver_argument_refusals(kwargs, match):
    args = {"source": (np.zeros((10, 2)), 5000)} | kwargs
    with pytest.raises(ReplayError, match=match):
        ReplayDriver(**args)


def test_random_block_sizes_refuses_bad_ranges():
    with pytest.raises(ReplayError):
        random_block_sizes(5, 4)
    with pytest.raises(ReplayError):
        random_block_sizes(0, 4)


def test_channel_selection():
    x = _noise(30, 4)
    with ReplayDriver((x, 5000), channels=[3, 1], speed="max", block_size=30) as d:
        np.testing.assert_array_equal(d.read().data, x[:, [3, 1]])
    assert ReplayDriver((x, 5000), channels=4).channels == 4


# --- sources from files -----------------------------------------------------------------------

def test_wav_and_session_sources(tmp_path):
    x = _noise(200, 2)
    write_wav(tmp_path / "bare.wav", x, 5000, dtype="float64")
    d = ReplayDriver(tmp_path / "bare.wav", speed="max")
    assert (d.rate, d.channels, d.labels) == (5000.0, 2, ())
    with d:
        np.testing.assert_array_equal(np.concatenate([b.data for b in _drain(d)]), x)
    _save(tmp_path, name="sess", frames=5000, channels=2)
    for p in ("sess.wav", "sess.json"):
        d = ReplayDriver(tmp_path / p, speed="max")
        assert [lab.label for lab in d.labels] == ["felt", "sandpaper"]
    s = load_session(tmp_path / "sess")
    assert ReplayDriver(s).labels == s.labels


def test_missing_file_is_device_unavailable(tmp_path):
    with pytest.raises(DeviceUnavailable):
        ReplayDriver(tmp_path / "nope.wav")
    with pytest.raises(DeviceUnavailable):
        ReplayDriver(tmp_path / "nope.json")


def test_bad_sidecar_next_to_wav_is_refused(tmp_path):
    _save(tmp_path, name="sess")
    (tmp_path / "sess.json").write_text("{}")
    with pytest.raises(SessionError, match="missing"):
        ReplayDriver(tmp_path / "sess.wav")


def test_filled_ranges_mark_blocks(tmp_path):
    _save(tmp_path, name="f", frames=100, filled=[(10, 15), (98, 100)], labels=[])
    with ReplayDriver(tmp_path / "f.json", block_size=10, speed="max", loop=2) as d:
        blocks = _drain(d)
        assert d.stats()["filled"] == 14
    mask = np.concatenate([np.zeros(b.frames, bool) if b.filled is None else b.filled for b in blocks])
    expected = np.zeros(100, bool)
    expected[10:15] = expected[98:] = True
    np.testing.assert_array_equal(mask, np.tile(expected, 2))
    assert blocks[0].filled is None and blocks[1].n_filled == 5


# --- resampling --------------------------------------------------------------------------------

def _peak_hz(x, rate):
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return np.fft.rfftfreq(len(x), 1 / rate)[np.argmax(spectrum)]


@pytest.mark.parametrize("src_rate, rate, f", [(44100, 5000, 440.0), (5000, 44100, 440.0), (44100, 48000, 1000.0)])
def test_resampling_length_and_frequency(src_rate, rate, f):
    n = 2 * src_rate
    x = 0.5 * np.sin(2 * np.pi * f * np.arange(n) / src_rate)[:, None]
    notes = []
    d = ReplayDriver((x, src_rate), rate=rate, speed="max", on_notice=notes.append)
    up, down = d.up, d.down
    assert up * src_rate == down * rate  # exact ratio here
    assert d.rate == rate
    assert d.data.shape == (math.ceil(n * up / down), 1)
    assert len(notes) == 1 and d.notices == notes and f"to {rate} Hz" in notes[0]
    with d:
        y = np.concatenate([b.data for b in _drain(d)])
    np.testing.assert_array_equal(y, d.data)
    assert abs(_peak_hz(y[:, 0], d.rate) - f) <= 1.0  # bins are 0.5 Hz wide
    mid = y[len(y) // 4: 3 * len(y) // 4, 0]
    assert abs(np.sqrt(np.mean(mid**2)) - 0.5 / np.sqrt(2)) < 0.01  # amplitude kept


def test_resampling_notice_goes_to_stderr_by_default(capsys):
    ReplayDriver((_noise(100, 1), 44100), rate=5000)
    err = capsys.readouterr().err
    assert err.count("resampling") == 1 and "up=50 down=441" in err
    ReplayDriver((_noise(100, 1), 44100), rate=5000, on_notice=None)
    ReplayDriver((_noise(100, 1), 44100))  # same rate: nothing to say
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("rate, max_den, says", [(44101, 100, "not resampling"), (5001, 1000, "resampling")])
def test_inexact_ratio_is_reported_and_rate_is_the_effective_one(rate, max_den, says):
    notes = []
    d = ReplayDriver((_noise(1000, 1), 44100), rate=rate, max_denominator=max_den, on_notice=notes.append)
    assert d.rate != rate and abs(d.rate - rate) / rate < 1e-3
    assert d.rate == 44100 * d.up / d.down
    assert d.down <= max_den
    assert len(notes) == 1 and notes[0].startswith(f"replay: {says}")
    assert f"not a ratio with denominator <= {max_den}" in notes[0]


def test_resampled_filled_mask_is_never_lost():
    x = _noise(4410, 1)
    ranges = ((100, 101), (300, 310), (4400, 4410))
    s = Session(data=x, rate=44100, source="t", filled=ranges)
    d = ReplayDriver(s, rate=5000, speed="max", block_size=10**4, on_notice=None)
    with d:
        b = d.read()
    src_time = np.arange(b.frames) * 441 / 50  # output frame j sits at source frame j*441/50
    near = np.zeros(b.frames, bool)
    for lo, hi in ranges:
        inside = (src_time >= lo) & (src_time < hi)
        assert b.filled[inside].all()  # every frame measured inside a filled range stays marked
        near |= (src_time > lo - 441 / 50) & (src_time < hi)
        assert b.filled[(src_time > lo - 441 / 50) & (src_time < hi)].any()  # even ranges shorter than a frame
    assert not b.filled[~near].any()  # and the marks spread by less than one output frame
    assert d.stats()["filled"] == b.n_filled


# --- looping and labels -------------------------------------------------------------------------

def test_looping_is_continuous_across_the_seam():
    x = np.arange(10, dtype=float)[:, None]
    with ReplayDriver((x, 100), block_size=4, speed="max", loop=True) as d:
        blocks = [d.read() for _ in range(8)]
        assert d.stats()["loops"] == 3 and d.stats()["frames"] == 32
    assert [b.start for b in blocks] == list(range(0, 32, 4))
    np.testing.assert_array_equal(blocks[2].data[:, 0], [8, 9, 0, 1])  # straddles the seam
    np.testing.assert_array_equal(np.concatenate([b.data for b in blocks])[:, 0], np.arange(32) % 10)


def test_block_longer_than_the_source_loops_within_the_block():
    x = np.arange(3, dtype=float)[:, None]
    with ReplayDriver((x, 100), block_size=7, speed="max", loop=True) as d:
        np.testing.assert_array_equal(d.read().data[:, 0], [0, 1, 2, 0, 1, 2, 0])
        assert d.stats()["loops"] == 2


def test_labels_shift_with_each_pass():
    s = Session(data=np.zeros((100, 1)), rate=100, source="t",
                labels=(Label(0.0, 0.5, "a"), Label(0.5, 1.0, "b")))
    d = ReplayDriver(s, block_size=30, speed="max", loop=True)
    assert d.period == 1.0
    assert d.labels == s.labels
    with d:
        for _ in range(4):  # 120 frames: into the second pass
            d.read()
    assert d.labels == s.labels + (Label(1.0, 1.5, "a"), Label(1.5, 2.0, "b"))
    assert d.labels_between(2.6, 3.2) == (Label(2.5, 3.0, "b"), Label(3.0, 3.5, "a"))
    finite = ReplayDriver(s, loop=2)
    assert [lab.start for lab in finite.labels_between(0, 10)] == [0.0, 0.5, 1.0, 1.5]


# --- pacing ---------------------------------------------------------------------------------------

def test_release_time_is_the_schedule():
    assert release_time(50, 5000) == 0.01
    assert release_time(50, 5000, speed=2.0, t0=10.0) == 10.005
    assert release_time(10**9, 5000, speed=math.inf, t0=3.0) == 3.0
    # block k of n frames at t0 + (k+1)*n/rate/speed
    times = [release_time((k + 1) * 441, 44100, 4.0, 100.0) for k in range(1000)]
    np.testing.assert_allclose(np.diff(times), 441 / 44100 / 4.0)


def test_arrival_follows_the_schedule_and_never_precedes_it():
    d = ReplayDriver((_noise(100, 1), 1000), block_size=10, speed=20.0)  # 0.5 ms per block
    with d:
        blocks = []
        for _ in range(10):
            b = d.read()
            assert time.monotonic() >= b.arrival  # never released early
            blocks.append(b)
    for b in blocks:
        assert b.arrival == d.release_time(b.start + b.frames)
    assert all(np.diff([b.arrival for b in blocks]) > 0)


def test_speed_max_releases_at_once():
    with ReplayDriver((_noise(10**6, 1), 1000), block_size=1000, speed="max") as d:
        for _ in range(100):
            assert d.read(timeout=0) is not None  # a paced driver would need 100 s


def test_read_times_out_before_the_release_and_returns_the_same_block_later():
    with ReplayDriver((_noise(10**5, 1), 1000), block_size=10**4, speed=1.0) as d:  # due in 10 s
        assert d.read(timeout=0) is None
        assert d.read(timeout=0.01) is None
        d._t0 -= 100.0  # shift the clock's origin: the block is now overdue
        b = d.read(timeout=0)
    assert b.start == 0 and b.frames == 10**4


def test_close_interrupts_a_paced_wait():
    d = ReplayDriver((_noise(10**6, 1), 1000), block_size=10**5, speed=1.0)  # first block due in 100 s
    d.open()
    outcome = []

    def reader():
        try:
            outcome.append(d.read())
        except DriverClosed as e:
            outcome.append(e)

    t = threading.Thread(target=reader)
    t.start()
    time.sleep(0.05)
    d.close()
    t.join(timeout=30)  # generous: only checks the wait was interrupted, not how fast
    assert not t.is_alive()
    assert len(outcome) == 1 and isinstance(outcome[0], DriverClosed)


def _arrivals(driver, blocks):
    """Ends and arrival stamps of the first ``blocks`` blocks, and the ``t0`` they count from.
    The clock's origin is moved back a day so that every block is overdue: the stamps are the
    schedule's, and the test does not wait for it."""
    with driver:
        driver._t0 -= 86400.0
        got = [driver.read(timeout=0) for _ in range(blocks)]
    return np.array([b.start + b.frames for b in got]), np.array([b.arrival for b in got]), driver._t0


def test_a_device_clock_paces_blocks_on_the_device_crystal_from_its_start():
    """Without delivery delay, block k ending at frame e arrives at t0 + (start + e / (rate (1 +
    ppm 1e-6))) / speed: the crystal's error stretches the schedule, the start shifts it."""
    rate, speed, ppm, start = 1000.0, 2.0, 250.0, 0.02
    clock = DeviceClock(ppm=ppm, start=start)
    ends, arrivals, t0 = _arrivals(ReplayDriver((_noise(2000, 1), rate), block_size=10, speed=speed,
                                                device_clock=clock), 50)
    true_rate = rate * (1 + ppm / 1e6)
    # (to a few ulps of host time, which counts from a day back here)
    np.testing.assert_allclose(arrivals - t0, (start + ends / true_rate) / speed, rtol=0, atol=1e-9)
    # the line through the arrivals has the device's rate, not the nominal one
    slope = np.polyfit(ends, arrivals - t0, 1)[0]
    assert 1e6 * (1 / (slope * speed * rate) - 1) == pytest.approx(ppm, abs=1e-3)


def test_a_device_clock_delivers_late_by_random_delays_but_never_early_or_out_of_order():
    rate, speed, mean_delay = 1000.0, 2.0, 0.001     # a block every 5 ms, delays of 1 ms
    clock = DeviceClock(ppm=-80.0, mean_delay=mean_delay, seed=7)
    drv = ReplayDriver((_noise(20000, 1), rate), block_size=10, speed=speed, device_clock=clock)
    ends, arrivals, t0 = _arrivals(drv, 1000)
    scheduled = t0 + ends / (rate * (1 - 80e-6)) / speed
    late = arrivals - scheduled
    assert late.min() >= 0.0                          # never before the device sampled it
    assert np.all(np.diff(arrivals) >= 0)             # in order, as USB and audio servers deliver
    # Where a block was not held back behind its predecessor, its lateness is its own delay:
    # exponential with the given mean (1000 draws, fixed seed: the mean within 10 %).
    own = late[1:][np.diff(arrivals) > 0]
    assert len(own) > 950
    assert np.mean(own) == pytest.approx(mean_delay, rel=0.1)
    # the same seed gives the same deliveries at every open()
    again = _arrivals(drv, 1000)
    np.testing.assert_allclose(again[1] - again[2], arrivals - t0, rtol=0, atol=1e-9)


def test_a_device_clock_has_no_effect_at_speed_max():
    drv = ReplayDriver((_noise(10**6, 1), 1000), block_size=1000, speed="max",
                       device_clock=DeviceClock(ppm=500, start=100.0, mean_delay=1.0, seed=0))
    with drv:
        for _ in range(100):
            assert drv.read(timeout=0) is not None


@pytest.mark.parametrize("kwargs, match", [
    ({"ppm": 1e4}, "ppm out of range"), ({"ppm": math.nan}, "ppm out of range"),
    ({"start": -0.1}, "start out of range"), ({"mean_delay": -1e-3}, "mean_delay out of range"),
    ({"mean_delay": True}, "mean_delay out of range"), ({"start": "1"}, "start out of range"),
])
def test_device_clock_refusals_name_the_field(kwargs, match):
    with pytest.raises(ReplayError, match=match):
        DeviceClock(**kwargs)


def test_device_clock_must_be_a_device_clock():
    with pytest.raises(ReplayError, match="device_clock must be a DeviceClock"):
        ReplayDriver((_noise(10, 1), 1000), device_clock={"ppm": 40})


def test_session_marks_come_back_in_the_blocks_at_any_rate_and_on_every_loop(tmp_path):
    """A session's restart and overrun marks reach the node as the blocks' ``restarts`` and
    ``overruns``: each once per pass, at its frame (at the frame at or after its time when resampled)."""
    x = np.random.default_rng(0).uniform(-0.5, 0.5, (1000, 1))
    save_session(tmp_path / "m", x, 5000, "test", marks=[(700, "overrun"), (250, "restart")])
    assert load_session(tmp_path / "m").marks == ((250, "restart"), (700, "overrun"))
    for rate, loop, want in ((None, 2, {"restart": [250, 1250], "overrun": [700, 1700]}),
                             (10000.0, False, {"restart": [500], "overrun": [1400]}),
                             (3000.0, False, {"restart": [150], "overrun": [420]})):
        drv = ReplayDriver(tmp_path / "m.json", rate=rate, block_size=97, speed="max", loop=loop, on_notice=None)
        got = {"restart": [], "overrun": []}
        with drv:
            while True:
                try:
                    b = drv.read()
                except DriverClosed:
                    break
                got["restart"] += [b.start + i for i in b.restarts]
                got["overrun"] += [b.start + i for i in b.overruns]
        assert got == want, (rate, loop)


def test_a_wav_header_rate_or_channels_beyond_any_sensor_is_refused_not_a_struct_error(tmp_path):
    """Issue 35, items 14 and 15: a header declaring 4e9 Hz, and 70000 channels to write, ended in
    struct.error tracebacks (a rate past 4.29e9 bytes a second, a 16-bit channel field)."""
    from supramodal.errors import InputError
    from supramodal.replay.wavio import MAX_WAV_RATE, wav_info

    (tmp_path / "fast.wav").write_bytes(_riff(1, 1, 4_000_000_000, 8, b"\x80" * 10))
    with pytest.raises(ReplayError, match=rf"fast.wav.*4000000000 Hz, beyond the {MAX_WAV_RATE} Hz"):
        wav_info(tmp_path / "fast.wav")
    with pytest.raises(InputError, match="70000 channels; a WAV holds at most 65535"):
        write_wav(tmp_path / "wide.wav", np.zeros((2, 70000)), 5000)
    with pytest.raises(InputError, match="4000000000 Hz is beyond"):
        write_wav(tmp_path / "fast2.wav", np.zeros((2, 1)), 4_000_000_000)
    assert not list(tmp_path.glob("wide*")) and not list(tmp_path.glob("fast2*"))
    (tmp_path / "ok.wav").write_bytes(_riff(1, 1, MAX_WAV_RATE, 8, b"\x80" * 10))
    assert wav_info(tmp_path / "ok.wav").rate == MAX_WAV_RATE
