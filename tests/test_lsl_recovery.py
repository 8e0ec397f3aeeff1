"""The LSL inlet against plain pylsl senders that misbehave as a lab's do (issue 26, items 8-10): a
sender with no source id killed and restarted; a sender that stamps at push time, holds 3 s and
flushes its backlog; two senders of one name.

Traffic stays on this machine (tests/harness/environment.py's loopback ``LSLAPICFG``, checked by every test). The
senders run in child processes (tests/lsl_senders.py)."""

import json
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from supramodal.drivers.base import DeviceUnavailable
from supramodal.drivers.lsl import LSLInletDriver

from lsl_only import loopback_only, require_lsl  # noqa: F401  (the fixture applies itself)

require_lsl()

SENDER = Path(__file__).with_name("lsl_senders.py")


def _sender(name: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(SENDER), "--name", name, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _end(proc: subprocess.Popen) -> None:
    proc.kill()
    proc.communicate(timeout=30)


def _read_for(driver, seconds: float, blocks: list) -> None:
    """Read for ``seconds`` of wall time, keeping the blocks (a read must never raise)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        b = driver.read(timeout=0.05)
        if b is not None:
            blocks.append(b)


def _read_until(driver, blocks: list, frames: int, limit: float) -> None:
    end = time.monotonic() + limit
    while sum(b.data.shape[0] for b in blocks) < frames and time.monotonic() < end:
        b = driver.read(timeout=0.05)
        if b is not None:
            blocks.append(b)


@pytest.mark.slow   # paced real time: a sender killed and started again
def test_a_sender_without_a_source_id_killed_and_restarted_is_found_again(tmp_path):
    """Issue 26 item 8: liblsl cannot recover a stream without a source id; its inlet raised
    ``the stream has been lost`` and the node stopped (exit 2). Now the driver says ``unplug``,
    searches by name, type and host, and reads the restarted sender (``reopened``, ``reconnect``),
    its outage filled and counted."""
    name = f"nosid-{uuid.uuid4().hex[:8]}"
    first = _sender(name, "--channels", "2", "--seconds", "60")
    second = None
    driver = LSLInletDriver(name, resolve_timeout=30.0, channels=2)
    assert driver._stream.source_id() == ""
    blocks: list = []
    try:
        driver.open()
        _read_until(driver, blocks, 5000, 30.0)               # 1 s of samples
        assert sum(b.data.shape[0] for b in blocks) >= 5000
        _end(first)
        _read_for(driver, 1.5, blocks)                         # gone: never an exception
        assert "unplug" in [e.kind for e in driver.take_events()[0]]
        second = _sender(name, "--channels", "2", "--seconds", "60")
        before = sum(b.data.shape[0] for b in blocks)
        _read_until(driver, blocks, before + 5000, 60.0)       # 1 s of the new sender's samples
        stats = driver.stats()
        assert sum(b.data.shape[0] for b in blocks) >= before + 5000, stats
        assert stats["reopened"] == 1 and stats["stalls"] >= 1, stats
        assert "reconnect" in [e.kind for e in driver.take_events()[0]]
        # The outage is in the stamps (the new sender stamps at push time): filled and counted.
        filled = sum(int(b.filled.sum()) for b in blocks if b.filled is not None)
        assert filled == stats["filled"] and stats["gaps"] + stats["restarts"] >= 1, stats
    finally:
        driver.close()
        for p in (first, second):
            if p is not None:
                _end(p)


def test_two_streams_of_one_name_are_refused_with_the_list_of_what_was_found():
    """Issue 26 item 10: ``resolve_bypred(minimum=1)`` returns at the first answer, so the node took
    whichever of two streams of one name answered first. Now both are listed and refused."""
    from supramodal.drivers.lsl import resolve_stream

    name = f"twice-{uuid.uuid4().hex[:8]}"
    ids = [f"{k}-{uuid.uuid4().hex[:6]}" for k in ("left", "right")]
    senders = [_sender(name, "--channels", "1", "--source-id", i, "--seconds", "60") for i in ids]
    try:
        for i in ids:                                  # both up
            assert resolve_stream(source_id=i, timeout=30.0).name() == name
        with pytest.raises(DeviceUnavailable, match=rf"2 streams match name='{name}'") as refused:
            resolve_stream(name, timeout=10.0)
        assert all(f"source_id='{i}'" in str(refused.value) for i in ids)
        assert "name one by its source_id" in str(refused.value)
    finally:
        for p in senders:
            _end(p)


#: Windows (0.5 s of stream) before the clock model of an LSL source has settled on the sender's clock.
WARM_UP = 5


@pytest.mark.slow   # paced real time: 8 s of a sender that holds 3 s
# alone: its first windows' ends came 1.14 ms from the sender's clock (the bound is 1 ms) in a CI run, with the
# other paced group's processes (a JACK server in real-time scheduling among them) beside the sender
@pytest.mark.alone
def test_push_time_stamps_held_3_s_and_flushed_fill_nothing_and_keep_the_sender_clock(tmp_path):
    """Issue 26 item 9 (Done when): a sender that stamps each chunk when it pushes it, holds 3 s and
    then pushes its backlog at once. The gap was judged from two raw stamps: 15,001 samples filled
    though none was lost, 1,350 dropped in the ring, stream time 3.64 s ahead. Judged on the
    clock model: 0 filled, 0 dropped, every window's end within 1 ms of the sender's sample clock (less
    the push stamps' own constant lateness, bounded below 1 ms on its own)."""
    from supramodal.drivers.lsl import import_pylsl, lsl_clock_offset
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import scene_from_dict
    from supramodal.node.runtime.sinks import ListSink

    class Sink(ListSink):
        def start(self, epoch):
            self.epoch = epoch

    name = f"held-{uuid.uuid4().hex[:8]}"
    sender = _sender(name, "--stamp", "push", "--hold-at", "2.0", "--hold-for", "3.0", "--seconds", "30", "--wait")
    try:
        scene = scene_from_dict({"driver": {"type": "lsl", "stream": name, "mapping": "per-channel",
                                            "resolve_timeout": 30.0},
                                 "bank": {"kind": "whisker"}, "features": {"names": ["Af"]}})
        sink = Sink()
        summary = build_node(scene, sinks_override=[sink]).run(max_seconds=8.0)
        t0 = json.loads(sender.stdout.readline())["t0"]            # sample 0, sender's clock (LSL's)
    finally:
        _end(sender)
    offset = lsl_clock_offset(import_pylsl())                       # host time minus LSL time
    d = summary["driver"]
    assert d["filled"] == 0 and d["gaps"] == 0 and d["restarts"] == 0, d
    frames = summary["frames"]
    assert frames["dropped"] == 0 and frames["filled"] == 0, frames
    windows = sink.windows
    assert [w.window for w in windows] == list(range(80))
    # Window w ends at sample 500 (w + 1): on the sender's clock t0 + 500 (w + 1) / 5000.
    late = np.array([(sink.epoch + w.end) - (t0 + offset + 500 * (w.window + 1) / 5000.0) for w in windows])
    shown = " ".join(f"{x * 1e3:.2f}" for x in late)
    # A push stamp is taken after the chunk's last sample: one sample (0.2 ms) by design, plus the sender's
    # sleep overshoot, which grows with the machine's load (0.45 ms idle). That constant is the sender's, not
    # the node's (the stamps are all the node sees), so it is bounded on its own: later than the samples, and
    # by less than 1 ms. Around it, each window within 1 ms: the node keeps the sender's clock through the hold.
    constant = float(np.median(late))
    assert 0.0 < constant < 1e-3, shown
    # The first windows close before the clock model holds more than a few chunks' stamps: a first push that
    # came late (4.4 ms once on a loaded machine) dates them late, and they are sent before later stamps can
    # correct it. Within WARM_UP windows, 5 ms; from then on, through the hold and the flush, 1 ms.
    assert np.max(np.abs(late[:WARM_UP] - constant)) < 5e-3, shown
    assert np.max(np.abs(late[WARM_UP:] - constant)) < 1e-3, shown
