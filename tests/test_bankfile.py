"""Banks as data: descriptions, bank files, through a model file, a scene and the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from supramodal.node.scene.build import bank_for, build_node
from supramodal.node.cli import main
from supramodal.node.workflows.manifest import read_manifest
from supramodal.node.scene.schema import SceneError, load_scene
from supramodal.node.runtime.sinks import ListSink
from supramodal.node.workflows.training import recording_windows
from supramodal.replay.wavio import write_wav
from supramodal.bankfile import BankFileError, bank_from_description, load_bank, save_bank
from supramodal.banks import cochlea_bank, erb_space, whisker_bank
from supramodal.model import TextureModel

SENSOR = {"kind": "cochlea", "channels": 12, "f_low": 30.0, "f_high": 1000.0, "fs": 2200.0}


def test_recipes_give_the_banks_they_name():
    assert bank_from_description({"kind": "whisker"}).matches(whisker_bank())
    assert bank_from_description({"kind": "whisker", "rows": "AB", "mean_B": 100.0}).matches(
        whisker_bank(rows="AB", mean_B=100.0))
    sensor = bank_from_description(SENSOR)
    assert sensor.matches(cochlea_bank(n=12, f_low=30.0, f_high=1000.0, fs=2200.0))
    np.testing.assert_allclose(np.sort(sensor.cf), np.sort(erb_space(30.0, 1000.0, 12)), rtol=1e-14)
    assert sensor.cf.max() < 1000.0 < sensor.fs / 2


def test_a_bank_file_round_trips_exactly_and_through_a_model_file(tmp_path):
    sensor = bank_from_description(SENSOR)
    loaded = load_bank(save_bank(tmp_path / "b.json", sensor))
    assert loaded.fs == sensor.fs and np.array_equal(loaded.cf, sensor.cf) and np.array_equal(loaded.b, sensor.b)
    assert loaded.names == sensor.names
    rng = np.random.default_rng(0)
    values, labels = rng.random((40, 1, 12)), np.repeat([0, 1], 20)
    model = TextureModel.train(values, labels, ("a", "b"), loaded, ("Af",), 220, epochs=5, seed=0)
    again = TextureModel.load(model.save(tmp_path / "m.npz"))
    assert again.bank.matches(loaded) and again.bank.kind == "custom"


@pytest.mark.parametrize("description, match", [
    ({"kind": "custom", "fs": 2200.0, "cf": [100.0, 1100.0], "b": [20.0, 20.0]}, r"1100 Hz, outside \(0, fs/2\)"),
    ({"kind": "custom", "fs": 2200.0, "cf": [], "b": []}, "cf: expected centre frequencies"),
    ({"kind": "custom", "fs": 2200.0, "cf": [float("nan")], "b": [10.0]}, "cf: expected"),
    ({"kind": "custom", "fs": 2200.0, "cf": [100.0, 200.0], "b": [10.0]}, "one entry per channel"),
    ({"kind": "custom", "cf": [100.0], "b": [10.0]}, r"\(custom bank\): missing required key 'fs'"),
    ({"kind": "cochlea", "channels": 10, "f_high": 3000.0, "fs": 2200.0}, "outside"),
    ({"kind": "cochlea", "channels": 0}, "channels: expected an integer"),
    ({"kind": "cochlea", "fs": float("inf")}, "fs: expected"),
    ({"kind": "whisker", "rows": "AZ"}, "rows: expected"),
    ({"kind": "whisker", "channels": 3}, r"\(whisker bank\): unknown key\(s\) \['channels'\]"),
    ({"kind": "cochlea", "fs": 1e7}, r"fs: expected sample rate, Hz, > 0 and at most 1e\+06"),
    ({"kind": "fingertip"}, "kind must be one of"),
    ([1, 2], "is a table"),
])
def test_banks_that_cannot_run_are_refused_naming_the_key(description, match):
    with pytest.raises(BankFileError, match=match):
        bank_from_description(description)


@pytest.mark.parametrize("content, match", [
    ({"format": "other", "version": 1, "bank": SENSOR}, "not a supramodal bank file"),
    ({"format": "supramodal-bank", "version": 2, "bank": SENSOR}, "version 2 is not supported"),
    ({"format": "supramodal-bank", "version": True, "bank": SENSOR}, "version True is not supported"),
    ({"format": "supramodal-bank", "version": 1, "bank": SENSOR, "extra": 1}, r"unknown key\(s\) \['extra'\]"),
    ({"format": "supramodal-bank", "version": 1, "bank": {**SENSOR, "fs": 1000.0}}, "outside"),
])
def test_bad_bank_files_are_refused(tmp_path, content, match):
    (tmp_path / "b.json").write_text(json.dumps(content))
    with pytest.raises(BankFileError, match=match):
        load_bank(tmp_path / "b.json")


def test_a_scene_takes_a_bank_file_and_nothing_beside_it(tmp_path):
    save_bank(tmp_path / "b.json", bank_from_description(SENSOR))
    (tmp_path / "s.toml").write_text('[driver]\ntype = "synth"\n[bank]\nfile = "b.json"\n')
    assert bank_for(load_scene(tmp_path / "s.toml")).matches(load_bank(tmp_path / "b.json"))
    (tmp_path / "t.toml").write_text('[driver]\ntype = "synth"\n[bank]\nfile = "b.json"\nkind = "cochlea"\n')
    with pytest.raises(SceneError, match=r"\[bank\] file: a bank file describes the whole bank"):
        load_scene(tmp_path / "t.toml")


def test_a_model_on_a_sensor_bank_runs_in_the_node_as_evaluated(tmp_path, capsys):
    """A 2.2 kHz sensor: recordings at its native rate, a bank file fitted to its band, `train
    --bank FILE`, then a replay scene with the same bank file and the model: the node's window
    decisions are the model's on the same recording offline."""
    rng = np.random.default_rng(5)
    t = np.arange(int(2.2 * 2200)) / 2200
    rows = ["path,label"]
    for k, (name, f) in enumerate([("low", 120.0), ("high", 600.0)]):
        for r in range(2):
            x = 0.3 * np.sin(2 * np.pi * f * t * (1 + 0.01 * r)) + 0.05 * rng.standard_normal(t.size)
            write_wav(tmp_path / f"{name}{r}.wav", x[:, None], 2200)
            rows.append(f"{name}{r}.wav,{name}")
    (tmp_path / "m.csv").write_text("\n".join(rows) + "\n")
    save_bank(tmp_path / "sensor.json", bank_from_description(SENSOR))
    assert main(["train", "--bank", str(tmp_path / "sensor.json"), "--manifest", str(tmp_path / "m.csv"),
                 "--out", str(tmp_path / "m.npz"), "--epochs", "50"]) == 0
    err = capsys.readouterr().err
    assert "resampl" not in err                                    # the bank runs at the sensor's rate
    model = TextureModel.load(tmp_path / "m.npz")
    (tmp_path / "s.toml").write_text('[driver]\ntype = "replay"\npath = "high1.wav"\nspeed = "max"\n'
                                     '[bank]\nfile = "sensor.json"\n[model]\npath = "m.npz"\n')
    sink = ListSink()
    build_node(load_scene(tmp_path / "s.toml"), sinks_override=[sink]).run()
    offline = recording_windows(read_manifest(tmp_path / "m.csv")[3], model.pipeline())
    assert [e["predicted"] for e in sink.events] == [model.classes[k] for k in model.predict(offline)]
    assert len(sink.events) == len(offline) == 22
