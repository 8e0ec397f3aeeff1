"""Grouped cross-validation: folds by recording, deterministic, and the scores a plain
re-training of each fold gives."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supramodal.node.cli import main
from supramodal.node.workflows.training import cross_validate_manifest, evaluate_manifest, train_from_manifest
from supramodal.banks import whisker_bank
from supramodal.errors import InputError
from supramodal.training import grouped_folds

from recordings import write_texture_recordings


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 9), st.sampled_from("abc")), min_size=1, max_size=60),
       st.integers(2, 6), st.integers(0, 2**16))
def test_folds_never_split_a_group_and_depend_only_on_the_seed(items, k, seed):
    groups = [f"rec{g}" for g, _ in items]
    labels_of = {}
    labels = [labels_of.setdefault(g, lab) for g, (_, lab) in zip(groups, items)]   # one label per group
    try:
        fold = grouped_folds(groups, labels, k, seed)
    except InputError as exc:
        per_label = {}
        for g, lab in labels_of.items():
            per_label.setdefault(lab, set()).add(g)
        assert len(labels_of) < k or any(len(gs) < 2 for gs in per_label.values()), str(exc)
        return
    assert fold.shape == (len(items),) and fold.min() >= 0 and fold.max() < k
    for g in set(groups):
        assert len({fold[i] for i in range(len(groups)) if groups[i] == g}) == 1     # a group in one fold
    np.testing.assert_array_equal(fold, grouped_folds(groups, labels, k, seed))
    # each label's groups are spread: no fold holds more than its share, rounded up
    for lab in set(labels):
        gs = sorted({g for g, l in zip(groups, labels) if l == lab})
        per_fold = np.bincount([fold[groups.index(g)] for g in gs], minlength=k)
        assert per_fold.max() <= -(-len(gs) // k)


@pytest.mark.parametrize("groups, labels, k, match", [
    (["a", "b"], ["x", "y"], 1, "k >= 2"),
    (["a", "b"], ["x", "x"], 3, "at least 3 recordings"),
    (["a", "b", "c"], ["x", "x", "y"], 2, r"\['y'\] have one trial"),
])
def test_folds_are_refused_where_they_cannot_work(groups, labels, k, match):
    with pytest.raises(InputError, match=match):
        grouped_folds(groups, labels, k)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """Three whisker textures, three recordings each (different stretches of the texture): 9 files."""
    return write_texture_recordings(tmp_path_factory.mktemp("cv"), per_texture=3)


@pytest.mark.slow   # a long run: a cross-validation run twice and each fold trained again
def test_each_fold_scores_as_training_on_the_other_recordings(recordings):
    """Fold by fold, the result equals a plain re-run: train_from_manifest on a manifest of the
    other folds' recordings, evaluate_manifest on this fold's."""
    bank = whisker_bank()
    cv = cross_validate_manifest(recordings / "all.csv", bank, ("Af",), 0.1, k=3, epochs=60, seed=4)
    all_recs = sorted(str(p) for p in recordings.glob("*.wav"))
    tested = sorted(p for f in cv["folds"] for p in f["recordings"])
    assert tested == all_recs                                       # every recording tested once
    lines = (recordings / "all.csv").read_text().splitlines()[1:]
    for f, fold in enumerate(cv["folds"]):
        test_names = {p.rsplit("/", 1)[-1] for p in fold["recordings"]}
        (recordings / "train.csv").write_text("path,label\n" + "\n".join(
            line for line in lines if line.split(",")[0] not in test_names) + "\n")
        (recordings / "test.csv").write_text("path,label\n" + "\n".join(
            line for line in lines if line.split(",")[0] in test_names) + "\n")
        model = train_from_manifest(recordings / "train.csv", bank, ("Af",), 0.1, epochs=60, seed=4)
        plain = evaluate_manifest(model, recordings / "test.csv")
        assert fold["window_accuracy"] == pytest.approx(plain["window_accuracy"], abs=1e-12)
        assert fold["recording_accuracy"] == pytest.approx(plain["recording_accuracy"], abs=1e-12)
    confusion = np.array(cv["confusion"])
    assert confusion.sum() == 9 * 15                                # 15 windows per 1.5 s recording
    means = np.mean([f["window_accuracy"] for f in cv["folds"]])
    assert cv["window_accuracy"]["mean"] == pytest.approx(means)
    assert cv["chance"] == pytest.approx(1 / 3)
    again = cross_validate_manifest(recordings / "all.csv", bank, ("Af",), 0.1, k=3, epochs=60, seed=4)
    assert again["folds"] == cv["folds"]                            # deterministic given the seed


@pytest.mark.slow   # a long run: a cross-validation and a calibrated training
def test_train_cv_reports_then_writes_the_model_and_the_confusion_files(recordings, tmp_path, capsys):
    out = tmp_path / "m.npz"
    assert main(["train", "--bank", "whisker", "--manifest", str(recordings / "all.csv"), "--out", str(out),
                 "--epochs", "60", "--cv", "3", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "grouped 3-fold cross-validation" in text and "+-" in text and "chance 0.333" in text
    assert out.is_file()
    rows = list(csv.reader(open(tmp_path / "m-cv.csv")))
    assert rows[0][1:] == ["T1", "T2", "T3"]
    assert sum(int(v) for row in rows[1:] for v in row[1:]) == 9 * 15


def test_train_takes_the_hidden_units_a_fit_scored_and_its_cross_validation_trains_alike(recordings, tmp_path, capsys):
    """`train --hidden N` (what `fit`'s next: line carries): every deployed network has N hidden units, the
    cross-validation's folds too (its score is cross_validate_manifest's with N); left out, the paper's rule (as
    many as the inputs); a fusion refuses it by name."""
    from supramodal.model import TextureModel

    out = tmp_path / "m.npz"
    assert main(["train", "--bank", "whisker", "--manifest", str(recordings / "all.csv"), "--out", str(out),
                 "--epochs", "20", "--hidden", "5", "--cv", "3", "--quiet"]) == 0
    said = capsys.readouterr().out
    model = TextureModel.load(out)
    assert len(model.mlp.members) > 1 and {m.shape[1] for m in model.mlp.members} == {5}
    direct = cross_validate_manifest(recordings / "all.csv", whisker_bank(), ("Af",), 0.1, k=3, epochs=20, hidden=5)
    rule = cross_validate_manifest(recordings / "all.csv", whisker_bank(), ("Af",), 0.1, k=3, epochs=20)
    assert f"window accuracy     {direct['window_accuracy']['mean']:.3f}" in said
    assert [f["window_accuracy"] for f in direct["folds"]] != [f["window_accuracy"] for f in rule["folds"]]
    assert main(["train", "--bank", "whisker", "--manifest", str(recordings / "all.csv"), "--out",
                 str(tmp_path / "rule.npz"), "--epochs", "20", "--quiet"]) == 0
    assert {m.shape[1] for m in TextureModel.load(tmp_path / "rule.npz").mlp.members} == {20}     # 20 vibrissae x Af
    capsys.readouterr()
    assert main(["train", "--fusion", "late", "--scene", str(tmp_path / "s.toml"), "--hidden", "5"]) == 2
    assert "--hidden sets one sense's networks" in capsys.readouterr().err


def test_lines_of_one_file_are_trials_and_must_not_overlap(recordings, tmp_path):
    """One recording per label, split into two lines each: two trials per label, folds possible;
    overlapping spans of one file are refused (a fold would test on windows it trained on)."""
    from supramodal.node.workflows.manifest import ManifestError

    names = sorted(p.name for p in recordings.glob("*_0.wav"))
    split = ["path,label,start,end"] + [f"{recordings / n},{n[:2]},{a},{b}" for n in names
                                        for a, b in ((0, 0.7), (0.7, 1.5))]
    (tmp_path / "split.csv").write_text("\n".join(split) + "\n")
    cv = cross_validate_manifest(tmp_path / "split.csv", whisker_bank(), ("Af",), 0.1, k=2, epochs=30)
    assert sum(len(f["recordings"]) for f in cv["folds"]) == 6
    overlap = split[:2] + [split[1].replace(",0,0.7", ",0.5,1.5")] + split[3:]
    (tmp_path / "overlap.csv").write_text("\n".join(overlap) + "\n")
    with pytest.raises(ManifestError, match="overlaps"):
        cross_validate_manifest(tmp_path / "overlap.csv", whisker_bank(), ("Af",), 0.1, k=2, epochs=30)


def test_pooled_accuracy_is_the_nodes_pooling_over_runs_of_windows():
    """Against a plain loop of the node's own accumulator (scope "last", n windows, log method)
    fed each run of n windows afresh."""
    from supramodal.decisions import DecisionAccumulator
    from supramodal.evaluation import pooled_accuracy

    rng = np.random.default_rng(2)
    outputs = [rng.random((int(rng.integers(0, 23)), 4)) for _ in range(7)]
    truths = rng.integers(0, 4, 7).tolist()
    for n in (1, 2, 3, 5, 10, 30):
        hits = runs = 0
        for out, t in zip(outputs, truths):
            for start in range(0, len(out) - n + 1, n):
                acc = DecisionAccumulator(4, scope="last", n=n)
                for o in out[start:start + n]:
                    d = acc.update(o)
                hits += d.label == t
                runs += 1
        got, got_runs = pooled_accuracy(outputs, truths, n)
        assert got_runs == runs and (got is None if runs == 0 else got == pytest.approx(hits / runs))


def test_permutation_importance_finds_the_channel_that_decides():
    from supramodal.evaluation import permutation_importance

    rng = np.random.default_rng(3)
    windows = rng.standard_normal((400, 1, 6))
    truth = (windows[:, 0, 4] > 0).astype(int)                       # only channel 4 decides

    def outputs(w):
        return np.stack([(w[:, 0, 4] <= 0).astype(float), (w[:, 0, 4] > 0).astype(float)], axis=1)

    importance = permutation_importance(outputs, windows, truth, repeats=3, seed=1)
    assert importance[4] > 0.4 and np.all(np.abs(np.delete(importance, 4)) == 0)


def test_evaluate_reports_chance_pooling_and_channels_and_writes_them(recordings, tmp_path, capsys):
    model_path = tmp_path / "m.npz"
    assert main(["train", "--bank", "whisker", "--manifest", str(recordings / "all.csv"), "--out", str(model_path),
                 "--epochs", "60", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(model_path), "--manifest", str(recordings / "all.csv"), "--out",
                 str(tmp_path / "eval"), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "chance 0.333" in text and "windows pooled" in text and "whole recording" in text
    assert "channels carrying the decision" in text
    rows = list(csv.reader(open(tmp_path / "eval" / "pooling.csv")))
    assert [r[0] for r in rows[1:]] == ["1", "2", "5", "10", "recording"]
    assert len(list(csv.reader(open(tmp_path / "eval" / "channels.csv")))) == 1 + 20
    assert main(["evaluate", str(model_path), "--manifest", str(recordings / "all.csv"), "--out",
                 str(tmp_path / "eval"), "--quiet"]) == 2                          # no silent overwrite


@pytest.mark.slow   # a long run: a model trained, then trained again fold by fold
def test_evaluate_cv_retrains_the_models_configuration_fold_by_fold(recordings, tmp_path, capsys):
    """`evaluate MODEL --cv K` cross-validates what the model file says it is (bank, features, window,
    epochs, seed, hidden units): the same folds and scores as cross-validating those settings
    directly, the confusion written, and --seed for --cv only."""
    import json

    model_path = tmp_path / "m.npz"
    assert main(["train", "--bank", "whisker", "--manifest", str(recordings / "all.csv"), "--out", str(model_path),
                 "--epochs", "60", "--seed", "4", "--features", "Af", "A", "--window", "0.1", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(model_path), "--manifest", str(recordings / "all.csv"), "--cv", "3", "--json",
                 "--out", str(tmp_path / "eval"), "--quiet"]) == 0
    got = json.loads(capsys.readouterr().out)
    direct = cross_validate_manifest(recordings / "all.csv", whisker_bank(), ("Af", "A"), 0.1, k=3, epochs=60, seed=4)
    assert got["folds"] == direct["folds"] and got["confusion"] == direct["confusion"]
    assert got["window_accuracy"] == direct["window_accuracy"] and got["seed"] == 4
    assert set(got["recall"]) == {"T1", "T2", "T3"} and got["recording_accuracy"]["sd"] >= 0
    rows = list(csv.reader(open(tmp_path / "eval" / "cv-confusion.csv")))
    assert sum(int(v) for row in rows[1:] for v in row[1:]) == 9 * 15
    # another seed: other folds or another training, still every recording tested once
    assert main(["evaluate", str(model_path), "--manifest", str(recordings / "all.csv"), "--cv", "3", "--json",
                 "--seed", "5", "--quiet"]) == 0
    other = json.loads(capsys.readouterr().out)
    assert other["seed"] == 5 and sum(len(f["recordings"]) for f in other["folds"]) == 9
    assert main(["evaluate", str(model_path), "--manifest", str(recordings / "all.csv"), "--seed", "5"]) == 2
    assert "--seed applies to --cv only" in capsys.readouterr().err
    assert main(["evaluate", str(model_path), "--manifest", str(recordings / "all.csv"), "--cv", "3",
                 "--out", str(tmp_path / "eval"), "--quiet"]) == 2                 # no silent overwrite
    assert "cv-confusion" in capsys.readouterr().err
