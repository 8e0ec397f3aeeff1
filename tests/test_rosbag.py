"""rosbag2 recordings (issue 33, item 4): a bag of a robot's two sensor topics on their own clocks, made
by a plain rosbags script (tests/ros2_bags.py: no ROS needed), imports into a replayable graph recording
(MCAP and sqlite3 alike), labelled by its String topic, and trains through ``train --scene``; a damaged
bag, a missing topic, a topic of another type and non-finite samples are refused naming the fix."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ros2_bags import require_rosbags, write_bag

require_rosbags()

from supramodal.replay.session import load_session  # noqa: E402


def _import(bag: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "supramodal", "import-recording", "--out", str(out), "--bag", str(bag),
                           "--topic", "whiskers=/whiskers", "--topic", "mic=/mic", "--bank", "whiskers=whisker",
                           "--bank", "mic=cochlea", *extra], capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_bag_of_two_topics_on_their_own_clocks_imports_with_its_labels(tmp_path, storage):
    """Each topic's samples come back as they were sent, in order and whole (the microphone's int16 to
    the bit); the two sources on one time (the whiskers' clock started 1.234 s after the microphone's),
    the labels on each source's own samples."""
    signals = write_bag(tmp_path / "bag", storage=storage)
    done = _import(tmp_path / "bag", tmp_path / "rec", "--label-topic", "/texture")
    assert done.returncode == 0, done.stderr
    w = load_session(tmp_path / "rec" / "imported.whiskers.wav")
    m = load_session(tmp_path / "rec" / "imported.mic.wav")
    assert w.rate == 5000 and m.rate == 44100
    assert np.array_equal(w.data, signals["whiskers"].astype(np.float32).astype(np.float64))
    assert np.array_equal(m.data, signals["mic"]) and not any(w.filled) and not any(m.filled)
    # the whiskers' first sample 1.234 s after the microphone's, on the recording's common time
    first_w = w.arrivals[1][0] - (w.arrivals[0][0] - 1) / 5000
    first_m = m.arrivals[1][0] - (m.arrivals[0][0] - 1) / 44100
    assert abs(first_w - first_m - 1.234) < 0.01, (first_w, first_m)
    assert [lab.label for lab in w.labels] == ["T1", "T2", "T3", "T4"]
    assert [round(lab.start, 3) for lab in w.labels] == [0.0, 2.0, 4.0, 6.0]
    assert [lab.label for lab in m.labels] == ["T1", "T2", "T3", "T4"]
    assert abs(m.labels[0].start - 1.234) < 0.01          # the first label came with the whiskers' start


@pytest.mark.slow   # trains a model (a few seconds of whiskers, 4 textures) with its calibration folds
def test_an_imported_bag_trains_through_train_scene(tmp_path):
    """Done when (issue 33): a bag made by a plain rosbags script of two sensor topics on their own clocks
    imports and trains through ``train --scene``: the model knows the bag's four textures and replays."""
    write_bag(tmp_path / "bag", seconds=3.0)
    assert _import(tmp_path / "bag", tmp_path / "rec", "--label-topic", "/texture").returncode == 0
    done = subprocess.run([sys.executable, "-m", "supramodal", "train", "--scene", str(tmp_path / "rec" / "imported.toml"),
                           "--stream", "whiskers", "--out", str(tmp_path / "w.npz")], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-1500:]
    from supramodal.model import TextureModel

    assert list(TextureModel.load(tmp_path / "w.npz").classes) == ["T1", "T2", "T3", "T4"]


def test_a_damaged_bag_a_missing_topic_another_type_and_nan_are_refused_naming_the_fix(tmp_path):
    write_bag(tmp_path / "bag")
    cut = tmp_path / "cut"
    cut.mkdir()
    data = (tmp_path / "bag" / "bag.mcap").read_bytes()
    (cut / "cut.mcap").write_bytes(data[:len(data) // 2])       # a truncated chunk
    done = _import(cut / "cut.mcap", tmp_path / "r1")
    assert done.returncode == 2 and "not a readable rosbag2" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "r1" / "imported.toml").exists()

    done = subprocess.run([sys.executable, "-m", "supramodal", "import-recording", "--out", str(tmp_path / "r2"),
                           "--bag", str(tmp_path / "bag"), "--topic", "w=/whisker", "--bank", "w=whisker"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and "no topic /whisker; the bag has /mic" in done.stderr, done.stderr

    done = subprocess.run([sys.executable, "-m", "supramodal", "import-recording", "--out", str(tmp_path / "r3"),
                           "--bag", str(tmp_path / "bag"), "--topic", "w=/texture", "--bank", "w=whisker"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and "/texture carries std_msgs/msg/String" in done.stderr, done.stderr

    write_bag(tmp_path / "nan", nan_at=7)
    done = _import(tmp_path / "nan", tmp_path / "r4")
    assert done.returncode == 2 and "NaN" in done.stderr and "/whiskers" in done.stderr, done.stderr
    assert not any((tmp_path / d).exists() and any((tmp_path / d).iterdir()) for d in ("r1", "r2", "r3", "r4"))


def test_the_import_refuses_a_bag_with_wav_sources_and_topics_without_a_bag(tmp_path):
    from supramodal.node.workflows.import_recording import ImportRecordingError, import_recording, sources_from_options

    with pytest.raises(ImportRecordingError, match="more than one of a WAV, an XDF stream and a bag topic"):
        sources_from_options(wav=[("a", "a.wav")], times=[("a", "t.csv")], banks=[("a", "whisker")],
                             topics=[("a", "/a")])
    sources = sources_from_options(banks=[("a", "whisker")], topics=[("a", "/a")])
    with pytest.raises(ImportRecordingError, match=r"no bag given \(--bag\)"):
        import_recording(tmp_path, "x", sources)
    assert json.dumps([s.topic for s in sources]) == '["/a"]'
