"""Bad input, third pass (issue 25): numbers bounded where a scene reads them, keys that do not
apply refused, two sinks on one file refused; each refusal names the key, the bound and the fix."""

from __future__ import annotations

import pytest

from supramodal.node.scene.build import build_node
from supramodal.node.scene.schema import SceneError, scene_from_dict
from supramodal.node.runtime.sinks import ListSink


def _graph(**first):
    return {"source": [{"name": "a", "type": "synth", "seconds": 1.0, **first}],
            "stream": [{"name": "s", "source": "a"}]}


@pytest.mark.parametrize("scene, needle", [
    # item 1: a ring of 37 GiB was a MemoryError traceback; 1e300 a bare numpy message
    ({"driver": {"type": "synth"}, "buffer": {"seconds": 1e6}}, r"\[buffer\] seconds: expected ring buffer capacity, "
                                                                  r"seconds, up to 600"),
    ({"driver": {"type": "synth"}, "buffer": {"seconds": 1e300}}, r"\[buffer\] seconds: expected .* up to 600"),
    ({**_graph(buffer={"seconds": 1e300})}, r"\[\[source\]\] #1 \[source.buffer\] seconds: expected .* up to 600"),
    # items 1, 2: the serial port's rate and baud rate
    ({"driver": {"type": "serial", "port": "loop://", "rate": 1e8}}, r"\(serial\) rate: expected frames per second, "
                                                                     r"Hz, up to 1e\+06"),
    ({"driver": {"type": "serial", "port": "loop://", "baudrate": 10**18}}, r"\(serial\) baudrate: expected .* up to "
                                                                            r"100000000"),
    # item 3: the LSL inlet's times
    ({"driver": {"type": "lsl", "stream": "x", "max_gap": 1e300}}, r"\(lsl\) max_gap: expected .* up to 60 s"),
    ({"driver": {"type": "lsl", "stream": "x", "resolve_timeout": 1e300}}, r"\(lsl\) resolve_timeout: expected .* up "
                                                                            r"to 3600 s"),
    ({"driver": {"type": "lsl", "stream": "x", "buffer_seconds": 1e300}}, r"\(lsl\) buffer_seconds: expected .* up "
                                                                           r"to 3600 s"),
    # item 6: speeds that never end, two-sense sets that never finish start-up or never pair
    ({"driver": {"type": "synth", "speed": 1e-300}}, r"\(synth\) speed: expected .* a factor from 0.001 to 1e\+06"),
    ({"driver": {"type": "replay", "path": "x.wav", "speed": 1e-300}}, r"\(replay\) speed: expected"),
    ({"driver": {"type": "twosense", "sense": "whiskers", "pairs": 1000000}}, r"\(twosense\) pairs: expected .* 1..25"),
    ({"driver": {"type": "twosense", "sense": "whiskers", "offset": 1e6}}, r"\(twosense\) offset: expected .* 0 to 60"),
    # item 11: keys that do not apply
    ({"driver": {"type": "synth"}, "bank": {"kind": "whisker", "channels": 7}},
     r"\[bank\] channels: a whisker bank has no 'channels'"),
    ({"driver": {"type": "synth"}, "bank": {"kind": "cochlea", "rows": "AB"}}, r"\[bank\] rows: a cochlea bank has no"),
    ({"driver": {"type": "synth"}, "bank": {"kind": "cochlea", "mean_B": 100}}, r"\[bank\] mean_B: a cochlea bank"),
    # item 16: the limit of a name is stated
    ({**_graph(name="x" * 65)}, r"name: expected a name: letters, digits, '-' or '_', at most 64 characters"),
])
def test_out_of_range_numbers_and_keys_that_do_not_apply_are_refused_naming_the_key(scene, needle):
    with pytest.raises(SceneError, match=needle):
        scene_from_dict(scene)


def test_a_ring_beyond_memory_is_refused_naming_the_key_before_anything_is_allocated():
    """600 s is a fine ring for one channel at 5 kHz, not for 64 channels at 100 kHz (31 GiB)."""
    scene = scene_from_dict({"driver": {"type": "serial", "port": "loop://", "rate": 1e5, "channels": 64},
                             "buffer": {"seconds": 600}})
    with pytest.raises(SceneError, match=r"\[buffer\] seconds: 600 s of 64 channels at 100000 Hz is a ring of 28.6 "
                                         r"GiB, more than the 1 GiB .* give fewer seconds"):
        build_node(scene, sinks_override=[ListSink()])


def test_late_fusion_keys_with_early_fusion_are_refused():
    two = {"source": [{"name": "w", "type": "twosense", "sense": "whiskers"},
                      {"name": "m", "type": "twosense", "sense": "microphone"}],
           "stream": [{"name": "w", "source": "w", "model": {"train_on_start": True}},
                      {"name": "m", "source": "m", "bank": {"kind": "cochlea"}, "model": {"train_on_start": True}}]}
    for key, value in (("weight", "learn"), ("weight", 0.5), ("sharpness", 2.0), ("correlation", 0.5)):
        with pytest.raises(SceneError, match=rf"\[fusion\] {key}: .* belong to late fusion"):
            scene_from_dict({**two, "fusion": {"streams": ["w", "m"], "method": "early", key: value}})
    assert scene_from_dict({**two, "fusion": {"streams": ["w", "m"], "method": "early"}}).fusion.method == "early"


@pytest.mark.parametrize("paths", [("out.jsonl", "out.jsonl"), ("out.jsonl", "./sub/../out.jsonl")])
def test_two_file_sinks_on_one_path_are_refused(tmp_path, paths):
    """Item 10: the file ended with lines of one stream, corrupt lines, and nothing of the other."""
    sinks = [{"type": "jsonl", "path": paths[0]}, {"type": "text", "path": paths[1]}]
    with pytest.raises(SceneError, match=r"\[\[sink\]\] #2 path: .* is the file of \[\[sink\]\] #1 too"):
        scene_from_dict({"driver": {"type": "synth"}, "sink": sinks}, base_dir=tmp_path)
    graph = {"source": [{"name": "w", "type": "twosense", "sense": "whiskers"},
                        {"name": "m", "type": "twosense", "sense": "microphone"}],
             "stream": [{"name": "w", "source": "w"}, {"name": "m", "source": "m", "bank": {"kind": "cochlea"}}],
             "sink": [{"type": "jsonl", "path": paths[0], "from": "w"}, {"type": "jsonl", "path": paths[1], "from": "m"}]}
    with pytest.raises(SceneError, match=r"\[\[sink\]\] #2 path"):
        scene_from_dict(graph, base_dir=tmp_path)
    assert not list(tmp_path.iterdir())
    # stdout twice stays allowed (a text and a JSON view of the same run), and two files are fine.
    scene_from_dict({"driver": {"type": "synth"}, "sink": [{"type": "text"}, {"type": "jsonl"}]})
    scene_from_dict({"driver": {"type": "synth"}, "sink": [{"type": "jsonl", "path": "a.jsonl"},
                                                            {"type": "jsonl", "path": "b.jsonl"}]}, base_dir=tmp_path)


def test_a_graph_sources_build_errors_name_its_source_table(tmp_path):
    """Item 17: "[[stream]] whiskers: [driver] path ..." named the wrong table for a key of [[source]] board."""
    scene = scene_from_dict({"source": [{"name": "board", "type": "replay", "path": "missing.wav"}],
                             "stream": [{"name": "whiskers", "source": "board"}]}, base_dir=tmp_path)
    with pytest.raises(SceneError, match=r"\[\[source\]\] board path: no recording at"):
        build_node(scene, sinks_override=[ListSink()])


@pytest.mark.parametrize("name", ["../x", "a/b", "x" * 65, ""])
def test_record_refuses_a_name_that_is_a_path_at_start(tmp_path, capsys, name):
    """Item 14: `record --name ../x` was accepted and failed only after training and recording,
    leaving an empty folder."""
    from supramodal.node import cli

    (tmp_path / "s.toml").write_text('[driver]\ntype = "synth"\nseconds = 0.5\n')
    with pytest.raises(SystemExit) as exit_:
        cli.main(["record", str(tmp_path / "s.toml"), "--out", str(tmp_path / "rec"), "--name", name])
    assert exit_.value.code == 2
    assert "--name: expected a name: letters, digits, '-' or '_', at most 64 characters" in capsys.readouterr().err
    assert not (tmp_path / "rec").exists()


def test_a_fused_model_error_names_its_table_once(tmp_path):
    """Item 18: "t4.toml: [fusion] t4.toml: [fusion] model: ..." repeated its prefix."""
    two = {"source": [{"name": "w", "type": "twosense", "sense": "whiskers", "seconds": 1.0},
                      {"name": "m", "type": "twosense", "sense": "microphone", "seconds": 1.0}],
           "stream": [{"name": "w", "source": "w", "model": {"train_on_start": True}},
                      {"name": "m", "source": "m", "bank": {"kind": "cochlea"}, "model": {"train_on_start": True}}],
           "fusion": {"streams": ["w", "m"], "method": "early", "model": "missing.npz"}}
    scene = scene_from_dict(two, str(tmp_path / "t4.toml"), tmp_path)
    with pytest.raises(SceneError) as caught:
        build_node(scene, sinks_override=[ListSink()])
    message = str(caught.value)
    assert message.startswith(f"{tmp_path / 't4.toml'}: [fusion] model: ") and message.count("[fusion]") == 1, message


def test_a_sink_on_a_named_pipe_never_holds_up_the_node_and_loses_nothing_once_read(tmp_path):
    """Item 8: a jsonl sink on a FIFO with no reader hung the node (open() waits for a reader, and
    no signal ends that wait); when a reader came, 19 of 20 windows were dropped."""
    import os
    import threading
    import time

    fifo = tmp_path / "windows"
    os.mkfifo(fifo)
    scene_path = tmp_path / "s.toml"
    scene_path.write_text('[driver]\ntype = "synth"\nseconds = 1.0\norder = ["T1", "T2"]\nspeed = "max"\n\n'
                          '[[sink]]\ntype = "jsonl"\npath = "windows"\n')
    from supramodal.node.scene.schema import load_scene

    # No reader at all: the node ends in bounded time, and says what it could not write.
    t = time.monotonic()
    summary = build_node(load_scene(scene_path)).run()
    assert time.monotonic() - t < 30
    (stats,) = summary["sinks"]
    assert stats["written"] == 0 and stats["dropped_windows"] == 20      # counted, not lost silently
    # A reader that comes late gets every window and the summary.
    lines = []

    def read_late():
        time.sleep(1.0)
        with open(fifo) as f:
            lines.extend(f.read().splitlines())

    reader = threading.Thread(target=read_late)
    reader.start()
    summary = build_node(load_scene(scene_path)).run()
    reader.join(timeout=30)
    assert not reader.is_alive()
    assert summary["sinks"][0]["dropped_windows"] == 0 and summary["sinks"][0]["written"] == 20
    assert len(lines) == 21 and '"summary": true' in lines[-1]
