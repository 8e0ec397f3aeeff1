"""XDF recordings replayed with their recorded timing: files written by tests/xdf_writer.py (from
the XDF specification) read back by pyxdf, and two streams of one file (5 kHz and 44.1 kHz, each
on its own clock, 37 ms apart) put on the node's common time to within one sample."""

import numpy as np
import pytest

from xdf_writer import XdfStream, write_xdf

pyxdf = pytest.importorskip("pyxdf", reason="the XDF tests need pyxdf (the lsl extra; CI installs it)")

from supramodal.node.scene.build import build_node  # noqa: E402
from supramodal.node.scene.schema import SceneError, scene_from_dict  # noqa: E402
from supramodal.node.runtime.sinks import ListSink  # noqa: E402
from supramodal.replay.errors import ReplayError  # noqa: E402
from supramodal.replay.xdf import xdf_session  # noqa: E402

T0 = 5000.0                     # the sender's clock at the first whisker sample
SECONDS = 3.0


def _two_streams(seconds=SECONDS):
    """Whiskers at 5 kHz (+40 ppm), a microphone at 44.1 kHz (-70 ppm, 37.1 ms later, and 10 ms
    behind on the recorder's clock by its clock offsets), and a marker stream."""
    rng = np.random.default_rng(5)
    n_w, n_m = int(seconds * 5000), int(seconds * 44100)
    whiskers = XdfStream("whiskers", "Whiskers", 5000.0, 0.1 * rng.standard_normal((n_w, 20)),
                         T0 + np.arange(n_w) / (5000.0 * (1 + 40e-6)), source_id="board-1",
                         offsets=[(T0 + k, 0.0) for k in range(4)])
    mic = XdfStream("mic", "Audio", 44100.0, 0.1 * rng.standard_normal((n_m, 1)),
                    T0 + 0.0371 + np.arange(n_m) / (44100.0 * (1 - 70e-6)), source_id="card-1",
                    offsets=[(T0 + k, 0.010) for k in range(4)], chunk=441)
    return whiskers, mic


def test_a_file_written_to_the_specification_reads_back_with_pyxdf(tmp_path):
    whiskers, mic = _two_streams(1.0)
    write_xdf(tmp_path / "r.xdf", [whiskers, mic])
    streams, header = pyxdf.load_xdf(str(tmp_path / "r.xdf"), dejitter_timestamps=False)
    by_name = {s["info"]["name"][0]: s for s in streams}
    for s, shift in ((whiskers, 0.0), (mic, 0.010)):
        got = by_name[s.name]
        np.testing.assert_array_equal(got["time_series"], s.samples.astype(np.float32))
        np.testing.assert_allclose(got["time_stamps"], s.stamps + shift, rtol=0, atol=1e-9)
        assert float(got["info"]["nominal_srate"][0]) == s.rate


def test_one_stream_becomes_a_session_with_its_recorded_times(tmp_path):
    whiskers, mic = _two_streams(1.0)
    write_xdf(tmp_path / "r.xdf", [whiskers, mic])
    session = xdf_session(tmp_path / "r.xdf", name="mic")
    assert session.rate == 44100 and session.data.shape == (44100, 1)
    np.testing.assert_array_equal(session.data, mic.samples.astype(np.float32))
    ends, times, rate = session.arrivals
    # The rate the timestamps show (the card's -70 ppm), which the node's clock model starts from.
    assert rate == pytest.approx(44100.0 * (1 - 70e-6), rel=1e-9)
    assert ends[-1] == 44100 and np.all(np.diff(ends) == 441)
    # Seconds from the file's earliest sample (the whiskers'), the clock offset applied.
    np.testing.assert_allclose(times, mic.stamps[ends - 1] + 0.010 - T0, rtol=0, atol=1e-9)


def test_the_stream_asked_for_must_be_there_and_be_a_signal(tmp_path):
    whiskers, mic = _two_streams(0.2)
    markers = XdfStream("events", "Markers", 0.0, np.zeros((3, 1)), T0 + np.arange(3.0))
    write_xdf(tmp_path / "r.xdf", [whiskers, mic, markers])
    with pytest.raises(ReplayError, match=r"no stream with name='eeg'; the file has name='whiskers' .*name='mic'"):
        xdf_session(tmp_path / "r.xdf", name="eeg")
    with pytest.raises(ReplayError, match="not a regularly sampled numeric stream"):
        xdf_session(tmp_path / "r.xdf", stream_type="Markers")
    (tmp_path / "bad.xdf").write_bytes(b"XDF:" + b"\x01\x05\x02\x00junk")
    with pytest.raises(ReplayError, match="not a readable XDF file"):
        xdf_session(tmp_path / "bad.xdf", name="whiskers")


def _graph(path, speed="max", **board):
    source = {"type": "xdf", "path": str(path), "speed": speed}
    return scene_from_dict({
        "source": [{"name": "board", **source, "stream": "whiskers", **board},
                   {"name": "card", **source, "source_id": "card-1"}],
        "stream": [{"name": "whiskers", "source": "board", "mapping": "per-channel", "bank": {"kind": "whisker"},
                    "features": {"names": ["Af"]}},
                   {"name": "mic", "source": "card", "mapping": "mono", "bank": {"kind": "cochlea"},
                    "features": {"names": ["Af"]}}],
        "sink": [{"type": "text", "path": "-"}]})


@pytest.mark.parametrize("speed", ["max", 6.0])
def test_two_streams_of_one_file_replay_aligned_to_within_one_sample(tmp_path, speed):
    """Every window of both streams starts, on the node's common time, within one sample of its
    first sample's recorded time (from the file's first sample, clock offsets applied)."""
    whiskers, mic = _two_streams()
    write_xdf(tmp_path / "r.xdf", [whiskers, mic])
    sink = ListSink()
    build_node(_graph(tmp_path / "r.xdf", speed), sinks_override=[sink]).run()
    seen = {"whiskers": 0, "mic": 0}
    for e in sink.windows:
        s, shift, W = (whiskers, 0.0, 500) if e.stream == "whiskers" else (mic, 0.010, 4410)
        truth = s.stamps[e.window * W] + shift - T0
        assert abs(e.start - truth) < 1.0 / s.rate, (e.stream, e.window, e.start - truth)
        seen[e.stream] += 1
    assert seen == {"whiskers": 30, "mic": 30}


def test_an_xdf_source_must_name_its_stream(tmp_path):
    whiskers, mic = _two_streams(0.2)
    write_xdf(tmp_path / "r.xdf", [whiskers, mic])
    # Refused when the scene is read, before anything is built.
    with pytest.raises(SceneError, match=r"type \"xdf\" needs the recorded stream's name \(stream = \.\.\.\)"):
        scene_from_dict({"driver": {"type": "xdf", "path": str(tmp_path / "r.xdf")}, "bank": {"kind": "whisker"}})
    scene = scene_from_dict({"driver": {"type": "xdf", "path": str(tmp_path / "r.xdf"), "stream": "nope"},
                             "bank": {"kind": "whisker"}})
    with pytest.raises(SceneError, match=r"\[driver\] .*no stream with name='nope'"):
        build_node(scene)


def test_samples_missing_from_a_recording_are_put_back_as_filled_zeros_and_time_stays_aligned(tmp_path):
    """The whisker stream lacks 0.3 s (samples 5000-6499: a sender that dropped out, or a
    signal outlet's hole): the replay fills exactly those samples (counted, their windows flagged
    gap), and every window after them is still within one sample of its recorded time."""
    whiskers, mic = _two_streams()
    full_stamps = whiskers.stamps
    keep = np.r_[0:5000, 6500:len(full_stamps)]
    holed = XdfStream("whiskers", "Whiskers", 5000.0, whiskers.samples[keep], full_stamps[keep],
                      source_id="board-1", offsets=whiskers.offsets)
    write_xdf(tmp_path / "r.xdf", [holed, mic])
    session = xdf_session(tmp_path / "r.xdf", name="whiskers")
    assert session.filled == ((5000, 6500),) and session.data.shape[0] == len(full_stamps)
    np.testing.assert_array_equal(session.data[5000:6500], 0.0)
    sink = ListSink()
    summary = build_node(_graph(tmp_path / "r.xdf"), sinks_override=[sink]).run()
    assert summary["streams"]["whiskers"]["frames"]["filled"] == 1500
    mine = [e for e in sink.windows if e.stream == "whiskers"]
    assert len(mine) == 30
    assert {e.window for e in mine if "gap" in e.flags} == set(range(10, 13))
    for e in mine:
        assert abs(e.start - (full_stamps[e.window * 500] - T0)) < 1.0 / 5000, (e.window, e.start)


def test_a_gap_longer_than_the_longest_filled_is_a_restart():
    from supramodal.replay.xdf import fill_gaps

    rate = 100.0
    stamps = np.r_[np.arange(10) / rate, 0.5 + np.arange(5) / rate, 30.0 + np.arange(3) / rate]
    data = np.arange(18.0)[:, None]
    out, times, filled, marks = fill_gaps(data, stamps, rate, tolerance=0.05, max_gap=10.0)
    # 0.09 -> 0.5: 40 samples missing (0.10 ... 0.49), filled; 0.54 -> 30.0: a restart, not filled.
    assert filled == ((10, 50),) and marks == ((55, "restart"),)
    np.testing.assert_array_equal(out[:, 0], np.r_[np.arange(10.0), np.zeros(40), np.arange(10.0, 18.0)])
    np.testing.assert_allclose(times[10:50], np.arange(10, 50) / rate, atol=1e-12)
    # A step back beyond the tolerance: a restart there, nothing filled (as the live inlet judges it).
    back = np.r_[np.arange(10) / rate, -1.0 + np.arange(5) / rate]
    assert fill_gaps(data[:15], back, rate, tolerance=0.05)[2:] == ((), ((10, "restart"),))
    # A step beyond the tolerance that rounds to no whole sample (5 Hz) fills nothing.
    slow = np.r_[0.0, 0.2, 0.46, 0.66]
    assert fill_gaps(data[:4], slow, 5.0, tolerance=0.05)[2:] == ((), ())
    # Jitter within the tolerance is not a gap.
    same = fill_gaps(data[:10], stamps[:10] + 0.004 * (np.arange(10) % 2), rate, tolerance=0.05)
    assert same[2] == () and same[3] == () and np.array_equal(same[0], data[:10])


def test_two_sources_of_one_file_read_it_once(tmp_path, monkeypatch):
    import supramodal.replay.xdf as xdf

    whiskers, mic = _two_streams(0.5)
    write_xdf(tmp_path / "r.xdf", [whiskers, mic])
    reads = []
    load = xdf.load_xdf_streams
    monkeypatch.setattr(xdf, "load_xdf_streams", lambda path: reads.append(path) or load(path))
    graph = build_node(_graph(tmp_path / "r.xdf"), sinks_override=[ListSink()])
    assert len(reads) == 1 and [s.driver.rate for s in graph.sources] == [5000.0, 44100.0]


def test_a_marker_stream_of_the_file_gives_the_truth_labels(tmp_path):
    """Markers "T1" at the first whisker sample, "T2" 1.5 s later, an empty one at 2.5 s: each
    whisker window's truth is the marker before its middle sample, none after the empty one;
    the marker stream must be one of strings."""
    whiskers, mic = _two_streams()
    markers = XdfStream("texture", "Markers", 0.0, [["T1"], ["T2"], [""]], T0 + np.array([0.0, 1.5, 2.5]),
                        fmt="string", chunk=1)
    write_xdf(tmp_path / "r.xdf", [whiskers, mic, markers])
    streams, _ = pyxdf.load_xdf(str(tmp_path / "r.xdf"), dejitter_timestamps=False)
    assert [s["time_series"] for s in streams if s["info"]["name"][0] == "texture"] == [[["T1"], ["T2"], [""]]]
    sink = ListSink()
    build_node(_graph(tmp_path / "r.xdf", labels="texture"), sinks_override=[sink]).run()
    truth = {e.window: e.truth for e in sink.windows if e.stream == "whiskers"}
    stamps = whiskers.stamps - T0
    for w, t in truth.items():
        middle = stamps[int((w + 0.5) * 500)]
        assert t == ("T1" if middle < 1.5 else "T2" if middle < 2.5 else None), (w, t)
    assert {e.truth for e in sink.windows if e.stream == "mic"} == {None}
    with pytest.raises(ReplayError, match=r"labels: stream name='whiskers' .* is not a marker stream"):
        xdf_session(tmp_path / "r.xdf", name="mic", labels="whiskers")
    with pytest.raises(ReplayError, match=r"labels: no stream\(s\) named 'events'"):
        xdf_session(tmp_path / "r.xdf", name="mic", labels="events")


@pytest.mark.parametrize("marker, shown", [("felt\x1b[31mRED\x1b[0m", r"'felt\\x1b\[31mRED\\x1b\[0m'"),
                                           ("x\ny\rz", r"'x\\ny\\rz'"), ("../x", r"'\.\./x'"),
                                           ("a" * 70, "'a{70}'")])
def test_a_marker_that_is_no_name_is_refused_not_made_a_label(tmp_path, marker, shown):
    """Issue 35, item 5: a marker is data from a file; a terminal escape, a line break, a path or a name of
    70 characters would become a model's class, a file name's part and a line printed raw: refused, named
    (escaped), with the fix."""
    whiskers, mic = _two_streams()
    markers = XdfStream("texture", "Markers", 0.0, [["T1"], [marker]], T0 + np.array([0.0, 1.5]), fmt="string",
                        chunk=1)
    write_xdf(tmp_path / "r.xdf", [whiskers, mic, markers])
    with pytest.raises(ReplayError, match=rf"r.xdf: labels 'texture': marker 1 says {shown}, which is no label "
                                          r"\(a name: .*supramodal label"):
        xdf_session(tmp_path / "r.xdf", name="whiskers", labels="texture")


@pytest.mark.parametrize("seed", range(5))
def test_a_gap_is_sized_on_the_sample_clock_not_from_its_two_jittered_edge_stamps(seed):
    """Issue 26 item 11: a 2,500-sample hole whose two edge stamps jitter apart (0.2 ms: one sample
    at 5 kHz) was filled with 2,501 zeros, and the windows after it were late. Sized on the
    sample clock each side of it (the median of 1 s of stamps), the fill is the hole."""
    from supramodal.replay.xdf import fill_gaps

    rate = 5000.0
    rng = np.random.default_rng(seed)
    index = np.r_[0:5000, 7500:15000]
    stamps = 100.0 + index / rate + rng.uniform(-1e-4, 1e-4, index.size)   # LSL's push jitter, not dejittered
    stamps[4999] = 100.0 + 4999 / rate - 1e-4                               # the edges as far apart as it goes
    stamps[5000] = 100.0 + 7500 / rate + 1e-4
    data = np.ones((index.size, 1))
    out, times, filled, marks = fill_gaps(data, stamps, rate, tolerance=0.05, max_gap=10.0)
    assert filled == ((5000, 7500),) and marks == () and out.shape[0] == 15000
    assert np.all(np.diff(times) > 0)


@pytest.mark.parametrize("declared", ["1000000000", "200000000", "65536", "-3", "1e9"])
def test_a_header_declaring_channels_no_sensor_has_is_refused_before_anything_is_allocated(tmp_path, declared):
    """Issue 35, item 7: a 306-byte file whose header said 1e9 channels took 12.7 GB before its refusal
    (2e8: 4 GB, then a struct.error). The headers are read first: refused at once, in bounded memory."""
    import resource
    import struct

    from xdf_writer import _chunk

    xml = (f'<?xml version="1.0"?><info><name>w</name><type>EEG</type><channel_count>{declared}</channel_count>'
           '<nominal_srate>5000.0</nominal_srate><channel_format>float32</channel_format></info>')
    body = bytearray(struct.pack("<I", 1) + bytes([1, 1]) + struct.pack("<Bd", 8, 1.0) + b"\0\0\0\0")
    data = (b"XDF:" + _chunk(1, b'<?xml version="1.0"?><info><version>1.0</version></info>')
            + _chunk(2, struct.pack("<I", 1) + xml.encode()) + _chunk(3, bytes(body)))
    (tmp_path / "big.xdf").write_bytes(data)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ReplayError, match=rf"big.xdf: a stream header declares channel_count '{declared}'"):
        xdf_session(tmp_path / "big.xdf", name="w")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000      # KB: no gigabytes


@pytest.mark.parametrize("nominal, stamps_rate, words", [
    (1.0, 5000.0, r"timestamps show 5000 samples a second \(over the whole stream\), where its nominal_srate says 1 Hz"),
    (50000.0, 5000.0, r"timestamps show 5000 samples a second \(by its median step\), where its nominal_srate says "
                      r"50000 Hz"),
])
def test_a_nominal_srate_that_the_stamps_contradict_is_refused_naming_both_rates(tmp_path, nominal, stamps_rate, words):
    """Issue 35, item 21: 1 Hz with 5 kHz stamps became 1999 restart marks; 50 kHz with 5 kHz stamps passed,
    nine zeros filled between every two samples."""
    n = 2000
    x = XdfStream("w", "Whiskers", nominal, 0.1 * np.random.default_rng(1).standard_normal((n, 1)),
                  T0 + np.arange(n) / stamps_rate)
    write_xdf(tmp_path / "r.xdf", [x])
    with pytest.raises(ReplayError, match=words):
        xdf_session(tmp_path / "r.xdf", name="w")


def test_a_stream_whose_stamps_leave_more_room_than_samples_is_refused_before_anything_is_filled(tmp_path):
    """Issue 35, item 8: 2000 samples stamped 10 s apart at nominal 5 kHz (40 KB) took 61 s and 3.2 GB before a
    sidecar limit refused them. Refused from the stamps, in well under a second, saying how much would be made
    up; a stream with a short pause still fills it."""
    import time

    bursts = 667                                        # 3 samples at 5 kHz every 9.99 s: the steps' median is
    stamps = (np.arange(bursts)[:, None] * 9.99 + np.array([0.0, 0.0002, 0.0004])).ravel()   # the period
    sparse = XdfStream("w", "Whiskers", 5000.0, np.zeros((stamps.size, 1)), T0 + stamps)
    write_xdf(tmp_path / "r.xdf", [sparse])
    t = time.monotonic()
    with pytest.raises(ReplayError, match=r"room for \d+ missing frames at nominal_srate 5000 Hz, more than the "
                                          r"2001 it holds: .*more made up than recorded"):
        xdf_session(tmp_path / "r.xdf", name="w")
    assert time.monotonic() - t < 5.0
    stamps = T0 + np.arange(10000) / 5000.0
    stamps[5000:] += 0.5                                # one pause of half a second: filled and flagged
    write_xdf(tmp_path / "p.xdf", [XdfStream("w", "Whiskers", 5000.0, np.ones((10000, 1)), stamps)])
    session = xdf_session(tmp_path / "p.xdf", name="w")
    assert abs(session.frames - 12500) <= 2 and len(session.filled) == 1
