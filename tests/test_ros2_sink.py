"""The ``ros2`` sink against real rclpy (issue 33, item 1): a plain subscriber started before the node
gets every window of every stream and of the fusion, the decisions equal the jsonl sink's, stamps are
the windows' ends on the ROS clock; driver events on ``~/events`` and ``/diagnostics`` within a second;
remapping by ``--ros-args``; a stopped subscriber never holds the node up.

DDS stays on this machine, in a domain of the run's own (tests/harness/environment.py; checked by ``localhost_only``);
every test uses a namespace of its own."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from supramodal.drivers.base import DriverEvent
from supramodal.drivers.ros2 import use_ros_arguments

from ros2_only import Subscriber, localhost_only, require_ros2, unique_namespace  # noqa: F401  (the fixture applies itself)

require_ros2()

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402  (needs rclpy)
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402

# two senses fused, a jsonl sink, a ros2 sink; a user's subscriber in a process of its own (reliable, keep
# last 10, on every decision and posteriors topic)
from supramodal.benchmarks.ros2_sink import SUBSCRIBER, scene  # noqa: E402
from supramodal.node.runtime.sinks.ros2 import Ros2Sink  # noqa: E402
from supramodal.node.runtime.sinks.ros2_publisher import ERROR, OK, Ros2Publisher, TopicStream  # noqa: E402


def _node(tmp_path: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "supramodal", "run", str(tmp_path / "node.toml"), "--quiet", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)


def _windows(path: Path) -> list[dict]:
    return [d for d in map(json.loads, path.read_text().splitlines()) if "window" in d]


@pytest.mark.slow   # a node process that trains two models on start (or reads them from the run's cache)
def test_a_subscriber_started_before_the_node_gets_every_window_as_the_jsonl_sink_stamped_on_the_ros_clock(tmp_path):
    """Done when (issue 33): a plain rclpy subscriber started before the node receives window 0 onward
    of decisions and posteriors, for every stream and the fusion; the decision's data is the jsonl
    sink's line (and the ``stamp``); every stamp is the window's end on the ROS clock, by one line
    (within 1 ms; here within a microsecond, what the jsonl's rounding leaves). The node is renamed by
    ``--ros-args -r __node:=``, as a launch file would. With the default ``history`` (10): a subscriber in
    a busy test process keeps up within a second of windows."""
    ns = unique_namespace()
    (tmp_path / "node.toml").write_text(scene(1.0, ns, "wait_for_subscribers = 120"))
    sub = Subscriber()
    streams = ("left", "right", "fused")
    try:
        for s in streams:
            sub.subscribe(f"{ns}/texture/{s}/decision", String, 100)
            sub.subscribe(f"{ns}/texture/{s}/posteriors", JointState, 100)
            sub.subscribe(f"{ns}/texture/{s}/features", JointState, qos_profile_sensor_data)
        sub.subscribe("/diagnostics", DiagnosticArray, 100)
        started_ns = time.time_ns()
        node = _node(tmp_path, "--ros-args", "-r", "__node:=texture")
        try:
            out, err = node.communicate(timeout=400)
        finally:
            node.kill()
        assert node.returncode == 0, err[-1500:]
        windows = _windows(tmp_path / "out.jsonl")
        by_stream = {s: [w for w in windows if w["stream"] == s] for s in streams}
        assert all(len(by_stream[s]) >= 70 for s in streams), {s: len(v) for s, v in by_stream.items()}
        came = sub.wait_for(lambda: all(len(sub.messages(f"{ns}/texture/{s}/decision")) >= len(by_stream[s])
                                        for s in streams), 10.0)
        assert came, {s: sorted(set(range(len(by_stream[s])))
                                - {json.loads(m.data)["window"] for m in sub.messages(f"{ns}/texture/{s}/decision")})
                      for s in streams}
        epochs = []
        for s in streams:
            decisions = [json.loads(m.data) for m in sub.messages(f"{ns}/texture/{s}/decision")]
            assert [d["window"] for d in decisions] == list(range(len(by_stream[s])))       # window 0 onward
            assert [{k: v for k, v in d.items() if k != "stamp"} for d in decisions] == by_stream[s]
            posteriors = sub.messages(f"{ns}/texture/{s}/posteriors")
            assert len(posteriors) == len(decisions)
            for d, p in zip(decisions, posteriors):
                assert (p.header.stamp.sec, p.header.stamp.nanosec) == (d["stamp"]["sec"], d["stamp"]["nanosec"])
                assert len(p.name) == 8 and len(p.position) == 8 and abs(sum(p.position) - 1) < 1e-9
                best = max(range(8), key=lambda i: p.position[i])
                assert p.name[best] == d["predicted"] and round(p.position[best], 4) == d["confidence"]
                epochs.append(d["stamp"]["sec"] * 10**9 + d["stamp"]["nanosec"] - round(d["end"] * 1e9))
            if s != "fused":
                features = sub.messages(f"{ns}/texture/{s}/features")
                assert features and all(len(f.name) == 20 and f.name[0].startswith("Af/") for f in features)
        # One line from common time to the ROS clock for all the windows of all the streams, and its
        # start (common time 0 on the ROS clock) after this test began and before the first window came.
        assert max(epochs) - min(epochs) < 1_000, (min(epochs), max(epochs))
        first_came = min(t for s in streams for t, _ in sub.timed(f"{ns}/texture/{s}/decision"))
        assert started_ns < min(epochs) < time.time_ns() - (time.monotonic() - first_came) * 1e9
        names = {st.name for _, m in sub.timed("/diagnostics") for st in m.status}
        assert {"texture: stream left", "texture: stream right", "texture: fusion", "texture: sinks"} <= names
        summary = json.loads((tmp_path / "out.jsonl").read_text().splitlines()[-1])
        ros = [s for s in summary["sinks"] if s["sink"].startswith("Ros2Sink")]
        assert len(ros) == 1 and ros[0]["node"] == f"{ns}/texture" and ros[0]["dropped_windows"] == 0
        assert sorted(ros[0]["subscribed"]) == sorted(f"{s}/decision" for s in streams)
    finally:
        sub.close()


def test_driver_events_reach_the_events_topic_and_the_diagnostics_within_a_second():
    """Done when (issue 33): an unplug appears on the diagnostics within 1 s (as ERROR, on the stream
    and its source), and on the latched ``~/events`` topic, which a subscriber that comes later still
    gets; a reconnect puts the source back to OK."""
    ns = unique_namespace()
    sink = Ros2Sink([TopicStream("main", ("a", "b"))], namespace=ns, diagnostics_period=60.0)
    sub = Subscriber()
    try:
        sub.subscribe("/diagnostics", DiagnosticArray, 100)
        assert sub.wait_for(lambda: sub.publishes(ns, "/diagnostics"), 10.0)
        time.sleep(0.5)                            # the publisher's side of the match (in its process)
        t = time.monotonic()
        sink.event(DriverEvent("unplug", "the port went away", time.time(), source="whiskers"))

        def status(level: int) -> bool:
            return any(st.name == "supramodal: source whiskers" and st.level == bytes([level])
                       for _, m in sub.timed("/diagnostics") for st in m.status)

        assert sub.wait_for(lambda: status(ERROR), 1.0)
        came = next(when for when, m in sub.timed("/diagnostics") for st in m.status
                    if st.name == "supramodal: source whiskers" and st.level == bytes([ERROR]))
        assert came - t < 1.0
        sink.event(DriverEvent("reconnect", "the port is back", time.time(), source="whiskers"))
        assert sub.wait_for(lambda: status(OK), 1.0)
        late = Subscriber("late")                  # after the events: the topic keeps them (transient local)
        try:
            from rclpy.qos import DurabilityPolicy, QoSProfile

            late.subscribe(f"{ns}/supramodal/events", String, QoSProfile(depth=20,
                                                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
            assert late.wait_for(lambda: len(late.messages(f"{ns}/supramodal/events")) == 2, 10.0)
            kinds = [json.loads(m.data)["event"] for m in late.messages(f"{ns}/supramodal/events")]
            assert kinds == ["unplug", "reconnect"]
        finally:
            late.close()
    finally:
        sub.close()
        sink.close()


def test_ros_arguments_remap_the_node_and_its_topics():
    """``--ros-args -r __ns:=... -r __node:=...`` (what a launch file passes) moves the node and every
    private topic; the scene's namespace is what a remapping overrides."""
    use_ros_arguments(["--ros-args", "-r", "__ns:=/robot/left_arm", "-r", "__node:=texture"])
    try:
        sink = Ros2Sink([TopicStream("main", ("a", "b"), ("Af",), ("w1",))], namespace=unique_namespace())
        try:
            assert sink.node_name == "/robot/left_arm/texture"
            assert sink.topic("main", "decision") == "/robot/left_arm/texture/main/decision"
            assert sink.topic("main", "features") == "/robot/left_arm/texture/main/features"
        finally:
            sink.close()
    finally:
        use_ros_arguments([])
    # a remapping of one node by its name (docs/ros2.md): the sink's, not a driver's beside it
    from supramodal.drivers.ros2 import RosNode

    use_ros_arguments(["--ros-args", "-r", "supramodal:__node:=texture"])
    try:
        ns = unique_namespace()
        sink = Ros2Sink([TopicStream("main", ("a", "b"))], namespace=ns)
        other = RosNode("supramodal_whiskers", ns)
        try:
            assert sink.node_name == f"{ns}/texture" and other.name == f"{ns}/supramodal_whiskers"
        finally:
            sink.close()
            other.close()
    finally:
        use_ros_arguments([])


@pytest.mark.slow   # a node process, paced in real time, with a model trained on start (or cached)
def test_a_stopped_subscriber_never_holds_the_node_up(tmp_path):
    """Done when (issue 33): a subscriber stopped with SIGSTOP, matched on every decision topic, does not
    hold the node up: the run (4 s of stream) ends on time, the jsonl sink has every window, the ros2 sink
    dropped none (DDS keeps the last few for the stopped reader and never blocks the publisher)."""
    ns = unique_namespace()
    (tmp_path / "node.toml").write_text(scene(0.5, ns, "wait_for_subscribers = 120\nhistory = 5"))
    stalled = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, ns], stdout=subprocess.PIPE, text=True)
    try:
        assert stalled.stdout is not None and stalled.stdout.readline().strip() == "up"
        node = _node(tmp_path)
        try:
            deadline = time.monotonic() + 300
            while not (tmp_path / "out.jsonl").exists() and time.monotonic() < deadline and node.poll() is None:
                time.sleep(0.05)                   # the first window: matched, the node runs
            os.kill(stalled.pid, signal.SIGSTOP)
            out, err = node.communicate(timeout=300)
        finally:
            node.kill()
        assert node.returncode == 0, err[-1500:]
        summary = json.loads((tmp_path / "out.jsonl").read_text().splitlines()[-1])
        assert summary["wall_seconds"] < 4.0 + 2.0, summary["wall_seconds"]
        windows = _windows(tmp_path / "out.jsonl")
        assert {s: len([w for w in windows if w["stream"] == s]) for s in ("left", "right")} == {"left": 40,
                                                                                               "right": 40}
        ros = next(s for s in summary["sinks"] if s["sink"].startswith("Ros2Sink"))
        assert ros["dropped_windows"] == 0 and ros["errors"] == 0, ros
        assert sorted(ros["subscribed"]) == ["fused/decision", "left/decision", "right/decision"]
    finally:
        os.kill(stalled.pid, signal.SIGCONT)
        stalled.kill()
        stalled.wait()


def test_under_use_sim_time_a_window_is_stamped_on_the_bags_clock():
    """``-p use_sim_time:=true`` (a bag played with ``--clock``): the ROS clock follows ``/clock``, and a
    window is stamped with that clock's now less the window's age on the host's clock."""
    from rosgraph_msgs.msg import Clock

    from supramodal.node.runtime.events import WindowEvent

    use_ros_arguments(["--ros-args", "-p", "use_sim_time:=true"])
    try:
        sink = Ros2Publisher([TopicStream("main", ("a", "b"))], namespace=unique_namespace())
    finally:
        use_ros_arguments([])
    pub = Subscriber("bag_clock")
    try:
        clock = pub.node.create_publisher(Clock, "/clock", 10)
        sim = 1234 * 10**9 + 500_000_000                     # 1234.5 s of the bag's time
        ros_clock = sink._ros.node.get_clock()

        def now_follows_the_bag() -> bool:
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = divmod(sim, 10**9)
            clock.publish(msg)
            return ros_clock.now().nanoseconds == sim

        assert pub.wait_for(now_follows_the_bag, 10.0)
        epoch = time.monotonic() - 10.0
        sink.start(epoch)                                    # common time 0 was 10 s ago
        sub = Subscriber()
        try:
            topic = f"{sink.node_name}/main/posteriors"
            sub.subscribe(topic, JointState, 10)
            assert sub.wait_for(lambda: sink._publishers[("main", "posteriors")].get_subscription_count() > 0, 10.0)
            time.sleep(0.3)
            import numpy as np

            age = time.monotonic() - (epoch + 9.5)           # the window ended that long ago, host's clock
            sink.emit(WindowEvent("main", 0, 9.4, 9.5, 9.5, posteriors=np.array([0.25, 0.75]), decision="b",
                                  confidence=0.75, classes=("a", "b")))
            assert sub.wait_for(lambda: len(sub.messages(topic)) == 1, 5.0)
            stamp = sub.messages(topic)[0].header.stamp
            # the bag's clock (stopped at 1234.5 s) less that age, within the few ms the call takes
            assert abs(stamp.sec * 10**9 + stamp.nanosec - (sim - age * 1e9)) < 20_000_000, (stamp, age)
        finally:
            sub.close()
    finally:
        pub.close()
        sink.close()


@pytest.mark.hardware   # a mock whisker board on a pty, paced in real time
def test_an_unplug_of_the_mock_board_is_on_the_diagnostics_within_a_second():
    """Done when (issue 33): the mock board unplugged (its pty closed) appears on ``/diagnostics`` as an
    ERROR of the source and its stream within 1 s of the unplug, and its return as OK again: the whole
    way, the serial driver, the node's event thread, the sink's queue and DDS."""
    import numpy as np

    from supramodal.banks import whisker_bank
    from supramodal.drivers.mock_whisker import FaultSpec, MockWhiskerDevice
    from supramodal.drivers.serial_whisker import SerialWhiskerDriver
    from supramodal.node.runtime.graph import Node
    from supramodal.node.runtime.sinks import QueuedSink
    from supramodal.pipeline import FeaturePipeline

    rate = 5000
    signal_ = 0.3 * np.random.default_rng(0).standard_normal((int(3.5 * rate), 1))
    dev = MockWhiskerDevice(signal_, rate, samples_per_frame=32,
                            faults=FaultSpec(unplug_every=1.2, unplug_for=0.6, unplug_limit=1), seed=1)
    ns = unique_namespace()
    sub = Subscriber()
    try:
        sub.subscribe("/diagnostics", DiagnosticArray, 100)
        with dev:
            driver = SerialWhiskerDriver(dev.port, rate=rate, channels=1, on_notice=None)
            sink = Ros2Sink([TopicStream("main", (), ("Af",), tuple(whisker_bank().names))], namespace=ns,
                            outputs=["features"])
            node = Node(driver, FeaturePipeline(whisker_bank(), ("Af",)), [QueuedSink(sink)])
            assert sub.wait_for(lambda: sub.publishes(ns, "/diagnostics"), 10.0)
            time.sleep(0.5)                        # the publisher's side of the match (in its process)

            def board():
                time.sleep(0.3)
                dev.start()
                dev.finished.wait(60)
                time.sleep(0.6)
                node.stop("test done")

            import threading

            t = threading.Thread(target=board, daemon=True)
            t.start()
            node.run()
            t.join(10)
            ledger = dev.ledger
        assert ledger.unplugs == 1

        def first(name: str, level: int, after: float) -> float | None:
            return next((when for when, m in sub.timed("/diagnostics") for st in m.status
                         if when > after and st.name == name and st.level == bytes([level])), None)

        down = first("supramodal: stream main", ERROR, ledger.unplug_times[0])
        assert down is not None and down - ledger.unplug_times[0] < 1.0, (down, ledger.unplug_times)
        assert first("supramodal: source main", ERROR, ledger.unplug_times[0]) is not None
        up = first("supramodal: source main", OK, ledger.replug_times[0])    # a reconnect: the source is back
        assert up is not None and up - ledger.replug_times[0] < 1.0, (up, ledger.replug_times)
    finally:
        sub.close()


def test_the_subscriber_docs_ros2_md_gives_to_copy_prints_the_fused_decisions():
    """docs/ros2.md's subscriber (copied as it is, its spin bounded) receives the fused decision and
    posteriors a ros2 sink in namespace /robot publishes."""
    import re

    import numpy as np

    from supramodal.node.runtime.events import WindowEvent

    doc = (Path(__file__).resolve().parents[1] / "docs" / "ros2.md").read_text()
    code = re.search(r"## A subscriber to copy\n\n```python\n(.*?)```", doc, re.S).group(1)
    assert "rclpy.spin(node)" in code
    code = code.replace("rclpy.spin(node)", "import time\nend = time.monotonic() + 20\n"
                        "while time.monotonic() < end:\n    rclpy.spin_once(node, timeout_sec=0.1)\n")
    listener = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    sink = Ros2Sink([TopicStream("fused", ("T1", "T2"))], namespace="/robot", wait_for_subscribers=20)
    try:
        sink.prepare()
        assert sink.subscribed == ["fused/decision"]
        sink.start(time.monotonic())
        post = np.array([0.8, 0.2])
        sink.emit(WindowEvent("fused", 0, 0.0, 0.1, 0.1, posteriors=post, decision="T1", confidence=0.8,
                              classes=("T1", "T2"), senses=("left", "right")))
        time.sleep(1.0)
    finally:
        sink.close()
        listener.terminate()
        out, err = listener.communicate(timeout=20)
    assert "decided T1" in out, (out, err[-800:])
    assert "{'T1': 0.8, 'T2': 0.2}" in out, out


def test_a_senses_windows_wait_for_the_fused_decision_a_bounded_time_and_none_is_lost(monkeypatch):
    """In a fused scene the senses' windows are held until the fused decision, then published with it (the
    publisher then takes the cores after the node has decided); one whose fused decision does not come is
    sent once it has waited ``HOLD_SECONDS`` (at the sink's next window), and the drain sends the rest:
    every window reaches the subscriber, in order, and the summary counts none unsent."""
    import numpy as np
    from rclpy.qos import QoSProfile

    from supramodal.node.runtime.events import WindowEvent
    from supramodal.node.runtime.sinks import ros2 as ros2_sink

    monkeypatch.setattr(ros2_sink, "HOLD_SECONDS", 0.3)
    ns = unique_namespace()
    names = ("left", "right", "fused")
    topics = {n: f"{ns}/supramodal/{n}/decision" for n in names}
    sub = Subscriber()
    for topic in topics.values():
        sub.subscribe(topic, String, QoSProfile(depth=50))
    sink = Ros2Sink([TopicStream(n, ("a", "b")) for n in names], namespace=ns, wait_for_subscribers=20,
                    fused_inputs=("left", "right"))

    def window(stream: str, i: int) -> WindowEvent:
        return WindowEvent(stream, i, 0.1 * i, 0.1 * i + 0.1, 0.1 * i + 0.1, decision="a", confidence=0.9,
                           posteriors=np.array([0.9, 0.1]), classes=("a", "b"))

    def got(stream: str) -> list[int]:
        return [json.loads(m.data)["window"] for m in sub.messages(topics[stream])]

    try:
        sink.prepare()
        assert sorted(sink.subscribed) == sorted(f"{n}/decision" for n in names)
        sink.start(time.monotonic())
        sink.emit(window("left", 0))
        sink.emit(window("right", 0))
        time.sleep(0.6)                      # published at once, they would be here by now (held: nothing)
        assert got("left") == got("right") == [], "a sense's window went out before the fused decision"
        sink.emit(window("fused", 0))
        assert sub.wait_for(lambda: got("left") == got("right") == got("fused") == [0], 10.0), \
            {n: got(n) for n in names}
        sink.emit(window("left", 1))         # its fused decision never comes (a sense given up on)
        time.sleep(0.5)
        sink.emit(window("left", 2))         # the next window: left 1 has waited long enough
        assert sub.wait_for(lambda: got("left") == [0, 1], 10.0), got("left")
        sink.drain(5.0)                      # the end: left 2 goes too
        assert sub.wait_for(lambda: got("left") == [0, 1, 2], 10.0), got("left")
        stats = sink.stats()
        assert "unsent_windows" not in stats and stats["published"]["decision"] == 5, stats
    finally:
        sink.close()
        sub.close()


def test_a_publisher_process_that_dies_is_counted_and_said_and_never_mistaken_for_a_closed_stdout():
    """The ros2 sink publishes from a process of its own: killed, each window after it is a counted error
    of the sink naming the process's end (never a ``BrokenPipeError``, which would stop the node as a
    closed stdout does), the drain says it could not, and closing does not wait on it."""
    from supramodal.node.runtime.events import WindowEvent
    from supramodal.node.runtime.sinks import QueuedSink

    sink = Ros2Sink([TopicStream("main", ("a", "b"))], namespace=unique_namespace())
    queued = QueuedSink(sink)
    queued.start(time.monotonic())

    def window(i: int) -> WindowEvent:
        return WindowEvent("main", i, 0.1 * i, 0.1 * i + 0.1, 0.1 * i + 0.1, decision="a", confidence=0.9,
                           posteriors=__import__("numpy").array([0.9, 0.1]), classes=("a", "b"))

    queued.emit(window(0))
    os.kill(sink.pid, signal.SIGKILL)
    sink._process.wait(10)
    for i in range(1, 4):
        queued.emit(window(i))
    t = time.monotonic()
    queued.drain(2.0)
    stats = queued.stats()
    queued.close()
    assert time.monotonic() - t < 5.0
    assert queued.reader_left is None
    assert stats["written"] == 1 and stats["errors"] == 3, stats
    assert "publisher process has ended (signal 9)" in stats["first_error"], stats
    assert stats["publisher_errors"] == 1 and "has ended" in stats["publisher_first_error"], stats   # its drain
    assert stats["publisher_exit"] == "signal 9", stats


def test_the_publisher_process_ends_when_the_node_is_killed():
    """A node killed with SIGKILL cannot close its sink: the publisher process sees its input end and
    ends on its own, within seconds (no orphan left publishing on the robot's bus)."""
    code = ("import sys, time\n"
            "from supramodal.node.runtime.sinks.ros2 import Ros2Sink\n"
            "from supramodal.node.runtime.sinks.ros2_publisher import TopicStream\n"
            f"sink = Ros2Sink([TopicStream('main', ('a', 'b'))], namespace={unique_namespace()!r})\n"
            "print(sink.pid, flush=True)\n"
            "time.sleep(120)\n")
    node = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert node.stdout is not None
        child = int(node.stdout.readline())
        assert _alive(child)
        node.kill()
        node.wait(10)
        deadline = time.monotonic() + 10
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child)
    finally:
        node.kill()


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, ended but not yet reaped by whoever adopted it, does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


def test_ros_arguments_that_rclpy_refuses_are_an_error_of_the_scene_naming_them():
    """The publisher process's refusal comes back as the sink's error, before the node starts: rclpy's
    own reason, and the arguments."""
    from supramodal.errors import InputError

    use_ros_arguments(["--ros-args", "-r", "not a remapping"])
    try:
        with pytest.raises(InputError, match=r"ROS 2 refused the arguments .*not a remapping"):
            Ros2Sink([TopicStream("main", ("a", "b"))], namespace=unique_namespace())
    finally:
        use_ros_arguments([])


def test_a_driver_event_that_names_no_source_goes_on_the_events_topic_as_the_jsonl_sink_writes_it():
    """The events topic carries the event's own JSON (no ``source`` made up for a one-source graph's event);
    the diagnostics file it under the graph's one source, with the counters of the moment."""
    ns = unique_namespace()
    sink = Ros2Sink([TopicStream("main", ("a", "b"))], namespace=ns, diagnostics_period=60.0)
    sink.watch(lambda: {"streams": {"main": {"windows": 3, "source": "whiskers", "frames": {}, "latency_ms": {}}}})
    sub = Subscriber()
    try:
        from rclpy.qos import DurabilityPolicy, QoSProfile

        sub.subscribe("/diagnostics", DiagnosticArray, 100)
        sub.subscribe(f"{ns}/supramodal/events", String, QoSProfile(depth=20,
                                                                    durability=DurabilityPolicy.TRANSIENT_LOCAL))
        assert sub.wait_for(lambda: sub.publishes(ns, "/diagnostics"), 10.0)
        time.sleep(0.5)
        ev = DriverEvent("gap", "12 frames lost", time.time(), stream_index=500)
        sink.event(ev)
        assert sub.wait_for(lambda: len(sub.messages(f"{ns}/supramodal/events")) == 1, 10.0)
        assert json.loads(sub.messages(f"{ns}/supramodal/events")[0].data) == ev.as_dict()
        assert sub.wait_for(lambda: any(st.name == "supramodal: source whiskers" and "gap" in st.message
                                        for m in sub.messages("/diagnostics") for st in m.status), 5.0)
        assert any(st.name == "supramodal: stream main" for m in sub.messages("/diagnostics") for st in m.status)
    finally:
        sub.close()
        sink.close()


def test_an_interrupted_wait_for_subscribers_ends_the_publisher_process():
    """Ctrl-C or SIGTERM while the sink waits for subscribers: the node will not start, nor close its
    sinks; the publisher process (which ignores both) is ended, not left on the bus."""
    sink = Ros2Sink([TopicStream("main", ("a", "b"))], namespace=unique_namespace(), wait_for_subscribers=60)

    class Interrupted(Exception):
        pass

    def interrupt(signum, frame):
        raise Interrupted

    before = signal.signal(signal.SIGALRM, interrupt)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.5)
        t = time.monotonic()
        with pytest.raises(Interrupted):
            sink.prepare()
        assert time.monotonic() - t < 5.0
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, before)
    assert sink._process.poll() is not None


def test_a_frozen_publisher_process_cannot_hold_the_node_s_end():
    """A publisher process that stops reading (SIGSTOP: a frozen rclpy) fills its pipe and holds the sink's
    thread; the node's end still comes within seconds: the summary's and the close's writes are bounded,
    and the process is killed."""
    import numpy as np

    from supramodal.node.runtime.events import WindowEvent
    from supramodal.node.runtime.sinks import QueuedSink

    sink = Ros2Sink([TopicStream("main", ("a", "b"))], namespace=unique_namespace())
    queued = QueuedSink(sink)
    queued.start(time.monotonic())
    os.kill(sink.pid, signal.SIGSTOP)
    try:
        for i in range(2000):                           # about 0.5 MB: the pipe holds 64 KiB
            queued.emit(WindowEvent("main", i, 0.1 * i, 0.1 * i + 0.1, 0.1 * i + 0.1, decision="a", confidence=0.9,
                                    posteriors=np.array([0.9, 0.1]), classes=("a", "b")))
        t = time.monotonic()
        queued.drain(1.0)
        queued.summary({})
        queued.close()
        assert time.monotonic() - t < 15.0
        assert sink._process.poll() is not None
    finally:
        with __import__("contextlib").suppress(ProcessLookupError):
            os.kill(sink.pid, signal.SIGCONT)
            os.kill(sink.pid, signal.SIGKILL)
