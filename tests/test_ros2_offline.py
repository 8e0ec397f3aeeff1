"""The ROS 2 sink's parts that need no rclpy: ROS names, the command line's ``--ros-args``, the
diagnostics' levels, the refusals a scene gets before anything starts, and the message when rclpy is
missing (issue 33, item 1)."""

from __future__ import annotations

import sys

import pytest

from supramodal.drivers.base import DriverEvent
from supramodal.drivers.ros2 import (
    Ros2Unavailable,
    check_namespace,
    check_node_name,
    import_rclpy,
    ros_arguments,
    split_ros_arguments,
    use_ros_arguments,
)
from supramodal.node.runtime.sinks.ros2_publisher import ERROR, OK, WARN, SourceState, diagnostic_report


@pytest.mark.parametrize("name, ok", [("supramodal", True), ("_x1", True), ("texture_node", True), ("", False),
                                      ("1st", False), ("a-b", False), ("a__b", False), ("a/b", False), (3, False)])
def test_node_names_follow_ros_rules(name, ok):
    assert check_node_name(name) is ok


@pytest.mark.parametrize("ns, ok", [("", True), ("/", True), ("/robot", True), ("robot/arm_2", True),
                                    ("/robot/", False), ("//robot", False), ("/1robot", False), ("/a-b", False),
                                    (None, False)])
def test_namespaces_follow_ros_rules(ns, ok):
    assert check_namespace(ns) is ok


def test_ros_arguments_are_taken_off_the_command_line_up_to_their_end_marker():
    own, ros = split_ros_arguments(["run", "s.toml", "--ros-args", "-r", "__ns:=/robot", "--", "--speed", "max",
                                    "--ros-args", "-p", "use_sim_time:=true"])
    assert own == ["run", "s.toml", "--speed", "max"]
    assert ros == ["--ros-args", "-r", "__ns:=/robot", "--ros-args", "-p", "use_sim_time:=true"]
    assert split_ros_arguments(["run", "--speed", "max"]) == (["run", "--speed", "max"], [])


def test_the_command_line_keeps_ros_arguments_for_the_node_and_parses_the_rest(capsys):
    from supramodal.node.cli import main

    try:
        assert main(["run", "--print-scene", "--ros-args", "-r", "__ns:=/robot", "-r", "__node:=texture"]) == 0
        assert ros_arguments() == ["--ros-args", "-r", "__ns:=/robot", "-r", "__node:=texture"]
        assert "[driver]" in capsys.readouterr().out           # the scene printed: the rest was parsed
        assert main(["run", "--print-scene"]) == 0
        assert ros_arguments() == []                          # each command line says its own
    finally:
        use_ros_arguments([])


def test_without_rclpy_the_error_names_the_extra_and_a_sourced_ros(monkeypatch):
    monkeypatch.setitem(sys.modules, "rclpy", None)           # import rclpy raises ImportError
    with pytest.raises(Ros2Unavailable, match=r'pip install "supramodal\[ros2\]".*source /opt/ros'):
        import_rclpy()


def _health(filled=0, dropped=0, alone=0, sink_dropped=0):
    return {"streams": {"main": {"windows": 12, "source": "whiskers", "latency_ms": {"p50": 1.0, "p99": 2.5, "max": 3.0},
                                 "frames": {"delivered": 6000 - filled - dropped, "filled": filled, "dropped": dropped,
                                            "stream": 6000}}},
            "clocks": {"whiskers": {"ppm": 12.5, "jitter_ms": 0.3, "delay_ms": 1.2}},
            "fusion": {"windows": 5, "paired": 5 - alone, "alone": alone, "late": {}},
            "sinks": [{"sink": "JsonLinesSink", "written": 10, "dropped_windows": sink_dropped, "dropped_events": 0,
                       "errors": 0}]}


def _by_name(statuses):
    return {s.name: s for s in statuses}


#: The reports' time (``time.time()`` units): a fixed one, so that no report depends on the wall clock.
NOW = 1_000_000.0


def test_diagnostics_say_what_changed_since_the_last_report_and_an_unplug_is_an_error():
    before = _health()
    steady = _by_name(diagnostic_report("n", _health(), {}, before, NOW))
    assert {s.level for s in steady.values()} == {OK}
    values = dict(steady["n: stream main"].values)
    assert values["frames_delivered"] == "6000" and values["latency_p99_ms"] == "2.5" and values["clock_ppm"] == "12.5"
    assert steady["n: stream main"].hardware_id == "whiskers"

    lossy = _by_name(diagnostic_report("n", _health(filled=40, dropped=2, alone=3, sink_dropped=1), {}, before,
                                       NOW))
    assert lossy["n: stream main"].level == WARN and "40 frames filled and 2 dropped" in lossy["n: stream main"].message
    assert lossy["n: fusion"].level == WARN and lossy["n: sinks"].level == WARN
    # the same counts a period later: nothing new, all OK again
    again = _by_name(diagnostic_report("n", _health(filled=40, dropped=2, alone=3, sink_dropped=1), {},
                                       _health(filled=40, dropped=2, alone=3, sink_dropped=1), NOW))
    assert {s.level for s in again.values()} == {OK}

    state = SourceState()
    state.last, state.unplugged = DriverEvent("unplug", "the port went away", NOW - 60.0, source="whiskers"), True
    state.counts["unplug"] += 1
    down = _by_name(diagnostic_report("n", _health(), {"whiskers": state}, before, NOW))
    assert down["n: stream main"].level == ERROR and "unplugged" in down["n: stream main"].message
    assert down["n: source whiskers"].level == ERROR and dict(down["n: source whiskers"].values)["events_unplug"] == "1"

    gap = SourceState()
    gap.last = DriverEvent("gap", "12 frames lost", 1000.0, source="whiskers")
    assert _by_name(diagnostic_report("n", _health(), {"whiskers": gap}, before, 1001.0))["n: source whiskers"].level \
        == WARN                                             # a lossy event of the last 2 s
    assert _by_name(diagnostic_report("n", _health(), {"whiskers": gap}, before, 1002.5))["n: source whiskers"].level \
        == OK

    starting = diagnostic_report("n", None, {}, None, NOW)
    assert len(starting) == 1 and starting[0].level == OK and "starting up" in starting[0].message
    # an event while the node starts up (a port that went away during the training) is said all the same
    assert [s.level for s in diagnostic_report("n", None, {"whiskers": state}, None, NOW)] == [OK, ERROR]


def test_a_scene_with_a_bad_ros2_sink_is_refused_naming_the_key_before_anything_starts(tmp_path):
    from supramodal.node.scene.schema import SceneError, scene_from_dict

    base = {"driver": {"type": "synth", "seconds": 1.0}, "model": {"train_on_start": True}}
    for key, value, words in [("namespace", "/robot/", "namespace"), ("node_name", "9lives", "node_name"),
                              ("outputs", ["decision", "labels"], "outputs"),
                              ("history", 0, "history"),
                              ("diagnostics_period", 0.0, "diagnostics_period")]:
        with pytest.raises(SceneError, match=words):
            scene_from_dict({**base, "sink": [{"type": "ros2", key: value}]}, "s.toml", tmp_path)


def test_a_stream_whose_name_cannot_be_a_topic_part_is_refused_saying_how_to_rename_it(tmp_path):
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import SceneError, scene_from_dict

    d = {"source": [{"name": "left-whisker", "type": "synth", "seconds": 1.0}],
         "stream": [{"name": "left-whisker", "source": "left-whisker", "model": {"train_on_start": True}}],
         "sink": [{"type": "ros2"}]}
    scene = scene_from_dict(d, "s.toml", tmp_path)
    with pytest.raises(SceneError, match=r"left-whisker.*ROS topic name; rename"):
        build_node(scene)


def test_a_frame_to_the_publisher_process_comes_back_as_it_was_sent():
    """The pipe's frames (JSON, then a NUL and float64 bytes): headers of every JSON kind, NUL characters
    and NaN in them, payloads holding NUL bytes, and none; checked against the values themselves."""
    import math

    import numpy as np

    from supramodal.node.runtime.sinks.ros2 import decode, encode

    rng = np.random.default_rng(7)
    for _ in range(200):
        values = rng.standard_normal(int(rng.integers(0, 70)))
        values[rng.random(values.size) < 0.1] = 0.0           # 0.0 is eight NUL bytes
        header = {"op": "window", "stream": "a\0b\n\u00e9", "end": float(rng.random()), "n": values.size,
                  "decision": {"predicted": "x", "confidence": np.float32(0.5), "nan": math.nan},
                  "classes": None}
        got, payload = decode(encode(header, values.tobytes()))
        assert got["stream"] == "a\0b\n\u00e9" and got["end"] == header["end"] and got["n"] == values.size
        assert got["decision"]["confidence"] == 0.5 and math.isnan(got["decision"]["nan"]) and got["classes"] is None
        assert np.array_equal(np.frombuffer(payload, dtype=np.float64), values)
    assert decode(encode({"op": "close"})) == ({"op": "close"}, b"")


def test_a_fast_dds_port_segment_left_empty_is_found_and_refused_naming_what_to_remove(tmp_path, monkeypatch):
    """An empty /dev/shm/fastdds_portN older than a few seconds (its maker killed before sizing it) makes every
    later participant spin for ever in rclpy.create_node: the node refuses to start instead, naming the file.
    Lock files (..._el), sized segments, a segment being made this instant and other middlewares are left be."""
    import os
    import time

    import supramodal.drivers.ros2 as ros2

    now = time.time()

    def make(name: str, size: int = 0, age: float = 60.0) -> None:
        (tmp_path / name).write_bytes(b"x" * size)
        os.utime(tmp_path / name, (now - age, now - age))

    make("fastdds_port7000")                                   # stale
    make("fastdds_port7413_el")                                # a lock file: empty by design
    make("fastdds_port7001", size=4096)                        # a live port
    make("fastdds_port7002", age=0.5)                          # being made now
    make("fastdds_0123456789abcdef")                           # a participant's own segment, not a port
    assert ros2.stale_port_segments(tmp_path, now) == [tmp_path / "fastdds_port7000"]
    assert ros2.stale_port_segments(tmp_path / "absent", now) == []
    monkeypatch.setattr(ros2, "SHARED_MEMORY_DIR", tmp_path)
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    with pytest.raises(Ros2Unavailable, match=f"rm {tmp_path / 'fastdds_port7000'}"):
        ros2.check_shared_memory()
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")
    ros2.check_shared_memory()                                 # not Fast DDS: nothing to check
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_dynamic_cpp")
    (tmp_path / "fastdds_port7000").unlink()
    ros2.check_shared_memory()
