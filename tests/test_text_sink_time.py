"""The text sink prints every window on one time basis, the node's common time, and says so in
its header (issue 26, item 5): a microphone window that starts 37 ms into the graph ends at
0.137 s there, as its fused window does, not at its stream's own 0.100 s."""

from __future__ import annotations

import re

import numpy as np
import pytest

from supramodal.node.scene.build import build_node
from supramodal.node.runtime.events import FUSED_STREAM, WindowEvent
from supramodal.node.scene.schema import scene_from_dict
from supramodal.node.runtime.sinks import ListSink
from supramodal.node.runtime.sinks.text import TextSink

_LINE = re.compile(r"^ *(\d+\.\d{3}) s  (\S+)")


def _lines(path):
    text = path.read_text().splitlines()
    rows = [m.groups() for m in map(_LINE.match, text) if m]
    return text[0], [(float(t), name) for t, name in rows]


def test_a_graphs_windows_are_printed_at_their_end_on_common_time(tmp_path):
    """Two sources of the two-sense world, the microphone's first sample 37 ms after the whiskers'
    (blocks of 37 and 263 frames), feature windows only: every
    line's time is its window's end on common time, and the microphone's window k ends at
    0.037 + 0.1 (k + 1) s (the offset the source was given: the independent reference)."""
    d = {"source": [{"name": "whiskers", "type": "twosense", "sense": "whiskers", "seconds": 0.5, "block": 37,
                     "speed": "max"},
                    {"name": "mic", "type": "twosense", "sense": "microphone", "seconds": 0.5, "block": 263,
                     "offset": 0.037, "speed": "max"}],
         "stream": [{"name": "whiskers", "source": "whiskers", "bank": {"kind": "whisker"}},
                    {"name": "mic", "source": "mic", "bank": {"kind": "cochlea"}}]}
    scene = scene_from_dict(d, str(tmp_path / "two.toml"), tmp_path)
    listed, text = ListSink(), TextSink(str(tmp_path / "out.txt"))
    build_node(scene, speed="max", sinks_override=[listed, text]).run()
    text.close()
    header, rows = _lines(tmp_path / "out.txt")
    assert "common time" in header and "end" in header
    events = listed.windows
    assert len(rows) == len(events) > 20
    assert sorted(rows) == sorted((round(e.end, 3), e.stream) for e in events)
    mic = sorted(t for t, name in rows if name == "mic")
    assert mic[0] == pytest.approx(0.137, abs=1e-3)                # not its own stream's 0.100
    assert np.allclose(mic, 0.037 + 0.1 * np.arange(1, len(mic) + 1), atol=1e-3)
    whiskers = sorted(t for t, name in rows if name == "whiskers")
    assert np.allclose(whiskers, 0.1 * np.arange(1, len(whiskers) + 1), atol=1e-3)


def test_a_streams_decision_and_its_fused_one_are_printed_on_one_basis(tmp_path):
    """A microphone window 0.037-0.137 s on common time (0.100 s of its own stream) and the fused
    window it makes with the whiskers' 0.000-0.100 s: both printed at 0.137 s."""
    post = np.array([0.9, 0.1])
    common = dict(posteriors=post, log_posteriors=np.log(post), classes=("T1", "T2"), decision="T1",
                  confidence=0.9, truth="T1")
    path = tmp_path / "out.txt"
    sink = TextSink(str(path))
    sink.emit(WindowEvent("mic", 0, 0.037, 0.137, 0.100, **common))
    sink.emit(WindowEvent(FUSED_STREAM, 0, 0.0, 0.137, 0.137, senses=("whiskers", "mic"), **common))
    sink.close()
    header, rows = _lines(path)
    assert "time: each window's end, s on the node's common time" in header
    assert rows == [(0.137, "mic"), (0.137, FUSED_STREAM)]


def test_two_streams_emitting_at_once_lose_no_line_and_head_the_file_once(tmp_path):
    """A text sink called on the graph's own threads (not queued) gets two streams' windows at once: the
    file, opened at the first write, is opened once and every line kept (unlocked, both threads opened it
    and a line was lost: a CI run printed 79 of 80 windows under load)."""
    import threading

    for k in range(150):
        path = tmp_path / f"out{k}.txt"
        sink = TextSink(str(path))
        start = threading.Barrier(2)

        def stream(name, sink=sink, start=start):
            start.wait()
            for w in range(5):
                sink.emit(WindowEvent(name, w, 0.1 * w, 0.1 * (w + 1), 0.1 * (w + 1), features={"A": np.ones(2)}))

        threads = [threading.Thread(target=stream, args=(n,)) for n in ("whiskers", "mic")]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        sink.close()
        header, rows = _lines(path)
        assert "common time" in header and len(rows) == 10, (k, path.read_text())
        assert path.read_text().count("common time") == 1
