"""`supramodal fit`: a bank, window and features fitted to a sensor's own recordings."""

from __future__ import annotations

import csv

import pytest

from supramodal.node.cli import main
from supramodal.node.workflows.fit import Candidate, fit_manifest
from supramodal.node.workflows.training import cross_validate_manifest
from supramodal.replay.wavio import write_wav
from supramodal.bankfile import load_bank
from supramodal.textures import synthesize
from supramodal.calibration import winner

#: A fingertip-like sensor: 2.2 kHz, content below 1 kHz, four textures whose peaks lie close
#: together low in the band.
SENSOR_RATE = 2200
TEXTURES = {"silk": (60, 180, 420), "denim": (75, 210, 480), "cork": (120, 300, 700), "felt": (95, 260, 600)}


@pytest.fixture(scope="module")
def sensor(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sensor")
    rows = ["path,label"]
    for t, (name, peaks) in enumerate(TEXTURES.items()):
        for r in range(3):
            x = 0.2 * synthesize(peaks, SENSOR_RATE, 1.0, seed=100 * t + r)
            write_wav(folder / f"{name}{r}.wav", x[:, None], SENSOR_RATE)
            rows.append(f"{name}{r}.wav,{name}")
    (folder / "m.csv").write_text("\n".join(rows) + "\n")
    return folder


@pytest.mark.slow   # a long run: a whole fit (every bank setting cross-validated), run twice
def test_fit_is_deterministic_and_its_best_is_the_cross_validation_of_that_setting(sensor):
    result = fit_manifest(sensor / "m.csv", k=3, epochs=30, seed=1, quick=True)
    assert result["fs"] == SENSOR_RATE
    assert [r["step"] for r in result["rows"]].count("b_scale") == 3 and set(result["paper"]) == {"whisker", "cochlea"}
    b = result["best"]
    fields = {f: b[f] for f in Candidate.__dataclass_fields__}
    best = Candidate(**{**fields, "features": tuple(fields["features"])})
    direct = cross_validate_manifest(sensor / "m.csv", best.bank(), best.features, best.window, 3, epochs=30, seed=1)
    assert b["window_mean"] == pytest.approx(direct["window_accuracy"]["mean"], abs=1e-12)
    last = [r for r in result["rows"] if r["step"] == "features"]
    assert b["window_mean"] == max(r["window_mean"] for r in last)       # the last step keeps its best
    assert fit_manifest(sensor / "m.csv", k=3, epochs=30, seed=1, quick=True)["rows"] == result["rows"]


def test_fit_writes_a_bank_whose_model_decides_in_the_node_as_evaluate_does_on_held_out_recordings(sensor, tmp_path, capsys):
    out = tmp_path / "fit"
    assert main(["fit", str(sensor / "m.csv"), "--out", str(out), "--cv", "3", "--epochs", "30", "--quick",
                 "--trials", "4", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "best (trial" in text and "the paper's whisker bank" in text and "next: supramodal train --bank" in text
    bank = load_bank(out / "bank.json")
    assert bank.fs == SENSOR_RATE and bank.cf.max() < SENSOR_RATE / 2
    assert len(list(csv.reader(open(out / "fit.csv")))) == 1 + 4
    assert main(["train", "--bank", str(out / "bank.json"), "--manifest", str(sensor / "m.csv"),
                 "--out", str(tmp_path / "m.npz"), "--epochs", "30", "--quiet"]) == 0
    # The whole path a user takes: the fitted bank's model, in `supramodal run` on replays of
    # recordings it never met (another seed, longer), decides every window as `evaluate` does.
    import json

    from supramodal.model import TextureModel
    from supramodal.node.workflows.manifest import read_manifest
    from supramodal.node.workflows.training import evaluate_manifest, recording_windows

    rows = ["path,label"]
    for t, (name, peaks) in enumerate(TEXTURES.items()):
        write_wav(tmp_path / f"held_{name}.wav", 0.2 * synthesize(peaks, SENSOR_RATE, 2.0, seed=9000 + t)[:, None],
                  SENSOR_RATE)
        rows.append(f"held_{name}.wav,{name}")
    (tmp_path / "held.csv").write_text("\n".join(rows) + "\n")
    model = TextureModel.load(tmp_path / "m.npz")
    evaluated = evaluate_manifest(model, tmp_path / "held.csv")
    for k, rec in enumerate(read_manifest(tmp_path / "held.csv")):
        scene = tmp_path / f"run{k}.toml"
        scene.write_text(f'[driver]\ntype = "replay"\npath = "{rec.path.name}"\nspeed = "max"\n'
                         f'[bank]\nfile = "fit/bank.json"\n[model]\npath = "m.npz"\n'
                         f'[features]\nnames = {json.dumps(list(model.features))}\nwindow = {model.window_samples / SENSOR_RATE}\n')
        capsys.readouterr()
        assert main(["run", str(scene), "--json", "--quiet"]) == 0
        events = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
        node = [e["predicted"] for e in events if "predicted" in e]
        won = winner(model.log_posteriors(recording_windows(rec, model.pipeline())))
        offline = [model.classes[i] if i >= 0 else "unknown" for i in won]          # a tie is no texture
        assert len(node) == 20 and node == offline
        row = evaluated["confusion"][evaluated["labels"].index(rec.label)]
        assert [node.count(label) for label in evaluated["labels"]] == list(row)
