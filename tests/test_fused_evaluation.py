"""`evaluate --scene` on a recorded graph (issue 26, item 4): `--contact-windows N` cuts each run
of one texture into contacts of N windows, and the JSON, CSV, PNG and table name the fusion
scored (method, weight, sharpness, correlation, model files) and what a contact is."""

from __future__ import annotations

import csv
import json
import tomllib

import numpy as np
import pytest

from supramodal.node.scene.build import build_node
from supramodal.node.cli import main
from supramodal.node.workflows.reports import FUSION_COLUMNS
from supramodal.node.scene.schema import load_scene
from supramodal.node.runtime.sinks import ListSink
from two_sense_scenes import two_sense_world_toml


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """One recording of the two-sense world, 0.8 s per texture (8 windows a run), and its replay scene."""
    folder = tmp_path_factory.mktemp("fused_eval")
    (folder / "w.toml").write_text(two_sense_world_toml(0.8, take=1, blocks=(37, 263)))
    assert main(["record", str(folder / "w.toml"), "--out", str(folder / "rec"), "--name", "t", "--quiet"]) == 0
    return folder / "rec" / "t.toml"


def _reference_contacts(scene_path, n):
    """Contacts counted and decided by hand from the replay's window events: per stream, each
    run of consecutive windows of one truth cut into n windows from its start, each decided by
    the largest summed log-posterior."""
    sink = ListSink()
    build_node(load_scene(scene_path), speed="max", sinks_override=[sink]).run()
    out = {}
    for name in ("whiskers", "mic", "fused"):
        events = [e for e in sink.windows if e.stream == name and e.truth is not None]
        runs, run = [], [events[0]]
        for e in events[1:]:
            if e.truth == run[-1].truth and e.window == run[-1].window + 1:
                run.append(e)
            else:
                runs.append(run)
                run = [e]
        runs.append(run)
        right = []
        for run in runs:
            size = len(run) if n is None else n
            for k in range(len(run) // size):
                part = run[k * size:(k + 1) * size]
                total = np.sum([e.log_posteriors for e in part], axis=0)
                right.append(part[0].classes[int(np.argmax(total))] == part[0].truth)
        out[name] = (len(right), float(np.mean(right)), sorted({len(r) for r in runs}))
    return out


@pytest.mark.parametrize("n", [None, 1, 3])
def test_contacts_of_n_windows_are_cut_and_pooled_as_counted_by_hand(recording, capsys, n):
    ref = _reference_contacts(recording, n)
    assert ref["fused"][2] == [8]                           # every run of one texture: 8 windows
    argv = ["evaluate", "--scene", str(recording), "--json", "--quiet"]
    assert main(argv + ([] if n is None else ["--contact-windows", str(n)])) == 0
    r = json.loads(capsys.readouterr().out)
    for name, (count, accuracy, _) in ref.items():
        assert r[name]["contacts"] == count == 8 * (1 if n is None else 8 // n)
        assert r[name]["contact_accuracy"] == pytest.approx(accuracy)
        assert r[name]["contact_windows"] == n
    if n == 1:                                             # a contact of one window is the window
        assert r["fused"]["contact_accuracy"] == pytest.approx(r["fused"]["window_accuracy"])


def test_the_outputs_name_the_fusion_scored(recording, tmp_path, capsys):
    replay = tomllib.loads(recording.read_text())
    fusion = replay["fusion"]                                # the learned weight the recording used
    assert main(["evaluate", "--scene", str(recording), "--json", "--quiet", "--contact-windows", "4",
                 "--out", str(tmp_path / "report")]) == 0
    r = json.loads(capsys.readouterr().out)
    (late,) = r["fused"]["scored"]
    assert late["method"] == "late"
    assert late["weight"] == pytest.approx(fusion["weight"]) and late["sharpness"] == pytest.approx(fusion["sharpness"])
    assert late["correlation"] == pytest.approx(fusion["correlation"]) and late["model"] is None
    folder = recording.parent
    assert late["senses"] == {"whiskers": str(folder / "t.whiskers.npz"), "mic": str(folder / "t.mic.npz")}
    assert r["whiskers"]["scored"] == [{"scene": str(recording), "model": str(folder / "t.whiskers.npz")}]
    with open(tmp_path / "report" / "fusion.csv") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == FUSION_COLUMNS
    by = {row[0]: dict(zip(FUSION_COLUMNS, row)) for row in rows[1:]}
    assert by["fused"]["method"] == "late" and by["fused"]["windows per contact"] == "4"
    assert float(by["fused"]["weight"]) == pytest.approx(fusion["weight"], rel=1e-5)
    assert float(by["fused"]["sharpness"]) == pytest.approx(fusion["sharpness"], rel=1e-5)
    assert by["fused"]["model files"] == "t.whiskers.npz + t.mic.npz"
    assert by["mic"]["model files"] == "t.mic.npz" and by["mic"]["method"] == ""
    assert int(by["fused"]["contacts"]) == r["fused"]["contacts"] == 16
    png = (tmp_path / "report" / "fusion.png").read_bytes()
    assert b"late fusion, weight" in png and b"4 windows each" in png and b"t.mic.npz" in png
    # the table says it too
    assert main(["evaluate", "--scene", str(recording), "--quiet", "--contact-windows", "4"]) == 0
    out = capsys.readouterr().out
    assert "fused: late fusion, weight" in out and "contacts: 4 windows each" in out


@pytest.mark.slow   # a long run: an early-fusion network trained and scored
def test_an_early_fusion_network_given_is_named(recording, tmp_path, capsys):
    """--fused-model: the scored fusion is that network, named by its file."""
    scenes = ["--scene", str(recording)]
    assert main(["train", "--fusion", "early", *scenes, "--out", str(tmp_path / "early.npz"), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["evaluate", *scenes, "--fused-model", str(tmp_path / "early.npz"), "--json", "--quiet"]) == 0
    (early,) = json.loads(capsys.readouterr().out)["fused"]["scored"]
    assert (early["method"], early["model"], early["weight"], early["sharpness"]) == \
        ("early", str(tmp_path / "early.npz"), None, None)


@pytest.mark.parametrize("argv, needle", [
    (["--contact-windows", "0"], "--contact-windows: expected a whole number >= 1"),
    (["--contact-windows", "2.5"], "--contact-windows: expected a whole number >= 1"),
    (["--contact-windows", "9"], "no run of windows of one texture is that long"),
])
def test_windows_per_contact_are_checked(recording, capsys, argv, needle):
    try:
        status = main(["evaluate", "--scene", str(recording), "--quiet", *argv])
    except SystemExit as exc:                  # argparse refuses the option's value itself
        status = exc.code
    assert status == 2
    assert needle in capsys.readouterr().err


def test_windows_per_contact_need_recorded_graphs(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["evaluate", "m.npz", "--manifest", "m.csv", "--contact-windows", "3"]) == 2
    assert "--contact-windows cuts the contacts of recorded graphs" in capsys.readouterr().err
