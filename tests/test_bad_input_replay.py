"""Bad input to replay, third pass (issue 25, items 4, 12, 13 and 15): recorded graph sessions whose
block times do not fit their frames, a missing sidecar, and XDF files with a rate, a channel count
or bytes nobody bounded. Each is refused at load with one line naming the file, the key, the bound
and the fix (exit 2, nothing written); what a real device or file could need still runs."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from xdf_writer import XdfStream, write_xdf

from supramodal.node.cli import main
from supramodal.replay import SessionError, load_session, save_session
from supramodal.replay.errors import MissingSidecarError, ReplayError
from supramodal.replay.session import ARRIVALS_CLOCK_ERROR, ARRIVALS_LATENCY

RATE = 5000                     # the recorded board's rate, Hz
SECONDS = 8.0                   # the recordings: 8 s of stream
BLOCK = 50                      # frames per recorded block (10 ms)


def _lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


def _run(scene, capsys) -> tuple[int, str, str]:
    """``supramodal run SCENE --quiet --speed max``: the scene's own sinks (a JSON-lines file)."""
    rc = main(["run", str(scene), "--quiet", "--speed", "max"])
    out, err = capsys.readouterr()
    return rc, out, err


def _run_process(scene) -> tuple[int, str, str]:
    """The same in a process of its own: what a user sees on the terminal (pyxdf's log goes to the
    real stderr there, not to pytest's log capture)."""
    proc = subprocess.run([sys.executable, "-m", "supramodal", "run", str(scene), "--quiet", "--speed", "max"],
                          capture_output=True, text=True, cwd=scene.parent, timeout=120)
    return proc.returncode, proc.stdout, proc.stderr


def _written(folder) -> list[dict]:
    return [json.loads(line) for line in (folder / "out.jsonl").read_text().splitlines()]


# -- a recorded graph session ------------------------------------------------------------------------

def _honest_times(frames: np.ndarray, rng=None) -> np.ndarray:
    """Block times as a live board gives them: 37 ms after the graph's start, a crystal 80 ppm
    fast, each block late by up to 20 ms (never out of order)."""
    rng = np.random.default_rng(3) if rng is None else rng
    t = 0.037 + frames / (RATE * (1 + 80e-6)) + rng.exponential(0.004, frames.size).clip(0, 0.02)
    return np.maximum.accumulate(t)


def _recorded(folder, arrivals=None, marks=()):
    """A recorded board session ``rec.board`` (8 s, 20 channels, its blocks' times) and the scene
    that replays it at its recorded times with a JSON-lines sink; returns the scene's path."""
    rng = np.random.default_rng(0)
    n = int(SECONDS * RATE)
    frames = np.arange(BLOCK, n + 1, BLOCK)
    if arrivals is None:
        arrivals = (frames, _honest_times(frames), float(RATE))
    save_session(folder / "rec.board", 0.01 * rng.standard_normal((n, 20)), RATE, "test", marks=marks,
                 arrivals=arrivals)
    scene = folder / "rec.toml"
    scene.write_text('[[source]]\nname = "board"\ntype = "replay"\npath = "rec.board.wav"\ntiming = "recorded"\n'
                     'speed = "max"\n\n[[stream]]\nname = "whiskers"\nsource = "board"\n[stream.bank]\n'
                     'kind = "whisker"\n\n[[sink]]\ntype = "jsonl"\npath = "out.jsonl"\n')
    return scene


def _edit_arrivals(folder, change) -> None:
    """Change the sidecar's arrivals by hand, as a user (or a damaged copy) would."""
    js = folder / "rec.board.json"
    meta = json.loads(js.read_text())
    change(meta["arrivals"])
    js.write_text(json.dumps(meta))


def _jump(arrivals):                    # the issue: 1e9 s added to every time after block 100
    arrivals["seconds"][100:] = [t + 1e9 for t in arrivals["seconds"][100:]]


def _still(arrivals):                   # the issue: every time 0
    arrivals["seconds"] = [0.0] * len(arrivals["seconds"])


def _rate(arrivals):                    # the issue: a clock rate of 1e300 Hz
    arrivals["rate"] = 1e300


def test_a_recorded_session_replays_in_step_when_its_times_fit(tmp_path, capsys):
    """The control: honest times (80 ppm, up to 20 ms late) load and replay, every window."""
    scene = _recorded(tmp_path)
    rc, out, err = _run(scene, capsys)
    assert rc == 0, err
    assert sum("window" in e for e in _written(tmp_path)) == 80


@pytest.mark.parametrize("change, key, said", [
    (_jump, r"arrivals.seconds[100]: ", "1e+09 s after arrivals.seconds["),
    (_still, "arrivals.seconds[", "0 s after arrivals.seconds[0]"),
    (_rate, "arrivals.seconds[", "s at arrivals.rate 1e+300 Hz: block times must follow the frames"),
], ids=["jump", "still", "rate"])
def test_block_times_that_do_not_fit_the_frames_are_refused_at_load(tmp_path, capsys, change, key, said):
    """Issue 25 item 12: each ran with exit 0 and paired the wrong windows; now exit 2 before
    anything runs, one line naming the sidecar, the block, the tolerance and the fix."""
    scene = _recorded(tmp_path)
    _edit_arrivals(tmp_path, change)
    rc, out, err = _run(scene, capsys)
    assert rc == 2 and out == ""
    (line,) = _lines(err)
    assert str(tmp_path / "rec.board.json") in line and key in line and said in line
    assert f"within {ARRIVALS_CLOCK_ERROR:.0%}" in line and f"plus {ARRIVALS_LATENCY:g} s of delivery delay" in line
    assert "delete the sidecar's 'arrivals'" in line
    assert not (tmp_path / "out.jsonl").exists()


def test_what_a_real_device_does_to_its_block_times_is_accepted(tmp_path):
    """Within the tolerance: a resonator 0.8 % slow, a host that stalled 3 s and then caught up,
    and a board restart after which the time jumps 100 s (at its mark, where it may)."""
    n = int(SECONDS * RATE)
    frames = np.arange(BLOCK, n + 1, BLOCK)
    t = frames / (RATE * (1 - 0.008))
    stalled = (frames > 10000) & (frames <= 15000)
    t[stalled] = t[frames <= 15000][-1] + 3.0                      # 100 blocks delivered 3 s late at once
    t = np.maximum.accumulate(t)
    t[frames > 20000] += 100.0                                      # the board restarted at frame 20000
    _recorded(tmp_path, (frames, t, float(RATE)), marks=[(20000, "restart")])
    s = load_session(tmp_path / "rec.board")
    assert s.arrivals[0].size == frames.size and s.marks == ((20000, "restart"),)
    # the same jump without the mark is refused, naming the first block after it
    _recorded(tmp_path, (frames, t, float(RATE)))
    with pytest.raises(SessionError, match=r"arrivals.seconds\[400\]: .* after arrivals.seconds\[\d+\]"):
        load_session(tmp_path / "rec.board")


def test_a_live_recording_is_saved_even_when_its_times_would_be_refused(tmp_path):
    """The recorder must never lose a recording at the end: save_session checks the form of the
    block times only; the load says what is wrong."""
    frames = np.arange(BLOCK, 40001, BLOCK)
    save_session(tmp_path / "s", np.zeros((40000, 1)), RATE, "t", arrivals=(frames, np.zeros(frames.size), 5000.0))
    assert (tmp_path / "s.json").exists()
    with pytest.raises(SessionError, match=r"arrivals.seconds\[\d+\]: 0.0 s is 0 s after"):
        load_session(tmp_path / "s")


# -- a missing sidecar ---------------------------------------------------------------------------------

def test_a_missing_sidecar_is_named_with_how_to_get_it_back(tmp_path):
    """Issue 25 item 13, where the session is loaded: the error names the missing file, what it
    held and how to get it back (it is the package's, and still a FileNotFoundError)."""
    _recorded(tmp_path)
    (tmp_path / "rec.board.json").unlink()
    with pytest.raises(MissingSidecarError) as caught:
        load_session(tmp_path / "rec.board.wav")
    message = str(caught.value)
    assert isinstance(caught.value, (FileNotFoundError, ReplayError))
    assert message.startswith(f"{tmp_path / 'rec.board.json'}: no sidecar: the session's sidecar file is missing")
    assert "copy it back from where the recording was made" in message and "'arrivals'" in message


def test_a_recorded_replay_whose_sidecar_is_gone_says_so(tmp_path, capsys):
    """Issue 25 item 13 through the command line: `rm rec.board.json` must not be answered with
    "use timing = 'nominal'" (that runs unsynchronised and unlabelled) but with the missing file."""
    scene = _recorded(tmp_path)
    (tmp_path / "rec.board.json").unlink()
    rc, out, err = _run(scene, capsys)
    assert rc == 2 and out == ""
    (line,) = _lines(err)
    assert f"{tmp_path / 'rec.board.json'}: no sidecar: the session's sidecar file is missing" in line
    assert "use timing = 'nominal'" not in line
    assert not (tmp_path / "out.jsonl").exists()


# -- XDF files -----------------------------------------------------------------------------------------

@pytest.fixture
def xdf():
    pytest.importorskip("pyxdf", reason="the XDF tests need pyxdf (the lsl extra; CI installs it)")


def _xdf_scene(folder, streams, *, raw: bytes | None = None) -> str:
    """``r.xdf`` (the streams, or ``raw`` bytes) and a scene replaying its stream "s" into a
    JSON-lines sink; returns the scene's path."""
    if raw is None:
        write_xdf(folder / "r.xdf", streams)
    else:
        (folder / "r.xdf").write_bytes(raw)
    (folder / "x.toml").write_text('[driver]\ntype = "xdf"\npath = "r.xdf"\nstream = "s"\n[bank]\nkind = "whisker"\n\n'
                                   '[[sink]]\ntype = "jsonl"\npath = "out.jsonl"\n')
    return folder / "x.toml"


def _stream(rate, stamps, channels=1, **kw) -> XdfStream:
    stamps = np.asarray(stamps, dtype=float)
    return XdfStream("s", "Whiskers", rate, 0.01 * np.ones((stamps.size, channels)), stamps, **kw)


def test_a_gigahertz_stream_is_refused_naming_its_rate_and_the_bound(tmp_path, capsys, xdf):
    """Issue 25 item 4: nominal_srate 1e9 with two samples 5 s apart was a MemoryError traceback
    (745 GiB at 20 channels); now one line naming the field, the bound and the fix."""
    scene = _xdf_scene(tmp_path, [_stream(1e9, [100.0, 105.0], channels=20)])
    rc, out, err = _run(scene, capsys)
    assert rc == 2 and out == ""
    (line,) = _lines(err)
    assert "nominal_srate 1e+09 Hz is out of range: the node replays streams of 1 to 1000000 Hz" in line
    assert "correct the stream's nominal_srate" in line and "MemoryError" not in line
    assert not (tmp_path / "out.jsonl").exists()


def test_gaps_that_would_fill_beyond_the_bound_are_refused_before_filling(tmp_path, xdf):
    """A stream at the highest rate with four gaps just short of the longest filled one (9 s each
    at 1 MHz, 20 channels: 720 M samples, 5.4 GiB) is refused before a sample is allocated."""
    from supramodal.replay.xdf import MAX_XDF_SAMPLES, xdf_session

    stamps = np.concatenate([100.0 + 9.0 * k + np.arange(10) / 1e6 for k in range(5)])
    write_xdf(tmp_path / "r.xdf", [_stream(1e6, stamps, channels=20)])
    with pytest.raises(ReplayError, match=rf"filled at nominal_srate 1e\+06 Hz it would be \d+ frames x 20 channel\(s\), "
                                          rf"more than the {MAX_XDF_SAMPLES} samples"):
        xdf_session(tmp_path / "r.xdf", name="s")


@pytest.mark.parametrize("case, needle", [
    ("garbage", "not a readable XDF file: no stream could be read (pyxdf: Error reading chunk length"),
    ("no channels", "channel_count is 0 in the file: the stream has no channel to replay"),
    ("1 GHz, no gap", "nominal_srate 1e+09 Hz is out of range"),
])
def test_a_bad_xdf_file_is_one_line_with_nothing_of_pyxdf_before_it(tmp_path, xdf, case, needle):
    """Issue 25 item 15: pyxdf's traceback and log lines came before the error; a stream of no
    channels read "an in-memory source must have shape"; 1 GHz read "raise max_denominator"."""
    if case == "garbage":
        scene = _xdf_scene(tmp_path, None, raw=b"XDF:" + b"\xff\x13garbage after the magic" * 10)
    elif case == "no channels":
        scene = _xdf_scene(tmp_path, [XdfStream("s", "Whiskers", 1000.0, np.zeros((100, 0)), 100 + np.arange(100) / 1e3)])
    else:
        scene = _xdf_scene(tmp_path, [_stream(1e9, 100.0 + np.arange(100) / 1e9)])
    rc, out, err = _run_process(scene)
    assert rc == 2 and out == ""
    (line,) = _lines(err)
    assert line.startswith("supramodal: error: ") and needle in line
    for word in ("Traceback", "in-memory source", "max_denominator"):
        assert word not in err
    assert not (tmp_path / "out.jsonl").exists()


@pytest.mark.parametrize("case", ["1 Hz", "1 MHz, 9 s gap"])
def test_slow_and_fast_streams_within_the_bounds_replay_without_pyxdf_noise(tmp_path, capsys, xdf, case):
    """Issue 25 item 15: a 1 Hz stream and a 1 MHz one with a 9 s gap are within the bounds and
    replay to the end (exit 0, the gap filled and flagged), with nothing of pyxdf's log on the
    terminal (it said "Segments and clock-segments differ" for every file). The 1 Hz file runs
    as a user runs it, in a process of its own; the 1 MHz one in this process (it is the slower)."""
    if case == "1 Hz":
        scene = _xdf_scene(tmp_path, [_stream(1.0, 100.0 + np.arange(20.0))])
        rc, out, err = _run_process(scene)
    else:
        stamps = np.r_[100 + np.arange(1000) / 1e6, 109 + np.arange(1000) / 1e6]
        scene = _xdf_scene(tmp_path, [_stream(1e6, stamps, chunk=1000)])
        rc, out, err = _run(scene, capsys)
    assert rc == 0, err
    windows = [e for e in _written(tmp_path) if "window" in e]
    assert len(windows) >= 19
    assert "Segments and clock-segments differ" not in err and "pyxdf" not in err
    if case != "1 Hz":
        assert sum(e.get("gap", False) for e in windows) >= 80             # the 9 s filled, flagged


def test_a_file_read_only_by_skipping_damage_says_so_in_a_warning(tmp_path, xdf):
    """A samples chunk with a broken count: pyxdf skips ahead (it logged that, with no handler, on
    the terminal); the stream is read as far as pyxdf could, with one XdfDamageWarning saying so."""
    from supramodal.replay.errors import XdfDamageWarning
    from supramodal.replay.xdf import xdf_session

    write_xdf(tmp_path / "r.xdf", [_stream(1000.0, 100 + np.arange(5000) / 1e3)])
    raw = bytearray((tmp_path / "r.xdf").read_bytes())
    tag = b"\x03\x00\x01\x00\x00\x00"                   # a Samples chunk of stream 1
    at = [i for i in range(len(raw) - 6) if raw[i:i + 6] == tag][20] + 6
    raw[at] = 7                                          # its sample count's length byte: not 1, 4 or 8
    (tmp_path / "r.xdf").write_bytes(bytes(raw))
    with pytest.warns(XdfDamageWarning, match=r"r.xdf: damaged: pyxdf skipped 1 damaged part\(s\) .*corruption"):
        session = xdf_session(tmp_path / "r.xdf", name="s")
    assert 0 < session.frames < 5000


@pytest.mark.parametrize("offset", [1e300, -1e300])
def test_damaged_clock_offsets_are_refused_not_replayed_at_4e300_seconds(tmp_path, capsys, xdf, offset):
    """Issue 25 item 6: XDF clock offsets of +-1e300 were accepted (every window at 4e300 s, flagged
    restart, exit 0); the stamps they give are beyond any LSL clock, and the file is refused."""
    stamps = 100.0 + np.arange(2000) / 1e3
    scene = _xdf_scene(tmp_path, [_stream(1000.0, stamps, offsets=[(100.5, offset), (101.5, offset)])])
    rc, out, err = _run(scene, capsys)
    assert rc == 2 and out == ""
    (line,) = _lines(err)
    assert "with the file's clock offsets applied, reach" in line and "(MAX_XDF_TIME)" in line
    assert not (tmp_path / "out.jsonl").exists()


def test_a_recording_far_faster_than_its_bank_is_refused_with_what_the_user_can_change():
    """Issue 35, item 21: a recording thousands of times faster than its bank's rate said "raise
    max_denominator", a key no scene or command sets. It names both rates and the two fixes."""
    from supramodal.replay.driver import ReplayDriver

    with pytest.raises(ReplayError, match=r"cannot resample 1e\+06 Hz to 400 Hz: more than 2000 times slower.*"
                                          r"resample the recording nearer that rate first, or give its stream a bank") \
            as refused:
        ReplayDriver((np.zeros((1000, 1)), 1_000_000.0), rate=400.0, on_notice=None)
    assert "max_denominator" not in str(refused.value)
