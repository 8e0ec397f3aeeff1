"""Gain augmentation of training windows (supramodal/model.py ``GainAugment``, ``TextureModel.train(augment=)``):
the copies it makes, written out; every network trained on them, the held-out windows not; no copies' worth of
change where the gains are all 1."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from supramodal.banks import whisker_bank
from supramodal.calibration import fit_network_calibration
from supramodal.fused_model import out_of_fold_logits
from supramodal.model import GAIN_LINEAR_FEATURES, GainAugment, ModelError, TextureModel

BANK = whisker_bank(rows="AB")            # 8 vibrissae
CLASSES = ("rough", "smooth", "medium")
FEATURES = ("Af", "A", "f")


def _data(seed=0, n=40):
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(3), n)
    values = rng.gamma(2.0, 1.0, (3 * n, len(FEATURES), 8)) * 100.0
    values[:, 0, :3] *= 1 + 0.6 * labels[:, None]
    return values, labels


def test_each_copy_scales_a_channels_gain_linear_features_by_one_gain_and_leaves_f():
    values, labels = _data()
    x = values.reshape(len(values), -1)
    rows, y = GainAugment(copies=3, spread=0.05).for_inputs(FEATURES, 8)(x, labels, 2)
    assert rows.shape == (4 * len(x), x.shape[1]) and np.array_equal(y, np.tile(labels, 4))
    copies = rows.reshape(4, len(x), len(FEATURES), 8)
    np.testing.assert_array_equal(copies[0], values)                      # the windows themselves first
    linear = [FEATURES.index(f) for f in GAIN_LINEAR_FEATURES]
    for c in copies[1:]:
        np.testing.assert_array_equal(c[:, FEATURES.index("f")], values[:, FEATURES.index("f")])
        gains = c[:, linear[0]] / values[:, linear[0]]                    # one gain per window and channel ...
        np.testing.assert_allclose(c[:, linear[1]] / values[:, linear[1]], gains, rtol=1e-14)   # ... for Af and A
        assert abs(np.std(np.log(gains)) - 0.05) < 0.01 and len(np.unique(gains)) == gains.size   # exp(N(0, 0.05))
    again, _ = GainAugment(copies=3, spread=0.05).for_inputs(FEATURES, 8)(x, labels, 2)
    other, _ = GainAugment(copies=3, spread=0.05).for_inputs(FEATURES, 8)(x, labels, 3)
    assert np.array_equal(again, rows) and not np.array_equal(other, rows)    # by seed and stream
    shared, _ = GainAugment(copies=1, spread=0.05, per_channel=False).for_inputs(FEATURES, 8)(x, labels, 0)
    g = shared.reshape(2, len(x), len(FEATURES), 8)[1, :, 0] / values[:, 0]
    np.testing.assert_allclose(g, g[:, :1] * np.ones((1, 8)), rtol=1e-14)   # one level for every channel


def test_gains_of_one_train_the_model_of_no_augmentation_to_the_bit():
    """iRPROP- follows the gradients' signs: exact copies of every window change none, in the calibration's
    fold networks or the model's; so the copies reach every network, and nothing else changes."""
    values, labels = _data()
    plain = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=40, seed=1)
    ones = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=40, seed=1,
                              augment=GainAugment(copies=2, spread=0.0))
    for a, b in zip(ones.mlp.params(), plain.mlp.params(), strict=True):       # every deployed network
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ones.mean, plain.mean)
    np.testing.assert_array_equal(ones.out_of_fold.logits, plain.out_of_fold.logits)
    assert ones.calibration == plain.calibration and ones.training["augment"]["copies"] == 2


def test_augmented_networks_differ_and_the_held_out_windows_are_the_originals():
    values, labels = _data()
    plain = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=40, seed=1)
    aug = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=40, seed=1,
                             augment=GainAugment(copies=2, spread=0.05))
    assert not np.array_equal(aug.mlp.stacked()[0], plain.mlp.stacked()[0])
    assert aug.out_of_fold.logits.shape == plain.out_of_fold.logits.shape    # one held-out row per window
    np.testing.assert_array_equal(aug.mean, plain.mean)                      # scaling from the originals
    assert aug.training["windows"] == len(values)


# -- gains by bank, the file's record, and every network of a model augmented alike (issue 34, the next slice) ----

def test_gains_by_bank_are_per_vibrissa_for_a_whisker_array_and_one_level_for_a_cochlea():
    by_bank = GainAugment(copies=1, spread=0.05, per_channel=None)
    assert by_bank.resolved("whisker").per_channel is True and by_bank.resolved("cochlea").per_channel is False
    assert GainAugment(per_channel=False).resolved("whisker").per_channel is False      # said: kept
    values, labels = _data()
    model = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=10, seed=1, augment=by_bank,
                               calibration_folds=0)
    assert model.augment == GainAugment(1, 0.05, True) and model.training["augment"]["per_channel"] is True
    with pytest.raises(ValueError, match="resolve"):
        by_bank.for_inputs(FEATURES, 8)(values.reshape(len(values), -1), labels, 0)


def test_a_models_record_of_its_augmentation_reads_back_and_a_bad_one_is_refused():
    a = GainAugment(copies=3, spread=0.04, per_channel=False, seed=7)
    assert GainAugment.from_dict(json.loads(json.dumps(a.to_dict())), ModelError) == a
    for bad in ({**a.to_dict(), "copies": 99}, {**a.to_dict(), "copies": 1.5}, {**a.to_dict(), "spread": -0.1},
                {**a.to_dict(), "spread": True}, {**a.to_dict(), "per_channel": "yes"}, {**a.to_dict(), "seed": -1},
                {"copies": 1}, [1, 2]):
        with pytest.raises(ModelError, match="augment"):
            GainAugment.from_dict(bad, ModelError)


def test_fit_network_calibration_trains_its_fold_networks_as_the_models_own_are_trained():
    """The same fold networks, augmented alike, whether a model's training or fit_network_calibration
    trains them: the held-out logits agree to the bit; without augmentation they differ."""
    values, labels = _data()
    x = values.reshape(len(values), -1)
    augment = GainAugment(copies=2, spread=0.05)
    model = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=40, seed=1, augment=augment)
    cal, _, oof = fit_network_calibration(x, labels, 3, epochs=40, seed=1, augment=augment.for_inputs(FEATURES, 8))
    np.testing.assert_array_equal(oof.logits, model.out_of_fold.logits)
    assert dataclasses.replace(model.calibration, changes=None) == cal       # the model adds its change detector's
    assert cal.fitted_on["windows"] == len(values)                            # the held-out rows: the originals
    _, _, plain = fit_network_calibration(x, labels, 3, epochs=40, seed=1)
    assert plain.logits.shape == oof.logits.shape and not np.array_equal(plain.logits, oof.logits)
    _, _, ones = fit_network_calibration(x, labels, 3, epochs=40, seed=1,
                                         augment=GainAugment(copies=2, spread=0.0).for_inputs(FEATURES, 8))
    np.testing.assert_array_equal(ones.logits, plain.logits)


def test_out_of_fold_copies_of_a_model_are_augmented_as_the_model_was():
    """A late fusion's out-of-fold copies of a sense model (fused_model.out_of_fold_logits) follow the
    model's file: augmented when it was, alike; never its held-out windows."""
    values, labels = _data()
    folds = np.arange(len(labels)) % 2                              # not the model's own folds: copies train
    augmented = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=30, seed=1,
                                   augment=GainAugment(copies=1, spread=0.05), calibration_folds=0)
    forgot = dataclasses.replace(augmented, training={k: v for k, v in augmented.training.items() if k != "augment"})
    z = out_of_fold_logits(augmented, values, labels, CLASSES, folds)
    z_plain = out_of_fold_logits(forgot, values, labels, CLASSES, folds)
    assert z.shape == z_plain.shape == (len(labels), 3) and not np.array_equal(z, z_plain)
    zero = dataclasses.replace(augmented, training={**augmented.training,
                                                    "augment": GainAugment(1, 0.0).to_dict()})
    np.testing.assert_array_equal(out_of_fold_logits(zero, values, labels, CLASSES, folds), z_plain)


# -- the early-fusion network augmented as each sense would be ------------------------------------------------

def _early_data(seed=0, n=30):
    from supramodal.banks import cochlea_bank
    from supramodal.fused_model import Sense

    senses = (Sense("whiskers", BANK, ("Af", "f"), 500), Sense("mic", cochlea_bank(), ("A",), 4410))
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(3), n)
    va = rng.gamma(2.0, 1.0, (3 * n, 2, 8)) * 100.0
    vb = rng.gamma(2.0, 1.0, (3 * n, 1, 50))
    va[:, 0, :2] *= 1 + 0.5 * labels[:, None]
    vb[:, 0, 40:] *= 1 + 0.4 * labels[:, None]
    return senses, va, vb, labels


def test_early_copies_scale_each_senses_columns_by_its_own_gains_whiskers_per_vibrissa_microphone_one_level():
    from supramodal.fused_model import EarlyGainCopies, early_augment
    from supramodal.fusion import early_inputs

    senses, va, vb, labels = _early_data()
    augments = early_augment(GainAugment(copies=2, spread=0.05, per_channel=None), senses)
    assert [a.per_channel for a in augments] == [True, False]                 # each by its own bank
    rows, y = EarlyGainCopies.of(augments, senses)(early_inputs(va, vb), labels, 1)
    assert rows.shape == (3 * len(va), 16 + 50) and np.array_equal(y, np.tile(labels, 3))
    a = rows[:, :16].reshape(3, len(va), 2, 8)
    b = rows[:, 16:].reshape(3, len(vb), 1, 50)
    np.testing.assert_array_equal(a[0], va)
    np.testing.assert_array_equal(b[0], vb)
    for k in (1, 2):
        np.testing.assert_array_equal(a[k][:, 1], va[:, 1])                   # f is not a gain's
        ga, gb = a[k][:, 0] / va[:, 0], b[k][:, 0] / vb[:, 0]
        assert len(np.unique(ga.round(12))) == ga.size                        # a gain per window and vibrissa
        np.testing.assert_allclose(gb, gb[:, :1] * np.ones((1, 50)), rtol=1e-13)    # one level a window
        # the two senses' gains are drawn apart (a touch's whisker gains and microphone level are independent)
        assert abs(np.corrcoef(np.log(ga[:, 0]), np.log(gb[:, 0]))[0, 1]) < 0.4
    # the whiskers' part draws the gains a whisker model of the same seed draws for the same network
    alone, _ = augments[0].for_inputs(("Af", "f"), 8)(va.reshape(len(va), -1), labels, 1)
    np.testing.assert_array_equal(rows[:, :16], alone)


def test_early_augmentation_one_sense_only_copies_the_others_columns_unchanged_and_differing_copies_refused():
    from supramodal.errors import InputError
    from supramodal.fused_model import early_augment

    senses, *_ = _early_data()
    pair = early_augment((GainAugment(copies=3, spread=0.05), None), senses)
    assert pair[1].copies == 3 and pair[1].spread == 0.0
    assert early_augment(None, senses) is None and early_augment((None, None), senses) is None
    with pytest.raises(InputError, match=r"\[2, 3\] copies.*same augment_copies"):
        early_augment((GainAugment(copies=3), GainAugment(copies=2)), senses)


def test_an_augmented_early_network_and_its_fold_networks_train_on_the_copies_and_its_file_keeps_it(tmp_path):
    from supramodal.fused_model import EarlyFusionModel

    senses, va, vb, labels = _early_data()
    kw = dict(epochs=30, seed=2, calibration_folds=3)
    plain = EarlyFusionModel.train(senses, va, vb, labels, CLASSES, **kw)
    ones = EarlyFusionModel.train(senses, va, vb, labels, CLASSES, augment=GainAugment(copies=2, spread=0.0), **kw)
    aug = EarlyFusionModel.train(senses, va, vb, labels, CLASSES, **kw,
                                 augment=GainAugment(copies=2, spread=0.05, per_channel=None))     # by bank
    # gains of 1: exact copies, which iRPROP- does not see: every network as without (so the copies reach them all)
    for a, b in zip(ones.mlp.params(), plain.mlp.params(), strict=True):       # every deployed network
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ones.out_of_fold.logits, plain.out_of_fold.logits)
    assert not np.array_equal(aug.mlp.stacked()[0], plain.mlp.stacked()[0])
    assert not np.array_equal(aug.out_of_fold.logits, plain.out_of_fold.logits)
    assert aug.out_of_fold.logits.shape == plain.out_of_fold.logits.shape     # one held-out row per pair
    np.testing.assert_array_equal(aug.mean, plain.mean)                        # scaling from the originals
    assert aug.training["windows"] == len(va) and plain.augment is None
    # the novelty allows for a new touch at least as far as the copies' gains spread (each sense's groups its own)
    assert aug.novelty.touch.spread >= 0.05 > plain.novelty.touch.spread
    groups = aug.novelty.touch.groups
    assert groups[:8] == tuple(range(8)) and groups[8:16] == (-1,) * 8 and set(groups[16:]) == {8}   # Af, f; A
    loaded = EarlyFusionModel.load(aug.save(tmp_path / "early.npz"))
    assert [a.per_channel for a in loaded.augment] == [True, False] and loaded.augment[0].copies == 2
    header_bad = dict(aug.training, augment=[aug.training["augment"][0]])
    broken = dataclasses.replace(aug, training=header_bad)
    with pytest.raises(ModelError, match="two senses' gain augmentation"):
        EarlyFusionModel.load(broken.save(tmp_path / "broken.npz"))
    for part in ({**aug.training["augment"][1], "copies": 3}, {**aug.training["augment"][1], "per_channel": None}):
        unlike = dataclasses.replace(aug, training=dict(aug.training, augment=[aug.training["augment"][0], part]))
        with pytest.raises(ModelError, match="same copies and per_channel true or false"):
            EarlyFusionModel.load(unlike.save(tmp_path / "unlike.npz"))


def test_an_early_sense_without_a_gain_linear_feature_is_repeated_unchanged_beside_the_others_copies():
    """A microphone of f alone has no gain to draw: its windows are repeated so that each pair stays a pair
    (the two senses' rows were joined at different lengths: a numpy error)."""
    from supramodal.banks import cochlea_bank
    from supramodal.fused_model import EarlyFusionModel, Sense

    _, va, vb, labels = _early_data()
    senses = (Sense("whiskers", BANK, ("Af", "f"), 500), Sense("mic", cochlea_bank(), ("f",), 4410))
    model = EarlyFusionModel.train(senses, va, vb, labels, CLASSES, epochs=20, seed=1, calibration_folds=3,
                                   augment=GainAugment(copies=2, spread=0.05, per_channel=None))
    from supramodal.fused_model import EarlyGainCopies, early_augment
    from supramodal.fusion import early_inputs

    rows, y = EarlyGainCopies.of(early_augment(GainAugment(2, 0.05, None), senses), senses)(
        early_inputs(va, vb), labels, 0)
    assert rows.shape == (3 * len(va), 16 + 50) and len(y) == len(rows)
    for k in range(3):
        np.testing.assert_array_equal(rows[k * len(vb):(k + 1) * len(vb), 16:], vb.reshape(len(vb), -1))
    assert model.augment is not None and model.calibration is not None
