"""Hardware in the loop: the node on the serial driver against the mock board on a real pty.

Without faults, the decisions equal those of replaying the same file; with faults, every
fault the mock injected is accounted for in the driver's counters and the node's output, and
every frame of the stream has one fate in the node's summary (delivered, filled or dropped).
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from supramodal.drivers.mock_whisker import FaultSpec, MockWhiskerDevice, quantise
from supramodal.drivers.serial_whisker import SerialWhiskerDriver
from supramodal.node.runtime.graph import Node
from supramodal.node.runtime.sinks import ListSink
from supramodal.replay.driver import ReplayDriver
from supramodal.replay.wavio import write_wav
from supramodal.banks import whisker_bank
from supramodal.model import TextureModel
from supramodal.pipeline import FeaturePipeline, extract_features
from supramodal.textures import reference_texture_set

pytestmark = pytest.mark.hardware

RATE = 5000
SPF = 32          # samples per serial frame
W = 500           # samples per 100 ms window


@pytest.fixture(scope="module")
def signal_and_model():
    """4 s of three reference textures in turn (int16-exact), and a model of them."""
    ts = reference_texture_set("whisker")
    bank = whisker_bank()
    x = np.concatenate([ts.synthesize(i, duration=6.0)[-int(4 / 3 * RATE):] for i in range(3)])
    x = quantise(x[:, None])[:, 0] / 32768.0                       # what an int16 board sends
    values, labels = [], []
    for i in range(3):
        v = extract_features(ts.synthesize(i, duration=6.0)[: 4 * RATE], bank, ("Af",)).values
        values.append(v)
        labels.append(np.full(len(v), i))
    model = TextureModel.train(np.concatenate(values), np.concatenate(labels), ts.names[:3], bank, ("Af",), W,
                               epochs=200, seed=2)
    return x, model


def _run_serial(x, model, faults=FaultSpec(), seed=0, buffer_seconds=2.0):
    """Stream x from the mock board into a node; stop once the board has sent everything."""
    dev = MockWhiskerDevice(x[:, None], RATE, samples_per_frame=SPF, faults=faults, seed=seed)
    driver = SerialWhiskerDriver(dev.port, rate=RATE, channels=1, on_notice=None)
    sink = ListSink()
    node = Node(driver, FeaturePipeline(whisker_bank(), ("Af",)), [sink], model=model, overrun="drop-oldest",
                buffer_seconds=buffer_seconds)

    def board():
        time.sleep(0.3)                       # the node has opened the port by then
        dev.start()
        dev.finished.wait(60)
        time.sleep(0.5)                       # let the last frames through the pty
        node.stop("board finished")

    with dev:
        t = threading.Thread(target=board, daemon=True)
        t.start()
        summary = node.run()
        t.join(5)
        ledger = dev.ledger
    return sink, summary, driver, ledger


def _offline_decisions(x, model, offset):
    windows = extract_features(x[offset:], whisker_bank(), ("Af",))
    return [model.classes[k] for k in model.predict(windows.values)]


def test_serial_node_decides_as_replaying_the_same_file(tmp_path, signal_and_model):
    x, model = signal_and_model
    sink, summary, driver, ledger = _run_serial(x, model)
    assert ledger.sent == ledger.frames and summary["frames"]["dropped"] == summary["frames"]["filled"] == 0
    assert driver.stats()["crc_errors"] == 0 and driver.stats()["filled"] == 0
    # The stream starts at the first frame the driver received (normally frame 0).
    offset = (driver.first_sequence - dev_first_seq()) * SPF
    got = [e["predicted"] for e in sink.events]
    assert len(got) >= (len(x) - offset) // W - 1
    # The same file replayed through a node gives the same decisions, window for window.
    wav = tmp_path / "same.wav"
    write_wav(wav, x[offset:, None], RATE, dtype="int16")
    replay_sink = ListSink()
    Node(ReplayDriver(str(wav), speed="max", on_notice=None), FeaturePipeline(whisker_bank(), ("Af",)),
         [replay_sink], model=model, overrun="block").run()
    replayed = [e["predicted"] for e in replay_sink.events]
    assert got == replayed[: len(got)]
    assert got == _offline_decisions(x, model, offset)[: len(got)]
    assert not any(e.get("gap") for e in sink.events)


def dev_first_seq() -> int:
    return 0   # MockWhiskerDevice's default first sequence number


def test_every_injected_fault_is_accounted_for(signal_and_model):
    x, model = signal_and_model
    faults = FaultSpec(garbage_rate=0.05, drop_rate=0.03, crc_rate=0.03)
    sink, summary, driver, ledger = _run_serial(x, model, faults, seed=11)
    st = driver.stats()
    assert ledger.truncated > 0 and ledger.crc > 0 and ledger.garbage > 0
    assert st["crc_errors"] == ledger.crc
    assert st["truncated"] == ledger.truncated
    assert st["frames_lost"] == len(ledger.lost) == ledger.truncated + ledger.crc + ledger.overflow
    assert st["filled"] == SPF * len(ledger.lost) == summary["frames"]["filled"]
    assert st["bytes_skipped"] >= ledger.garbage_bytes
    # Every window touched by a lost frame, and only those, is flagged in the node's output.
    k0 = driver.first_sequence - dev_first_seq()
    touched = set()
    for k in ledger.lost:
        a, b = (k - k0) * SPF, (k - k0 + 1) * SPF
        touched.update(range(a // W, (b - 1) // W + 1))
    emitted = {e["window"] for e in sink.events}
    assert {e["window"] for e in sink.events if e.get("gap")} == touched & emitted
    assert summary["windows"] == len(sink.events) >= len(x) // W - 2


@pytest.mark.slow   # paced real time: the example scene on the mock board for 10 s
def test_the_serial_example_scene_decides_on_the_mock_board():
    """examples/whisker_serial.toml as shipped (its port pointed at the mock's pty): it trains its
    model at start-up on the reference textures and decides, per contact, the texture the
    board plays (synth:T3, fanned out to 20 whiskers)."""
    from pathlib import Path

    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import load_scene

    scene = load_scene(Path(__file__).resolve().parents[1] / "examples" / "whisker_serial.toml")
    ts = reference_texture_set("whisker")
    x = quantise(np.repeat(ts.synthesize(ts.names.index("T3"), duration=3.0)[:, None], 20, axis=1)) / 32768.0
    dev = MockWhiskerDevice(x, RATE, samples_per_frame=SPF)
    board = scene.only_source()
    scene = replace(scene, sources=(replace(board, options={**board.options, "port": dev.port}),))
    sink = ListSink()
    node = build_node(scene, sinks_override=[sink])

    def board():
        time.sleep(0.3)
        dev.start()
        dev.finished.wait(60)
        time.sleep(0.5)
        node.stop("board finished")

    with dev:
        t = threading.Thread(target=board, daemon=True)
        t.start()
        node.run()
        t.join(5)
    pooled = [e["accumulated"]["label"] for e in sink.events if e.get("accumulated")]
    assert len(sink.events) >= 25 and "predicted" in sink.events[0]
    assert pooled[-1] == "T3" and pooled.count("T3") >= 0.8 * len(pooled)


# -- every frame has one fate: each fault kind, and an outage longer than the ring ------------------

FAULTS = {
    "garbage": dict(garbage_rate=0.1),
    "drop bytes": dict(drop_rate=0.05),
    "crc": dict(crc_rate=0.05),
    "omit": dict(omit_rate=0.05),
    "wrong channels": dict(channels_rate=0.05),
    "wrong version": dict(version_rate=0.05),
    "unplugs": dict(unplug_every=0.6, unplug_for=0.3),
    "all": dict(garbage_rate=0.03, drop_rate=0.02, crc_rate=0.02, omit_rate=0.02, channels_rate=0.02,
                version_rate=0.02, unplug_every=0.8, unplug_for=0.3),
}
SHORT = int(2.5 * RATE)  # rows of the signal streamed per fault kind


def _check_one_fate(summary, st, ledger, n_rows):
    """``delivered + filled + dropped == stream`` and each count against the mock's ledger."""
    f = summary["frames"]
    assert f["delivered"] + f["filled"] + f["dropped"] == f["stream"], f
    assert f["dropped"] == f["dropped_in_ring"] and f["dropped_by_driver"] == 0, f
    # The stream runs from frame 0 (sent clean, the port open before) to the last frame the
    # driver received; frames lost after it (an unplug at the end) are in no stream.
    last = max(k for k in range(ledger.frames) if k not in ledger.lost)
    lost = [k for k in ledger.lost if k < last]
    assert f["stream"] == st["frames"] == min(n_rows, SPF * (last + 1))
    # Every row the driver made up is a row of a frame the board lost, counted filled exactly
    # once, whatever the ring did with it.
    assert f["filled"] == st["filled"] == SPF * len(lost)
    # The measured rows were processed or, if the ring overran, dropped: no other fate.
    assert f["delivered"] + f["dropped"] == st["frames"] - st["filled"]


# every fault at once in the quick command; each fault alone is slow (paced real time: 3 s each)
@pytest.mark.parametrize("kind", [pytest.param(k, marks=() if k == "all" else pytest.mark.slow) for k in FAULTS])
def test_one_fate_per_frame_under_each_fault_of_the_mock_board(signal_and_model, kind):
    x = signal_and_model[0][:SHORT]
    _, summary, driver, ledger = _run_serial(x, None, FaultSpec(**FAULTS[kind]), seed=4)
    st = driver.stats()
    if kind != "garbage":
        assert ledger.lost, "the fault was injected"
    if kind == "unplugs":
        assert ledger.unplugs >= 1 and st["unplugs"] == ledger.unplugs
    _check_one_fate(summary, st, ledger, len(x))


def test_an_outage_longer_than_the_ring_is_filled_not_dropped(signal_and_model):
    """1.2 s unplugged with a 0.5 s ring: the fill (one block) is longer than the ring, which
    drops its oldest rows. They are the driver's zeros, so they stay filled, and the filled
    count still equals the ledger's lost frames (before: dropped and filled both grew).

    The driver retries at 0.05, 0.15, 0.35, 0.75 and 1.55 s after the loss: 1.2 s leaves
    0.35 s either side of the replug, so it reconnects at its 1.55 s attempt whatever the load.
    """
    x = signal_and_model[0][:SHORT]
    faults = FaultSpec(unplug_every=0.5, unplug_for=1.2, unplug_limit=1)
    _, summary, driver, ledger = _run_serial(x, None, faults, buffer_seconds=0.5)
    st = driver.stats()
    assert ledger.unplugs == 1 == st["reconnects"]
    _check_one_fate(summary, st, ledger, len(x))
    f = summary["frames"]
    assert f["filled"] > 1.2 * RATE > 0.5 * RATE    # the outage was longer than the ring
    assert f["filled_lost_in_ring"] > 0             # and the ring dropped part of its fill


def test_the_mock_counts_clean_bytes_as_in_the_port_only_once_they_had_time_to_get_there():
    """Before an unplug the mock waits until a fault's judging bytes are in the port's input queue. Bytes written
    count there only PTY_FLUSH_SECONDS after they were written (the kernel moves them in a worker, and the input
    count does not see them on their way: a soak lost a truncated frame's judging bytes so); the mock's own pending
    tail never counts."""
    from supramodal.drivers.mock_whisker import PTY_FLUSH_SECONDS

    dev = MockWhiskerDevice(np.zeros((64, 2)), 5000.0)
    try:
        dev._clean_run = 300
        assert dev._clean_bytes_flushed(10.0) == 0                          # just written
        assert dev._clean_bytes_flushed(10.0 + PTY_FLUSH_SECONDS / 2) == 0
        dev._clean_run = 500
        assert dev._clean_bytes_flushed(10.0 + PTY_FLUSH_SECONDS) == 300    # the first 300 are there by now
        assert dev._clean_bytes_flushed(10.0 + 2 * PTY_FLUSH_SECONDS) == 500
        dev._pending, dev._clean_run = memoryview(b"x" * 50), 600             # 50 of the last 100 not yet written
        assert dev._clean_bytes_flushed(12.0) == 500
        assert dev._clean_bytes_flushed(12.0 + PTY_FLUSH_SECONDS) == 550
    finally:
        dev._pending = None
        dev.close()
