"""The streaming node: replay vs offline, gaps, scenes, imports, train/evaluate, signals."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from supramodal.node.scene.build import build_node
from supramodal.node.runtime.graph import Node, channel_mapper
from supramodal.node.scene.schema import SceneError, default_scene, load_scene, scene_from_dict
from supramodal.node.runtime.sinks import ListSink, Sink
from supramodal.replay.driver import ReplayDriver, random_block_sizes
from supramodal.replay.session import save_session
from supramodal.replay.wavio import write_wav
from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.errors import InputError
from supramodal.gammatone import relative_error
from supramodal.model import TextureModel
from supramodal.pipeline import FeaturePipeline, extract_features
from supramodal.textures import reference_texture_set
from supramodal.decisions import DecisionRules

from stand_ins import StandInDriver

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data" / "lmt-surface-sounds"


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


@pytest.fixture(scope="module")
def whisker_signal():
    """Three reference textures, 3 s each, one after the other, at 5 kHz."""
    ts = reference_texture_set("whisker")
    parts = [ts.synthesize(i, duration=3.0) for i in range(3)]
    return ts, np.concatenate(parts)


@pytest.fixture(scope="module")
def small_model(whisker_signal):
    """A model of the first three reference textures, trained on their first 2 s."""
    ts, _ = whisker_signal
    bank = whisker_bank()
    values, labels = [], []
    for i in range(3):
        v = extract_features(ts.synthesize(i, duration=6.0)[: 2 * 5000], bank, ("Af",)).values
        values.append(v)
        labels.append(np.full(len(v), i))
    return TextureModel.train(np.concatenate(values), np.concatenate(labels), ts.names[:3], bank, ("Af",), 500,
                              epochs=200, seed=1)


def _run_node(driver, model=None, features=("Af",), **kw):
    pipeline = FeaturePipeline(whisker_bank(), features)
    sink = ListSink()
    kw.setdefault("overrun", "block")   # lossless replay, as the scene builder chooses for replay drivers
    if "decision" in kw:
        kw["decision"] = DecisionRules(**kw["decision"])
    Node(driver, pipeline, [sink], model=model, **kw).run()
    return sink


@pytest.mark.parametrize("block", [50, 1, 499, "random"])
def test_replay_through_node_equals_offline(tmp_path, whisker_signal, small_model, block):
    _, x = whisker_signal
    path = tmp_path / "sig.wav"
    write_wav(path, x[:, None], 5000, dtype="float64")
    block_size = random_block_sizes(1, 700) if block == "random" else block
    driver = ReplayDriver(str(path), block_size=block_size, seed=7, speed="max", on_notice=None)
    sink = _run_node(driver, model=small_model, features=("Af",))
    offline = extract_features(x, whisker_bank(), ("Af",))
    assert [e["window"] for e in sink.events] == list(range(len(offline)))
    # Features: the node's model saw exactly the offline windows; compare decisions and confidences.
    logits = small_model.logits(offline.values)          # the outputs' winner, and one where they tie at 1.0
    assert [e["predicted"] for e in sink.events] == [small_model.classes[k] for k in logits.argmax(1)]
    conf = np.exp(small_model.log_posteriors(offline.values).max(1))      # calibrated (issue 23)
    np.testing.assert_allclose([e["confidence"] for e in sink.events], np.round(conf, 4), atol=1e-12)
    assert sink.final["frames"]["dropped"] == 0 and sink.final["windows"] == len(offline)


def test_feature_windows_through_node_equal_offline_to_1e12(tmp_path, whisker_signal):
    _, x = whisker_signal
    driver = ReplayDriver((x[:, None], 5000.0), block_size=random_block_sizes(1, 300), seed=3, speed="max",
                          on_notice=None)
    sink = _run_node(driver, features=("Af", "A", "f"))
    offline = extract_features(x, whisker_bank(), ("Af", "A", "f"))
    got = np.array([[e["features"][f] for f in ("Af", "A", "f")] for e in sink.events])
    assert got.shape == offline.values.shape
    rel = relative_error(got, offline.values, axis=(0, 2))     # per feature
    assert np.all(rel <= 1e-12), rel


def test_per_channel_mapping_feeds_each_filter_its_own_signal():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((5000, 20)) * 0.1
    driver = ReplayDriver((x, 5000.0), block_size=123, speed="max", on_notice=None)
    sink = _run_node(driver, features=("A",))
    offline = extract_features(x.T, whisker_bank(), ("A",))
    got = np.array([e["features"]["A"] for e in sink.events])
    np.testing.assert_allclose(got, offline.values[:, 0], rtol=1e-12)


def test_channel_mapper_refuses_mismatch_with_a_fix():
    with pytest.raises(ValueError, match="mean"):
        channel_mapper("auto", 3, 20)
    with pytest.raises(ValueError, match="does not exist"):
        channel_mapper(5, 2, 20)
    frames = np.arange(6.0).reshape(3, 2)
    np.testing.assert_array_equal(channel_mapper("mean", 2, 20)(frames), [0.5, 2.5, 4.5])
    np.testing.assert_array_equal(channel_mapper(1, 2, 20)(frames), [1, 3, 5])


def test_filled_frames_mark_their_windows_and_are_counted(tmp_path, whisker_signal):
    _, x = whisker_signal
    x = x[:10000].copy()
    x[2600:2700] = 0.0
    save_session(tmp_path / "s", x[:, None], 5000, "test", labels=[(0.0, 1.0, "T1")], filled=[(2600, 2700)])
    driver = ReplayDriver(str(tmp_path / "s.wav"), block_size=77, speed="max", on_notice=None)
    sink = _run_node(driver, features=("A",))
    gaps = [e["window"] for e in sink.events if e.get("gap")]
    assert gaps == [5]                                   # samples 2600..2699 lie in window 5 (2500..2999)
    f = sink.final["frames"]
    assert (f["stream"], f["delivered"], f["filled"], f["dropped"]) == (10000, 9900, 100, 0)
    assert [e["truth"] for e in sink.events] == ["T1"] * 10 + [None] * 10


def test_accumulated_decision_over_the_last_windows(tmp_path, whisker_signal, small_model):
    _, x = whisker_signal
    driver = ReplayDriver((x[:, None], 5000.0), block_size=50, speed="max", on_notice=None)
    sink = _run_node(driver, model=small_model, decision={"scope": "last", "n": 5, "method": "vote"})
    acc = [e["accumulated"] for e in sink.events]
    assert [a["windows"] for a in acc[:7]] == [1, 2, 3, 4, 5, 5, 5]
    for i in range(4, len(acc)):
        votes = [e["predicted"] for e in sink.events[i - 4 : i + 1]]
        assert votes.count(acc[i]["label"]) == max(votes.count(v) for v in set(votes))


def test_contact_scope_resets_on_silence(whisker_signal, small_model):
    _, x = whisker_signal
    sig = np.concatenate([x[:5000], np.zeros(2500), x[5000:10000]])
    driver = ReplayDriver((sig[:, None], 5000.0), block_size=50, speed="max", on_notice=None)
    sink = _run_node(driver, model=small_model, decision={"scope": "contact", "contact_threshold": 0.01})
    acc = [e["accumulated"] for e in sink.events]
    assert [a["windows"] for a in acc[:10]] == list(range(1, 11))
    assert all(a["label"] is None and a["windows"] == 0 for a in acc[10:15])   # 0.5 s of silence
    assert acc[15]["windows"] == 1 and acc[24]["windows"] == 10


# -- scenes ----------------------------------------------------------------------------------------


def _scene(**sections):
    base = {"driver": {"type": "synth", "seconds": 1.0}}
    base.update(sections)
    return base


@pytest.mark.parametrize("scene, needle", [
    ({"driver": {"type": "synth"}, "bogus": {}}, "unknown section"),
    (_scene(bank={"kind": "retina"}), "[bank] kind"),
    (_scene(bank={"rows": "AZ"}), "[bank] rows"),
    (_scene(features={"names": ["Af", "Q"]}), "[features] names"),
    (_scene(features={"window": -1}), "[features] window"),
    (_scene(features={"windw": 0.1}), "unknown key(s) ['windw']"),
    (_scene(decision={"scope": "touch"}), "[decision] scope"),
    (_scene(decision={"scope": "last", "n": 0}), "[decision] n"),
    ({"driver": {"type": "replay"}}, "missing required key 'path'"),
    ({"driver": {"type": "serial", "port": "/dev/x", "rate": "fast"}}, "rate"),
    ({"driver": {"type": "bluetooth"}}, "[driver] type"),
    ({"bank": {}}, "[driver] type is required"),
    (_scene(sink=[{"type": "pigeon"}]), "[[sink]] #1 type"),
    (_scene(sink=[{"type": "jsonl", "file": "x"}]), "unknown key(s) ['file']"),
    (_scene(driver={"type": "synth", "speed": 0}), "speed"),
])
def test_scene_errors_name_the_key(scene, needle):
    with pytest.raises(SceneError) as info:
        scene_from_dict(scene, "s.toml")
    assert needle in str(info.value)


def test_scene_file_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[driver\ntype = 'synth'")
    with pytest.raises(SceneError, match="not valid TOML"):
        load_scene(bad)
    with pytest.raises(SceneError, match="no scene file"):
        load_scene(tmp_path / "missing.toml")


def test_a_scene_refused_late_leaves_no_sink_file(tmp_path):
    """The mapping is checked against the driver only when the node is built, after the sinks
    are opened: the refused scene must not leave an empty output file behind."""
    write_wav(tmp_path / "mono.wav", np.zeros(5000, np.float32), 5000)
    (tmp_path / "s.toml").write_text(
        '[driver]\ntype = "replay"\npath = "mono.wav"\nmapping = "per-channel"\n'
        '[[sink]]\ntype = "jsonl"\npath = "out.jsonl"\n')
    with pytest.raises(SceneError, match="per-channel"):
        build_node(load_scene(tmp_path / "s.toml"), speed="max")
    assert not (tmp_path / "out.jsonl").exists()
    (tmp_path / "out.jsonl").write_text("kept\n")                   # a file that was there stays
    with pytest.raises(InputError, match="out.jsonl exists; pass --force"):
        build_node(load_scene(tmp_path / "s.toml"), speed="max")
    with pytest.raises(SceneError):
        build_node(load_scene(tmp_path / "s.toml"), speed="max", overwrite=True)
    assert (tmp_path / "out.jsonl").read_text() == "kept\n"        # checked, never opened


def test_scene_refuses_a_model_for_another_bank(tmp_path, small_model):
    small_model.save(tmp_path / "whisker.npz")
    (tmp_path / "s.toml").write_text(
        '[driver]\ntype = "synth"\nseconds = 1.0\n[bank]\nkind = "cochlea"\n[model]\npath = "whisker.npz"\n')
    with pytest.raises(Exception, match="whisker bank of 20 channels"):
        build_node(load_scene(tmp_path / "s.toml"), speed="max")


def test_scene_refuses_a_model_for_other_features(tmp_path, small_model):
    small_model.save(tmp_path / "m.npz")
    (tmp_path / "s.toml").write_text('[driver]\ntype = "synth"\n[features]\nnames = ["A"]\n[model]\npath = "m.npz"\n')
    with pytest.raises(Exception, match=r"takes features \['Af'\]"):
        build_node(load_scene(tmp_path / "s.toml"), speed="max")


def test_whisker_replay_scene_runs_without_sounddevice_serial_or_lsl(tmp_path, whisker_signal):
    _, x = whisker_signal
    write_wav(tmp_path / "w.wav", x[:, None], 5000)
    scene = tmp_path / "s.toml"
    scene.write_text('[driver]\ntype = "replay"\npath = "w.wav"\nblock = 50\n[features]\nnames = ["A"]\n'
                     '[[sink]]\ntype = "jsonl"\n')
    code = (
        "import sys\n"
        "for name in ('sounddevice', 'serial', 'pylsl', 'pyxdf'):\n"
        "    sys.modules[name] = None  # any import of them fails\n"
        "from supramodal.node.cli import main\n"
        f"rc = main(['run', {str(scene)!r}, '--speed', 'max', '--quiet'])\n"
        "assert 'sounddevice' not in [m for m, v in sys.modules.items() if v is not None]\n"
        "sys.exit(rc)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(lines) == 91 and lines[-1]["summary"] is True and lines[-1]["windows"] == 90
    assert set(lines[0]["features"]) == {"A"}


def test_default_scene_is_valid_and_synthesises_held_out_textures():
    scene = default_scene()
    assert scene.only_source().type == "synth" and scene.only_stream().model.train_on_start
    assert scene.only_stream().bank.kind == "whisker"


# -- train / evaluate ---------------------------------------------------------------------------


def test_train_evaluate_round_trip_on_synthesised_recordings(tmp_path):
    from supramodal.node.cli import main

    ts = reference_texture_set("whisker")
    rows_train, rows_test = ["path,label"], ["path,label,start,end"]
    for i, name in enumerate(ts.names[:4]):
        # A 44.1 kHz copy of one recording exercises resampling to the bank's 5 kHz.
        x = ts.synthesize(i, duration=8.0)
        write_wav(tmp_path / f"{name}.wav", x[:, None], 5000)
        rows_train.append(f"{name}.wav,{name}")
        rows_test.append(f"{name}.wav,{name},6.0,8.0")
    from scipy.signal import resample_poly
    write_wav(tmp_path / "hi.wav", resample_poly(ts.synthesize(0, duration=8.0), 441, 50)[:, None], 44100)
    rows_test.append(f"hi.wav,{ts.names[0]},6.0,8.0")
    (tmp_path / "train.csv").write_text("\n".join(rows_train) + "\n")
    (tmp_path / "test.csv").write_text("\n".join(rows_test) + "\n")
    # The model is written to exactly the path given (no suffix added), and read back from it.
    assert main(["train", "--bank", "whisker", "--manifest", str(tmp_path / "train.csv"), "--out",
                 str(tmp_path / "m"), "--epochs", "200", "--quiet"]) == 0
    assert sorted(p.name for p in tmp_path.glob("m*")) == ["m"]
    assert main(["evaluate", str(tmp_path / "m"), "--manifest", str(tmp_path / "test.csv"), "--quiet"]) == 0
    model = TextureModel.load(tmp_path / "m")
    assert model.classes == tuple(sorted(ts.names[:4]))
    from supramodal.node.workflows.training import evaluate_manifest

    result = evaluate_manifest(model, tmp_path / "test.csv")
    assert set(result) >= {"window_accuracy", "recording_accuracy", "labels", "confusion"}
    assert result["window_accuracy"] > 0.6 and result["recording_accuracy"] >= 0.8
    confusion = np.array(result["confusion"])
    assert confusion.sum() == 5 * 20 and confusion.shape == (4, 4)


def test_manifest_errors(tmp_path):
    from supramodal.node.workflows.training import read_manifest

    (tmp_path / "m.csv").write_text("file,label\nx.wav,a\n")
    with pytest.raises(ValueError, match="columns must be path,label"):
        read_manifest(tmp_path / "m.csv")
    (tmp_path / "m.csv").write_text("path,label,start,end\nx.wav,a,2,1\n")
    with pytest.raises(ValueError, match="line 2"):
        read_manifest(tmp_path / "m.csv")


@pytest.mark.skipif(not SHARED_DATA.is_dir(), reason="the LMT surface recordings are not distributed with "
                    "supramodal; this check runs only on the developers' machines, which hold a copy")
def test_real_surface_recordings_cochlea(tmp_path):
    from supramodal.node.workflows.training import evaluate_manifest, train_from_manifest

    names = ["carpet", "fiber", "rough_paper", "sheep_skin", "textile", "wallpaper"]
    cut = 0.7 * 211611 / 44100
    (tmp_path / "train.csv").write_text("path,label,start,end\n" + "".join(
        f"{SHARED_DATA / n}.wav,{n},0,{cut}\n" for n in names))
    (tmp_path / "test.csv").write_text("path,label,start,end\n" + "".join(
        f"{SHARED_DATA / n}.wav,{n},{cut},\n" for n in names))
    model = train_from_manifest(tmp_path / "train.csv", cochlea_bank(), ("Af",))
    result = evaluate_manifest(model, tmp_path / "test.csv")
    # Chance is 1/6; measured 0.82 of windows and 6/6 recordings (docs/model.md).
    assert result["window_accuracy"] >= 0.6
    assert result["recording_accuracy"] >= 5 / 6


# -- signals ----------------------------------------------------------------------------------------


def _the_rest(proc: subprocess.Popen, timeout: float) -> tuple[str, str]:
    """Return what ``proc`` writes on stdout and stderr from now until it ends, killed after ``timeout`` s.

    Read through the pipes' own file objects: ``Popen.communicate`` reads their descriptors, and so misses what
    an earlier ``readline`` read ahead into the file object's buffer (a CI run lost the sixth window's line,
    which had come in with the fifth). stderr is read beside stdout, so that neither pipe fills and stalls.
    """
    timer = threading.Timer(timeout, proc.kill)
    timer.start()
    try:
        err: list[str] = []
        reader = threading.Thread(target=lambda: err.append(proc.stderr.read()))
        reader.start()
        out = proc.stdout.read()
        reader.join()
        proc.wait()
    finally:
        timer.cancel()
    return out, err[0] if err else ""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_clean_shutdown_on_signal(sig):
    """A signal stops the default scene cleanly: exit 0, no traceback, every window decided printed, the summary
    last, counting them."""
    proc = subprocess.Popen([sys.executable, "-m", "supramodal.node.cli", "run", "--json", "--quiet"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
    try:
        lines = []
        deadline = time.monotonic() + 120
        while len(lines) < 5 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(json.loads(line))
        assert len(lines) == 5, proc.stderr.read()
        proc.send_signal(sig)
        out, err = _the_rest(proc, 60)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    records = [json.loads(line) for line in out.splitlines()]
    summary = records[-1]
    assert summary["summary"] is True and summary["stopped_by"] == signal.Signals(sig).name
    assert summary["windows"] == 5 + len(records) - 1
    assert summary["stream_seconds"] < 40                 # stopped well before the 80 s session ends


# -- defaults: one home each ------------------------------------------------------------------------


def test_default_serial_scene_meets_the_frame_formats_link_budget():
    """20 channels at 5 kHz in frames of the board's size, 10 bits a byte on a UART (8N1):
    the baud rate the default serial scene opens the port with must carry them."""
    import inspect

    from supramodal.drivers.frames import frame_size
    from supramodal.drivers.mock_whisker import MockWhiskerDevice
    from supramodal.drivers.serial_whisker import DEFAULT_BAUDRATE
    from supramodal.node.scene.build import driver_for

    scene = scene_from_dict({"driver": {"type": "serial", "port": "loop://"}})
    spf = inspect.signature(MockWhiskerDevice.__init__).parameters["samples_per_frame"].default
    driver, _, _ = driver_for(scene, whisker_bank())     # the default scene's rate and channels: its bank's
    need = driver.rate / spf * frame_size(spf, driver.channels) * 10
    assert (driver.rate, driver.channels) == (whisker_bank().fs, whisker_bank().channels)
    assert need == pytest.approx(2.02e6, rel=1e-3)            # docs/serial-frames.md
    assert driver.baudrate == DEFAULT_BAUDRATE >= need
    scene = scene_from_dict({"driver": {"type": "serial", "port": "loop://", "baudrate": 4_000_000}})
    assert driver_for(scene, whisker_bank())[0].baudrate == 4_000_000


def test_replay_speed_and_block_defaults_are_the_replay_drivers(whisker_signal):
    from supramodal.node.scene.build import driver_for

    scene = scene_from_dict({"driver": {"type": "synth", "order": ["T1"], "seconds": 1.0}})
    driver, _, _ = driver_for(scene, whisker_bank())
    own = ReplayDriver((np.zeros((100, 1)), whisker_bank().fs))
    assert (driver.speed, driver._sizes) == (own.speed, own._sizes)
    driver, _, _ = driver_for(scene, whisker_bank(), speed_override="max")
    assert driver.speed == float("inf")


def test_command_line_model_and_scene_share_the_defaults():
    import inspect

    from supramodal.node.cli import build_parser
    from supramodal.features import DEFAULT_WINDOW
    from supramodal.mlp import DEFAULT_EPOCHS, train_mlp
    from supramodal.pipeline import FeaturePipeline

    parser = build_parser()
    train = parser.parse_args(["train", "--bank", "whisker", "--manifest", "m.csv", "--out", "m.npz"])
    experiment = parser.parse_args(["experiment", "fig1"])
    assert train.epochs == experiment.epochs == DEFAULT_EPOCHS
    for fn in (train_mlp, TextureModel.train):
        assert inspect.signature(fn).parameters["epochs"].default == DEFAULT_EPOCHS
    assert train.window == default_scene().only_stream().features.window == DEFAULT_WINDOW
    assert inspect.signature(FeaturePipeline).parameters["window"].default == DEFAULT_WINDOW
    assert f"(default {DEFAULT_EPOCHS})" in parser._subparsers._group_actions[0].choices["train"].format_help()


@pytest.mark.parametrize("train_fraction, accepted", [(0.75, False), (0.6, True)])
def test_held_out_share_follows_the_training_fraction(monkeypatch, train_fraction, accepted):
    """Held-out segments come from the part the model did not train on: 1 - TRAIN_FRACTION of each texture."""
    import supramodal.training as training
    from supramodal.node.scene.build import driver_for

    monkeypatch.setattr(training, "TRAIN_FRACTION", train_fraction)
    ts = reference_texture_set("whisker")
    seconds = 0.3 * ts.duration                                   # within 40 %, beyond 25 %
    scene = scene_from_dict({"driver": {"type": "synth", "order": ["T1"], "seconds": seconds}})
    if accepted:
        driver, _, _ = driver_for(scene, whisker_bank())
        assert driver.data.shape[0] == round(seconds * ts.fs)
    else:
        with pytest.raises(SceneError, match=f"at most the last 25% of the set's {ts.duration:g} s"):
            driver_for(scene, whisker_bank())


@pytest.mark.parametrize("seed", range(5))
def test_latency_histogram_percentiles_are_within_a_bin_of_the_exact_ones(seed):
    """The node's constant-memory latency record against numpy on the same values: percentiles
    (numpy's "lower" method) within the 1 % bin width, count and maximum exact."""
    from supramodal.node.runtime.latency import LatencyHistogram

    rng = np.random.default_rng(seed)
    values = np.concatenate([rng.lognormal(0.0, 1.5, int(rng.integers(1, 5000))), rng.uniform(0.01, 80.0, 50)])
    rng.shuffle(values)
    hist = LatencyHistogram()
    for v in values:
        hist.add(float(v))
    s = hist.summary()
    assert s["count"] == values.size and s["max"] == values.max()
    for q, key in ((50, "p50"), (99, "p99")):
        exact = np.percentile(values, q, method="lower")
        assert abs(s[key] / exact - 1) <= 0.0101, (q, s[key], exact)
    assert LatencyHistogram().summary() is None


class _ArrayDriver(StandInDriver):
    """A live driver's stream as an array, in random blocks (1..700 frames), NaN and Inf passed on
    as a device could deliver them (replay refuses them in its files)."""

    def __init__(self, x, rate, seed):
        self.rate, self.channels, self._x, self._i = rate, 1, x[:, None], 0
        self._rng = np.random.default_rng(seed)

    def stats(self):
        return {"frames": self._i, "filled": 0}

    def read(self, timeout=None):
        from supramodal.drivers.base import Block, DriverClosed

        if self._i >= len(self._x):
            raise DriverClosed("end of the array")
        n = int(self._rng.integers(1, 701))
        block = Block(self._x[self._i : self._i + n], self._i, time.monotonic())
        self._i += block.frames
        return block


def test_nonfinite_and_out_of_range_samples_are_replaced_counted_and_reported(tmp_path, whisker_signal):
    """A stream with NaN, Inf and a sample beyond the filterbank's max_input runs on (policy "zero"):
    each kind counted apart in the summary and shown in the text sink's summary line, and the
    feature windows are those of the stream with those samples set to 0."""
    from supramodal.node.runtime.sinks.text import TextSink

    _, x = whisker_signal
    x = x[:20000].copy()
    fb_limit = FeaturePipeline(whisker_bank(), ("Af",)).filterbank.max_input
    bad_at = {1234: np.nan, 5000: np.inf, 7777: -np.inf, 9000: 10 * fb_limit, 15000: -1e300}
    for i, v in bad_at.items():
        x[i] = v
    pipeline = FeaturePipeline(whisker_bank(), ("Af",), nonfinite="zero")
    listed, text_path = ListSink(), tmp_path / "out.txt"
    text = TextSink(str(text_path))
    Node(_ArrayDriver(x, 5000.0, seed=7), pipeline, [listed, text], overrun="block").run()
    text.close()
    s = listed.final
    assert (s["nonfinite_replaced"], s["out_of_range_replaced"]) == (3, 2)
    assert "nonfinite replaced 3, out of range replaced 2" in text_path.read_text()
    clean = x.copy()
    clean[list(bad_at)] = 0.0
    ref = extract_features(clean, whisker_bank(), ("Af",)).values
    got = np.array([e["features"]["Af"] for e in listed.events])
    assert got.shape == ref[:, 0].shape
    assert relative_error(got, ref[:, 0]) <= 1e-12


# -- sinks that block or fail never stall processing --------------------------------------------

class _BlockingSink(Sink):
    """A sink stuck on its first window until released (a stalled disk or network peer)."""

    def __init__(self):
        self.release = threading.Event()
        self.windows = 0
        self.path = None

    def emit(self, event):
        self.release.wait()
        self.windows += 1

    def summary(self, summary):
        self.final = summary

    def close(self):
        pass


class _FailingSink(_BlockingSink):
    def emit(self, event):
        self.windows += 1
        raise OSError("No space left on device")


def test_a_sink_that_blocks_or_fails_never_stalls_processing():
    """A replay at full speed with three sinks: one stuck for the whole run behind a small queue,
    one raising on every window, one plain. The plain one gets every window, the run ends at
    once, and the summary counts what the stuck one dropped and what the failing one raised."""
    from supramodal.node.runtime.sinks import QueuedSink

    x = np.random.default_rng(0).standard_normal(5000 * 20) * 0.3       # 20 s: 200 windows
    stuck, failing, plain = _BlockingSink(), _FailingSink(), ListSink()
    sinks = [QueuedSink(stuck, capacity=8), QueuedSink(failing), plain]
    node = Node(ReplayDriver((x, 5000.0), speed="max", block_size=50, on_notice=None),
                FeaturePipeline(whisker_bank(), ("Af",)), sinks)
    result = {}
    runner = threading.Thread(target=lambda: result.update(summary=node.run()), daemon=True)
    runner.start()
    runner.join(120)            # a node waiting on the stuck sink would never end: the sink is never released
    assert not runner.is_alive(), "processing waited on a stuck sink"
    stuck.release.set()
    summary = result["summary"]
    assert len(plain.events) == summary["windows"] == 200
    q_stuck, q_failing = summary["sinks"]
    # the stuck sink held one window in its call and 8 in its queue; every other window was dropped
    assert q_stuck["dropped_windows"] + q_stuck["written"] <= 200 and q_stuck["dropped_windows"] >= 200 - 9
    assert q_failing["errors"] == 200 and "No space left on device" in q_failing["first_error"]
    assert q_failing["dropped_windows"] == 0
    assert plain.final["sinks"] == summary["sinks"]


class _Refusing(StandInDriver):
    """A live board whose every frame the driver refuses (another channel count than the scene's): it says
    so, and delivers nothing."""

    rate, channels = 5000.0, 1

    def stats(self):
        return {"frames": 0, "filled": 0}

    def read(self, timeout=None):
        self._record("channels", "frame has 1 channels; configured for 20")
        time.sleep(0.01)
        return None


def test_a_source_that_delivers_nothing_does_not_keep_the_stream_length_from_ending_the_run(monkeypatch):
    """--seconds on a source that never delivers a sample: the run ends on the wall clock (twice the stream's
    time, at least SILENT_SOURCE_GRACE more), and says which source and why; one that delivers runs its length."""
    import supramodal.node.runtime.graph as graph_module

    monkeypatch.setattr(graph_module, "SILENT_SOURCE_GRACE", 0.5)
    sink = ListSink()
    node = Node(_Refusing(), FeaturePipeline(whisker_bank(), ("Af",)), [sink])
    t = time.monotonic()
    summary = node.run(max_seconds=0.3)
    took = time.monotonic() - t
    assert 0.8 <= took < 10.0, took                 # 0.3 s of stream + 0.5 s, then the next check of the loop
    assert "source(s) main delivered no sample" in summary["stopped_by"] and "0.3 s of stream" in summary["stopped_by"]
    assert sink.windows == [] and any(ev.kind == "channels" for ev in sink.driver_events)
    # a replay at max speed reaches its length long before: the rule never fires
    x = 0.1 * np.random.default_rng(0).standard_normal((5000, 1))
    replayed = Node(ReplayDriver((x, 5000.0), speed="max", on_notice=None), FeaturePipeline(whisker_bank(), ("Af",)),
                    [ListSink()]).run(max_seconds=0.5)
    assert replayed["stopped_by"] == "stream length reached"
