"""Gain augmentation of training windows (supramodal/model.py ``GainAugment``, ``TextureModel.train(augment=)``):
the copies it makes, written out; every network trained on them, the held-out windows not; no copies' worth of
change where the gains are all 1."""

from __future__ import annotations

import numpy as np

from supramodal.banks import whisker_bank
from supramodal.model import GAIN_LINEAR_FEATURES, GainAugment, TextureModel

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
    np.testing.assert_array_equal(ones.mlp.w1, plain.mlp.w1)
    np.testing.assert_array_equal(ones.mean, plain.mean)
    np.testing.assert_array_equal(ones.out_of_fold.logits, plain.out_of_fold.logits)
    assert ones.calibration == plain.calibration and ones.training["augment"]["copies"] == 2


def test_augmented_networks_differ_and_the_held_out_windows_are_the_originals():
    values, labels = _data()
    plain = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=40, seed=1)
    aug = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=40, seed=1,
                             augment=GainAugment(copies=2, spread=0.05))
    assert not np.array_equal(aug.mlp.w1, plain.mlp.w1)
    assert aug.out_of_fold.logits.shape == plain.out_of_fold.logits.shape    # one held-out row per window
    np.testing.assert_array_equal(aug.mean, plain.mean)                      # scaling from the originals
    assert aug.training["windows"] == len(values)
