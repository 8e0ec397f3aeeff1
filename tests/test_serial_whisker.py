"""Serial whisker driver: parsing on loop://, link-loss state machine on a fake
port, and end to end against the mock board on a real pty (``hardware``).

No assertion here is on wall time: streams are stopped by sample count (or by
the mock having finished and the port staying idle), with generous timeouts.
"""

from __future__ import annotations

import errno
import threading
import time

import numpy as np
import pytest
import serial
from scipy.io import wavfile

from supramodal.drivers.base import Block, DeviceUnavailable, Driver, DriverClosed
from supramodal.drivers.frames import FLAG_OVERRUN, encode_frame
from supramodal.drivers.mock_whisker import FaultSpec, MockWhiskerDevice, quantise
from supramodal.node.cli import main as cli_main
from supramodal.errors import InputError


def main(argv):
    """`supramodal mock-whisker ARGV`."""
    return cli_main(["mock-whisker", *argv])
from supramodal.drivers.serial_whisker import SerialWhiskerDriver


def frames_bytes(seqs, channels=3, n=4, value=None, flags=0):
    """Frames whose samples encode (seq, row, channel), or all ``value``."""
    out = b""
    for s in seqs:
        if value is None:
            x = (s % 100) * 100 + np.arange(n)[:, None] * 10 + np.arange(channels)[None, :]
        else:
            x = np.full((n, channels), value)
        out += encode_frame(s, x.astype(np.int16), flags=flags)
    return out


def read_all(drv, want_rows, timeout=0.5, max_reads=100):
    blocks, rows = [], 0
    for _ in range(max_reads):
        if rows >= want_rows:
            break
        b = drv.read(timeout)
        if b is not None:
            blocks.append(b)
            rows += b.frames
    return blocks


def joined(blocks):
    data = np.concatenate([b.data for b in blocks])
    filled = np.concatenate([np.zeros(b.frames, bool) if b.filled is None else b.filled
                             for b in blocks])
    return data, filled


def assert_tiled(blocks, channels):
    start = blocks[0].start
    for b in blocks:
        assert isinstance(b, Block)
        assert b.start == start
        assert b.data.dtype == np.float32 and b.data.shape == (b.frames, channels)
        assert b.filled is None or (b.filled.dtype == bool and b.filled.shape == (b.frames,))
        start += b.frames


# -- loop:// --------------------------------------------------------------------------


def test_driver_follows_the_contract():
    drv = SerialWhiskerDriver("loop://", 1000, 3)
    assert isinstance(drv, Driver)
    with pytest.raises(DriverClosed):
        drv.read(0)
    with drv:
        assert drv.read(0.05) is None
    with pytest.raises(DriverClosed):
        drv.read(0)


def test_parses_frames_on_loop_url():
    with SerialWhiskerDriver("loop://", 1000, 3) as drv:
        drv._ser.write(b"\x00\x13noise" + frames_bytes([65534, 65535, 0, 1]))
        blocks = read_all(drv, 16)
        assert_tiled(blocks, 3)
        data, filled = joined(blocks)
        expect = np.concatenate([np.frombuffer(frames_bytes([s])[10:-4], "<i2").reshape(4, 3)
                                 for s in (65534, 65535, 0, 1)]) / 32768
        np.testing.assert_array_equal(data, expect)
        assert not filled.any() and blocks[0].start == 0
        assert drv.first_sequence == 65534
        st = drv.stats()
        assert st["frames"] == 16 and st["filled"] == 0 and st["frames_ok"] == 4
        assert st["bytes_skipped"] == 7 and st["sequence_gaps"] == 0


def test_gap_is_filled_with_zeros_and_marked():
    with SerialWhiskerDriver("loop://", 1000, 3) as drv:
        drv._ser.write(frames_bytes([65533, 65534]) + frames_bytes([2, 3], value=7))
        blocks = read_all(drv, 4 * 7)
        data, filled = joined(blocks)
        # 65535, 0 and 1 lost across the wrap: 3 frames x 4 rows of zeros.
        assert filled.tolist() == [False] * 8 + [True] * 12 + [False] * 8
        assert np.all(data[filled] == 0) and np.all(data[20:] == np.float32(7 / 32768))
        st = drv.stats()
        assert (st["sequence_gaps"], st["frames_lost"]) == (1, 3)
        assert (st["filled"], st["frames"]) == (12, 28)
        assert sum(b.n_filled for b in blocks) == 12


def test_channel_mismatch_is_skipped_counted_and_explained():
    with SerialWhiskerDriver("loop://", 1000, 3) as drv:
        drv._ser.write(frames_bytes([0], 3) + frames_bytes([1], channels=5) + frames_bytes([2], 3))
        blocks = read_all(drv, 12)
        data, filled = joined(blocks)
        st = drv.stats()
        assert st["channel_mismatch"] == 1 and st["frames_ok"] == 2
        assert filled.tolist() == [False] * 4 + [True] * 4 + [False] * 4
        assert np.all(data[filled] == 0)
        assert any("5 channels" in e and "configured for 3" in e for e in drv.events)


def test_device_overrun_flag_is_counted():
    with SerialWhiskerDriver("loop://", 1000, 3) as drv:
        drv._ser.write(frames_bytes([0]) + frames_bytes([1], flags=FLAG_OVERRUN))
        read_all(drv, 8)
        assert drv.stats()["device_overruns"] == 1


def test_restart_of_the_board_is_a_discontinuity_not_a_fill():
    # 40000 frames (160 s) cannot have passed between two frames read together.
    with SerialWhiskerDriver("loop://", 1000, 3) as drv:
        drv._ser.write(frames_bytes([5, 6, 40000, 40001]))
        blocks = read_all(drv, 16)
        data, filled = joined(blocks)
        assert len(data) == 16 and not filled.any()
        st = drv.stats()
        assert st["discontinuities"] == 1 and st["filled"] == 0 and st["frames_lost"] == 0
        assert any("restarted" in e for e in drv.events)


def test_gap_longer_than_max_gap_is_not_filled():
    with SerialWhiskerDriver("loop://", 1000, 3, max_gap=0.01) as drv:
        drv._ser.write(frames_bytes([0, 1, 5]))  # 3 lost frames = 12 ms > 10 ms
        read_all(drv, 12)
        assert drv.stats()["discontinuities"] == 1
        assert any("max_gap" in e for e in drv.events)


def test_missing_port_names_the_port_and_the_fix(tmp_path):
    path = str(tmp_path / "ttyNOPE")
    drv = SerialWhiskerDriver(path, 5000, 20)
    with pytest.raises(DeviceUnavailable) as info:
        drv.open()
    assert path in str(info.value) and "ls /dev/ttyACM*" in str(info.value)


def test_bad_arguments():
    with pytest.raises(ValueError):
        SerialWhiskerDriver("loop://", 1000, 0)
    with pytest.raises(ValueError):
        SerialWhiskerDriver("loop://", 0, 3)


# -- a port that sends no valid frame ---------------------------------------------------


def read_until_notices(drv, notices, n, max_reads=200):
    """Read (0.02 s each) until ``n`` notices came; the blocks read meanwhile."""
    blocks = []
    for _ in range(max_reads):
        if len(notices) >= n:
            break
        b = drv.read(0.02)
        if b is not None:
            blocks.append(b)
    return blocks


def test_silent_port_warns_and_keeps_warning_with_a_count():
    notices = []
    with SerialWhiskerDriver("loop://", 1000, 3, silence_warning=0.1, on_notice=notices.append) as drv:
        assert read_until_notices(drv, notices, 3) == []
        assert len(notices) == 3 and drv.stats()["silence_warnings"] == 3
        first, third = notices[0], notices[2]
        assert "'loop://'" in first and "since the port opened" in first and "(notice 1)" in first
        assert "no byte at all" in first and "not streaming" in first and "by-id" in first
        assert "notice 3, every 0.1 s" in third
        assert float(third.split("no valid frame for ")[1].split(" s")[0]) >= 0.3
        assert all(any(m in e for e in drv.events) for m in notices)
        # Frames end the silence; a new one counts from the last frame, notices from 1 again.
        drv._ser.write(frames_bytes([0, 1]))
        blocks = read_until_notices(drv, notices, 4)
        assert sum(b.frames for b in blocks) == 8
        assert "since the last frame" in notices[3] and "(notice 1)" in notices[3]
        assert drv.stats()["silence_warnings"] == 4


def test_bytes_without_a_valid_frame_point_at_the_baud_rate():
    notices = []
    with SerialWhiskerDriver("loop://", 1000, 3, silence_warning=0.1, on_notice=notices.append) as drv:
        bad = bytearray(frames_bytes([7]))
        bad[20] ^= 0xFF  # CRC fails
        noise = np.random.default_rng(0).integers(0, 256, 500, dtype=np.uint8).tobytes()
        drv._ser.write(noise + bytes(bad) + noise)
        read_until_notices(drv, notices, 1)
        st = drv.stats()
    assert st["bytes_read"] == len(noise) * 2 + len(bad) and st["frames_ok"] == 0
    assert f"{st['bytes_read']} bytes arrived but no valid frame" in notices[0]
    assert "1 CRC errors" in notices[0] and "wrong baud rate" in notices[0]


def test_frames_of_the_wrong_channel_count_only_are_a_silence_explained():
    notices = []
    with SerialWhiskerDriver("loop://", 1000, 3, silence_warning=0.1, on_notice=notices.append) as drv:
        drv._ser.write(frames_bytes([0, 1, 2], channels=5))
        assert read_until_notices(drv, notices, 1) == []
    assert "3 frame(s) arrived" in notices[0] and "other than the 3 configured" in notices[0]


def test_silence_warning_off_and_refused_values():
    notices = []
    with SerialWhiskerDriver("loop://", 1000, 3, silence_warning=None, on_notice=notices.append) as drv:
        for _ in range(10):
            drv.read(0.02)
        assert notices == [] and drv.stats()["silence_warnings"] == 0
    for bad in (0, -1.0):
        with pytest.raises(InputError, match="silence_warning"):
            SerialWhiskerDriver("loop://", 1000, 3, silence_warning=bad)


def test_node_prints_the_silence_notice_and_counts_it(capsys):
    from supramodal.node.runtime.graph import Node
    from supramodal.banks import whisker_bank
    from supramodal.pipeline import FeaturePipeline

    drv = SerialWhiskerDriver("loop://", 5000, 1, silence_warning=0.1)  # default: notices on stderr
    node = Node(drv, FeaturePipeline(whisker_bank(), ("Af",)), [])
    stopper = threading.Thread(target=lambda: (time.sleep(0.5), node.stop("test")))
    stopper.start()
    summary = node.run()
    stopper.join()
    err = capsys.readouterr().err
    assert summary["driver"]["silence_warnings"] >= 2
    assert err.count("no valid frame for") == summary["driver"]["silence_warnings"]
    assert "no byte at all" in err


@pytest.mark.parametrize("kind", ["file", "devnull", "directory"])
def test_a_path_that_is_not_a_serial_device_is_refused_as_such(tmp_path, kind):
    path = {"file": tmp_path / "capture.bin", "devnull": "/dev/null", "directory": tmp_path}[kind]
    if kind == "file":
        path.write_bytes(frames_bytes([0, 1]))
    drv = SerialWhiskerDriver(str(path), 5000, 20)
    with pytest.raises(DeviceUnavailable) as info:
        drv.open()
    text = str(info.value)
    assert f"{str(path)!r} is not a serial device" in text
    assert {"file": "regular file", "devnull": "not a terminal", "directory": "directory"}[kind] in text
    assert "/dev/ttyACM0" in text and "cable" not in text


@pytest.mark.hardware
def test_pty_board_that_never_streams_is_reported():
    notices = []
    with MockWhiskerDevice(np.zeros((64, CHANNELS)), RATE) as dev, \
            SerialWhiskerDriver(dev.port, RATE, CHANNELS, silence_warning=0.2,
                                on_notice=notices.append) as drv:
        # dev.start() never called: the port opens and nothing comes.
        assert read_until_notices(drv, notices, 2) == []
    assert "no byte at all" in notices[0] and "notice 2" in notices[1]
    assert drv.stats()["silence_warnings"] == 2


# -- link loss on a scripted port ------------------------------------------------------


class FakeLink:
    """Stands in for ``serial.serial_for_url``: a byte queue that can be unplugged."""

    def __init__(self):
        self.data = bytearray()
        self.present = True
        self.generation = 0
        self.opens = 0

    def unplug(self):
        self.present = False
        self.generation += 1
        self.data.clear()

    def __call__(self, url, **kwargs):
        return FakePort(self, url, kwargs.get("timeout"))


class FakePort:
    def __init__(self, link, url, timeout):
        self.link, self.url, self.timeout = link, url, timeout
        self.generation = link.generation

    def open(self):
        self.link.opens += 1
        if not self.link.present:
            raise serial.SerialException(
                errno.ENOENT,
                f"could not open port {self.url}: [Errno 2] No such file or directory")

    def _check(self, exc):
        if self.generation != self.link.generation:
            raise exc

    @property
    def in_waiting(self):
        self._check(OSError(errno.EIO, "Input/output error"))
        return len(self.link.data)

    def read(self, size):
        self._check(serial.SerialException("device reports readiness to read but returned "
                                           "no data (device disconnected or multiple access "
                                           "on port?)"))
        if not self.link.data:
            time.sleep(min(self.timeout or 0, 0.01))
            return b""
        out = bytes(self.link.data[:size])
        del self.link.data[:size]
        return out

    def close(self):
        pass


def test_a_byte_read_just_before_the_link_went_down_is_counted(monkeypatch):
    """The port hands over its first byte, then dies before the rest: the byte is kept and counted among the
    bytes read and skipped (a soak's ledger of skipped bytes was one byte ahead of the driver's), and the loss is
    reported on the next read."""
    link = FakeLink()
    monkeypatch.setattr(serial, "serial_for_url", link)
    with SerialWhiskerDriver("/dev/ttyFAKE", 1000, 3) as drv:
        link.data += frames_bytes([10, 11])
        assert len(joined(read_all(drv, 8))[0]) == 8
        before = drv.stats()
        port = drv._ser

        def read_then_die(size):
            # nothing was waiting, so the driver waits for a first byte: it comes, and the port is gone
            # before the rest (the next in_waiting fails)
            assert size == 1
            link.unplug()
            return b"\x07"

        monkeypatch.setattr(port, "read", read_then_die)
        assert drv.read(0.1) is None
        st = drv.stats()
        assert st["bytes_read"] == before["bytes_read"] + 1
        assert st["bytes_skipped"] == before["bytes_skipped"] + 1      # the half frame dropped at the reset
        assert st["unplugs"] == 1


def test_unplug_reopens_with_backoff_and_fills_the_gap(monkeypatch):
    link = FakeLink()
    monkeypatch.setattr(serial, "serial_for_url", link)
    with SerialWhiskerDriver("/dev/ttyFAKE", 1000, 3) as drv:
        link.data += frames_bytes([10, 11])
        assert len(joined(read_all(drv, 8))[0]) == 8
        link.unplug()
        # Unplugged: read() returns None within its timeout and keeps trying.
        assert drv.read(0.1) is None
        assert drv.stats()["unplugs"] == 1 and drv.stats()["reconnects"] == 0
        opens = link.opens
        assert drv.read(0.3) is None
        assert link.opens > opens  # retried with backoff
        link.present = True
        link.data += frames_bytes([13, 14])  # 12 was lost while unplugged
        _, filled = joined(read_all(drv, 12))
        assert filled.tolist() == [True] * 4 + [False] * 8
        st = drv.stats()
        assert (st["unplugs"], st["reconnects"], st["frames_lost"]) == (1, 1, 1)
        text = "\n".join(drv.events)
        assert "lost /dev/ttyFAKE" in text and "reconnected" in text and "not found" in text


def test_port_that_dies_before_sending_is_a_failed_attempt_not_an_unplug(monkeypatch):
    link = FakeLink()
    monkeypatch.setattr(serial, "serial_for_url", link)
    with SerialWhiskerDriver("/dev/ttyFAKE", 1000, 3) as drv:
        link.data += frames_bytes([0])
        read_all(drv, 4)
        link.unplug()
        link.present = True  # the node is still there ...
        drv.read(0.15)  # ... reopened,
        link.generation += 1  # ... and it dies again before a byte came.
        drv.read(0.15)
        st = drv.stats()
        assert st["unplugs"] == 1 and st["reconnects"] == 0


def test_without_reconnect_an_unplug_raises_then_closes(monkeypatch):
    link = FakeLink()
    monkeypatch.setattr(serial, "serial_for_url", link)
    drv = SerialWhiskerDriver("/dev/ttyFAKE", 1000, 3, reconnect=False)
    drv.open()
    link.unplug()
    with pytest.raises(DeviceUnavailable, match="ttyFAKE"):
        drv.read(0.1)
    with pytest.raises(DriverClosed):
        drv.read(0.1)


# -- the mock board on a real pty --------------------------------------------------------

RATE, CHANNELS, SPF = 5000.0, 20, 32


def source(seconds, seed=0):
    rng = np.random.default_rng(seed)
    n = int(seconds * RATE)
    t = np.arange(n)[:, None] / RATE
    x = 0.6 * np.sin(2 * np.pi * (40 + 13 * np.arange(CHANNELS)) * t) + rng.normal(0, 0.1, (n, 20))
    x[::97, 0] = 1.5  # clipped to +32767
    x[::89, 1] = -1.5  # clipped to -32768
    return x


def stream(dev, drv, n):
    """Read until every row of the source arrived, or the mock finished and the
    port stayed idle for 2 s (frames lost at the end never arrive)."""
    blocks, idle, rows = [], 0, 0
    dev.start()
    for _ in range(4000):  # about 400 s at most, only if something hangs
        if drv.first_sequence is not None:
            offset = ((drv.first_sequence - dev.first_seq) % 65536) * dev.samples_per_frame
            if rows >= n - offset:
                break
        b = drv.read(0.1)
        if b is None:
            idle = idle + 1 if dev.finished.is_set() else 0
            if idle >= 20:
                break
            continue
        idle = 0
        blocks.append(b)
        rows += b.frames
    return blocks


def check_against_ledger(blocks, dev, drv, src):
    """Measured rows bit-exact at their place, filled rows zero, and filled frames
    exactly the frames the ledger says were lost between the first and last frames
    the driver received. Returns (filled frame indices, those lost frames, ledger)."""
    assert dev.error is None
    led = dev.ledger
    assert_tiled(blocks, CHANNELS)
    data, filled = joined(blocks)
    offset = ((drv.first_sequence - dev.first_seq) % 65536) * SPF
    q = quantise(src)[offset:offset + len(data)]
    assert len(q) == len(data)
    np.testing.assert_array_equal((data[~filled] * 32768).astype(np.int16), q[~filled])
    assert np.all(data[filled] == 0)
    filled_frames = set((offset + np.flatnonzero(filled)) // SPF)
    k_first, k_last = offset // SPF, (offset + len(data) - 1) // SPF
    st = drv.stats()
    assert st["frames"] == len(data) and st["filled"] == int(filled.sum())
    assert st["discontinuities"] == 0
    return filled_frames, {k: v for k, v in led.lost.items() if k_first < k < k_last}, led


@pytest.mark.hardware
def test_pty_end_to_end_bit_exact_across_the_sequence_wrap():
    src = source(1.5)
    with MockWhiskerDevice(src, RATE, samples_per_frame=SPF, first_seq=65500) as dev, \
            SerialWhiskerDriver(dev.port, RATE, CHANNELS) as drv:
        blocks = stream(dev, drv, len(src))
        filled_frames, lost, led = check_against_ledger(blocks, dev, drv, src)
        st = drv.stats()
    assert filled_frames == set(lost)  # empty unless the machine stalled the reader
    assert set(lost.values()) <= {"overflow"}
    assert st["crc_errors"] == st["truncated"] == st["header_errors"] == st["channel_mismatch"] == 0
    assert st["bytes_skipped"] == 0 and st["unplugs"] == 0
    if not led.lost:
        assert st["frames"] == len(src) and st["frames_ok"] == dev.n_frames
        assert drv.first_sequence == 65500


@pytest.mark.hardware
def test_pty_every_injected_fault_is_accounted_for():
    src = source(2.0, seed=1)
    faults = FaultSpec(garbage_rate=0.1, drop_rate=0.06, crc_rate=0.06, omit_rate=0.04,
                       channels_rate=0.04, version_rate=0.04)
    with MockWhiskerDevice(src, RATE, samples_per_frame=SPF, faults=faults, seed=7,
                           first_seq=65400) as dev, \
            SerialWhiskerDriver(dev.port, RATE, CHANNELS) as drv:
        blocks = stream(dev, drv, len(src))
        filled_frames, lost, led = check_against_ledger(blocks, dev, drv, src)
        st = drv.stats()
    assert led.crc > 5 and led.truncated > 5 and led.garbage > 10  # the schedule did inject
    assert min(led.omitted, led.wrong_channels, led.wrong_version) > 3
    assert st["crc_errors"] == led.crc
    assert st["truncated"] == led.truncated
    assert st["channel_mismatch"] == led.wrong_channels
    assert st["header_errors"] >= led.wrong_version  # and sync words by chance in skipped bytes
    assert st["bytes_skipped"] == led.garbage_bytes + led.damaged_bytes
    assert filled_frames == set(lost)
    assert {k for k, v in led.lost.items() if v != "overflow"} <= set(lost)
    assert st["frames_lost"] == len(lost)
    assert st["filled"] == SPF * len(lost)
    assert st["frames_ok"] == led.sent


@pytest.mark.hardware
def test_pty_reader_stall_overflow_is_filled_not_a_discontinuity():
    src = source(2.5, seed=2)
    with MockWhiskerDevice(src, RATE, samples_per_frame=SPF) as dev, \
            SerialWhiskerDriver(dev.port, RATE, CHANNELS) as drv:
        dev.start()
        blocks = []
        for _ in range(600):
            if sum(b.frames for b in blocks) >= 2500:
                break
            b = drv.read(0.5)
            if b is not None:
                blocks.append(b)
        time.sleep(1.0)  # the node stalls; the pty (~22 kB, ~0.1 s) overflows
        rest = stream(dev, drv, len(src) - sum(b.frames for b in blocks))
        blocks += rest
        filled_frames, lost, led = check_against_ledger(blocks, dev, drv, src)
    assert led.overflow > 0 and lost
    assert filled_frames == set(lost) and set(lost.values()) == {"overflow"}
    # Frames the pty lost after the last frame the driver read leave no gap it could see (a loaded
    # machine can overflow the pty again near the end): the driver counts those between its first
    # and last frames, every one of them.
    assert drv.stats()["frames_lost"] == len(lost)


@pytest.mark.hardware
def test_pty_unplug_replug_same_path_resumes_and_fills_the_gap():
    src = source(2.8, seed=3)
    faults = FaultSpec(unplug_every=0.8, unplug_for=0.3)
    with MockWhiskerDevice(src, RATE, samples_per_frame=SPF, faults=faults, seed=1) as dev, \
            SerialWhiskerDriver(dev.port, RATE, CHANNELS) as drv:
        blocks = stream(dev, drv, len(src))
        filled_frames, lost, led = check_against_ledger(blocks, dev, drv, src)
        st = drv.stats()
        events = "\n".join(drv.events)
    assert led.unplugs == 2 and len(led.unplug_at) == 2
    assert st["unplugs"] == 2 and st["reconnects"] == 2, events
    # Exactly the frames the ledger lost are filled: those produced while unplugged (or
    # before the driver reopened), those left in the port when it went, and any overflow.
    assert filled_frames == set(lost)
    assert {v for v in lost.values()} <= {"unplugged", "unplug", "overflow"}
    assert st["frames_lost"] == len(lost) and st["bytes_skipped"] == led.cut_bytes
    assert led.unplugs_forced == 0
    assert events.count("reconnected to") == 2


@pytest.mark.hardware
def test_pty_frames_left_in_the_port_at_an_unplug_are_in_the_ledger():
    """The reader stalls across an unplug: what sat in the pty is lost with it, and the ledger
    knows exactly which frames (and how many bytes of a frame the reader had) were lost."""
    src = source(2.5, seed=6)
    faults = FaultSpec(unplug_every=1.0, unplug_for=0.2, unplug_limit=1)
    with MockWhiskerDevice(src, RATE, samples_per_frame=SPF, faults=faults, seed=2) as dev, \
            SerialWhiskerDriver(dev.port, RATE, CHANNELS) as drv:
        dev.start()
        blocks = read_all(drv, 1000, timeout=0.5, max_reads=600)
        assert dev.ledger.unplugs == 0  # the stall below begins well before the unplug
        for _ in range(300):  # the node stalls until the board is unplugged
            if dev.ledger.unplugs:
                break
            time.sleep(0.01)
        blocks += stream(dev, drv, len(src) - sum(b.frames for b in blocks))
        filled_frames, lost, led = check_against_ledger(blocks, dev, drv, src)
        st = drv.stats()
    assert led.unplugs == 1 and led.unplugs_forced == 0
    assert led.unplug_lost > 0 and "unplug" in lost.values()
    assert filled_frames == set(lost) and st["frames_lost"] == len(lost)
    assert st["bytes_skipped"] == led.cut_bytes  # the head of a frame whose tail was lost


@pytest.mark.hardware
def test_mock_never_blocks_when_nobody_reads(tmp_path, capsys):
    rate = 5000
    x = (np.random.default_rng(4).normal(0, 3000, (int(0.4 * rate), 1))).astype(np.int16)
    wav = tmp_path / "mono.wav"
    wavfile.write(wav, rate, x)
    port = str(tmp_path / "whisker0")
    result = {}
    t = threading.Thread(target=lambda: result.setdefault(
        "rc", main([str(wav), "--channels", "20", "--port", port, "--linger", "0",
                    "--garbage-rate", "0.1", "--seed", "3"])))
    t.start()
    t.join(60)
    assert not t.is_alive(), "the mock blocked with no reader"
    assert result["rc"] == 0
    out, err = capsys.readouterr()
    assert out.strip() == port
    assert "overflow" in err
    assert int(err.split("overflow ")[1].split(",")[0]) > 0  # 80 kB into a ~22 kB pty


@pytest.mark.hardware
def test_mock_unplugs_again_when_no_reader_reopens_the_port():
    """A replugged board waits for a reader to open the port; when none does before its next
    unplug, it unplugs anyway and replugs later, its writer thread alive (it once read the status
    of the pty it had just closed: a TypeError)."""
    src = source(0.5, seed=7)
    faults = FaultSpec(unplug_every=0.1, unplug_for=0.05)
    with MockWhiskerDevice(src, RATE, samples_per_frame=SPF, loop=True, faults=faults, seed=1) as dev:
        dev.start()
        deadline = time.monotonic() + 20.0
        while dev.ledger.unplugs < 3 and not dev.finished.is_set() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert dev.error is None
        assert dev.ledger.unplugs >= 3 and len(dev.ledger.replug_times) >= 2


# -- the CLI pieces -------------------------------------------------------


def test_cli_refuses_fanning_out_a_multichannel_source(tmp_path, capsys):
    path = tmp_path / "s.wav"
    wavfile.write(path, 5000, np.zeros((10, 2), np.int16))
    assert main([str(path), "--channels", "20"]) == 2
    assert "fans out mono" in capsys.readouterr().err


def test_fault_spec_validation():
    with pytest.raises(ValueError):
        FaultSpec(crc_rate=1.5)
    with pytest.raises(ValueError):
        FaultSpec(drop_rate=0.6, crc_rate=0.6)
    with pytest.raises(ValueError, match="at most one fault"):
        FaultSpec(omit_rate=0.5, channels_rate=0.3, version_rate=0.3)


@pytest.mark.hardware
def test_second_reader_is_refused_with_a_clear_message():
    with MockWhiskerDevice(np.zeros((64, 2)), 1000) as dev, \
            SerialWhiskerDriver(dev.port, 1000, 2):
        with pytest.raises(DeviceUnavailable, match="in use by another program"):
            SerialWhiskerDriver(dev.port, 1000, 2).open()


@pytest.mark.hardware
def test_pty_loop_mode_replays_the_source():
    src = source(0.05, seed=5)  # 250 rows: not a multiple of 32, so frames straddle the end
    with MockWhiskerDevice(src, RATE, samples_per_frame=SPF, loop=True) as dev, \
            SerialWhiskerDriver(dev.port, RATE, CHANNELS) as drv:
        dev.start()
        blocks = read_all(drv, 4 * len(src), timeout=1.0, max_reads=2000)
        dev.close()
        assert dev.error is None and not dev.finished.is_set()
    data, filled = joined(blocks)
    offset = ((drv.first_sequence - dev.first_seq) % 65536) * SPF
    expect = np.tile(quantise(src), (8, 1))[offset:offset + len(data)]
    np.testing.assert_array_equal((data[~filled] * 32768).astype(np.int16), expect[~filled])
