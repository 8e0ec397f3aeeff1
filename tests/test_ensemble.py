"""The networks a calibrated model deploys: its calibration's fold networks, deciding by the mean of their logits.

What is checked: an ensemble's logits against a plain computation of each member's; a fold network
re-expressed on the model's input scaling is the same function; the deployed members are the very
networks whose held-out logits the calibration was fitted on; the model file of several networks (version 3)
round-trips and is refused where its arrays do not fit its ``networks``; a version 2 file (one network)
loads as before; the change detector's and the novelty's batched sums against their plain loops.
"""

import json

import numpy as np
import pytest

from supramodal.calibration import input_scaling
from supramodal.errors import InputError
from supramodal.fused_model import Sense
from supramodal.mlp import MLP, Ensemble, rescaled
from supramodal.model import MAX_NETWORKS, ModelError, TextureModel
from tests.test_model_io import BANK, CLASSES, FEATURES, read_parts, training_data, write_parts


def _plain_logits(net: MLP, x: np.ndarray) -> np.ndarray:
    """A network's logits, unit by unit in plain Python floats (math.exp), for a few rows."""
    import math

    out = np.empty((len(x), net.w2.shape[1]))
    for n, row in enumerate(x):
        hidden = [1.0 / (1.0 + math.exp(-(sum(row[i] * net.w1[i, j] for i in range(len(row))) + net.b1[j])))
                  for j in range(net.w1.shape[1])]
        for k in range(net.w2.shape[1]):
            out[n, k] = sum(h * net.w2[j, k] for j, h in enumerate(hidden)) + net.b2[k]   # steepness 0.5: 2 s = 1
    return out


def test_an_ensemble_decides_by_the_mean_of_its_members_logits():
    rng = np.random.default_rng(0)
    members = tuple(MLP.create(5, 4, 3, seed=s) for s in range(3))
    for m in members:                               # weights of a trained network's size, not the start's
        for p in m.params():
            p *= 20
    x = rng.normal(0, 2, (6, 5))
    ens = Ensemble(members)
    want = np.mean([_plain_logits(m, x) for m in members], axis=0)
    assert ens.shape == (5, 4, 3)
    np.testing.assert_allclose(ens.logits(x), want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ens.outputs(x), 1 / (1 + np.exp(-want)), rtol=1e-12)
    assert np.array_equal(ens.predict(x), np.argmax(want, axis=1))
    assert [a.shape for a in ens.stacked()] == [(3, 5, 4), (3, 4), (3, 4, 3), (3, 3)]
    one = Ensemble(members[:1])
    np.testing.assert_allclose(one.logits(x), members[0].logits(x), rtol=0, atol=0)


def test_an_ensemble_refuses_no_networks_or_networks_of_other_shapes():
    with pytest.raises(InputError, match="at least one network"):
        Ensemble(())
    with pytest.raises(InputError, match="one shape"):
        Ensemble((MLP.create(5, 4, 3, seed=0), MLP.create(5, 6, 3, seed=0)))


@pytest.mark.parametrize("seed", range(4))
def test_a_network_rescaled_to_other_inputs_is_the_same_function(seed):
    """A fold network standardised by its fold's mean and scale, re-expressed on the model's: the same logits
    of the same raw rows (scales over three decades, a constant input of scale 1)."""
    rng = np.random.default_rng(seed)
    n_in = 6
    net = MLP.create(n_in, 5, 4, seed=seed)
    for p in net.params():
        p *= 30
    raw = rng.normal(0, 1, (50, n_in)) * 10.0 ** rng.uniform(-2, 2, n_in) + rng.normal(0, 100, n_in)
    raw[:, 2] = 7.0
    mean, scale = input_scaling(raw[:30])
    to_mean, to_scale = input_scaling(raw)
    assert scale[2] == to_scale[2] == 1.0
    moved = rescaled(net, mean, scale, to_mean, to_scale)
    want = net.logits((raw - mean) / scale)
    np.testing.assert_allclose(moved.logits((raw - to_mean) / to_scale), want, rtol=1e-9,
                               atol=1e-9 * np.abs(want).max())


@pytest.fixture(scope="module")
def model():
    values, labels = training_data()
    groups = np.repeat(np.arange(12), 10)                   # four recordings per class
    return TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=60, seed=3, groups=groups), values


def test_a_calibrated_model_deploys_the_networks_its_calibration_was_fitted_on(model):
    """Each member, on the model's scaling, gives the held-out logits the calibration was fitted on for its
    own fold's windows (which it never trained on); the model decides by their mean."""
    m, values = model
    assert isinstance(m.mlp, Ensemble) and len(m.mlp.members) == 3
    assert m.calibration.fitted_on["folds"] == 3 and m.calibration.fitted_on["folds_by"] == "recording"
    x = (values.reshape(len(values), -1) - m.mean) / m.scale
    held = m.out_of_fold
    for f, member in zip(sorted(set(held.folds.tolist())), m.mlp.members):
        rows = held.folds == f
        want = held.logits[rows]
        np.testing.assert_allclose(member.logits(x[rows]), want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
    np.testing.assert_allclose(m.logits(values), np.mean([mb.logits(x) for mb in m.mlp.members], axis=0),
                               rtol=1e-12, atol=1e-12)
    assert np.mean(m.predict(values) == training_data()[1]) > 0.9


def test_a_model_without_calibration_folds_is_one_network_of_every_window():
    values, labels = training_data()
    m = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=60, seed=3, calibration_folds=0)
    assert isinstance(m.mlp, MLP) and not m.calibrated and m.training["windows"] == len(values)


def test_a_file_of_several_networks_round_trips(model, tmp_path):
    m, values = model
    path = m.save(tmp_path / "m.npz")
    header, arrays = read_parts(path)
    assert header["version"] == 3 and header["networks"] == 3 and arrays["w1"].shape == (3, 16, 16)
    back = TextureModel.load(path)
    assert isinstance(back.mlp, Ensemble) and len(back.mlp.members) == 3
    assert np.array_equal(back.log_posteriors(values), m.log_posteriors(values))
    assert np.array_equal(back.novelty_score(values), m.novelty_score(values))


def test_a_version_2_file_of_one_network_loads_as_it_did(model, tmp_path):
    """A file written before ensembles: version 2, one network's arrays, no 'networks'."""
    m, values = model
    header, arrays = read_parts(m.save(tmp_path / "m.npz"))
    first = m.mlp.members[0]
    header["version"] = 2
    del header["networks"]
    arrays.update(w1=first.w1, b1=first.b1, w2=first.w2, b2=first.b2)
    old = TextureModel.load(write_parts(tmp_path / "v2.npz", header, arrays))
    assert isinstance(old.mlp, MLP)
    np.testing.assert_allclose(old.logits(values), first.logits((values.reshape(len(values), -1) - m.mean) / m.scale),
                               rtol=0, atol=0)
    header["networks"] = 1                                  # a version 2 file never said it
    with pytest.raises(ModelError, match=r"unknown header key\(s\) \['networks'\]"):
        TextureModel.load(write_parts(tmp_path / "v2n.npz", header, arrays))


@pytest.mark.parametrize("networks, says", [
    (2, "expected float \\(2, 16, 16\\)"), (4, "and 4 network\\(s\\)"), (0, "'networks' must be an integer 1..64"),
    (MAX_NETWORKS + 1, "must be an integer 1..64"), (True, "must be an integer"), ("3", "must be an integer"),
    (3.0, "must be an integer")])
def test_a_file_whose_networks_do_not_fit_its_arrays_is_refused(model, tmp_path, networks, says):
    m, _ = model
    header, arrays = read_parts(m.save(tmp_path / "m.npz"))
    header["networks"] = networks
    with pytest.raises(ModelError, match=says):
        TextureModel.load(write_parts(tmp_path / "bad.npz", header, arrays))


def test_a_version_3_file_without_networks_is_refused_not_read_as_one_network(model, tmp_path):
    """Its arrays would be one network's under a calibration fitted for three: refused by name, for both kinds."""
    from supramodal.fused_model import EarlyFusionModel

    m, _ = model
    header, arrays = read_parts(m.save(tmp_path / "m.npz"))
    del header["networks"]
    arrays.update({k: arrays[k][0] for k in ("w1", "b1", "w2", "b2")})
    with pytest.raises(ModelError, match="must say its 'networks'"):
        TextureModel.load(write_parts(tmp_path / "bad.npz", header, arrays))
    rng = np.random.default_rng(4)
    y = np.repeat(np.arange(3), 30)
    senses = (Sense("a", BANK, ("Af",), 500), Sense("b", BANK, ("A",), 500))
    early = EarlyFusionModel.train(senses, rng.normal(size=(90, 1, 8)) + y[:, None, None], rng.normal(size=(90, 1, 8)),
                                   y, CLASSES, epochs=20)
    header, arrays = read_parts(early.save(tmp_path / "e.npz"))
    assert header["networks"] == 3 and isinstance(EarlyFusionModel.load(tmp_path / "e.npz").mlp, Ensemble)
    del header["networks"]
    with pytest.raises(ModelError, match="must say its 'networks'"):
        EarlyFusionModel.load(write_parts(tmp_path / "eb.npz", header, arrays))


def test_an_ensemble_is_never_written_as_one_networks_arrays(model, tmp_path):
    from supramodal.model import save_model_archive

    m, _ = model
    header = m.header()
    del header["networks"]
    with pytest.raises(ValueError, match="give it 'networks'"):
        save_model_archive(tmp_path / "x.npz", header, m.mlp, m.mean, m.scale)
    assert not (tmp_path / "x.npz").exists()


def test_a_one_network_model_is_written_with_networks_1_and_read_back_as_one(tmp_path):
    values, labels = training_data()
    m = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=30, seed=1, calibration_folds=0)
    header, arrays = read_parts(m.save(tmp_path / "m.npz"))
    assert header["networks"] == 1 and arrays["w1"].shape == (1, 16, 16)
    assert json.loads(json.dumps(header))["version"] == 3
    back = TextureModel.load(tmp_path / "m.npz")
    assert isinstance(back.mlp, MLP) and np.array_equal(back.logits(values), m.logits(values))


# -- the training's batched sums against their plain loops -------------------------------------------

@pytest.mark.parametrize("seed", range(3))
def test_the_change_statistics_of_a_touch_are_the_detectors_own_window_by_window(seed):
    """change_statistics weighs every window's stretches at once: the same numbers as a ChangeDetector fed
    the touch window by window (touches shorter and longer than the look-back, with and without caps)."""
    from supramodal.decisions import CHANGE_LOOKBACK, ChangeDetector, change_statistics

    rng = np.random.default_rng(seed)
    for _ in range(30):
        c = int(rng.integers(2, 9))
        t = int(rng.integers(1, 3 * CHANGE_LOOKBACK))
        z = rng.normal(0, 3, (t, c))
        lp = z - np.log(np.exp(z).sum(axis=1, keepdims=True))
        caps = None if rng.random() < 0.5 else np.abs(rng.normal(3, 1, (c, c))) + 0.1
        min_windows, rho, label = int(rng.integers(1, 5)), float(rng.random()), int(rng.integers(c))
        detector = ChangeDetector(c, 2.0, rho, caps, threshold=np.inf, min_windows=min_windows)
        want = []
        for row in lp:
            detector.update(row, label)
            want.append(detector.statistic)
        got = change_statistics(lp, label, rho, caps, min_windows)
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)
        assert np.array_equal(np.isneginf(got), np.isneginf(want))
    # as the detector: no decision to test against (-1) tests nothing; a touch of no window has no statistic
    assert np.isneginf(change_statistics(lp, -1)).all() and change_statistics(lp[:0], 0).shape == (0,)


def test_the_novelty_of_a_new_touch_is_each_class_quadratic_form():
    """Novelty.class_scores with a touch's allowance against the quadratic forms summed term by term."""
    from supramodal.calibration import NOVELTY_TOUCH_SPREAD, fit_novelty

    rng = np.random.default_rng(2)
    labels = np.repeat(np.arange(3), 40)
    x = rng.normal(0, 1, (120, 6)) + labels[:, None] * 0.5
    groups = np.repeat(np.arange(12), 10)
    folds = groups % 3
    nov = fit_novelty(x, labels, 3, folds, groups, np.zeros(6), np.ones(6), touch_groups=(0, 1, 2, 0, 1, 2),
                      touch_floor=NOVELTY_TOUCH_SPREAD)
    u = nov.warped(x[:7])
    for n in (1, 4):
        p = nov._touch_precisions(n)
        want = np.array([[sum((r - mu)[i] * p[k][i, j] * (r - mu)[j] for i in range(6) for j in range(6))
                          for k, mu in enumerate(nov.means)] for r in u])
        np.testing.assert_allclose(nov.class_scores(u, n), want, rtol=1e-12)


def test_evaluate_cv_copies_a_model_with_as_many_fold_networks_as_it_deploys(model):
    """`evaluate --cv` re-trains a model's configuration: the number of networks it deploys is part of it."""
    import dataclasses

    from supramodal.node.workflows.training import _deployed_folds

    m, _ = model
    assert _deployed_folds(m) == 3
    assert _deployed_folds(dataclasses.replace(m, mlp=Ensemble(m.mlp.members[:2]))) == 2
    assert _deployed_folds(dataclasses.replace(m, calibration=None)) == 0            # uncalibrated: one network
    assert _deployed_folds(dataclasses.replace(m, mlp=m.mlp.members[0])) is None     # a version 2 file: as made now


# -- fold networks stopped early on their own held-out windows -------------------------------------------

def test_each_member_is_its_fold_network_of_the_epochs_the_file_says(model):
    """A model's fold networks stop early by default: each member is the network of its fold after the epochs the
    file records (a network trained that many epochs on the same rows, re-expressed, gives the same logits)."""
    from supramodal.calibration import fold_scaling, fold_tasks
    from supramodal.mlp import EARLY_STOP_PATIENCE, train_mlp

    m, values = model
    assert m.training["patience"] == EARLY_STOP_PATIENCE and m.training["epochs"] == 60
    x, y = values.reshape(len(values), -1), training_data()[1]
    held = m.out_of_fold
    tasks = list(fold_tasks(x, y, 3, held.folds, 3, None, 60, 3, None, None))
    assert len(m.training["network_epochs"]) == 3 and len(set(m.training["network_epochs"])) == 1   # one age
    for f, (task, member, epochs) in enumerate(zip(tasks, m.mlp.members, m.training["network_epochs"])):
        assert 1 <= epochs <= 60
        net, _ = train_mlp(task.x, task.labels, 3, epochs=epochs, seed=3)
        again = rescaled(net, *fold_scaling(x, held.folds, f), m.mean, m.scale)
        for p, q in zip(again.params(), member.params()):
            np.testing.assert_allclose(p, q, rtol=1e-12, atol=1e-12)


def test_without_patience_every_fold_network_trains_every_epoch():
    values, labels = training_data()
    groups = np.repeat(np.arange(12), 10)
    m = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=40, seed=3, groups=groups,
                           patience=None)
    assert m.training["patience"] is None and m.training["network_epochs"] == [40, 40, 40]


def test_overfitting_fold_networks_stop_before_their_last_epoch():
    """Classes that overlap: the fold networks' held-out error turns up well before 400 epochs; they stop there."""
    rng = np.random.default_rng(5)
    labels = np.repeat(np.arange(3), 60)
    values = rng.gamma(2.0, 1.0, (180, 2, 8)) * 100.0
    values[:, 0, :] *= 1 + 0.15 * labels[:, None]
    m = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=400, seed=0, patience=30)
    assert all(e < 400 - 30 for e in m.training["network_epochs"])


@pytest.mark.parametrize("patience", [0, -3, 2.5, True, "100", [100]])
def test_a_file_whose_patience_is_not_a_number_of_epochs_is_refused(model, tmp_path, patience):
    m, _ = model
    header, arrays = read_parts(m.save(tmp_path / "m.npz"))
    header["training"]["patience"] = patience
    with pytest.raises(ModelError, match="training.patience"):
        TextureModel.load(write_parts(tmp_path / "bad.npz", header, arrays))


def test_a_file_without_patience_loads_and_its_copies_train_every_epoch(model, tmp_path):
    """A file from before early stopping (no 'patience'): loads; its out-of-fold copies train every epoch, as its
    networks did."""
    import dataclasses

    from supramodal.fused_model import out_of_fold_logits

    m, values = model
    header, arrays = read_parts(m.save(tmp_path / "m.npz"))
    del header["training"]["patience"]
    old = TextureModel.load(write_parts(tmp_path / "old.npz", header, arrays))
    assert "patience" not in old.training
    labels, folds = training_data()[1], np.arange(len(values)) % 2
    z_old = out_of_fold_logits(dataclasses.replace(old, out_of_fold=None), values, labels, CLASSES, folds)
    z_new = out_of_fold_logits(dataclasses.replace(m, out_of_fold=None), values, labels, CLASSES, folds)
    assert not np.array_equal(z_old, z_new)


def test_out_of_fold_copies_on_the_models_own_folds_are_its_fold_networks(model):
    """Copies of a model trained on its own calibration's folds (not taken from the file) are its fold networks,
    stopped where they stopped: the same held-out logits."""
    import dataclasses

    from supramodal.fused_model import out_of_fold_logits

    m, values = model
    labels, held = training_data()[1], m.out_of_fold
    z = out_of_fold_logits(dataclasses.replace(m, out_of_fold=None), values, labels, CLASSES, held.folds)
    np.testing.assert_array_equal(z, held.logits)


def test_evaluate_cv_copies_stop_early_as_the_model_did(model, monkeypatch):
    """`evaluate --cv` re-trains a model's configuration: its early stopping too (a file from before it trained
    every epoch; a version 2 file's copies are made as this version makes them)."""
    import dataclasses

    from supramodal.mlp import EARLY_STOP_PATIENCE
    from supramodal.node.workflows import training

    m, _ = model
    asked = []
    monkeypatch.setattr(training, "_cross_validate", lambda *args: asked.append(args[-1]) or {})
    training.cross_validate_model(m, "manifest.csv")
    training.cross_validate_model(dataclasses.replace(m, training={**m.training, "patience": 7}), "manifest.csv")
    before = {k: v for k, v in m.training.items() if k != "patience"}
    training.cross_validate_model(dataclasses.replace(m, training=before), "manifest.csv")
    training.cross_validate_model(dataclasses.replace(m, training=before, mlp=m.mlp.members[0]), "manifest.csv")
    assert asked == [EARLY_STOP_PATIENCE, 7, None, EARLY_STOP_PATIENCE]


def test_the_joint_epochs_are_those_of_the_lowest_summed_held_out_error():
    from supramodal.calibration import joint_stop_epochs

    a = ((10, 0.30), (20, 0.20), (30, 0.25), (40, 0.28))
    b = ((10, 0.40), (20, 0.38), (30, 0.30), (40, 0.35), (50, 0.36))
    assert joint_stop_epochs([a, b], [100, 100]) == 30           # 0.55 at 30 against 0.58 at 20
    assert joint_stop_epochs([a, b], [300, 100]) == 20           # a's windows weigh more: 0.98 at 20 against 1.05
    assert joint_stop_epochs([a, ((10, 0.4), (20, 0.4), (30, 0.3))], [1, 1]) == 30
    assert joint_stop_epochs([((10, 0.2), (20, 0.2))], [5]) == 10  # a tie: the fewest epochs
    with pytest.raises(InputError, match="no common epochs"):
        joint_stop_epochs([((10, 0.2),), ((15, 0.1),)], [1, 1])


def test_fold_networks_stop_together_at_the_epochs_best_for_all_their_held_out_windows():
    """Fold networks of unequal folds that stop at their own bests at different epochs: each network's
    held-out error every 10 epochs computed plainly (a plain network trained that many epochs), the members
    are the networks of the epochs whose error summed over every held-out window is lowest, to the bit, all
    of one age; those that stopped elsewhere were trained again to it, and progress was told as each was back."""
    from supramodal.calibration import fold_tasks, train_fold_networks
    from supramodal.mlp import one_hot, train_mlp, train_task

    rng = np.random.default_rng(2)
    y = np.repeat(np.arange(3), 60)
    x = rng.normal(size=(180, 8)) + 0.5 * np.eye(3)[y] @ rng.normal(size=(3, 8))
    folds = rng.integers(0, 3, 180)
    own = [len(train_task(t).history) for t in fold_tasks(x, y, 3, folds, 3, None, 300, 0, None, 30)]
    assert len(set(own)) > 1 and len(set(np.bincount(folds))) == 3        # the premise: bests and folds differ
    told, retold = [], []
    results = train_fold_networks(x, y, 3, folds, 3, None, 300, 0, None, 30, done=lambda i, r: told.append(i),
                                  redone=lambda i, r: retold.append((i, len(r.history))))
    ages = {len(r.history) for r in results}
    assert len(ages) == 1
    age = ages.pop()
    assert sorted(told) == [0, 1, 2] and retold == [(i, age) for i in range(3) if own[i] != age] and retold
    last = min(r.held_out_errors[-1][0] for r in results)
    summed = {}
    for f in range(3):
        train, test = folds != f, folds == f
        mean, scale = input_scaling(x[train])
        for e in range(10, last + 1, 10):
            net, _ = train_mlp((x[train] - mean) / scale, y[train], 3, epochs=e, seed=0)
            out = 1 / (1 + np.exp(-net.logits((x[test] - mean) / scale)))
            summed[e] = summed.get(e, 0.0) + float(np.sum((one_hot(y[test], 3) - out) ** 2)) / 3
        net, _ = train_mlp((x[train] - mean) / scale, y[train], 3, epochs=age, seed=0)
        for p, q in zip(net.params(), results[f].network.params()):
            np.testing.assert_array_equal(p, q)
        np.testing.assert_array_equal(results[f].logits, net.logits((x[test] - mean) / scale))
    assert age == min(summed, key=lambda e: (round(summed[e], 9), e))


def test_a_models_held_out_logits_are_those_of_its_members_stopped_together():
    """The calibration's held-out logits are the deployed members' (trained again to the joint epochs), not
    those of the networks at their own bests."""
    from supramodal.calibration import fold_tasks
    from supramodal.mlp import train_task

    rng = np.random.default_rng(0)
    labels = np.repeat(np.arange(3), 60)
    values = np.exp(rng.normal(size=(180, 2, 8)) * 0.3 + 0.15 * labels[:, None, None] * (np.arange(8) < 3))
    groups = labels * 4 + rng.integers(0, 4, 180)                  # four recordings a texture
    m = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=300, seed=0, groups=groups,
                           patience=30)
    held = m.out_of_fold
    own = [len(train_task(t).history)
           for t in fold_tasks(values.reshape(180, -1), labels, 3, held.folds, 3, None, 300, 0, None, 30)]
    assert len(set(own)) > 1 and len(set(m.training["network_epochs"])) == 1    # the premise: one was trained again
    x = (values.reshape(len(values), -1) - m.mean) / m.scale
    for f, member in zip(sorted(set(held.folds.tolist())), m.mlp.members):
        rows = held.folds == f
        np.testing.assert_allclose(member.logits(x[rows]), held.logits[rows], rtol=1e-9, atol=1e-9)
