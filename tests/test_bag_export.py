"""``record --bag`` (issue 33, item 4): a recording written as a rosbag2 (MCAP) that a second reader
(``mcap`` + ``mcap-ros2-support``) and ``rosbags`` read, and that ``import-recording --bag`` turns back
into the same recording: the same samples to the bit, the same labels, the same windows on replay."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ros2_bags import require_rosbags

require_rosbags()

from supramodal.node.runtime.sinks import ListSink  # noqa: E402  (after the skip)
from supramodal.node.scene.build import build_node  # noqa: E402
from supramodal.node.scene.schema import load_scene  # noqa: E402
from supramodal.node.workflows.bag_export import BAG_EPOCH_NS, LABEL_TOPIC, BagExportError, export_bag  # noqa: E402
from supramodal.replay.session import load_session  # noqa: E402

SCENE = """
[[source]]
name = "whiskers"
type = "twosense"
sense = "whiskers"
seconds = 0.5
block = 50
speed = "max"

[[source]]
name = "mic"
type = "twosense"
sense = "microphone"
seconds = 0.5
block = 441
offset = 0.037
speed = "max"

[[stream]]
name = "whiskers"
source = "whiskers"
[stream.bank]
kind = "whisker"

[[stream]]
name = "mic"
source = "mic"
[stream.bank]
kind = "cochlea"
"""


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "supramodal", *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd)


def _windows(scene: Path) -> dict[str, list]:
    sink = ListSink()
    build_node(load_scene(scene), speed="max", sinks_override=[sink]).run()
    out: dict[str, list] = {}
    for w in sink.windows:
        out.setdefault(w.stream, []).append(w)
    return out


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A two-sense graph recorded with ``record --bag``, and the bag imported back."""
    root = tmp_path_factory.mktemp("bag")
    (root / "g.toml").write_text(SCENE)
    done = _cli("record", "g.toml", "--out", "rec", "--name", "r", "--bag", "rec/r_bag", "--quiet", cwd=root)
    assert done.returncode == 0, done.stderr
    assert "rosbag2 (MCAP) in rec/r_bag" in done.stderr
    back = _cli("import-recording", "--out", "imp", "--bag", "rec/r_bag",
                "--topic", "whiskers=/supramodal/whiskers/samples", "--topic", "mic=/supramodal/mic/samples",
                "--bank", "whiskers=whisker", "--bank", "mic=cochlea", "--label-topic", LABEL_TOPIC, cwd=root)
    assert back.returncode == 0, back.stderr
    return root


def test_a_bag_written_by_record_imports_back_to_the_same_samples_labels_and_windows(recorded):
    for source in ("whiskers", "mic"):
        a = load_session(recorded / "rec" / f"r.{source}.wav")
        b = load_session(recorded / "imp" / f"imported.{source}.wav")
        assert np.array_equal(a.data, b.data) and a.rate == b.rate and not b.filled
    # one label topic, on the recording's time: the first labelled source's labels, to the sample
    a, b = (load_session(recorded / d / f) for d, f in (("rec", "r.whiskers.wav"), ("imp", "imported.whiskers.wav")))
    assert [x.label for x in a.labels] == [x.label for x in b.labels]
    assert all(abs(x.start - y.start) <= 1 / a.rate and abs(x.end - y.end) <= 1 / a.rate
               for x, y in zip(a.labels, b.labels))
    original, imported = _windows(recorded / "rec" / "r.toml"), _windows(recorded / "imp" / "imported.toml")
    assert set(original) == set(imported) == {"whiskers", "mic"}
    for stream in original:
        assert len(original[stream]) == len(imported[stream]) == 40
        for x, y in zip(original[stream], imported[stream]):
            assert x.window == y.window
            assert all(np.array_equal(x.features[f], y.features[f]) for f in x.features)
            # on one time line as recorded: the microphone's windows 37 ms after the whiskers'
            assert y.start - imported["whiskers"][y.window].start == pytest.approx(
                x.start - original["whiskers"][x.window].start, abs=1e-6)


def test_a_second_reader_reads_the_bag_s_messages_and_values(recorded):
    """mcap + mcap-ros2-support (not rosbags, which wrote it): every block as a message of the samples'
    topic, values and stamps as recorded; the labels' strings."""
    reader_module = pytest.importorskip("mcap.reader", reason="the second reader (mcap) is in the test extra")
    decoder = pytest.importorskip("mcap_ros2.decoder", reason="the second reader (mcap-ros2-support)")
    bag = next((recorded / "rec" / "r_bag").glob("*.mcap"))
    got: dict[str, list] = {}
    with bag.open("rb") as f:
        reader = reader_module.make_reader(f, decoder_factories=[decoder.DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages():
            got.setdefault(channel.topic, []).append((message.log_time, msg))
    session = load_session(recorded / "rec" / "r.whiskers.wav")
    images = got["/supramodal/whiskers/samples"]
    ends = session.arrivals[0]
    assert len(images) == len(ends) == 400
    # 32FC1 where every sample is a float32, else 64FC1: never rounded
    exact = np.array_equal(session.data.astype(np.float32).astype(np.float64), session.data)
    dtype, encoding = ("<f4", "32FC1") if exact else ("<f8", "64FC1")
    data = np.concatenate([np.frombuffer(bytes(m.data), dtype).reshape(m.height, m.width) for _, m in images])
    assert np.array_equal(data.astype(np.float64), session.data)
    assert all(m.encoding == encoding and m.header.frame_id == "whiskers" for _, m in images)
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in images]) - BAG_EPOCH_NS
    assert np.all(np.diff(stamps) > 0) and abs(stamps[0] - (ends[0] - 1) / 5000 * 1e9) < 1e4
    assert len(got["/supramodal/mic/samples"]) == 400
    labels = [m.data for _, m in got[LABEL_TOPIC]]
    assert labels == [x.label for x in session.labels] + [""]


def test_a_bag_is_refused_before_anything_is_recorded_where_it_cannot_be_written(tmp_path):
    (tmp_path / "g.toml").write_text(SCENE)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    for bag, says in (("mine", "exists; choose another --bag"), ("x.bag", "taken for a ROS 1 bag"),
                      ("no/such/b", "no such folder for the bag")):
        done = _cli("record", "g.toml", "--out", "rec", "--bag", bag, "--quiet", cwd=tmp_path)
        assert done.returncode != 0 and says in done.stderr and "Traceback" not in done.stderr, done.stderr
        assert not (tmp_path / "rec").exists()             # nothing recorded
    done = _cli("record", "g.toml", "--out", "rec", "--bag", "mine", "--force", "--quiet", cwd=tmp_path)
    assert done.returncode != 0 and "no rosbag2 folder" in done.stderr
    assert (tmp_path / "mine" / "notes.txt").read_text() == "mine"      # a user's folder is never replaced
    with pytest.raises(BagExportError, match="ROS name token"):
        export_bag([("left arm", tmp_path / "x.wav")], tmp_path / "b")


def test_the_node_s_decisions_go_on_a_decision_topic_per_stream_stamped_at_each_window_s_end(recorded, tmp_path):
    """The windows the recording node wrote (its JSON Lines): each one with a decision becomes a
    std_msgs/String on /supramodal/STREAM/decision, the ros2 sink's form (the line and its stamp), at the
    window's end on the recording's time; events, the summary and windows without a model are not."""
    import json

    from rosbags.highlevel import AnyReader

    lines = [{"stream": "whiskers", "t": 0.1, "window": 0, "start": 0.0, "end": 0.1, "predicted": "H1a",
              "confidence": 0.9, "truth": "H1a", "latency_ms": None},
             {"stream": "fused", "t": 0.137, "window": 0, "start": 0.0, "end": 0.137, "predicted": "H1b",
              "confidence": 0.6, "senses": ["whiskers", "mic"], "truth": None, "latency_ms": None},
             {"stream": "mic", "t": 0.137, "window": 0, "start": 0.037, "end": 0.137, "features": {"Af": [1.0]}},
             {"event": "gap", "message": "x"}, {"windows": 2, "stream_seconds": 4.0}]
    jsonl = tmp_path / "w.jsonl"
    jsonl.write_text("".join(json.dumps(d) + "\n" for d in lines))
    done = export_bag([("whiskers", recorded / "rec" / "r.whiskers.wav")], tmp_path / "b", windows=jsonl)
    assert done["topics"]["/supramodal/whiskers/decision"] == 1 and done["topics"]["/supramodal/fused/decision"] == 1
    assert not any(t.startswith("/supramodal/mic") for t in done["topics"])
    got = {}
    with AnyReader([tmp_path / "b"]) as reader:
        for con, logged, raw in reader.messages():
            if con.topic.endswith("/decision"):
                got[con.topic] = (logged, json.loads(reader.deserialize(raw, con.msgtype).data))
    logged, d = got["/supramodal/fused/decision"]
    assert logged == BAG_EPOCH_NS + 137_000_000
    assert d == {**lines[1], "stamp": {"sec": logged // 10**9, "nanosec": logged % 10**9}}
    (tmp_path / "bad.jsonl").write_text("{\n")
    with pytest.raises(BagExportError, match="line 1: not JSON"):
        export_bag([("whiskers", recorded / "rec" / "r.whiskers.wav")], tmp_path / "c", windows=tmp_path / "bad.jsonl")
    assert not (tmp_path / "c").exists()
