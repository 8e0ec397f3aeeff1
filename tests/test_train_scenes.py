"""Issue 26, item 2: sense models trained straight from recorded graphs (`train --scene ... --stream`),
and a fusion that learns from recordings those models never saw, or from out-of-fold posteriors,
saying which."""

from __future__ import annotations

import numpy as np
import pytest

from supramodal.model import TextureModel
from supramodal.node.cli import main
from supramodal.node.scene.schema import load_scene
from supramodal.node.workflows.training import session_fingerprint

# One worker runs this module's tests one after the other: a fusion's test trains from the models the
# test before it writes into the module's recordings (on another worker it found none and skipped).
pytestmark = pytest.mark.xdist_group("train-scenes")


def _world(texture: str, take: int, block: int) -> str:
    """One contact of the two-sense world, both senses, no model (a robot recording), random blocks."""
    return "\n".join([
        '[[source]]\nname = "whiskers"\ntype = "twosense"\nsense = "whiskers"\nseconds = 1.5',
        f'order = ["{texture}"]\ntake = {take}\nblock = {block}\nclock_ppm = 40.0\n',
        '[[source]]\nname = "mic"\ntype = "twosense"\nsense = "microphone"\nseconds = 1.5',
        f'order = ["{texture}"]\ntake = {take}\nblock = {block * 9}\noffset = 0.037\nclock_ppm = -70.0\n',
        '[[stream]]\nname = "whiskers"\nsource = "whiskers"\n[stream.bank]\nkind = "whisker"\n',
        '[[stream]]\nname = "mic"\nsource = "mic"\n[stream.bank]\nkind = "cochlea"\n'])


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """Two takes of two textures, each recorded with `record --label --replace`."""
    root = tmp_path_factory.mktemp("rec")
    rng = np.random.default_rng(26)
    for texture in ("H1a", "H1b"):
        for take in (1, 2):
            scene = root / f"{texture}-{take}.src.toml"
            scene.write_text(_world(texture, take, int(rng.integers(20, 200))))
            assert main(["record", str(scene), "--out", str(root / "rec"), "--name", f"{texture}-{take}", "--label",
                         texture, "--replace", "--quiet"]) == 0
    return root


@pytest.fixture(scope="module")
def models_of_take_2(recordings):
    """``--model`` arguments of both streams' models trained on take 2 (the recordings have no [fusion]: --model
    names the two to fuse), for a fusion learned on take 1."""
    models = []
    for stream in ("whiskers", "mic"):
        path = recordings / f"{stream}-take-2.npz"
        assert main(["train", *_scenes(recordings, 2), "--stream", stream, "--out", str(path), "--epochs", "60",
                     "--quiet"]) == 0
        models += ["--model", f"{stream}={path}"]
    return models


def _scenes(root, take):
    return [a for t in ("H1a", "H1b") for a in ("--scene", str(root / "rec" / f"{t}-{take}.toml"))]


def test_a_sense_model_is_trained_straight_from_recorded_graphs(recordings, capsys):
    """`train --scene A --scene B --stream mic` (refused before: "a fusion is trained with --fusion"):
    the stream's bank and features from the scene, its labels from the sessions, and the sessions it
    saw named in the model."""
    out = recordings / "mic.npz"
    assert main(["train", *_scenes(recordings, 1), "--stream", "mic", "--out", str(out), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "stream mic, cochlea bank" in said and "train the fusion on other recordings" in said
    model = TextureModel.load(out)
    assert model.classes == ("H1a", "H1b") and model.bank.kind == "cochlea" and model.calibrated
    assert model.training["windows"] == 2 * 15
    assert sorted(model.training["sessions"]) == sorted(
        session_fingerprint(recordings / "rec" / f"{t}-1.mic.wav") for t in ("H1a", "H1b"))
    assert main(["train", *_scenes(recordings, 1), "--stream", "whiskers", "--out", str(recordings / "whiskers.npz"),
                 "--quiet"]) == 0
    assert TextureModel.load(recordings / "whiskers.npz").bank.kind == "whisker"


def test_a_streams_model_trains_with_gain_augmentation_by_its_bank_and_says_it(recordings, capsys, tmp_path):
    """Issue 34: `train --stream mic --augment-gains 2,0.05`, the gains left to the bank: one level for the
    microphone's cochlea; the held-out windows the originals."""
    from supramodal.model import GainAugment

    out = tmp_path / "mic-aug.npz"
    assert main(["train", *_scenes(recordings, 1), "--stream", "mic", "--out", str(out), "--augment-gains", "2,0.05",
                 "--seed", "5", "--quiet"]) == 0
    said = capsys.readouterr().out.splitlines()
    assert [line for line in said if line.startswith("gain augmentation:")] == [
        "gain augmentation: 2 more copies of each training window, one gain for all channels, exp(N(0, 0.05)) "
        "(seed 5); held-out windows, scaling and calibration on the originals; the networks cost 3 times the CPU"]
    model = TextureModel.load(out)
    assert model.augment == GainAugment(2, 0.05, False, 5) and model.bank.kind == "cochlea"
    assert model.training["windows"] == 2 * 15 and model.calibration.fitted_on["windows"] == 2 * 15


def test_an_early_fusion_trains_with_gain_augmentation_each_sense_by_its_bank_and_says_it(recordings, models_of_take_2,
                                                                                          capsys, tmp_path):
    """Issue 34: `train --fusion early --augment-gains 1,0.05`: the early network's copies scale the whiskers per
    vibrissa and the microphone by one level; the model file keeps it, per sense."""
    from supramodal.fused_model import EarlyFusionModel
    from supramodal.model import GainAugment

    out = tmp_path / "early-aug.npz"
    assert main(["train", "--fusion", "early", *_scenes(recordings, 1), *models_of_take_2, "--out", str(out),
                 "--augment-gains", "1,0.05", "--seed", "3", "--epochs", "60", "--quiet"]) == 0
    said = [line for line in capsys.readouterr().out.splitlines() if "gain augmentation:" in line]
    assert [line.split(":")[0] for line in said] == ["whiskers", "mic"]
    assert "one gain per channel" in said[0] and "one gain for all channels" in said[1]
    model = EarlyFusionModel.load(out)
    assert model.augment == (GainAugment(1, 0.05, True, 3), GainAugment(1, 0.05, False, 3))
    assert model.training["windows"] == model.calibration.fitted_on["windows"]        # held out: the originals


def test_an_early_fusion_of_few_touches_without_augmentation_is_warned_of_and_one_with_it_is_not(
        recordings, models_of_take_2, capsys, tmp_path):
    """One contact of each texture, no --augment-gains: one warning line naming the fix (an early network learns
    the touches' gains: docs/results.md); the same with --augment-gains, or a late fusion (no network), none."""
    warning = "an early network learns from 1 contact(s) of some texture, without gain augmentation"
    for extra, warned in (([], True), (["--augment-gains", "1,0.05"], False)):
        out = tmp_path / f"early{len(extra)}.npz"
        assert main(["train", "--fusion", "early", *_scenes(recordings, 1), *models_of_take_2, "--out", str(out),
                     "--epochs", "30", "--quiet", *extra]) == 0
        err = capsys.readouterr().err
        assert (warning in err) == warned, err
        if warned:
            line = next(x for x in err.splitlines() if warning in x)
            assert line.startswith("supramodal: warning: ") and "add --augment-gains 4,0.03" in line
    assert main(["train", "--fusion", "late", *_scenes(recordings, 1), *models_of_take_2, "--quiet"]) == 0
    assert "early network learns" not in capsys.readouterr().err


def test_a_fusion_says_whether_it_learned_from_unseen_recordings_or_out_of_fold(recordings, capsys):
    models = ["--model", f"whiskers={recordings / 'whiskers.npz'}", "--model", f"mic={recordings / 'mic.npz'}"]
    if not (recordings / "whiskers.npz").exists():
        pytest.skip("needs the models of the test before")
    capsys.readouterr()
    live = recordings / "run.toml"
    assert main(["train", "--fusion", "late", *_scenes(recordings, 2), *models, "--live",
                 str(recordings / "H1a-1.src.toml"), "--write-scene", str(live), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "sense posteriors: unseen (the sense models were trained on 2 and 2 other recording(s), none of these 2" \
        in said
    scene = load_scene(live)
    assert scene.fusion.streams == ("whiskers", "mic") and scene.fusion.method == "late"
    assert [s.model.path for s in scene.streams] == [str(recordings / "whiskers.npz"),
                                                              str(recordings / "mic.npz")]
    # on the very recordings the models were trained on: out-of-fold copies instead
    assert main(["train", "--fusion", "late", *_scenes(recordings, 1), *models, "--quiet"]) == 0
    assert "sense posteriors: out-of-fold (the sense models saw 4 of these recordings' sessions" in \
        capsys.readouterr().out


@pytest.mark.parametrize("argv, needle", [
    (["--stream", "nose"], "no stream 'nose'; its streams are ['whiskers', 'mic']"),
    (["--stream", "mic", "--bank", "whisker"], "leave out --manifest, --bank"),
    (["--fusion", "late", "--model", "mic"], "write STREAM=FILE"),
    (["--fusion", "late", "--model", "mic=x.npz"], "a fusion takes two"),
    (["--fusion", "late", "--model", "mic=x.npz", "--model", "whiskers=y.npz"], "no model file there"),
    (["--fusion", "late", "--live", "x.toml"], "go together"),
    (["--fusion", "late", "--augment-gains", "4"], "--augment-gains trains one sense"),
])
def test_training_from_scenes_refuses_with_the_fix(recordings, capsys, argv, needle, tmp_path):
    out = [] if "--fusion" in argv else ["--out", str(tmp_path / "m.npz")]
    assert main(["train", *_scenes(recordings, 1), *argv, *out, "--quiet"]) == 2
    assert needle in capsys.readouterr().err


def test_an_unlabelled_recording_is_refused_naming_the_fix(tmp_path, capsys):
    (tmp_path / "w.toml").write_text(_world("H1a", 1, 100))
    assert main(["record", str(tmp_path / "w.toml"), "--out", str(tmp_path / "rec"), "--name", "u", "--quiet"]) == 0
    # the two-sense driver labels its stream itself: strip the labels, as a live robot's recording has none
    import json

    for source in ("whiskers", "mic"):
        js = tmp_path / "rec" / f"u.{source}.json"
        meta = json.loads(js.read_text())
        meta["labels"] = []
        js.write_text(json.dumps(meta))
    assert main(["train", "--scene", str(tmp_path / "rec" / "u.toml"), "--stream", "mic", "--out",
                 str(tmp_path / "m.npz"), "--quiet"]) == 2
    assert "has no labels; label it (supramodal label" in capsys.readouterr().err


def test_a_recording_given_twice_or_copied_is_refused_before_training(recordings, capsys, tmp_path):
    """Issue 35, item 23: `--scene a.toml --scene a.toml` counted one recording twice, the calibration fitted on
    leaked copies (held-out log loss 0.006 against 1.559 for a.toml alone). The same samples twice, by the same
    scene or a copy under another name, are refused, naming both, for a sense model and a fusion alike."""
    import shutil

    rec = recordings / "rec"
    copy = tmp_path / "copy"
    copy.mkdir()
    for suffix in (".toml", ".whiskers.wav", ".whiskers.json", ".mic.wav", ".mic.json"):
        shutil.copyfile(rec / f"H1a-1{suffix}", copy / f"again{suffix}")
    text = (copy / "again.toml").read_text().replace("H1a-1.", "again.")
    (copy / "again.toml").write_text(text)
    twice = [*_scenes(recordings, 1), "--scene", str(rec / "H1a-1.toml")]
    copied = [*_scenes(recordings, 1), "--scene", str(copy / "again.toml")]
    for scenes in (twice, copied):
        assert main(["train", *scenes, "--stream", "whiskers", "--out", str(tmp_path / "m.npz"), "--quiet"]) == 2
        assert "H1a-1.toml's again (the same samples); give each recording once" in capsys.readouterr().err
        assert main(["train", *scenes, "--fusion", "late", "--quiet"]) == 2
        assert "H1a-1.toml's again (the same samples)" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()
