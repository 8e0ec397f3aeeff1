"""The session recorder: raw driver frames to WAV + JSON, replayed to identical node output."""

from __future__ import annotations

import random
import time

import numpy as np
import pytest

from supramodal.node.scene.build import bank_for, build_node, driver_for
from supramodal.node.cli import main
from supramodal.node.runtime.graph import Node
from supramodal.node.runtime.taps.recorder import SessionRecorder
from supramodal.node.runtime.ringbuffer import RingBuffer
from supramodal.node.scene.schema import scene_from_dict
from supramodal.node.runtime.sinks import ListSink
from supramodal.replay.driver import ReplayDriver
from supramodal.replay.session import load_session
from supramodal.banks import whisker_bank
from supramodal.pipeline import FeaturePipeline


def test_recorded_session_replays_to_identical_node_output(tmp_path):
    scene = scene_from_dict({"driver": {"type": "synth", "seconds": 0.5, "held_out": False, "block": 37},
                             "features": {"names": ["Af", "A"]}})
    live = ListSink()
    recorder = SessionRecorder(tmp_path, "rec", "test", label="bench")
    summary = build_node(scene, speed="max", sinks_override=[live], recorder=recorder).run()
    wav, sidecar = (tmp_path / "rec.wav"), (tmp_path / "rec.json")
    assert summary["recorded"] == [str(wav), str(sidecar)]
    session = load_session(wav)
    assert session.data.shape == (8 * 2500, 1) and session.rate == 5000
    # The synth driver's truth is kept with its times (the "bench" label of the whole recording
    # applies only where the driver carries none).
    _, truth, _ = driver_for(scene, whisker_bank())
    assert [(lab.start, lab.end, lab.label) for lab in session.labels] == truth.ranges
    assert [lab.label for lab in session.labels] == [f"T{i}" for i in range(1, 9)]
    assert not list(tmp_path.glob(".*.raw"))                     # the spool file is gone
    replayed = ListSink()
    Node(ReplayDriver(str(wav), block_size=101, speed="max", on_notice=None),
         FeaturePipeline(whisker_bank(), ("Af", "A"), chunk=scene.only_stream().features.chunk), [replayed],
         overrun="block").run()
    assert len(replayed.events) == len(live.events) == 40
    for a, b in zip(live.events, replayed.events):
        assert a["window"] == b["window"] and a["features"] == b["features"]     # bit-identical


def test_marks_and_filled_frames_are_kept(tmp_path):
    ring = RingBuffer(10000, 2, overrun="block")
    reader = ring.add_reader("recorder")
    rec = SessionRecorder(tmp_path, "m", "test")
    position = [0]
    rec.attach(1000.0, 2, lambda: position[0])
    data = np.random.default_rng(0).uniform(-1, 1, (3000, 2)).astype(np.float32)
    filled = np.zeros(3000, bool)
    filled[1200:1300] = True
    ring.write(data, filled)
    for pos, label in ((500, "grit"), (1500, None), (2000, "felt")):
        position[0] = pos
        rec.mark(label)
    ring.close()
    rec.run(reader)
    s = load_session(tmp_path / "m.wav")
    assert s.data.dtype == np.float64 and np.array_equal(s.data, data.astype(np.float64))   # float32 exact
    assert [(lab.start, lab.end, lab.label) for lab in s.labels] == [(0.5, 1.5, "grit"), (2.0, 3.0, "felt")]
    assert [tuple(r) for r in s.filled] == [(1200, 1300)]


def test_record_command_stops_after_seconds(tmp_path):
    (tmp_path / "s.toml").write_text('[driver]\ntype = "synth"\nseconds = 1.0\nheld_out = false\nspeed = "max"\n'
                                     '[[sink]]\ntype = "jsonl"\npath = "out.jsonl"\n')
    assert main(["record", str(tmp_path / "s.toml"), "--out", str(tmp_path / "rec"), "--name", "x",
                 "--seconds", "2.5", "--quiet"]) == 0
    s = load_session(tmp_path / "rec" / "x.wav")
    assert s.data.shape[0] == 12500
    # The driver's labels, clipped where the recording stopped: its replay reports accuracy.
    assert [(lab.start, lab.end, lab.label) for lab in s.labels] == [(0.0, 1.0, "T1"), (1.0, 2.0, "T2"),
                                                                       (2.0, 2.5, "T3")]
    assert len((tmp_path / "out.jsonl").read_text().splitlines()) == 25 + 1


def test_a_whole_recording_label_is_refused_where_the_driver_labels_the_stream(tmp_path, capsys):
    (tmp_path / "s.toml").write_text('[driver]\ntype = "synth"\nseconds = 1.0\nheld_out = false\nspeed = "max"\n')
    assert main(["record", str(tmp_path / "s.toml"), "--out", str(tmp_path / "rec"), "--name", "x",
                 "--seconds", "1", "--label", "grit", "--quiet"]) == 2
    assert "labels its stream itself" in capsys.readouterr().err
    assert not (tmp_path / "rec").exists()


class Jittery:
    """Calls ``read`` of what it wraps after a random sleep: usually under a millisecond,
    one time in five up to 30 ms, so that ring reads end anywhere and sometimes span
    several windows, as on a busy machine."""

    def __init__(self, read, seed):
        self._read, self._rng = read, random.Random(seed)

    def read(self, *args, **kwargs):
        r = self._rng.random()
        time.sleep(self._rng.uniform(0, 0.03) if r < 0.2 else self._rng.uniform(0, 0.001))
        return self._read(*args, **kwargs)


class JitteryReader(Jittery):
    def __init__(self, reader, seed):
        super().__init__(reader.read, seed)
        self._reader = reader

    def stats(self):
        return self._reader.stats()


@pytest.mark.parametrize("seed", [None, 1, 2])
@pytest.mark.parametrize("chunk", [None, 0.0074, 0.0])
def test_node_output_does_not_depend_on_ring_read_timing(seed, chunk):
    """The node's pipeline runs at cut points fixed by stream index (each chunk, default 10 ms,
    or each window end with chunk 0), so the features equal, to the last bit, the offline
    pipeline fed the same cuts, whatever the driver's and the processing thread's timing.
    (Before the cuts: a ring read spanning several windows was filtered in one pass, which
    rounds differently, about 1 run in 20 on a busy machine.)"""
    features = {"names": ["Af", "A"]} | ({} if chunk is None else {"chunk": chunk})
    scene = scene_from_dict({"driver": {"type": "synth", "seconds": 0.5, "held_out": False, "block": 37},
                             "features": features})
    data = driver_for(scene, bank_for(scene))[0].data
    chunk = scene.only_stream().features.chunk
    pipeline = FeaturePipeline(whisker_bank(), ("Af", "A"), chunk=chunk)
    # With chunks the pipeline cuts the offline signal itself; without, it is fed window by window.
    offline = pipeline.run(data[:, 0], block=4096 if chunk else pipeline.window_samples)
    sink = ListSink()
    node = build_node(scene, speed="max", sinks_override=[sink])
    if seed is not None:
        driver = node.sources[0].driver
        driver.read = Jittery(driver.read, seed).read
        feed = node.streams[0].feed
        feed.reader = JitteryReader(feed.reader, seed + 100)
    node.run()
    assert len(sink.events) == len(offline) == 40
    for e in sink.events:
        w = e["window"]
        assert e["features"] == {f: offline.values[w, k].tolist() for k, f in enumerate(offline.features)}
