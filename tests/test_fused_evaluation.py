"""`evaluate --scene` on a recorded graph (issue 26, item 4): `--contact-windows N` cuts each run
of one texture into contacts of N windows, and the JSON, CSV, PNG and table name the fusion
scored (method, weight, sharpness, correlation, model files) and what a contact is."""

from __future__ import annotations

import csv
import json
import tomllib

import numpy as np
import pytest

from supramodal.decisions import PooledDecision, TextureChange
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
    assert r["whiskers"]["scored"] == [{"scene": str(recording), "model": str(folder / "t.whiskers.npz"),
                                        "asked": {"unknown": None, "change": None}}]
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


def test_decision_checks_count_false_unknowns_and_changes_per_contact_by_hand():
    """evaluate's checks of the decision rules on events made by hand: two contacts (a lift-off between), the
    first sliding from a to b; "unknown" said on known windows; changes signalled and scored per contact."""
    from supramodal.node.runtime.events import WindowEvent
    from supramodal.node.workflows.fused_training import _contact_runs, decision_check_lines, decision_checks

    def ev(w, truth, decision="a", pooled_label="a", change=None, in_contact=True):
        pooled = PooledDecision(pooled_label, 0.9, 1, change=TextureChange("a", "b", 1) if change else None)
        return WindowEvent("s", w, w * 0.1, (w + 1) * 0.1, (w + 1) * 0.1, decision=decision, confidence=0.9,
                           pooled=pooled, truth=truth, in_contact=in_contact)

    events = ([ev(w, "a") for w in range(5)] + [ev(5, "b", decision="unknown"), ev(6, "b"), ev(7, "b", change=True)]
              + [ev(8, "b", change=True), ev(9, "b", in_contact=False)]          # a second change: false; lift-off
              + [ev(w, "a", decision="unknown", pooled_label="unknown") for w in range(10, 14)])
    runs = _contact_runs(events)
    assert [[e.window for e in r] for r in runs] == [list(range(9)), list(range(10, 14))]
    asked = [{"asked": {"unknown": 0.05, "change": 1.0}}]
    r = decision_checks(runs, ("a", "b"), asked)
    assert r["false_unknown"] == {"windows": 5, "of": 13, "asked": 0.05, "contacts": 1, "contacts_of": 1}
    c = r["changes"]
    assert (c["boundaries"], c["detected"], c["delays"], c["false"], c["asked"]) == (1, 1, [3], 1, 1.0)
    assert c["minutes"] == pytest.approx(13 * 0.1 / 60)
    lines = decision_check_lines(r)
    assert lines[0] == 'said "unknown" on 5 of 13 windows of known textures (0.385; 1 of 1 contacts, 1.000; asked 0.05)'
    assert lines[1].startswith("texture changes within a contact: 1 of 1 detected within 5 windows (median delay 3 "
                               "windows); 1 false in 0.02 min")
    # an unlabelled window inside a contact splits nothing: the boundary after it is found, nothing is made up
    gapped = [ev(0, "a"), ev(1, None), ev(2, "b"), ev(3, "b", change=True)]
    runs = _contact_runs(gapped)
    assert len(runs) == 1
    c = decision_checks(runs, ("a", "b"), asked)
    assert (c["changes"]["boundaries"], c["changes"]["delays"], c["changes"]["false"]) == (1, [2], 0)
    assert c["false_unknown"]["of"] == 3
    # rules not asked: no change report, and no unknown line where none was said
    quiet = decision_checks([[ev(0, "a"), ev(1, "b")]], ("a", "b"), [{"asked": {"unknown": None, "change": None}}])
    assert "changes" not in quiet and decision_check_lines(quiet) == []
