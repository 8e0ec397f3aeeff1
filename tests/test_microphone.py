"""Tests of the microphone driver (drivers/microphone.py) and the device listing.

Unit tests drive CaptureBuffer.callback, the function PortAudio calls, directly
with synthetic blocks; the hardware tests run MicrophoneDriver on a real
PortAudio stream whose "sound card" is ALSA's file plugin serving a raw file
(configured by the test itself, no sound card needed), in a subprocess.
"""

from __future__ import annotations

import ctypes.util
import json
import os
import secrets
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import supramodal.drivers.microphone
from supramodal.drivers import Block, DeviceUnavailable, Driver, DriverClosed, DriverError
from supramodal.drivers.microphone import CaptureBuffer, MicrophoneDriver

ROOT = Path(__file__).resolve().parents[1]
# An editable install of another checkout must not stand in for this one.
assert Path(supramodal.drivers.microphone.__file__).resolve().is_relative_to(ROOT), supramodal.drivers.microphone.__file__
CHILD = Path(__file__).with_name("mic_hil_child.py")
RATE = 44100.0


def _sounddevice():
    """sounddevice, or None when the PortAudio library is missing."""
    try:
        import sounddevice
    except OSError:
        return None
    return sounddevice


def flags(overflow: bool = False):
    """A sounddevice.CallbackFlags, as PortAudio passes to the callback.

    Falls back to an object with the one attribute the driver reads when PortAudio
    is missing, so that the buffer's logic is tested on every machine.
    """
    sd = _sounddevice()
    if sd is None:
        return SimpleNamespace(input_overflow=overflow)
    f = sd.CallbackFlags()
    f.input_overflow = overflow
    return f


def adc(t: float):
    """PortAudio's callback time info with inputBufferAdcTime = t s."""
    return SimpleNamespace(inputBufferAdcTime=t, currentTime=t, outputBufferDacTime=0.0)


NO_TIME = adc(0.0)  # the host API gives no timestamps


def ramp(first: int, frames: int, channels: int = 1, dtype=np.float32) -> np.ndarray:
    """indata whose frame k holds first + k (and its negative on channel 1)."""
    x = np.arange(first, first + frames, dtype=np.float64)
    cols = [x, -x][:channels] + [x] * max(0, channels - 2)
    return np.stack(cols, axis=1).astype(dtype)


def drain(buf: CaptureBuffer) -> list[Block]:
    """Every block left once the stream has ended."""
    out = []
    while True:
        try:
            block = buf.get(0)
        except DriverClosed:
            return out
        assert block is not None, "an ended buffer must deliver or raise, never time out"
        out.append(block)


def assert_tiles(blocks: list[Block], first: int = 0) -> None:
    """Blocks tile the stream from index ``first``: no hole, no overlap."""
    pos = first
    arrival = -np.inf
    for b in blocks:
        assert b.start == pos
        assert b.arrival >= arrival, "arrival never goes back"
        arrival = b.arrival
        assert b.data.dtype == np.float32 and b.data.ndim == 2
        if b.filled is not None:
            assert b.filled.shape == (b.frames,) and b.filled.dtype == bool
            assert not b.data[b.filled].any(), "filled frames are zeros"
        pos += b.frames


# -- (a) the bounded buffer, overflow and drop accounting ---------------------------


def test_blocks_tile_and_are_copies():
    buf = CaptureBuffer(RATE, channels=2, capacity=44100, gap_block=441)
    indata = np.empty((441, 2), np.float32)  # PortAudio reuses one buffer
    for k in range(5):
        indata[:] = ramp(k * 441, 441, 2)
        buf.callback(indata, 441, NO_TIME, flags())
    indata[:] = -7  # PortAudio overwrites it after the callback returns
    buf.end()
    blocks = drain(buf)
    assert [b.start for b in blocks] == [0, 441, 882, 1323, 1764]
    assert all(b.filled is None and b.n_filled == 0 for b in blocks)
    np.testing.assert_array_equal(np.concatenate([b.data for b in blocks]), ramp(0, 2205, 2))
    arrivals = [b.arrival for b in blocks]
    assert arrivals == sorted(arrivals)
    assert buf.stats() == {
        "frames": 2205, "filled": 0, "dropped": 0, "lost": 0, "overflows": 0,
        "callbacks": 5, "errors": 0, "captured": 2205, "buffered": 0,
        "implausible": 2 * (2205 - 17),         # a ramp of frame numbers is beyond 16 from frame 17, both channels
    }


def test_float32_samples_of_an_absurd_level_are_counted_and_said_with_the_fix():
    """Another sample format read as float32 (an int16 file served raw by ALSA's file plugin) gives samples
    far beyond full scale, or NaN: each block says so in a `level` event naming the dtype, the samples are
    counted and passed on as they are (the filterbank then counts what it cannot filter); a plausible
    level (within 16x full scale) and int16 capture say nothing."""
    buf = CaptureBuffer(RATE, channels=1, capacity=44100, gap_block=441)
    rng = np.random.default_rng(5)
    plausible = rng.uniform(-1.5, 1.5, (441, 1)).astype(np.float32)
    buf.callback(plausible, 441, NO_TIME, flags())
    int16_bytes = rng.integers(-32768, 32768, 882).astype("<i2").tobytes()
    misread = np.frombuffer(int16_bytes, "<f4").reshape(441, 1)         # what the device hands over
    expected = int(np.count_nonzero(~(np.abs(misread) <= 16.0)))
    assert expected > 0
    buf.callback(misread, 441, NO_TIME, flags())
    nan = plausible.copy()
    nan[[3, 7]] = np.nan
    buf.callback(nan, 441, NO_TIME, flags())
    buf.callback((plausible * 32767).astype(np.int16), 441, NO_TIME, flags())   # int16: bounded by its scaling
    events, _ = buf.events.take()
    level = [e for e in events if e.kind == "level"]
    assert [e.stream_index for e in level] == [441, 882]
    assert 'set dtype = "int16"' in level[0].message and f"{expected} sample(s) of 441" in level[0].message
    assert "2 sample(s) of 441" in level[1].message
    assert buf.stats()["implausible"] == expected + 2
    buf.end()
    data = np.concatenate([b.data for b in drain(buf)])
    np.testing.assert_array_equal(data[441:882], misread)                 # passed on as it came


def test_int16_is_scaled_exactly():
    buf = CaptureBuffer(RATE, channels=1, capacity=1000, gap_block=100)
    values = np.array([-32768, -1, 0, 1, 12345, 32767], np.int16)
    buf.callback(values[:, None], 6, NO_TIME, flags())
    block = buf.get(0)
    assert block.data.dtype == np.float32
    np.testing.assert_array_equal(block.data[:, 0], values.astype(np.float64) / 32768)
    assert block.data[0, 0] == -1.0


def test_full_buffer_drops_new_blocks_and_fills_their_place():
    # Room for 3 blocks of 441: the 4th and 5th are dropped, not waited for.
    buf = CaptureBuffer(RATE, channels=1, capacity=3 * 441, gap_block=441)
    for k in range(5):
        buf.callback(ramp(k * 441, 441), 441, NO_TIME, flags())
    s = buf.stats()
    assert (s["dropped"], s["buffered"], s["captured"], s["filled"]) == (882, 1323, 2205, 0)
    first = buf.get(0)  # the reader frees one block of room...
    assert first.start == 0
    buf.callback(ramp(5 * 441, 441), 441, NO_TIME, flags())  # ...so the 6th is taken
    buf.end()
    blocks = [first] + drain(buf)
    assert_tiles(blocks)
    assert [(b.start, b.n_filled) for b in blocks] == [
        (0, 0), (441, 0), (882, 0), (1323, 441), (1764, 441), (2205, 0),
    ]
    np.testing.assert_array_equal(blocks[-1].data[:, 0], np.arange(2205, 2646))
    s = buf.stats()
    assert s["dropped"] == s["filled"] == 882
    assert s["frames"] == s["captured"] == 6 * 441


def test_long_gap_comes_in_bounded_blocks():
    buf = CaptureBuffer(RATE, channels=1, capacity=441, gap_block=400)
    buf.callback(ramp(0, 441), 441, NO_TIME, flags())
    for k in range(1, 4):  # dropped: 1323 frames of gap
        buf.callback(ramp(k * 441, 441), 441, NO_TIME, flags())
    assert buf.get(0).start == 0
    buf.callback(ramp(4 * 441, 441), 441, NO_TIME, flags())
    buf.end()
    blocks = drain(buf)
    assert_tiles(blocks, first=441)
    assert [b.frames for b in blocks] == [400, 400, 400, 123, 441]
    assert [b.n_filled for b in blocks] == [400, 400, 400, 123, 0]
    assert blocks[-1].start == 4 * 441


def test_gap_pending_at_end_is_delivered():
    buf = CaptureBuffer(RATE, channels=1, capacity=441, gap_block=441)
    buf.callback(ramp(0, 441), 441, NO_TIME, flags())
    buf.callback(ramp(441, 441), 441, NO_TIME, flags())  # dropped, last callback
    buf.end()
    blocks = drain(buf)
    assert_tiles(blocks)
    assert [b.n_filled for b in blocks] == [0, 441]
    assert buf.stats()["filled"] == buf.stats()["dropped"] == 441


def test_input_overflow_counts_and_fills_lost_frames():
    """PortAudio lost frames: estimated from the jump of the ADC timestamps."""
    sd = _sounddevice()
    if sd is None:
        pytest.skip("PortAudio library missing (apt-get install libportaudio2): no CallbackFlags")
    status = sd.CallbackFlags()
    status.input_overflow = True
    buf = CaptureBuffer(RATE, channels=1, capacity=44100, gap_block=441)
    t0 = 1000.0
    buf.callback(ramp(0, 441), 441, adc(t0), sd.CallbackFlags())
    buf.callback(ramp(441, 441), 441, adc(t0 + 441 / RATE), sd.CallbackFlags())
    # 1000 frames never reached the callback: the next block was captured later.
    buf.callback(ramp(882, 441), 441, adc(t0 + (882 + 1000) / RATE), status)
    buf.callback(ramp(1323, 441), 441, adc(t0 + (1323 + 1000) / RATE), sd.CallbackFlags())
    buf.end()
    blocks = drain(buf)
    assert_tiles(blocks)
    assert [(b.start, b.frames, b.n_filled) for b in blocks] == [
        (0, 441, 0), (441, 441, 0), (882, 441, 441), (1323, 441, 441), (1764, 118, 118),
        (1882, 441, 0), (2323, 441, 0),
    ]
    np.testing.assert_array_equal(blocks[-2].data[:, 0], np.arange(882, 1323))
    s = buf.stats()
    assert (s["overflows"], s["lost"], s["filled"], s["dropped"]) == (1, 1000, 1000, 0)
    assert s["frames"] == s["captured"] + s["lost"] == 4 * 441 + 1000


def test_input_overflow_without_timestamps_is_counted_only():
    buf = CaptureBuffer(RATE, channels=1, capacity=44100, gap_block=441)
    buf.callback(ramp(0, 441), 441, NO_TIME, flags())
    buf.callback(ramp(441, 441), 441, NO_TIME, flags(overflow=True))
    buf.end()
    blocks = drain(buf)
    assert [(b.start, b.n_filled) for b in blocks] == [(0, 0), (441, 0)]
    s = buf.stats()
    assert (s["overflows"], s["lost"], s["filled"]) == (1, 0, 0)


def test_lost_estimate_is_capped_and_never_negative():
    buf = CaptureBuffer(RATE, channels=1, capacity=882, gap_block=10_000)
    buf.callback(ramp(0, 441), 441, adc(50.0), flags())
    buf.callback(ramp(441, 441), 441, adc(40.0), flags(overflow=True))  # clock went back
    assert buf.stats()["lost"] == 0
    buf.get(0)
    buf.get(0)
    buf.callback(ramp(882, 441), 441, adc(4000.0), flags(overflow=True))  # absurd jump
    assert buf.stats()["lost"] == 882  # at most the buffer's capacity
    assert buf.stats()["overflows"] == 2


def test_callback_never_raises_and_read_surfaces_the_failure():
    buf = CaptureBuffer(RATE, channels=1, capacity=44100, gap_block=441)
    buf.callback(ramp(0, 441), 441, NO_TIME, flags())
    buf.callback(ramp(441, 441, channels=2), 441, NO_TIME, flags())  # wrong shape
    buf.callback("not an array", 441, NO_TIME, flags())  # a failure in the second...
    buf.callback(ramp(1323, 441), 441, NO_TIME, flags())
    buf.callback(ramp(1764, 441), 441, NO_TIME, None)  # ...and no status at all
    s = buf.stats()
    assert (s["errors"], s["callbacks"], s["dropped"]) == (3, 5, 3 * 441)
    assert buf.get(0).start == 0
    with pytest.raises(DriverError, match="shape") as info:
        buf.get(0)
    assert isinstance(info.value.__cause__, ValueError)
    # Only one error waits at a time; the others are counted, and the stream goes on.
    rest, raised = [], 0
    buf.end()
    while True:
        try:
            b = buf.get(0)
        except DriverClosed:
            break
        except DriverError:
            raised += 1
            continue
        rest.append(b)
    assert raised == 0, "the 2nd and 3rd failures came while the 1st was pending"
    assert_tiles(rest, first=441)
    assert [(b.start, b.n_filled) for b in rest] == [(441, 441), (882, 441), (1323, 0), (1764, 441)]
    s = buf.stats()
    assert s["filled"] == s["dropped"] and s["frames"] == s["captured"] == 5 * 441


def test_get_times_out_with_none_and_end_is_final():
    buf = CaptureBuffer(RATE, channels=1, capacity=441, gap_block=441)
    assert buf.get(0) is None
    assert buf.get(0.01) is None
    assert buf.get(-1) is None
    buf.end()
    buf.end()  # idempotent: one end marker
    for _ in range(3):
        with pytest.raises(DriverClosed):
            buf.get(None)


def test_reader_waits_for_the_callback_thread():
    buf = CaptureBuffer(RATE, channels=1, capacity=44100, gap_block=441)
    results = []
    reader = threading.Thread(target=lambda: results.append(buf.get(60.0)))
    reader.start()
    buf.callback(ramp(0, 441), 441, NO_TIME, flags())
    reader.join(60.0)
    assert not reader.is_alive()
    assert results[0].start == 0 and results[0].frames == 441


def test_end_wakes_a_blocked_reader():
    buf = CaptureBuffer(RATE, channels=1, capacity=44100, gap_block=441)
    raised = []

    def reader():
        try:
            buf.get(None)
        except DriverClosed as exc:
            raised.append(exc)

    t = threading.Thread(target=reader)
    t.start()
    buf.end()
    t.join(60.0)
    assert not t.is_alive() and len(raised) == 1


def test_concurrent_callback_and_reader_keep_the_books():
    """A producer thread as fast as it can go against a reader: whatever is dropped,
    the stream tiles, measured frames sit at their index, and the counters agree."""
    n_blocks, bs = 3000, 64
    buf = CaptureBuffer(RATE, channels=1, capacity=8 * bs, gap_block=bs)
    blocks: list[Block] = []

    def reader():
        while True:
            try:
                b = buf.get(60.0)
            except DriverClosed:
                return
            if b is not None:
                blocks.append(b)

    t = threading.Thread(target=reader)
    t.start()
    indata = np.empty((bs, 1), np.float32)
    for k in range(n_blocks):
        indata[:, 0] = np.arange(k * bs, (k + 1) * bs)
        buf.callback(indata, bs, NO_TIME, flags())
    buf.end()
    t.join(60.0)
    assert not t.is_alive()
    assert_tiles(blocks)
    data = np.concatenate([b.data[:, 0] for b in blocks])
    measured = np.ones(len(data), bool)
    for b in blocks:
        if b.filled is not None:
            measured[b.start:b.start + b.frames] = ~b.filled
    idx = np.flatnonzero(measured)
    np.testing.assert_array_equal(data[idx], idx)  # no lost frames: stream index = capture index
    s = buf.stats()
    assert s["frames"] == len(data) == s["captured"] == n_blocks * bs
    assert s["filled"] == s["dropped"] == len(data) - len(idx)


# One callback: (frames, overflow, frames lost before it, reads after it).
_events = st.lists(
    st.tuples(
        st.integers(1, 300), st.booleans(), st.integers(0, 2000), st.integers(0, 3)
    ),
    max_size=40,
)


@settings(max_examples=200, deadline=None)
@given(events=_events, capacity=st.integers(300, 2000), gap_block=st.integers(1, 500))
def test_any_sequence_keeps_the_stream_aligned_with_time(events, capacity, gap_block):
    """Frames measured, dropped by the buffer or lost by PortAudio: every measured
    frame is delivered at the index it was captured at on the stream's clock."""
    buf = CaptureBuffer(RATE, channels=1, capacity=capacity, gap_block=gap_block)
    blocks: list[Block] = []
    clock = 0  # frames elapsed on the device's clock, lost ones included
    captured = 0
    index_of = {}  # capture index of a block's first frame -> expected stream index
    first_callback = True
    for frames, overflow, lost, reads in events:
        if not overflow:
            lost = 0  # frames only go missing in an overflow
        clock += lost
        expected_lost = 0
        if overflow and not first_callback:  # the first has no previous timestamp
            expected_lost = min(lost, capacity)
        index_of[captured] = (clock, expected_lost)
        t = 1000.0 + clock / RATE
        buf.callback(ramp(captured, frames), frames, adc(t), flags(overflow))
        first_callback = False
        clock += frames
        captured += frames
        for _ in range(reads):
            b = buf.get(0)
            if b is not None:
                blocks.append(b)
    buf.end()
    blocks += drain(buf)
    assert_tiles(blocks)
    s = buf.stats()
    assert s["captured"] == captured
    assert s["filled"] == s["dropped"] + s["lost"]
    assert s["frames"] == s["captured"] + s["lost"] == sum(b.frames for b in blocks)
    assert s["overflows"] == sum(1 for e in events if e[1])
    # With lost frames capped only by capacity, stream index - capture index is the
    # sum of lost frames so far.
    assert s["lost"] == sum(v[1] for v in index_of.values())
    shift = 0
    starts = sorted(index_of)
    for b in blocks:
        if b.filled is not None:
            continue
        c = int(b.data[0, 0])
        assert c in index_of, "a measured block starts where a callback's block did"
        np.testing.assert_array_equal(b.data[:, 0], np.arange(c, c + b.frames))
        shift = sum(index_of[k][1] for k in starts if k <= c)
        assert b.start == c + shift


# -- the driver object, without a stream -----------------------------------------------


def test_driver_follows_the_contract_and_checks_its_arguments():
    mic = MicrophoneDriver()
    assert isinstance(mic, Driver)
    assert (mic.rate, mic.channels, mic.blocksize, mic.dtype) == (44100.0, 1, 441, "float32")
    assert mic.stats()["frames"] == 0
    with pytest.raises(DriverError, match="not open"):
        mic.read(0)
    mic.close()  # closing a driver never opened is harmless
    for kwargs in ({"dtype": "int32"}, {"rate": 0}, {"channels": 0}, {"blocksize": -1},
                   {"buffer_seconds": 0.001}):
        with pytest.raises(ValueError):
            MicrophoneDriver(**kwargs)


def test_read_reports_a_stream_that_portaudio_stopped():
    """An unplugged device: PortAudio stops calling back and marks the stream inactive.
    A stand-in stream plays that part; what was buffered still comes first."""
    if _sounddevice() is None:
        pytest.skip("PortAudio library missing (apt-get install libportaudio2)")
    calls = []
    mic = MicrophoneDriver()
    mic._buffer = CaptureBuffer(RATE, channels=1, capacity=44100, gap_block=441)
    mic._stream = SimpleNamespace(
        active=False,
        stop=lambda ignore_errors=True: calls.append("stop"),
        close=lambda ignore_errors=True: calls.append("close"),
    )
    mic._buffer.callback(ramp(0, 441), 441, NO_TIME, flags())
    assert mic.read(0).start == 0
    with pytest.raises(DeviceUnavailable, match="stopped the microphone stream"):
        mic.read(0)
    mic.close()
    assert calls == ["stop", "close"]
    with pytest.raises(DriverClosed):
        mic.read(0)


# -- (c) import drivers does not import sounddevice ------------------------------------


def _run_python(code: str, env: dict | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    full_env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    full_env.update(env or {})
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=full_env, timeout=timeout,
        cwd=ROOT,
    )


def test_import_drivers_imports_neither_sounddevice_nor_pyserial():
    r = _run_python(
        "import sys, supramodal.drivers, supramodal.drivers.microphone, supramodal.drivers.devices\n"
        "from supramodal.drivers.microphone import MicrophoneDriver\n"
        "MicrophoneDriver(device='x', rate=48000, channels=2)\n"
        "bad = sorted(m for m in ('sounddevice', '_sounddevice', 'serial', 'supramodal.node', 'supramodal.replay')\n"
        "             if m in sys.modules)\n"
        # The error root, the validation vocabulary and the signal hold over an optional import
        # (supramodal.errors, supramodal.checks, supramodal.interrupts: the standard library and the
        # root) are what of the model package a driver may load: nothing of the DSP.
        "bad += sorted(m for m in sys.modules if m.startswith('supramodal.')\n"
        "              and m not in ('supramodal.errors', 'supramodal.checks', 'supramodal.interrupts')\n"
        "              and not m.startswith('supramodal.drivers'))\n"
        "print(bad)\n"
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


# -- (d) the errors people will see -----------------------------------------------------


def test_missing_portaudio_names_the_package_to_install():
    """sounddevice raises OSError without libportaudio; simulated by hiding the library."""
    r = _run_python(
        "import ctypes.util\n"
        "real = ctypes.util.find_library\n"
        "ctypes.util.find_library = lambda name: None if 'portaudio' in name else real(name)\n"
        "from supramodal.drivers import DeviceUnavailable\n"
        "from supramodal.drivers.microphone import MicrophoneDriver\n"
        "from supramodal.drivers.devices import list_audio_inputs, format_devices\n"
        "for f in (MicrophoneDriver().open, list_audio_inputs):\n"
        "    try:\n"
        "        f()\n"
        "    except DeviceUnavailable as exc:\n"
        "        print('ERR', exc)\n"
        "print(format_devices())\n"
    )
    assert r.returncode == 0, r.stderr
    errs = [line for line in r.stdout.splitlines() if line.startswith("ERR")]
    assert len(errs) == 2
    for line in errs:
        assert "PortAudio library not found" in line and "apt-get install libportaudio2" in line
    assert "Serial ports:" in r.stdout, "the serial section is listed all the same"


def test_missing_device_is_device_unavailable_with_a_fix():
    if _sounddevice() is None:
        pytest.skip("PortAudio library missing (apt-get install libportaudio2)")
    with pytest.raises(DeviceUnavailable) as info:
        MicrophoneDriver(device="no-such-microphone-xyz").open()
    msg = str(info.value)
    # On a machine with sound cards: "No input device matching ..."; with none at all,
    # "PortAudio found no input device at all". Either way: which device, and the fix.
    assert "no-such-microphone-xyz" in msg
    assert "supramodal devices" in msg


def test_device_lists_are_plain_data():
    from supramodal.drivers.devices import format_devices, list_serial_ports

    ports = list_serial_ports()
    assert isinstance(ports, list)
    for p in ports:
        assert isinstance(p, dict) and isinstance(p["device"], str)
    text = format_devices()
    assert "Audio inputs" in text and "Serial ports:" in text


# -- (b) a real PortAudio stream with no sound card -------------------------------------


def _alsa_file_device(tmp_path: Path, raw: Path) -> dict:
    """Environment serving ``raw`` as ALSA's default capture device (file plugin).

    The file plugin reads ``raw`` in whatever sample format the application asked
    for (the null slave accepts any), so the file's format is the driver's dtype.
    """
    alsa_conf = Path("/usr/share/alsa/alsa.conf")
    assert alsa_conf.exists(), f"{alsa_conf} missing: it comes with libasound2 (libasound2-data)"
    conf = tmp_path / "asound.conf"
    conf.write_text(
        "pcm.!default {\n"
        "    type file\n"
        '    slave.pcm "null"\n'
        '    file "/dev/null"\n'
        f'    infile "{raw}"\n'
        '    format "raw"\n'
        "}\n"
    )
    return {"ALSA_CONFIG_PATH": f"{alsa_conf}:{conf}", "JACK_NO_START_SERVER": "1"}


def _require_portaudio():
    if ctypes.util.find_library("portaudio") is None:
        pytest.skip("PortAudio library missing: apt-get install libportaudio2")


def _run_child(args: list[str], env: dict) -> None:
    full_env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    full_env.update(env)
    r = subprocess.run(
        [sys.executable, str(CHILD), *args], capture_output=True, text=True, env=full_env,
        timeout=300, cwd=ROOT,
    )
    jackd_log = Path(args[1]).parent / "jackd.log"      # the JACK server's messages, when it paced the device
    said = f"\njackd said:\n{jackd_log.read_text()[-2000:]}" if jackd_log.exists() else ""
    assert r.returncode == 0, f"child failed:\nstdout:\n{r.stdout}\nstderr:\n{r.stderr}{said}"


def _source_signal(frames: int) -> np.ndarray:
    """Deterministic int16 test signal: a chirp under seeded full-scale noise, with
    both extremes, so that every bit of every sample is checked."""
    t = np.arange(frames) / RATE
    chirp = 0.5 * np.sin(2 * np.pi * (100 * t + 2000 * t**2))
    noise = np.random.default_rng(2010).uniform(-0.5, 0.5, frames)
    x = np.clip(np.round((chirp + noise) * 32768), -32768, 32767).astype(np.int16)
    x[:4] = [-32768, 32767, 0, -1]
    return x


def _capture(tmp_path: Path, dtype: str, file_seconds: float, n: int, buffer_seconds: float,
             stall: bool = False):
    """Serve the source signal as a file and capture it through the driver in a child.

    Returns (expected, data, filled, info): the source as float32, every frame the
    driver delivered (before and after close), its filled mask, and the child's notes.
    """
    _require_portaudio()
    source = _source_signal(int(file_seconds * RATE))
    expected = source.astype(np.float32) / np.float32(32768)
    raw = tmp_path / "mic.raw"
    (source.astype("<i2") if dtype == "int16" else expected.astype("<f4")).tofile(raw)
    prefix = str(tmp_path / "capture")
    args = ["capture", prefix, str(n), dtype, str(buffer_seconds)] + (["stall"] if stall else [])
    _run_child(args, _alsa_file_device(tmp_path, raw))
    got = np.load(prefix + ".npz")
    info = json.loads(Path(prefix + ".json").read_text())
    data, filled = got["data"], got["filled"]
    assert info["device"] == "default"
    assert info["dtypes"] == ["float32"] and data.shape[1] == 1
    return expected, data[:, 0], filled, info


def _assert_consistent(expected, data, filled, info) -> None:
    """Everything delivered, before and after close(): the blocks tile, the books
    balance, and every measured frame the file covered sits at its own index (frames
    dropped when the reader fell behind are zero-filled gaps, not shifts). After the
    file's end the plugin repeats stale frames, which are not compared."""
    starts, frames = info["starts"], info["frames"]
    assert starts == [int(x) for x in np.cumsum([0] + frames[:-1])]
    assert info["arrivals"] == sorted(info["arrivals"])
    final = info["final"]
    assert final["frames"] == len(data) == sum(frames)
    assert final["filled"] == int(filled.sum()) == final["dropped"] + final["lost"]
    assert final["frames"] == final["captured"] + final["lost"]
    assert final["overflows"] == 0 and final["errors"] == 0 and final["buffered"] == 0
    # Only now that the stream has stopped: while it runs, a snapshot of the counters
    # may catch the callback between two of them.
    assert final["captured"] == final["callbacks"] * 441
    assert not data[filled].any()
    m = min(len(data), len(expected))
    measured = ~filled[:m]
    np.testing.assert_array_equal(data[:m][measured], expected[:m][measured])


@pytest.mark.hardware
@pytest.mark.parametrize("dtype", ["int16", "float32"])
def test_real_stream_delivers_the_file_bit_exact(tmp_path, dtype):
    n = int(3 * RATE)  # 3 s of audio read through the driver, from a longer file
    # Room for all n frames: the unpaced stream outruns the reader, and blocks are only
    # dropped once the buffer is full, so none of the first n frames can be.
    expected, data, filled, info = _capture(tmp_path, dtype, 5.0, n, n / RATE + 1.0)
    np.testing.assert_array_equal(data[:n], expected[:n])
    assert not filled[:n].any()
    at_n = info["at_n"]
    assert at_n["frames"] == n and at_n["filled"] == 0 and at_n["errors"] == 0
    _assert_consistent(expected, data, filled, info)


@pytest.mark.hardware
def test_real_stream_overrun_drops_and_fills_in_place(tmp_path):
    """A reader that falls behind a real stream: new blocks are dropped, never waited
    for, and come back as filled frames at their own indices."""
    buffer_seconds = 0.25  # 11025 frames = 25 blocks of 441
    expected, data, filled, info = _capture(
        tmp_path, "int16", 20.0, int(3 * RATE), buffer_seconds, stall=True
    )
    capacity = int(buffer_seconds * RATE)
    # Nothing was read until the buffer was full: it holds the first 25 blocks, and
    # the first block dropped is the 26th.
    np.testing.assert_array_equal(data[:capacity], expected[:capacity])
    assert not filled[:capacity].any() and filled[capacity]
    assert info["final"]["dropped"] > 0
    _assert_consistent(expected, data, filled, info)


@pytest.mark.hardware
def test_real_device_refusals_and_listing(tmp_path):
    _require_portaudio()
    raw = tmp_path / "mic.raw"
    _source_signal(int(RATE)).astype("<i2").tofile(raw)
    out = tmp_path / "errors.json"
    _run_child(["errors", str(out)], _alsa_file_device(tmp_path, raw))
    r = json.loads(out.read_text())
    assert "No input device matching 'no-such-microphone-xyz'" in r["no_such_device"]
    assert "supramodal devices" in r["no_such_device"]
    assert "device=999" in r["bad_index"] and "supramodal devices" in r["bad_index"]
    assert "Invalid sample rate" in r["bad_rate"] and "10000000 Hz" in r["bad_rate"]
    assert "its default is 44100 Hz" in r["bad_rate"]
    default = [d for d in r["inputs"] if d["default"]]
    assert len(default) == 1 and default[0]["name"] == "default" and default[0]["channels"] >= 1
    assert default[0]["hostapi"] == "ALSA"
    assert "*" in r["text"] and "default" in r["text"]


# -- (c) in real time: a JACK dummy clock under the file device ---------------------------

JACK_PLUGIN = Path("/usr/lib") / f"{os.uname().machine}-linux-gnu" / "alsa-lib" / "libasound_module_pcm_jack.so"


@pytest.fixture
def jack_server(tmp_path):
    """A private JACK server on the dummy backend (a clock, no sound card): its name, unique to this
    test, so that parallel runs never share one. Real-time scheduling where allowed, else not.

    Its messages go to a file, never to an unread pipe: on a loaded machine jackd reports every late
    cycle, and once a pipe's 64 KiB fill, jackd blocks writing and its clock stops (the capture then
    sees no block at all). A late client is given 10 s instead of 0.5 s before JACK drops it."""
    if shutil.which("jackd") is None or shutil.which("jack_wait") is None:
        pytest.skip("JACK missing: apt-get install --no-install-recommends jackd2")
    if not JACK_PLUGIN.exists():
        pytest.skip(f"ALSA's JACK plugin missing ({JACK_PLUGIN}): apt-get install --no-install-recommends "
                    "libasound2-plugins")
    name = f"supramodal-{os.getpid()}-{secrets.token_hex(4)}"
    backend = ["-d", "dummy", "-r", "44100", "-p", "1024", "-C", "1", "-P", "1"]
    log = tmp_path / "jackd.log"
    for realtime in (["-R", "-P", "20"], ["--no-realtime"]):
        with open(log, "w") as messages:
            proc = subprocess.Popen(["jackd", *realtime, "-t", "10000", "-n", name, *backend],
                                    stdout=messages, stderr=subprocess.STDOUT)
        ready = subprocess.run(["jack_wait", "-s", name, "-w", "-t", "10"], capture_output=True, text=True)
        if ready.returncode == 0 and proc.poll() is None:
            break
        proc.kill()
        proc.wait()
    else:
        pytest.skip(f"jackd does not start here: {log.read_text()[-500:]}")
    try:
        yield name
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _paced_file_device(tmp_path: Path, raw: Path, server: str) -> dict:
    """Environment serving ``raw`` as the default capture device, paced by JACK's dummy clock: the
    file plugin reads the file as its slave (ALSA's JACK plugin) takes frames, in real time."""
    env = _alsa_file_device(tmp_path, raw)
    conf = tmp_path / "asound.conf"
    conf.write_text(conf.read_text().replace(
        'slave.pcm "null"',
        "slave.pcm { type plug slave.pcm { type jack capture_ports { 0 system:capture_1 } "
        "playback_ports { 0 system:playback_1 } } }"))
    env["JACK_DEFAULT_SERVER"] = server
    return env


@pytest.mark.hardware
@pytest.mark.parametrize("dtype", ["int16", "float32"])
@pytest.mark.slow   # paced real time: 8 s of audio at the pace of a sound card
def test_real_time_capture_through_jack_is_the_played_signal(tmp_path, jack_server, dtype):
    """8 s of audio at the pace of a sound card: no overflow, nothing dropped or filled, every sample
    the file's, and the 8 s take about 8 s (an unpaced file device delivers them in ~10 ms)."""
    _require_portaudio()
    n = int(8 * RATE)
    source = _source_signal(int(10 * RATE))
    expected = source.astype(np.float32) / np.float32(32768)
    raw = tmp_path / "mic.raw"
    (source.astype("<i2") if dtype == "int16" else expected.astype("<f4")).tofile(raw)
    prefix = str(tmp_path / "capture")
    # A 0.5 s buffer, far less than the 8 s read: a paced stream never needs more.
    _run_child(["capture", prefix, str(n), dtype, "0.5"], _paced_file_device(tmp_path, raw, jack_server))
    data = np.load(prefix + ".npz")["data"][:, 0]
    info = json.loads(Path(prefix + ".json").read_text())
    at_n = info["at_n"]
    assert at_n["overflows"] == 0 and at_n["dropped"] == 0 and at_n["filled"] == 0 and at_n["errors"] == 0
    np.testing.assert_array_equal(data[:n], expected[:n])
    frames = np.cumsum(info["frames"])
    last = int(np.searchsorted(frames, n))                 # the block that completed the 8 s
    span = info["arrivals"][last] - info["arrivals"][0]
    assert span >= 6.0, f"8 s of audio arrived in {span:.2f} s: the stream is not paced"


def _int16_device(tmp_path: Path, raw: Path, server: str, kind: str) -> dict:
    """The paced file device, giving int16 only: behind ALSA's ``linear`` plugin (integer formats
    only, so PortAudio converts to float32 itself) or ``plug`` (ALSA converts). Paced, because an
    unpaced device behind a converting plugin overruns and skips whole periods unreported."""
    env = _paced_file_device(tmp_path, raw, server)
    conf = tmp_path / "asound.conf"
    conf.write_text(conf.read_text().replace("pcm.!default {", "pcm.filedev {", 1)
                    + f'pcm.!default {{\n    type {kind}\n    slave {{ pcm "filedev" format S16_LE }}\n}}\n')
    return env


@pytest.mark.hardware
@pytest.mark.parametrize("kind", ["plug", "linear"])
def test_example_scene_float32_default_on_an_int16_device_is_exact(tmp_path, jack_server, kind):
    """examples/microphone.toml leaves the driver's dtype at its default, float32; on a device that
    gives int16 the conversion (PortAudio's behind ``linear``, ALSA's behind ``plug``) is exactly
    x / 32768, sample for sample."""
    import inspect

    from supramodal.node.scene.schema import load_scene

    _require_portaudio()
    assert load_scene(ROOT / "examples" / "microphone.toml").only_source().options["dtype"] is None
    default = inspect.signature(MicrophoneDriver).parameters["dtype"].default
    assert default == "float32"
    n = int(2 * RATE)
    source = _source_signal(int(4 * RATE))
    raw = tmp_path / "mic.raw"
    source.astype("<i2").tofile(raw)
    prefix = str(tmp_path / "capture")
    _run_child(["capture", prefix, str(n), default, "0.5"], _int16_device(tmp_path, raw, jack_server, kind))
    data = np.load(prefix + ".npz")["data"][:, 0]
    info = json.loads(Path(prefix + ".json").read_text())
    assert info["dtypes"] == ["float32"]
    assert info["at_n"]["overflows"] == 0 and info["at_n"]["dropped"] == 0 and info["at_n"]["filled"] == 0
    np.testing.assert_array_equal(data[:n], source[:n].astype(np.float32) / np.float32(32768))


# -- (e) the whole node on a real PortAudio stream ----------------------------------------


@pytest.mark.hardware
def test_node_on_a_real_stream_equals_replaying_the_file(tmp_path):
    """`supramodal run` with a microphone scene, captured through ALSA's file plugin, emits the
    same feature windows (to 1e-12) as the offline pipeline on the file itself."""
    from supramodal.banks import cochlea_bank
    from supramodal.gammatone import relative_error
    from supramodal.pipeline import extract_features

    _require_portaudio()
    source = _source_signal(int(4 * RATE))
    raw = tmp_path / "mic.raw"
    source.astype("<i2").tofile(raw)
    scene = tmp_path / "mic.toml"
    # Buffers larger than the capture: the unpaced file device outruns real time, and nothing may drop.
    scene.write_text('[driver]\ntype = "microphone"\ndtype = "int16"\nbuffer_seconds = 10.0\n'
                     '[bank]\nkind = "cochlea"\n[features]\nnames = ["Af", "A", "f"]\n'
                     '[buffer]\nseconds = 10.0\n')
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.update(_alsa_file_device(tmp_path, raw))
    r = subprocess.run([sys.executable, "-m", "supramodal.node.cli", "run", str(scene), "--json", "--quiet", "--seconds", "2"],
                       capture_output=True, text=True, env=env, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stdout.splitlines()]
    summary = lines[-1]
    events = [d for d in lines[:-1] if "event" not in d]        # the windows
    said = [d for d in lines[:-1] if "event" in d]
    # The unpaced file device outruns real time by ~700x: its 10 s buffer fills within ms, and from
    # then on the driver drops (and counts) what PortAudio still pushes. On a loaded machine that is
    # said while the node still computes its 2 s; every such drop lies beyond the 2 s compared.
    assert all(d["event"] == "dropped" and d["stream_index"] >= 2 * int(RATE) for d in said), said
    assert summary["summary"] and summary["stream_seconds"] == 2.0 and len(events) == 20
    assert not any(e.get("gap") for e in events)
    offline = extract_features(source[: 2 * int(RATE)] / 32768.0, cochlea_bank(), ("Af", "A", "f"))
    got = np.array([[e["features"][f] for f in ("Af", "A", "f")] for e in events])
    rel = relative_error(got, offline.values, axis=(0, 2))     # per feature
    assert np.all(rel <= 1e-12), rel


@pytest.mark.hardware
def test_the_microphones_drops_are_said_as_they_happen_and_flag_their_windows(tmp_path):
    """`supramodal run --json` on the unpaced file device (about 700x real time) with a driver buffer
    of 20 ms: PortAudio's callback finds the buffer full and drops; the driver's 'dropped' events
    reach the JSON output while the node runs, every frame it dropped is counted in the summary's
    fates, and the windows its fills touch are flagged gap."""
    _require_portaudio()
    source = _source_signal(int(4 * RATE))
    raw = tmp_path / "mic.raw"
    source.astype("<i2").tofile(raw)
    scene = tmp_path / "mic.toml"
    scene.write_text('[driver]\ntype = "microphone"\ndtype = "int16"\nbuffer_seconds = 0.02\n'
                     '[bank]\nkind = "cochlea"\n[features]\nnames = ["Af"]\n')
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.update(_alsa_file_device(tmp_path, raw))
    r = subprocess.run([sys.executable, "-m", "supramodal.node.cli", "run", str(scene), "--json", "--quiet",
                        "--seconds", "3"], capture_output=True, text=True, env=env, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stdout.splitlines()]
    summary = lines[-1]
    said = [d for d in lines if d.get("event") == "dropped"]
    windows = [d for d in lines if "window" in d]
    assert said and all("buffer full" in d["message"] for d in said)
    last_window = max(i for i, d in enumerate(lines) if "window" in d)
    assert lines.index(said[0]) < last_window           # said while windows were still coming
    fates = summary["frames"]
    assert fates["dropped_by_driver"] > 0 and fates["dropped"] >= fates["dropped_by_driver"]
    assert fates["delivered"] + fates["filled"] + fates["dropped"] == fates["stream"] == 3 * int(RATE)
    assert summary["events"]["counts"]["dropped"] >= len(said)
    assert any(d.get("gap") for d in windows)
