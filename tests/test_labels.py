"""Labels of recorded graphs (issue 26, items 1 and 3): `record --label/--marks` of several sources,
on the node's common time and mapped to each source through its clock; `supramodal label REC.toml
SPANS.csv` after the fact; label times in seconds of the device's own stream."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from supramodal.node.scene.build import build_node
from supramodal.node.cli import main
from supramodal.node.workflows.graph_recording import graph_recorders
from supramodal.node.workflows.labels import LabelError, frames_at, read_spans
from supramodal.node.scene.schema import scene_from_dict
from supramodal.replay.session import load_session, save_session

WHISKERS, MIC = 5000, 44100


def _sources(ppm=(1000.0, -1000.0), seconds=0.5, order=("F1a", "F1b")):
    """Two two-sense sources on simulated clocks ``ppm`` off, the microphone 37 ms later, random
    block sizes; feature streams (no model: nothing trained)."""
    rng = np.random.default_rng(7)
    return {
        "source": [{"name": "whiskers", "type": "twosense", "sense": "whiskers", "seconds": seconds,
                    "order": list(order), "clock_ppm": ppm[0], "block": int(rng.integers(20, 300))},
                   {"name": "mic", "type": "twosense", "sense": "microphone", "seconds": seconds,
                    "order": list(order), "clock_ppm": ppm[1], "offset": 0.037, "block": int(rng.integers(200, 900))}],
        "stream": [{"name": "whiskers", "source": "whiskers", "bank": {"kind": "whisker"}},
                   {"name": "mic", "source": "mic", "bank": {"kind": "cochlea"}}],
    }


def _true_frame(t, rate, ppm, offset=0.0):
    """The sample a two-sense source takes at common time ``t``."""
    return (t - offset) * rate * (1 + ppm * 1e-6)


def test_marks_on_common_time_land_on_each_sources_own_sample(tmp_path):
    """A label started at 0.6 s of common time and ended at 0.8 s lands, in each source's session,
    at the sample that source took then (its clock 1000 ppm off, the microphone 37 ms later): not at
    0.6 s x its nominal rate (the microphone's would be 1,700 samples off)."""
    scene = scene_from_dict(_sources(), "w.toml")
    recorders = graph_recorders(scene, tmp_path, "r", replace=True)
    for rec in recorders.values():
        rec.mark_at(0.6, "F1b")
        rec.mark_at(0.8, None)
    build_node(scene, speed="max", sinks_override=[], recorder=recorders).run()
    for name, rate, ppm, offset in (("whiskers", WHISKERS, 1000.0, 0.0), ("mic", MIC, -1000.0, 0.037)):
        (label,) = load_session(tmp_path / f"r.{name}.wav").labels
        assert label.label == "F1b"
        assert label.start * rate == pytest.approx(_true_frame(0.6, rate, ppm, offset), abs=1.0)
        assert label.end * rate == pytest.approx(_true_frame(0.8, rate, ppm, offset), abs=1.0)


def test_record_marks_and_label_a_graph_recording_from_the_command_line(tmp_path, monkeypatch, capsys):
    """`record GRAPH --marks` labels every source (it exited 2 before: "--label and --marks label a
    one-source recording"); a source that labels itself is refused without --replace; --label names
    every source's whole recording."""
    (tmp_path / "g.toml").write_text(_toml(_sources()))
    out = tmp_path / "rec"
    assert main(["record", str(tmp_path / "g.toml"), "--out", str(out), "--name", "a", "--marks", "--quiet"]) == 2
    assert "--replace" in capsys.readouterr().err and not out.exists()
    monkeypatch.setattr("sys.stdin", io.StringIO("bad label\nF1a\n"))
    assert main(["record", str(tmp_path / "g.toml"), "--out", str(out), "--name", "a", "--marks", "--replace",
                 "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "'bad label' is not a name" in err
    for name in ("whiskers", "mic"):
        s = load_session(out / f"a.{name}.wav")
        assert [lab.label for lab in s.labels] == ["F1a"] and s.labels[0].end == pytest.approx(s.data.shape[0] / s.rate)
    assert main(["record", str(tmp_path / "g.toml"), "--out", str(out), "--name", "b", "--label", "F1b",
                 "--replace", "--quiet"]) == 0
    for name in ("whiskers", "mic"):
        s = load_session(out / f"b.{name}.wav")
        assert [(lab.start, lab.label) for lab in s.labels] == [(0.0, "F1b")]
        assert s.labels[0].end == pytest.approx(s.data.shape[0] / s.rate)
    with pytest.raises(SystemExit) as exit_:
        main(["record", str(tmp_path / "g.toml"), "--out", str(out), "--name", "c", "--label", "no way"])
    assert exit_.value.code == 2 and "not a name" in capsys.readouterr().err


def _toml(d: dict) -> str:
    lines = []
    for table in ("source", "stream"):
        for item in d[table]:
            lines.append(f"[[{table}]]")
            sub = {k: v for k, v in item.items() if not isinstance(v, dict)}
            lines += [f"{k} = {json.dumps(v)}" for k, v in sub.items()]
            for k, v in item.items():
                if isinstance(v, dict):
                    lines.append(f"[{table}.{k}]")
                    lines += [f"{kk} = {json.dumps(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


def _drifting_recording(tmp_path, ppm=90.0, seconds=240.0, seed=3, labels=()):
    """A one-channel 5 kHz session recorded by a graph from a device ``ppm`` fast, delivered in
    blocks of random sizes after random delays (exponential, 2 ms mean), with its replay scene."""
    rng = np.random.default_rng(seed)
    true_rate = WHISKERS * (1 + ppm * 1e-6)
    n = int(seconds * WHISKERS)
    ends = np.cumsum(rng.integers(16, 400, size=n // 16))
    ends = ends[ends < n]
    stamps = np.maximum.accumulate(0.25 + (ends - 1) / true_rate + rng.exponential(0.002, len(ends)))
    save_session(tmp_path / "r.board", np.zeros((int(ends[-1]), 1)), WHISKERS, "test", labels=labels,
                 arrivals=(ends, stamps, float(WHISKERS)))
    (tmp_path / "r.toml").write_text('[[source]]\nname = "board"\ntype = "replay"\npath = "r.board.wav"\n'
                                     'timing = "recorded"\n\n[[stream]]\nname = "board"\nsource = "board"\n')
    return 0.25, true_rate


def test_a_label_lands_at_the_right_sample_of_a_device_90_ppm_fast(tmp_path, capsys):
    """Item 3: `supramodal label` puts a span at 200 s of common time, on a device 90 ppm fast
    (4 minutes, jittered blocks), at the sample the device took then, to within one sample; frames
    / nominal rate would put it 90 samples (18 ms) early."""
    t0, true_rate = _drifting_recording(tmp_path)
    (tmp_path / "spans.csv").write_text("start,end,label\n200,210,grit\n")
    assert main(["label", str(tmp_path / "r.toml"), str(tmp_path / "spans.csv")]) == 0
    assert "board: 1 label(s) ['grit']" in capsys.readouterr().out
    (label,) = load_session(tmp_path / "r.board.wav").labels
    truth = (200 - t0) * true_rate
    assert abs(label.start * WHISKERS - truth) <= 1.0
    assert abs(label.end * WHISKERS - (210 - t0) * true_rate) <= 1.0
    assert abs((200 - t0) * WHISKERS - truth) > 80               # what reading seconds as nominal would do
    # the mapping itself: the clock replayed as the node feeds it
    frames, seconds, rate = load_session(tmp_path / "r.board.wav").arrivals
    times = np.array([1.0, 30.0, 120.0, 239.0])
    np.testing.assert_allclose(frames_at((frames, seconds, rate), times), (times - t0) * true_rate, atol=1.0)


def test_label_never_overwrites_silently_and_validates_the_spans(tmp_path, capsys):
    _drifting_recording(tmp_path, seconds=20.0, labels=[(1.0, 2.0, "old")])
    spans = tmp_path / "spans.csv"
    spans.write_text("start,end,label\n2,4,grit\n5,6,felt\n")
    assert main(["label", str(tmp_path / "r.toml"), str(spans)]) == 2
    err = capsys.readouterr().err
    assert "already holds 1 label(s)" in err and "--replace" in err
    assert [lab.label for lab in load_session(tmp_path / "r.board.wav").labels] == ["old"]
    assert main(["label", str(tmp_path / "r.toml"), str(spans), "--replace"]) == 0
    assert [lab.label for lab in load_session(tmp_path / "r.board.wav").labels] == ["grit", "felt"]
    spans.write_text("start,end,label\n30,31,late\n")
    assert main(["label", str(tmp_path / "r.toml"), str(spans), "--replace"]) == 2
    assert "starts after the recording ends" in capsys.readouterr().err


@pytest.mark.parametrize("text, needle", [
    ("start,end,label\n1,2,a\n1.5,3,b\n", r"line 3: \[1.5, 3\) 'b' overlaps \[1, 2\) 'a'"),
    ("start,end,label\n2,3,a\n1,1.5,b\n", "starts before the span above it"),
    ("start,end,label\n2,1,a\n", "end 1 s is not after start 2 s"),
    ("start,end,label\n-1,1,a\n", "start '-1' is not a finite number of seconds >= 0"),
    ("start,end,label\nnan,1,a\n", "start 'nan' is not a finite number"),
    ("start,end,label\n0,1,rough wood\n", "'rough wood' is not a name"),
    ("start,end,label\n0,1\n", "2 fields, expected 3"),
    ("begin,end,label\n0,1,a\n", "the header is 'begin,end,label'"),
    ("start,end,label\n", "no span"),
])
def test_bad_spans_are_refused_naming_the_line_and_the_fix(tmp_path, text, needle):
    (tmp_path / "s.csv").write_text(text)
    with pytest.raises(LabelError, match=needle):
        read_spans(tmp_path / "s.csv")


def _two_sessions(tmp_path):
    """A recording of two sources (``a``, ``b``), 20 s each at 5 kHz, with its replay scene."""
    ends = np.arange(500, 100_001, 500)
    for name in ("a", "b"):
        save_session(tmp_path / f"r.{name}", np.zeros((100_000, 1)), WHISKERS, "test",
                     arrivals=(ends, 0.25 + ends / WHISKERS, float(WHISKERS)))
    (tmp_path / "r.toml").write_text("".join(
        f'[[source]]\nname = "{n}"\ntype = "replay"\npath = "r.{n}.wav"\ntiming = "recorded"\n\n'
        f'[[stream]]\nname = "{n}"\nsource = "{n}"\n\n' for n in ("a", "b")))
    return [tmp_path / f"r.{n}.json" for n in ("a", "b")]


def test_spans_that_would_make_a_sidecar_too_big_to_load_are_refused_before_anything_is_written(
        tmp_path, monkeypatch, capsys):
    """Issue 35, item 1: 150,000 spans made 19.4 MB sidecars (the reader's limit is 16 MiB) and label said
    nothing: the recording no longer loaded, its old labels were gone. The size is checked first (here
    against a limit made small, MAX_SIDECAR_BYTES as the reader has it): refused, every sidecar as it was."""
    from supramodal.node.workflows import labels as labels_module

    sidecars = _two_sessions(tmp_path)
    before = [p.read_bytes() for p in sidecars]
    monkeypatch.setattr(labels_module, "MAX_SIDECAR_BYTES", max(len(b) for b in before) + 500)
    spans = tmp_path / "spans.csv"
    spans.write_text("start,end,label\n" + "".join(f"{1 + k * 0.1:.1f},{1.05 + k * 0.1:.2f},s{k}\n"
                                                   for k in range(100)))
    assert main(["label", str(tmp_path / "r.toml"), str(spans)]) == 2
    err = capsys.readouterr().err
    assert "100 spans would make r.a.json" in err and "nothing was written" in err
    assert [p.read_bytes() for p in sidecars] == before
    spans.write_text("start,end,label\n1,2,grit\n")                  # a few: written
    assert main(["label", str(tmp_path / "r.toml"), str(spans)]) == 0
    assert all(load_session(p.with_suffix(".wav")).labels[0].label == "grit" for p in sidecars)


def test_a_signal_while_label_writes_leaves_every_session_labelled_and_then_stops(tmp_path, monkeypatch):
    """Issue 35, item 4: Ctrl-C while the sidecars were replaced left one session relabelled and the other
    not. A SIGINT that comes after the first one is put in place waits until the last is: both are
    labelled, then it stops the command (KeyboardInterrupt), and no temporary file is left."""
    import os
    import signal

    from supramodal.node.workflows import labels as labels_module

    sidecars = _two_sessions(tmp_path)
    spans = tmp_path / "spans.csv"
    spans.write_text("start,end,label\n1,2,grit\n")
    real = os.replace
    calls = []

    def replace_then_signal(src, dst):
        real(src, dst)
        calls.append(dst)
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGINT)         # Ctrl-C between the two sessions
    monkeypatch.setattr(labels_module.os, "replace", replace_then_signal)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            labels_module.label_recording(tmp_path / "r.toml", spans)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert len(calls) == 2
    assert [load_session(p.with_suffix(".wav")).labels[0].label for p in sidecars] == ["grit", "grit"]
    assert not list(tmp_path.glob(".*.tmp"))
