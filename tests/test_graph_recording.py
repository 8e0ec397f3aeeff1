"""Recording a graph of several sources, and replaying the recording in step: sessions with their
blocks' times (sidecar ``arrivals``), the replay driver's recorded timing, the recorded timebase,
and the scene `supramodal record` writes to replay it."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest

from supramodal.node.scene.build import build_node
from supramodal.node.cli import main
from supramodal.node.workflows.graph_recording import graph_recorders, write_replay_scene
from supramodal.node.scene.schema import SceneError, load_scene, scene_from_dict
from supramodal.node.runtime.sinks import ListSink
from supramodal.replay import ReplayDriver, ReplayError, Session, SessionError, load_session, save_session

from test_graph import _two_sense_scene
from two_sense_scenes import two_sense_world_toml


# -- sessions keep their blocks' times --------------------------------------------------------------

def test_arrivals_round_trip_through_a_session_to_the_microsecond(tmp_path):
    frames = np.array([50, 100, 150, 200])
    seconds = np.array([0.0101234567, 0.0203, 0.0301, 0.0402])
    save_session(tmp_path / "s", np.zeros((200, 1)), 5000, "test", arrivals=(frames, seconds, 5000.2))
    s = load_session(tmp_path / "s")
    np.testing.assert_array_equal(s.arrivals[0], frames)
    np.testing.assert_allclose(s.arrivals[1], seconds, rtol=0, atol=5e-7)
    assert s.arrivals[2] == 5000.2
    save_session(tmp_path / "plain", np.zeros((200, 1)), 5000, "test")
    assert load_session(tmp_path / "plain").arrivals is None


@pytest.mark.parametrize("arrivals, needle", [
    ({"frames": [50, 100], "seconds": [0.0, 0.1]}, "exactly the keys 'frames', 'seconds' and 'rate'"),
    ({"frames": [50, 100], "seconds": [0.0], "rate": 5000}, "one length >= 1"),
    ({"frames": [], "seconds": [], "rate": 5000}, "one length >= 1"),
    ({"frames": [50, 50], "seconds": [0.0, 0.1], "rate": 5000}, r"arrivals.frames\[1\]: 50 is not after .* \(50\)"),
    ({"frames": [0, 50], "seconds": [0.0, 0.1], "rate": 5000}, r"arrivals.frames\[0\]: 0 is outside \(0, 200\]"),
    ({"frames": [50, 300], "seconds": [0.0, 0.1], "rate": 5000}, r"arrivals.frames\[1\]: 300 is outside \(0, 200\]"),
    ({"frames": [50, 10**30], "seconds": [0.0, 0.1], "rate": 5000}, r"arrivals.frames\[1\]: 1000000000000000000000000000000 is outside"),
    ({"frames": [50, 100], "seconds": [0.1, 0.05], "rate": 5000}, r"arrivals.seconds\[1\]: 0.05 comes before"),
    ({"frames": [50, 100.5], "seconds": [0.0, 0.1], "rate": 5000}, r"arrivals.frames\[1\]: must be an integer"),
    ({"frames": [50, 100], "seconds": [0.0, "x"], "rate": 5000}, r"arrivals.seconds\[1\]: must be a finite number"),
    ({"frames": [50, 100], "seconds": [0.0, 0.1], "rate": 0}, "arrivals.rate: must be a positive number"),
])
def test_bad_arrivals_are_refused_naming_the_key(tmp_path, arrivals, needle):
    save_session(tmp_path / "s", np.zeros((200, 1)), 5000, "test")
    meta = json.loads((tmp_path / "s.json").read_text())
    meta["arrivals"] = arrivals
    (tmp_path / "s.json").write_text(json.dumps(meta))
    with pytest.raises(SessionError, match=needle):
        load_session(tmp_path / "s")


# -- the replay driver's recorded timing ------------------------------------------------------------

def _session(arrivals=((30, 70, 100), (0.5, 1.25, 2.0), 40.0), rate=40):
    x = np.arange(100, dtype=float)[:, None] / 100
    return Session(x, rate, "test", arrivals=tuple(np.asarray(a) if i < 2 else a for i, a in enumerate(arrivals)))


def test_recorded_timing_replays_the_recorded_blocks_at_their_times():
    """Blocks as recorded (sizes 30, 40, 30), each stamped with its recorded time; released at
    t0 + time / speed (tested against a day-old origin so nothing waits); at 'max', at once."""
    drv = ReplayDriver(_session(), speed=4.0, timing="recorded", on_notice=None)
    assert drv.recorded_rate == 40.0
    with drv:
        drv._t0 -= 86400.0
        blocks = [drv.read(timeout=0) for _ in range(3)]
        t0 = drv.opened_at
    assert [(b.start, b.frames, b.recorded) for b in blocks] == [(0, 30, 0.5), (30, 40, 1.25), (70, 30, 2.0)]
    np.testing.assert_allclose([b.arrival - t0 for b in blocks], [0.125, 0.3125, 0.5], atol=1e-9)
    np.testing.assert_array_equal(np.concatenate([b.data for b in blocks]), _session().data)
    with ReplayDriver(_session(), speed="max", timing="recorded", on_notice=None) as fast:
        assert [fast.read(timeout=0).recorded for _ in range(3)] == [0.5, 1.25, 2.0]


def test_a_recording_cut_short_of_its_data_ends_with_the_last_time():
    drv = ReplayDriver(_session(((30, 70), (0.5, 1.25), 40.0)), speed="max", timing="recorded", on_notice=None)
    with drv:
        blocks = [drv.read(timeout=0) for _ in range(3)]
    assert [(b.frames, b.recorded) for b in blocks] == [(30, 0.5), (40, 1.25), (30, 1.25)]


def test_a_resampled_recording_keeps_its_recorded_times_on_the_new_frames():
    """At twice the session's rate each block ends at the output frame of its recorded end, with
    its recorded time, and the recording's clock counts output frames."""
    drv = ReplayDriver(_session(), rate=80, speed="max", timing="recorded", on_notice=None)
    with drv:
        blocks = [drv.read(timeout=0) for _ in range(3)]
    assert [(b.start, b.frames, b.recorded) for b in blocks] == [(0, 60, 0.5), (60, 80, 1.25), (140, 60, 2.0)]
    assert drv.recorded_rate == 80.0


@pytest.mark.parametrize("kwargs, needle", [
    ({"source": Session(np.zeros((10, 1)), 40, "t")}, "needs a session recorded by a node of several sources"),
    ({"block_size": 10}, "leave out the block size and the device clock"),
    ({"loop": True}, "plays the session once"),
    ({"timing": "sometimes"}, "timing must be one of"),
])
def test_recorded_timing_refusals(kwargs, needle):
    args = {"source": _session(), "timing": "recorded", "on_notice": None, **kwargs}
    with pytest.raises(ReplayError, match=needle):
        ReplayDriver(args.pop("source"), **args)


# -- record a graph, replay it in step --------------------------------------------------------------

def _fused(sink):
    return [(e.window, e.senses, e.decision, "alone" in e.flags) for e in sink.windows if e.stream == "fused"]


@pytest.mark.slow   # paced: 32 s of stream at speed 8, recorded and replayed twice
def test_a_two_sense_session_recorded_live_replays_with_the_same_fused_decisions(tmp_path):
    """The two-sense world paced like live devices (speed 8, +-100 ppm, 2 ms jitter, 37 ms apart)
    recorded by the graph; its replay scene, at 'max' and at a finite speed, puts the sources on
    common time as the live run did (the clock models fed the recorded times) and pairs and fuses
    the same windows to the same decisions, at the same times (to the microsecond kept)."""
    d = _two_sense_scene(seconds=4.0)                         # 32 s of stream, 4 s of host time
    d["source"][0].update(clock_ppm=100.0, jitter=0.002, speed=8.0)
    d["source"][1].update(clock_ppm=-100.0, jitter=0.002, speed=8.0)
    d["fusion"]["max_wait"] = 10.0                            # nothing alone on a busy machine
    scene = scene_from_dict(d, str(tmp_path / "world.toml"), tmp_path)
    live = ListSink()
    graph = build_node(scene, sinks_override=[live], recorder=graph_recorders(scene, tmp_path, "s"))
    summary = graph.run()
    assert summary["clocks"]["whiskers"]["fitted"] and summary["clocks"]["mic"]["fitted"]
    # the recorders' feeds keep nothing unread (they take times from the sources themselves)
    recorder_feeds = [f for src in graph.sources for f in src.feeds if not f.track]
    assert len(recorder_feeds) == 2 and not any(f.arrivals or f.marks for f in recorder_feeds)
    replay_scene = write_replay_scene(scene, graph, tmp_path, "s")
    replay = load_scene(replay_scene)
    assert [(st.mapping, src.buffer.overrun) for st, src in zip(replay.streams, replay.sources)] == \
        [("auto", "auto")] * 2
    assert {p.name for p in tmp_path.iterdir()} == {"s.toml", "s.whiskers.wav", "s.whiskers.json", "s.mic.wav",
                                                   "s.mic.json", "s.whiskers.npz", "s.mic.npz"}
    assert load_session(tmp_path / "s.mic").arrivals[2] == 44100 * 8.0      # the clock as it was set up
    # Each stream's 320 windows fused once each, paired or alone. (The count of fused windows was asserted
    # 320: at speed 8 a window is 12.5 ms of host time and the 37 ms offset 4.6 ms, so 1.6 ms of clock error
    # under load paired each whisker window with the microphone's one before, one alone at each end: 321 in
    # a CI dry run, the replay the same. The replay's equality is what this test is about.)
    fused_live = [e for e in live.windows if e.stream == "fused"]
    for sense in ("whiskers", "mic"):
        assert sum(sense in e.senses for e in fused_live) == 320, sense
    assert sum("alone" in e.flags for e in fused_live) <= 2
    for speed in ("max", 4.0):
        again = ListSink()
        result = build_node(load_scene(replay_scene), speed=speed, sinks_override=[again]).run()
        assert _fused(again) == _fused(live)
        for a, b in zip((e for e in live.windows if e.stream == "fused"),
                        (e for e in again.windows if e.stream == "fused")):
            assert (a.start, a.end) == (b.start, b.end)     # the clocks were fed the very same stamps
        assert result["clocks"]["whiskers"]["ppm"] == pytest.approx(summary["clocks"]["whiskers"]["ppm"], abs=0.5)
        assert result["fusion"]["window_accuracy"] == summary["fusion"]["window_accuracy"]


# the early network's training is slow (a long run: an early-fusion network trained on the spot)
@pytest.mark.parametrize("fusion", ['weight = "learn"', pytest.param('method = "early"', marks=pytest.mark.slow)])
def test_record_of_a_graph_scene_writes_the_sessions_models_and_replay_scene(tmp_path, capsys, fusion):
    d = _two_sense_scene(seconds=0.5)
    lines = ["[[source]]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in s.items()) for s in d["source"]]
    for st in d["stream"]:
        lines.append(f'[[stream]]\nname = "{st["name"]}"\nsource = "{st["source"]}"\n[stream.bank]\n'
                     f'kind = "{st["bank"]["kind"]}"\n[stream.model]\ntrain_on_start = true\n')
    # max_wait: on a loaded machine a window half a second late was decided alone in the recording's live run and
    # paired in its replay (a CI run); the test asks whether the replay decides as the recording did, not when
    lines.append(f'[fusion]\nstreams = ["whiskers", "mic"]\n{fusion}\nmax_wait = 30\n[[sink]]\ntype = "jsonl"\n'
                 'path = "live.jsonl"\n')
    (tmp_path / "w.toml").write_text("\n".join(lines))
    out = tmp_path / "rec"
    assert main(["record", str(tmp_path / "w.toml"), "--out", str(out), "--name", "s", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert f"supramodal run {out / 's.toml'}" in err
    early = "early" in fusion
    assert {p.name for p in out.iterdir()} == {"s.toml", "s.whiskers.wav", "s.whiskers.json", "s.mic.wav",
                                               "s.mic.json", "s.whiskers.npz", "s.mic.npz"} | ({"s.fused.npz"} if early else set())
    replay = load_scene(out / "s.toml")
    assert [s.options["timing"] for s in replay.sources] == ["recorded", "recorded"]
    if early:
        assert replay.fusion.method == "early" and replay.fusion.model == "s.fused.npz"
    else:
        assert isinstance(replay.fusion.weight, float)               # the learned weight, as learned
    # its replay decides as the recording did
    assert main(["run", str(out / "s.toml"), "--json", "--quiet"]) == 0
    replayed = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    live = [json.loads(x) for x in (tmp_path / "live.jsonl").read_text().splitlines()]
    fused = lambda events: [(e["window"], e["predicted"]) for e in events if e.get("stream") == "fused"]  # noqa: E731
    assert fused(replayed) == fused(live) and len(fused(live)) == 40
    # nothing replaced without --force, checked before anything runs
    assert main(["record", str(tmp_path / "w.toml"), "--out", str(out), "--name", "s", "--quiet"]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    # a graph's sources that label themselves keep their labels unless --replace (tests/test_labels.py)
    (tmp_path / "live.jsonl").unlink()
    assert main(["record", str(tmp_path / "w.toml"), "--out", str(out), "--name", "t", "--label", "x"]) == 2
    assert "label their streams themselves" in capsys.readouterr().err


def test_a_replay_source_with_recorded_timing_needs_a_recorded_session(tmp_path):
    save_session(tmp_path / "plain", np.zeros((5000, 1)), 5000, "test")
    d = {"source": [{"name": "a", "type": "replay", "path": "plain.wav", "timing": "recorded"}],
         "stream": [{"name": "a", "source": "a", "bank": {"kind": "whisker"}}]}
    with pytest.raises(SceneError, match='timing = "recorded": .* needs a session recorded by a node of several'):
        build_node(scene_from_dict(d, str(tmp_path / "x.toml"), tmp_path), sinks_override=[])


# -- a fusion learned and scored on recorded two-sense sessions ---------------------------------------

@pytest.mark.slow   # a long run: four recordings, two fusions trained and scored
def test_a_fusion_trained_on_recorded_sessions_scores_on_another_recording(tmp_path, capsys, monkeypatch):
    """Three recordings of the two-sense world (other contacts each: take 1, 2, 3) train the
    supramodal network and a late weight with `train --fusion --scene`; `evaluate --scene` on a
    fourth scores each stream and the fusion per window and per contact: the network decides
    what each sense alone confuses."""
    for take in (1, 2, 3, 4):
        (tmp_path / f"w{take}.toml").write_text(two_sense_world_toml(1.0, take=take))
        assert main(["record", str(tmp_path / f"w{take}.toml"), "--out", str(tmp_path / "rec"), "--name",
                     f"t{take}", "--quiet"]) == 0
    scenes = [a for t in (1, 2, 3) for a in ("--scene", str(tmp_path / "rec" / f"t{t}.toml"))]
    capsys.readouterr()
    assert main(["train", "--fusion", "early", *scenes, "--out", str(tmp_path / "early.npz"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "240 pairs of windows" in out
    # what a contact is, said where the folds are counted in them (3 recordings held more contacts than 3)
    assert re.search(r"240 pairs in \d+ contacts, a contact a run of consecutive windows of one texture;", out), out
    assert main(["train", "--fusion", "late", *scenes, "--quiet"]) == 0
    assert "set [fusion] weight = " in capsys.readouterr().out
    held = str(tmp_path / "rec" / "t4.toml")
    monkeypatch.chdir(tmp_path)                       # --fused-model is taken from here, not the scene's folder
    assert main(["evaluate", "--scene", held, "--fused-model", "early.npz", "--json", "--quiet"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["fused"]["windows"] == r["whiskers"]["windows"] == 80 and r["fused"]["contacts"] == 8
    best = max(r["whiskers"]["window_accuracy"], r["mic"]["window_accuracy"])
    assert r["fused"]["window_accuracy"] >= best + 0.2 and r["fused"]["contact_accuracy"] == 1.0
    # the scene's own (late) fusion, scored the same way, and written as files
    assert main(["evaluate", "--scene", held, "--json", "--quiet", "--out", "report"]) == 0
    late = json.loads(capsys.readouterr().out)
    # (its fused windows are not the early network's: with calibrated senses late fusion is as good, not worse)
    assert late["whiskers"] == r["whiskers"] and late["fused"]["window_accuracy"] >= best + 0.2
    assert late["fused"]["window_accuracy"] != r["fused"]["window_accuracy"] or late["fused"] != r["fused"]
    with open(tmp_path / "report" / "fusion.csv") as fh:
        rows = list(csv.reader(fh))
    assert rows[0][:5] == ["stream", "window accuracy", "windows", "contact accuracy", "contacts"]
    assert {row[0]: (float(row[1]), int(row[2])) for row in rows[1:]} == \
        {name: (v["window_accuracy"], v["windows"]) for name, v in late.items()}
    for name, v in late.items():
        with open(tmp_path / "report" / f"confusion-{name}.csv") as fh:
            table = list(csv.reader(fh))
        counts = np.array([[int(c) for c in row[1:]] for row in table[1:]])
        assert table[0][1:] == [row[0] for row in table[1:]] == v["labels"]
        assert counts.sum() == v["windows"] and np.trace(counts) / counts.sum() == pytest.approx(v["window_accuracy"])
        assert (tmp_path / "report" / f"confusion-{name}.png").stat().st_size > 0
    assert (tmp_path / "report" / "fusion.png").stat().st_size > 0
    # written once: a second run refuses to replace the files
    assert main(["evaluate", "--scene", held, "--quiet", "--out", "report"]) == 2
    assert "fusion.csv" in capsys.readouterr().err


@pytest.mark.parametrize("argv, needle", [
    (["train", "--fusion", "early", "--scene", "x.toml"], "--fusion early needs --out"),
    (["train", "--fusion", "late", "--scene", "x.toml", "--out", "w.npz"], "it writes no file: leave out --out"),
    (["train", "--scene", "x.toml", "--out", "m.npz"], "trained with --fusion early|late and one --scene"),
    (["train", "--fusion", "late", "--scene", "x.toml", "--manifest", "m.csv"], "--manifest and --cv train one sense"),
    (["train", "--out", "m.npz"], "train needs --bank, --manifest and --out"),
    (["evaluate", "m.npz", "--scene", "x.toml"], "with --scene, the scenes name the models"),
    (["evaluate", "m.npz", "--manifest", "m.csv", "--fused-model", "f.npz"], "--fused-model scores a fusion"),
])
def test_fusion_training_and_scoring_options_are_checked(tmp_path, capsys, argv, needle, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert needle in capsys.readouterr().err


def test_a_one_source_scene_cannot_train_a_fusion(tmp_path, capsys):
    (tmp_path / "one.toml").write_text('[driver]\ntype = "synth"\nseconds = 1.0\n')
    assert main(["train", "--fusion", "late", "--scene", str(tmp_path / "one.toml"), "--quiet"]) == 2
    assert "a scene with a [fusion] block of two streams is needed" in capsys.readouterr().err


# -- what a recording keeps, checked piece by piece ----------------------------------------------------

def test_a_looped_source_is_recorded_with_its_labels_on_every_pass(tmp_path):
    d = _two_sense_scene(seconds=0.25)                    # 2 s a pass
    for src in d["source"]:
        src["loop"] = True
    scene = scene_from_dict(d, str(tmp_path / "w.toml"), tmp_path)
    graph = build_node(scene, speed="max", sinks_override=[], recorder=graph_recorders(scene, tmp_path, "s"))
    graph.run(5.0)
    labels = load_session(tmp_path / "s.whiskers").labels
    assert len(labels) == 20 and labels[-1].end == pytest.approx(5.0)       # 2.5 passes of 8 textures
    assert [lab.label for lab in labels[8:16]] == [lab.label for lab in labels[:8]]


def test_a_stamp_the_clock_skips_is_left_out_of_the_recording_too(tmp_path):
    """A block stamped before the one before it is no measurement: the clock model leaves it out,
    and so does the recording (else its session would not save); it replays with the next one."""
    from supramodal.drivers.base import Block
    from supramodal.node.runtime.taps.recorder import SessionRecorder
    from supramodal.node.runtime.sources import Source

    source = Source("s", ReplayDriver((np.zeros((100, 1)), 100.0), on_notice=None), timebase="host")
    rec = SessionRecorder(tmp_path, "s", "test", keep_arrivals=True)
    rec.attach(100.0, 1, lambda: 0)
    source.recorder = rec
    source.epoch = 1000.0
    for start, arrival in ((0, 1000.10), (10, 1000.20), (20, 1000.15), (30, 1000.40)):
        source._note(Block(np.zeros((10, 1)), start, arrival))
    assert source.clock_skipped == 1
    assert list(rec._arrival_frames) == [10, 20, 40] and list(rec._arrival_seconds) == [0.1, 0.2, 0.4]


def test_a_sidecar_keeps_block_times_on_one_line_and_refuses_to_outgrow_the_reader(tmp_path, monkeypatch):
    import supramodal.replay.session as session

    save_session(tmp_path / "s", np.zeros((200, 1)), 5000, "t", arrivals=(np.arange(1, 201), np.arange(200) * 1e-3, 5e3))
    lines = (tmp_path / "s.json").read_text().splitlines()
    assert sum('"arrivals"' in line for line in lines) == 1 and len(lines) < 20
    monkeypatch.setattr(session, "MAX_SIDECAR_BYTES", 2000)
    with pytest.raises(SessionError, match="the sidecar would take .* more than the 2000"):
        save_session(tmp_path / "t", np.zeros((200, 1)), 5000, "t",
                     arrivals=(np.arange(1, 201), np.arange(200) * 1e-3, 5e3))
    assert not (tmp_path / "t.wav").exists()                 # refused before anything is written
