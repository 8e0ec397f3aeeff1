"""The ``ros2`` source driver against real rclpy (issue 33, item 2): a plain rclpy publisher of a
synthesised whisker array (tests/ros2_publisher.py, a process of its own, on its own sample clock) gives
the node the same windows as a local replay of the same samples; killed and started again, the node
says so and fills the gap exactly; stalled for 3 s and then flushing, nothing is filled. Bad input:
a topic of another type, a message of another layout, non-finite samples, a topic that never comes.

DDS stays on this machine, in a domain of the run's own (tests/harness/environment.py; checked by ``localhost_only``);
every test uses topics of its own."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from supramodal.benchmarks.lsl_link import RATE, whisker_signal
from supramodal.replay.wavio import write_wav

from ros2_only import Subscriber, localhost_only, require_ros2, unique_namespace  # noqa: F401  (the fixture applies itself)

require_ros2()

from std_msgs.msg import Float32MultiArray, MultiArrayDimension, String  # noqa: E402  (needs rclpy)

from supramodal.drivers.base import DriverError  # noqa: E402
from supramodal.drivers.ros2 import Ros2TopicDriver  # noqa: E402
from supramodal.errors import InputError  # noqa: E402

PUBLISHER = Path(__file__).resolve().parent / "ros2_publisher.py"

#: The same bank, features, model and decisions over two sources: the topic, or the WAV file replayed.
SCENE = """
[driver]
{driver}
mapping = "per-channel"

[bank]
kind = "whisker"

[features]
names = ["Af"]

[model]
train_on_start = true

[decision]
scope = "window"

[[sink]]
type = "jsonl"
path = "{out}"
"""


def _windows(path: Path) -> list[dict]:
    return [d for d in map(json.loads, path.read_text().splitlines()) if "window" in d]


def _summary(path: Path) -> dict:
    return json.loads(path.read_text().splitlines()[-1])


def _run(folder: Path, name: str, driver: str, *args: str) -> subprocess.Popen:
    (folder / f"{name}.toml").write_text(SCENE.format(driver=driver, out=f"{name}.jsonl"))
    return subprocess.Popen([sys.executable, "-m", "supramodal", "run", f"{name}.toml", "--quiet", *args], cwd=folder,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _replayed(folder: Path, signal_: np.ndarray) -> list[dict]:
    """The windows of a local replay of ``signal_`` through the same scene, at once."""
    write_wav(folder / "local.wav", signal_, RATE)
    node = _run(folder, "local", 'type = "replay"\npath = "local.wav"\nspeed = "max"')
    _, err = node.communicate(timeout=600)
    assert node.returncode == 0, err[-1500:]
    return _windows(folder / "local.jsonl")


def _publisher(topic: str, wav: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(PUBLISHER), topic, str(wav), *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_for_driver(topic: str, node: subprocess.Popen, timeout: float = 300.0) -> None:
    """Until the node's driver is on the bus (its ROS node, named after ``topic``, appears once the node's model
    is trained or read from the run's cache; it subscribes when a publisher advertises the topic): a test whose
    publisher keeps a sample clock from a fixed time must not start it while the node still trains."""
    probe = Subscriber("probe")
    name = "supramodal_" + "_".join(t for t in topic.split("/") if t)        # the driver's default node name
    try:
        deadline = time.monotonic() + timeout
        while name not in probe.node.get_node_names():
            assert node.poll() is None, node.communicate()[1][-1500:]
            assert time.monotonic() < deadline, f"the node's driver {name} did not come in {timeout:g} s"
            time.sleep(0.05)
    finally:
        probe.close()


def _same_decisions(live: list[dict], local: list[dict]) -> None:
    assert len(live) >= 1 and len(live) <= len(local)
    got = [(w["window"], w["predicted"], w["confidence"]) for w in live]
    want = [(w["window"], w["predicted"], w["confidence"]) for w in local[:len(live)]]
    assert got == want, next((g, w) for g, w in zip(got, want) if g != w)


@pytest.mark.slow   # 21 s of a publisher in real time, a model trained on start (or read from the run's cache)
def test_a_plain_publisher_gives_the_windows_of_a_local_replay(tmp_path):
    """Done when (issue 33): a plain rclpy publisher of a synthesised whisker signal (stamped
    sensor_msgs/Image, 10 ms blocks), fed to the ros2 driver, gives the same windows as a local replay of
    the same signal: >= 200 windows, all equal."""
    signal_ = whisker_signal(21.5)
    write_wav(tmp_path / "s.wav", signal_, RATE)
    topic = f"{unique_namespace()}/whiskers"
    node = _run(tmp_path, "live", f'type = "ros2"\ntopic = "{topic}"\nmessage = "sensor_msgs/msg/Image"', "--seconds",
                "21")
    pub = _publisher(topic, tmp_path / "s.wav", "--kind", "image", "--wait-subscriber", "300")
    try:
        _, err = node.communicate(timeout=600)
    finally:
        node.kill()
        pub.kill()
    assert node.returncode == 0, err[-1500:]
    live = _windows(tmp_path / "live.jsonl")
    assert len(live) == 210
    _same_decisions(live, _replayed(tmp_path, signal_))
    summary = _summary(tmp_path / "live.jsonl")
    assert summary["frames"]["filled"] == 0 and summary["frames"]["dropped"] == 0
    assert summary["driver"]["messages"] == 21 * RATE // 50 and summary["driver"]["refused"] == 0


@pytest.mark.slow   # a publisher in real time, killed and started again; a model trained on start (or cached)
def test_a_publisher_killed_and_started_again_is_said_and_its_gap_filled_exactly(tmp_path):
    """Done when (issue 33): the publisher killed (SIGKILL, after it hung) and started again on its sample
    clock: the node says unplug, then reconnect, fills exactly the samples that were due while it was
    down (flagging those windows ``gap``), and every window equals a local replay of the signal with those
    samples zeroed."""
    signal_ = whisker_signal(12.0)
    write_wav(tmp_path / "s.wav", signal_, RATE)
    topic = f"{unique_namespace()}/whiskers"
    node = _run(tmp_path, "live", f'type = "ros2"\ntopic = "{topic}"', "--seconds", "11")
    _wait_for_driver(topic, node)           # the node trains (or reads the run's cache) first
    t0 = time.time_ns() + 5 * 10**9         # sample 0's time: the publisher starts (its rclpy, a match) meanwhile
    first = _publisher(topic, tmp_path / "s.wav", "--t0-ns", str(t0), "--hold-at", str(4 * RATE),
                       "--wait-subscriber", "300")
    second = None
    try:
        assert first.stdout is not None and first.stdout.readline().strip() == "first 0"
        assert first.stdout.readline().strip() == f"held {4 * RATE}"
        time.sleep(1.0)
        first.kill()
        second = _publisher(topic, tmp_path / "s.wav", "--t0-ns", str(t0))
        assert second.stdout is not None
        line = second.stdout.readline().strip()
        assert line.startswith("first "), (line, second.stderr.read() if second.stderr else "")
        back = int(line.split()[1])
        _, err = node.communicate(timeout=600)
    finally:
        node.kill()
        first.kill()
        if second is not None:
            second.kill()
    assert node.returncode == 0, err[-1500:]
    lost = back - 4 * RATE              # a second or more (under load the new process takes longer to start)
    assert 1.0 * RATE < lost < 10.0 * RATE, lost      # below max_gap (10 s): a gap to fill, not a restart
    summary = _summary(tmp_path / "live.jsonl")
    assert summary["frames"]["filled"] == lost and summary["driver"]["gaps"] == 1
    assert summary["events"]["counts"].get("unplug") == 1 and summary["events"]["counts"].get("reconnect") == 1
    live = _windows(tmp_path / "live.jsonl")
    flagged = [w["window"] for w in live if w.get("gap")]
    assert flagged == list(range(4 * RATE // 500, -(-back // 500))), flagged
    zeroed = signal_.copy()
    zeroed[4 * RATE:back] = 0.0
    _same_decisions(live, _replayed(tmp_path, zeroed))


@pytest.mark.slow   # a publisher in real time, stopped 3 s; a model trained on start (or cached)
def test_a_publisher_stalled_3_s_then_flushing_causes_no_false_fill(tmp_path):
    """Done when (issue 33): a publisher stopped (SIGSTOP) for 3 s that then sends its backlog at once
    (unstamped Float32MultiArray: the driver has only the arrival times) leaves nothing filled: a
    backlog, and every window equal to a local replay."""
    signal_ = whisker_signal(11.0)
    write_wav(tmp_path / "s.wav", signal_, RATE)
    topic = f"{unique_namespace()}/whiskers"
    node = _run(tmp_path, "live", f'type = "ros2"\ntopic = "{topic}"', "--seconds", "10")
    pub = _publisher(topic, tmp_path / "s.wav", "--kind", "float32", "--wait-subscriber", "300")
    try:
        assert pub.stdout is not None and pub.stdout.readline().strip() == "first 0"
        time.sleep(3.5)
        os.kill(pub.pid, signal.SIGSTOP)
        time.sleep(3.0)
        os.kill(pub.pid, signal.SIGCONT)
        _, err = node.communicate(timeout=600)
    finally:
        node.kill()
        os.kill(pub.pid, signal.SIGCONT)
        pub.kill()
    assert node.returncode == 0, err[-1500:]
    summary = _summary(tmp_path / "live.jsonl")
    assert summary["frames"]["filled"] == 0 and summary["driver"]["gaps"] == 0, summary["driver"]
    assert summary["driver"]["backlogs"] >= 1, summary["driver"]
    live = _windows(tmp_path / "live.jsonl")
    assert len(live) == 100
    _same_decisions(live, _replayed(tmp_path, signal_))


# -- bad input, with the driver in the test's process ----------------------------------------------------

def _arrays(pub, rows: np.ndarray, dims: bool = True) -> None:
    msg = Float32MultiArray()
    n, c = rows.shape
    if dims:
        msg.layout.dim = [MultiArrayDimension(label="samples", size=n, stride=n * c),
                          MultiArrayDimension(label="channels", size=c, stride=c)]
    msg.data = rows.astype(np.float32).ravel().tolist()
    pub.publish(msg)


def _read_until(driver, frames: int, timeout: float = 10.0) -> list:
    blocks, end = [], time.monotonic() + timeout
    while sum(b.frames for b in blocks) < frames and time.monotonic() < end:
        b = driver.read(0.05)
        if b is not None:
            blocks.append(b)
    return blocks


def _matched_publisher(talker, topic: str):
    """A Float32MultiArray publisher of ``talker`` on ``topic``, matched with the open driver's subscription
    (and 0.3 s more, as a publisher that waits for its subscribers before it speaks)."""
    pub = talker.node.create_publisher(Float32MultiArray, topic, 100)
    assert talker.wait_for(lambda: pub.get_subscription_count() > 0, 10.0)
    time.sleep(0.3)
    return pub


def test_a_message_of_another_layout_is_refused_counted_and_said_and_nan_set_to_zero():
    """Bad input (issue 33): a message of 3 channels where the scene reads 2 is refused, counted and said
    (``channels``); non-finite values are set to 0, counted and said (``nan``); both layouts of the
    docs are read (``[samples, channels]`` and none)."""
    topic = f"{unique_namespace()}/samples"
    driver = Ros2TopicDriver(topic, 1000.0, 2, message="std_msgs/msg/Float32MultiArray")
    talker = Subscriber("talker")
    try:
        with driver:
            pub = _matched_publisher(talker, topic)
            rows = np.arange(20, dtype=np.float32).reshape(10, 2) / 100
            _arrays(pub, rows)
            _arrays(pub, np.zeros((10, 3)))                       # refused
            bad = rows.copy()
            bad[3, 1] = np.nan
            bad[5, 0] = np.inf
            _arrays(pub, bad, dims=False)
            blocks = _read_until(driver, 20)
            events, _ = driver.take_events()
        got = np.concatenate([b.data for b in blocks])
        want = rows.astype(np.float32).astype(np.float64)
        fixed = want.copy()
        fixed[3, 1] = fixed[5, 0] = 0.0
        assert np.array_equal(got, np.concatenate([want, fixed]))
        stats = driver.stats()
        assert stats["refused"] == 1 and stats["nan"] == 2 and stats["messages"] == 2
        said = {e.kind: e.message for e in events}
        assert "3 channels" in said["channels"] and "not the 2" in said["channels"]
        assert "2 non-finite values" in said["nan"]
    finally:
        talker.close()


def test_a_message_of_another_size_than_the_scene_s_block_is_kept_counted_and_said():
    """Item 2 (issue 33): the block size comes from the scene (``block``) and is checked against what
    arrives: a message of another size is kept (no sample lost) but counted (``odd_blocks``) and said."""
    topic = f"{unique_namespace()}/samples"
    driver = Ros2TopicDriver(topic, 1000.0, 2, message="std_msgs/msg/Float32MultiArray", block=10)
    talker = Subscriber("talker")
    try:
        with driver:
            pub = _matched_publisher(talker, topic)
            rows = np.arange(50, dtype=np.float32).reshape(25, 2) / 100
            for part in (rows[:10], rows[10:17], rows[17:]):     # 10, then 7 and 8: two of another size
                _arrays(pub, part)
            blocks = _read_until(driver, 25)
            events, _ = driver.take_events()
        assert np.array_equal(np.concatenate([b.data for b in blocks]), rows.astype(np.float64))
        assert driver.stats()["odd_blocks"] == 2
        said = [e.message for e in events if e.kind == "block"]
        assert len(said) == 2 and "holds 7 samples, not the 10 the scene says" in said[0]
    finally:
        talker.close()
    with pytest.raises(InputError, match="block must be a positive integer"):
        Ros2TopicDriver(topic, 1000.0, 2, block=0)


def test_a_topic_of_another_type_is_refused_naming_both():
    """Bad input (issue 33): a topic that carries std_msgs/String is refused, with the types the driver
    reads; given a type, a topic of another one is refused too."""
    topic = f"{unique_namespace()}/words"
    talker = Subscriber("talker")
    try:
        pub = talker.node.create_publisher(String, topic, 10)
        for message in ("auto", "std_msgs/msg/Float32MultiArray"):
            driver = Ros2TopicDriver(topic, 1000.0, 2, message=message)
            with driver:
                with pytest.raises(DriverError, match=r"carries \['std_msgs/msg/String'\]"):
                    end = time.monotonic() + 10.0
                    while time.monotonic() < end:
                        driver.read(0.05)
        assert pub.get_subscription_count() == 0
    finally:
        talker.close()


def test_a_node_waiting_for_a_topic_that_never_comes_says_so_and_stops_on_sigint(tmp_path):
    """Bad input (issue 33): a topic with no publisher: the node says it waits (one ``waiting`` event,
    no unplug: nothing was lost), and Ctrl-C stops it at once, cleanly, with its summary."""
    topic = f"{unique_namespace()}/nobody"
    (tmp_path / "n.toml").write_text(f'[driver]\ntype = "ros2"\ntopic = "{topic}"\nrate = 5000.0\nchannels = 20\n'
                                     'mapping = "per-channel"\n\n[bank]\nkind = "whisker"\n\n'
                                     '[[sink]]\ntype = "jsonl"\npath = "out.jsonl"\n')
    node = subprocess.Popen([sys.executable, "-m", "supramodal", "run", "n.toml", "--quiet"], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not (tmp_path / "out.jsonl").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        t = time.monotonic()
        node.send_signal(signal.SIGINT)
        _, err = node.communicate(timeout=20)
        assert time.monotonic() - t < 5.0
    finally:
        node.kill()
    assert node.returncode == 0, err[-1500:]
    lines = [json.loads(x) for x in (tmp_path / "out.jsonl").read_text().splitlines()]
    assert [d["event"] for d in lines if "event" in d] == ["waiting"]
    assert "waiting for the first message" in lines[0]["message"] and "(no publisher)" in lines[0]["message"]
    assert lines[-1]["summary"] and lines[-1]["windows"] == 0


@pytest.mark.slow   # 4 s of a publisher in real time
def test_a_topic_recorded_replays_to_the_windows_the_node_computed_live(tmp_path):
    """``supramodal record`` of a scene whose source is a ROS 2 topic (what docs/ros2.md points at for
    training one's own models): the session replays to the feature windows the node computed live, to
    the bit, and keeps its label."""
    signal_ = whisker_signal(6.0)
    write_wav(tmp_path / "s.wav", signal_, RATE)
    topic = f"{unique_namespace()}/whiskers"
    bank = 'mapping = "per-channel"\n\n[bank]\nkind = "whisker"\n\n[features]\nnames = ["Af"]\n\n[[sink]]\ntype = "jsonl"\n'
    (tmp_path / "rec.toml").write_text(f'[driver]\ntype = "ros2"\ntopic = "{topic}"\n{bank}path = "live.jsonl"\n')
    node = subprocess.Popen([sys.executable, "-m", "supramodal", "record", "rec.toml", "--out", "rec", "--name", "t1",
                             "--label", "T1", "--seconds", "4", "--quiet"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    pub = _publisher(topic, tmp_path / "s.wav", "--kind", "image", "--wait-subscriber", "300")
    try:
        _, err = node.communicate(timeout=300)
    finally:
        node.kill()
        pub.kill()
    assert node.returncode == 0, err[-1500:]
    (tmp_path / "replay.toml").write_text('[driver]\ntype = "replay"\npath = "rec/t1.wav"\nspeed = "max"\n'
                                          f'{bank}path = "replayed.jsonl"\n')
    done = subprocess.run([sys.executable, "-m", "supramodal", "run", "replay.toml", "--quiet"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-1500:]
    live, replayed = _windows(tmp_path / "live.jsonl"), _windows(tmp_path / "replayed.jsonl")
    assert len(live) == len(replayed) == 40
    assert [w["features"] for w in live] == [w["features"] for w in replayed]
    assert {w["truth"] for w in replayed} == {"T1"}
