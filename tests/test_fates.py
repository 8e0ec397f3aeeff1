"""Every frame of the stream has one fate in the node's summary: delivered, filled or dropped.

``delivered + filled + dropped == stream`` must hold exactly, whatever the thread timing: under
gap fills longer than the ring, a fast source overrunning it (either drop policy), a stream cut
mid-block, and the microphone's own losses. The filled count must equal what the driver
synthesised, and fills the ring drops must never be reported as real data lost (issue 14, item 2;
docs/node.md, "Every frame has one fate"). The same under every fault kind of the mock board, and
an unplug longer than the ring, on a real pty: tests/test_hil_serial.py.
"""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

from supramodal.drivers.base import Block, DriverClosed
from supramodal.drivers.microphone import CaptureBuffer, MicrophoneDriver
from supramodal.node.runtime.graph import Node
from supramodal.node.runtime.sinks import ListSink
from supramodal.node.runtime.sinks.text import TextSink
from supramodal.banks import whisker_bank
from supramodal.pipeline import FeaturePipeline

from stand_ins import StandInDriver

RATE = 5000


def assert_one_fate(f: dict) -> None:
    """The identity, and the parts of ``dropped`` adding up."""
    assert f["delivered"] + f["filled"] + f["dropped"] == f["stream"], f
    assert f["dropped"] == f["dropped_in_ring"] + f["dropped_by_driver"], f
    assert min(f.values()) >= 0, f


class ScriptDriver(StandInDriver):
    """A live driver playing a script of blocks ``(frames, filled)`` as fast as it is asked.

    ``filled`` is False (measured), True (all synthesised) or a bool mask. With ``wait_for``
    set to a node, each read waits until the node's processing has read everything before,
    so that the only ring losses are those a single write longer than the ring makes: the
    counts are then exact, not merely consistent.
    """

    def __init__(self, script, channels: int = 1, seed: int = 0):
        self.rate, self.channels = float(RATE), channels
        self._script = list(script)
        self._rng = np.random.default_rng(seed)
        self._i = self._pos = 0
        self.wait_for: Node | None = None
        self.synthesised = self.measured = 0

    def stats(self):
        return {"frames": self._pos, "filled": self.synthesised}

    def read(self, timeout=None):
        if self._i >= len(self._script):
            raise DriverClosed("end of the script")
        if self.wait_for is not None:
            reader = self.wait_for.streams[0].feed.reader
            while reader.available:
                time.sleep(0.001)
        n, filled = self._script[self._i]
        self._i += 1
        mask = np.full(n, filled, bool) if isinstance(filled, bool) else np.asarray(filled, bool)
        data = self._rng.uniform(-0.1, 0.1, (n, self.channels))
        data[mask] = 0.0
        block = Block(data, self._pos, time.monotonic(), mask if mask.any() else None)
        self._pos += n
        self.synthesised += int(mask.sum())
        self.measured += int((~mask).sum())
        return block


def _node(driver, buffer_seconds, overrun="drop-oldest", sinks=()):
    sink = ListSink()
    node = Node(driver, FeaturePipeline(whisker_bank(), ("A",)), [sink, *sinks],
                mapping="mean" if driver.channels > 1 else "auto",
                buffer_seconds=buffer_seconds, overrun=overrun)
    return node, sink


def test_a_fill_longer_than_the_ring_stays_filled_and_drops_nothing(tmp_path):
    """The issue's unplug: a 4.5 s outage filled as one block (with the first frames after it)
    through a 2 s ring. The ring drops the block's oldest rows, zeros the driver synthesised:
    they stay filled; no real sample was lost, and the text summary line shows the identity."""
    cap = 2 * RATE
    fill, after = int(4.5 * RATE), 160
    mask = np.r_[np.zeros(0, bool), np.ones(fill, bool), np.zeros(after, bool)]
    script = [(50, False)] * 40 + [(fill + after, mask)] + [(50, False)] * 40
    driver = ScriptDriver(script)
    text_path = tmp_path / "out.txt"
    text = TextSink(str(text_path))
    node, sink = _node(driver, buffer_seconds=2.0, sinks=[text])
    driver.wait_for = node
    node.run()
    f = sink.final["frames"]
    assert_one_fate(f)
    assert f["stream"] == 80 * 50 + fill + after
    assert f["filled"] == fill == driver.synthesised       # the driver's count, not more
    assert f["dropped"] == 0                                 # no measured row was lost
    assert f["filled_lost_in_ring"] == fill + after - cap    # the head of the one block
    assert f["delivered"] == driver.measured
    line = f"frames             {f['stream']} = delivered {f['delivered']} + filled {fill} + dropped 0"
    assert line in text_path.read_text()


@pytest.mark.parametrize("overrun", ["drop-oldest", "drop-newest"])
def test_a_fast_source_overrunning_the_ring_counts_each_frame_once(overrun):
    """Random blocks up to 4x the ring, some filled in part, as fast as the driver thread can
    write them: measured rows lost in the ring are dropped, filled ones stay filled, and the
    node's zeros in their place are not counted again. Exact whatever the thread timing."""
    rng = np.random.default_rng(5)
    cap = 250                                     # 0.05 s at 5 kHz
    script = []
    for _ in range(300):
        n = int(rng.integers(1, 4 * cap))
        kind = rng.integers(3)
        filled = False if kind == 0 else True if kind == 1 else rng.random(n) < 0.3
        script.append((n, filled))
    script.append((3 * cap, False))              # a measured block longer than the ring: always loses rows
    driver = ScriptDriver(script, channels=2, seed=1)
    node, sink = _node(driver, buffer_seconds=cap / RATE, overrun=overrun)
    node.run()
    f = sink.final["frames"]
    assert_one_fate(f)
    assert f["stream"] == driver.synthesised + driver.measured
    assert f["filled"] == driver.synthesised     # every synthesised row, lost in the ring or not
    assert f["delivered"] + f["dropped"] == driver.measured
    assert f["dropped"] == f["dropped_in_ring"] >= 2 * cap and f["dropped_by_driver"] == 0
    ring = sink.final["ring"]
    assert (ring["written"], ring["filled"]) == (f["stream"], f["filled"])


def test_the_identity_holds_on_a_stream_cut_mid_block():
    """``run(max_seconds)`` cuts the block that crosses the end: only its head is in the stream,
    and only the head's filled rows are counted (not the driver's whole count)."""
    script = [(700, False), (700, True), (700, np.arange(700) % 2 == 0)] * 10
    driver = ScriptDriver(script)
    node, sink = _node(driver, buffer_seconds=2.0, overrun="block")
    node.run(max_seconds=1.0)                   # 5000 frames: 7 blocks and 100 rows of the 8th
    f = sink.final["frames"]
    assert_one_fate(f)
    assert f["stream"] == 5000
    # blocks measured, filled, half, measured, filled, half, measured, then 100 filled rows
    assert f["filled"] == 700 + 350 + 700 + 350 + 100 and f["dropped"] == 0
    assert driver.synthesised > f["filled"]      # the driver made more than the stream kept


class FastMicrophone(MicrophoneDriver):
    """The microphone driver on a stand-in for PortAudio that delivered everything at once:
    ``blocks`` callbacks of ``blocksize`` frames before the node reads anything, every
    ``overflow_every``-th flagged as an input overflow with a timestamp jump of ``jump``
    frames. The capture buffer holds ``buffer_seconds``; what exceeds it is dropped."""

    def __init__(self, blocks, blocksize, overflow_every, jump, **kw):
        super().__init__(rate=RATE, channels=1, blocksize=blocksize, **kw)
        self._plan = (blocks, blocksize, overflow_every, jump)

    def open(self):
        blocks, bs, every, jump = self._plan
        self._buffer = buf = CaptureBuffer(self.rate, self.channels, self._capacity, gap_block=bs)
        self._stream = SimpleNamespace(active=True, stop=lambda ignore_errors=True: None,
                                       close=lambda ignore_errors=True: None)
        self._closed = False
        rng = np.random.default_rng(3)
        t = 1.0
        for k in range(blocks):
            overflow = k % every == every - 1
            if overflow:
                t += jump / self.rate            # PortAudio lost `jump` frames before this block
            data = rng.uniform(-0.1, 0.1, (bs, 1)).astype(np.float32)
            buf.callback(data, bs, SimpleNamespace(inputBufferAdcTime=t),
                         SimpleNamespace(input_overflow=overflow))
            t += bs / self.rate
        buf.end()


def test_microphone_overflows_and_a_full_buffer_are_dropped_not_filled():
    """The microphone fills only for audio the host lost (input overflows, a full capture
    buffer): those frames are dropped, by the driver; its blocks longer than the node's ring
    also lose measured rows there. Nothing is filled, and nothing is counted twice (before,
    the driver's dropped frames were counted as dropped and again as filled)."""
    mic = FastMicrophone(blocks=400, blocksize=441, overflow_every=7, jump=300, buffer_seconds=1.0)
    node, sink = _node(mic, buffer_seconds=0.05)  # 250 frames: every 441-frame block loses rows
    node.run()
    f, drv = sink.final["frames"], sink.final["driver"]
    assert_one_fate(f)
    assert drv["dropped"] > 0 and drv["lost"] > 0      # both of the microphone's losses happened
    assert f["filled"] == 0
    assert f["dropped_by_driver"] == drv["filled"] == drv["dropped"] + drv["lost"]
    assert f["stream"] == drv["frames"] == drv["captured"] + drv["lost"]
    assert f["delivered"] + f["dropped_in_ring"] == drv["captured"] - drv["dropped"]
    assert f["dropped_in_ring"] >= (441 - 250) * (drv["captured"] - drv["dropped"]) // 441
