"""Calibrated confidence (issue 23): stable log-posteriors, the window map and the contact pooling,
the measures, ties, the novelty score, and the calibration's round trip through a model file."""

import json

import mpmath
import numpy as np
import pytest

from supramodal.banks import whisker_bank
from supramodal.calibration import (DEFAULT_CALIBRATION_FOLDS, NOVELTY_QUANTILES, NOVELTY_RUN, Calibration, Novelty,
                                    brier_score, cap_gaps, calibration_folds, fit_novelty, novelty_warp,
                                    expected_calibration_error, fit_calibration, fit_capped_pooling, fit_pooling, fit_window_calibration,
                                    log_loss, normalised_log_posteriors, pool_log_posteriors, winner)
from supramodal.decisions import DecisionAccumulator
from supramodal.errors import InputError
from supramodal.model import MODEL_VERSION, ModelError, TextureModel

mpmath.mp.dps = 50


# -- stable log-posteriors, against extended precision -------------------------------------------

def _reference_normalised(z):
    """log(o_k / sum o), o = 1 / (1 + exp(-z)), at 50 digits."""
    o = [1 / (1 + mpmath.exp(-mpmath.mpf(float(v)))) for v in z]
    total = mpmath.fsum(o)
    return [float(mpmath.log(v / total)) for v in o]


@pytest.mark.parametrize("z", [[-800.0, 30.0, 0.5], [-647.0, -300.0, 46.0, 12.0], [1e-3, -1e-3, 0.0],
                               [700.0, 699.0, -700.0], [-40.0, -41.0, -39.5]])
def test_normalised_log_posteriors_match_extended_precision_without_clipping(z):
    """The outputs of the losing classes round to exactly 0.0 in float64 (z = -800); their
    log-posteriors must still be finite and right, not the log of a clip at 1e-12."""
    got = normalised_log_posteriors(np.array(z))
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, _reference_normalised(z), rtol=1e-12, atol=1e-12)


def test_calibrated_log_posteriors_match_extended_precision():
    cal = Calibration(3.0, 10.0, 0.2)
    z = np.array([-647.0, 46.0, 0.3, -2.0])
    s = [3.0 * mpmath.asinh(mpmath.mpf(float(v)) / 10) for v in z]
    lse = mpmath.log(mpmath.fsum(mpmath.exp(v) for v in s))
    np.testing.assert_allclose(cal.log_posteriors(z), [float(v - lse) for v in s], rtol=1e-13, atol=1e-13)


def test_calibration_keeps_every_windows_winner():
    """The paper's winner-take-all is unchanged: the map is increasing in each logit."""
    rng = np.random.default_rng(0)
    z = rng.normal(0, 50, (500, 7)) * rng.uniform(0.01, 10, (500, 1))
    for cal in (Calibration(0.01, 1e4, 0.0), Calibration(3.0, 10.0, 0.5), Calibration(100.0, 0.01, 1.0)):
        np.testing.assert_array_equal(np.argmax(cal.log_posteriors(z), axis=1), np.argmax(z, axis=1))
        np.testing.assert_allclose(np.exp(cal.log_posteriors(z)).sum(axis=1), 1.0, rtol=1e-12)


# -- fitting ------------------------------------------------------------------------------------------

def _sampled(a, c, n=6000, k=5, seed=0):
    """Logits and labels drawn from a known calibrated model softmax(a asinh(z / c))."""
    rng = np.random.default_rng(seed)
    z = rng.normal(0, 30, (n, k))
    p = np.exp(Calibration(a, c, 0.0).log_posteriors(z))
    y = np.array([rng.choice(k, p=row) for row in p])
    return z, y, p


def test_window_calibration_recovers_the_posteriors_it_was_drawn_from():
    z, y, p = _sampled(2.0, 15.0)
    a, c = fit_window_calibration(z, y)
    fitted = np.exp(Calibration(a, c, 0.0).log_posteriors(z))
    assert np.max(np.abs(fitted - p)) < 0.06
    # and it beats the uncalibrated normalised outputs, which are sure of everything
    assert log_loss(np.log(fitted), y) < log_loss(normalised_log_posteriors(z), y) - 0.5


def test_all_right_held_out_windows_do_not_make_the_calibration_infinitely_sure():
    """Laplace's rule: n right windows of n allow about 1 - 1/(n + 2), not 1.0."""
    rng = np.random.default_rng(1)
    y = rng.integers(0, 4, 400)
    z = rng.normal(0, 1, (400, 4))
    z[np.arange(400), y] += 20.0
    cal = Calibration(*fit_window_calibration(z, y), 0.0)
    top = np.exp(cal.log_posteriors(z).max(axis=1))
    assert top.max() < 1 - 1e-5 and np.median(top) > 0.99


def test_pooling_of_copies_is_one_window_and_of_independent_windows_naive_bayes():
    rng = np.random.default_rng(2)
    runs, labels, copies = [], [], []
    for i in range(300):
        y = i % 3
        p = np.full(3, 0.2)
        p[y] = 0.6
        draws = rng.choice(3, size=8, p=p)          # each window a fresh draw: independent evidence
        lp = np.log(np.where(np.arange(3)[None, :] == draws[:, None], 0.6, 0.2))
        runs.append(lp)
        labels.append(y)
        copies.append(np.repeat(lp[:1], 8, axis=0))  # one window repeated: no new evidence
    assert fit_pooling(runs, labels) < 0.1
    assert fit_pooling(copies, labels) > 0.9


def test_pooled_log_posteriors_match_a_plain_computation():
    rng = np.random.default_rng(3)
    lp = np.log(rng.dirichlet(np.ones(4), size=6))
    for rho in (0.0, 0.3, 0.9, 1.0):
        # n_eff of 6 windows with correlation rho^|i-j|: n^2 / sum_ij rho^|i-j| (the variance of their mean)
        n_eff = mpmath.mpf(36) / mpmath.fsum(mpmath.mpf(rho) ** abs(i - j) for i in range(6) for j in range(6))
        g = n_eff / 6
        s = [g * mpmath.fsum(mpmath.mpf(float(lp[t, k])) for t in range(6)) for k in range(4)]
        total = mpmath.log(mpmath.fsum(mpmath.exp(v) for v in s))
        np.testing.assert_allclose(pool_log_posteriors(lp, rho), [float(v - total) for v in s], rtol=1e-12)


def test_fit_calibration_reports_what_it_was_fitted_on():
    z, y, _ = _sampled(1.0, 20.0, n=800, k=3)
    cal = fit_calibration(z, y, groups=y)
    assert cal.fitted_on["windows"] == 800 and cal.fitted_on["log_loss"] < cal.fitted_on["log_loss_uncalibrated"]
    assert 0.0 <= cal.correlation <= 1.0


def test_calibration_folds_are_by_recording_when_there_are_enough_else_by_span():
    labels = np.repeat([0, 1], 30)
    groups = np.repeat(np.arange(6), 10)                    # three recordings per label
    folds, by = calibration_folds(labels, groups, k=3)
    assert by == "recording"
    for g in range(6):
        assert len(set(folds[groups == g])) == 1            # a recording's windows on one side
    folds, by = calibration_folds(labels, labels, k=5)      # one recording per label
    assert by == "span"
    for lab in (0, 1):
        f = folds[labels == lab]
        assert list(f) == sorted(f) and set(f) == set(range(5))   # consecutive spans, in time order


# -- measures, against plain loops ------------------------------------------------------------------

def test_ece_and_brier_against_plain_loops():
    rng = np.random.default_rng(4)
    p = rng.dirichlet(np.ones(5) * 0.5, size=1000)
    y = rng.integers(0, 5, 1000)
    conf, ok = p.max(axis=1), p.argmax(axis=1) == y
    ece = 0.0
    for b in range(15):
        lo, hi = b / 15, (b + 1) / 15
        inside = [i for i in range(1000) if (lo < conf[i] <= hi) or (b == 0 and conf[i] == 0)]
        if inside:
            ece += len(inside) / 1000 * abs(np.mean(ok[inside]) - np.mean(conf[inside]))
    assert expected_calibration_error(conf, ok) == pytest.approx(ece, abs=1e-12)
    brier = np.mean([sum((p[i, k] - (k == y[i])) ** 2 for k in range(5)) for i in range(1000)])
    assert brier_score(p, y) == pytest.approx(brier, rel=1e-12)


# -- ties ---------------------------------------------------------------------------------------------

def test_a_tie_is_no_decision_whatever_the_class_order():
    lp = np.log(np.array([[0.4, 0.4, 0.2], [0.2, 0.4, 0.4], [0.5, 0.3, 0.2]]))
    assert winner(lp).tolist() == [-1, -1, 0]
    order = [2, 0, 1]
    assert winner(lp[:, order]).tolist() == [-1, -1, 1]


def test_late_fusion_at_equal_weight_does_not_break_ties_by_class_name():
    from supramodal.fusion import fuse_late

    a = np.log(np.array([[0.7, 0.3]]))
    b = np.log(np.array([[0.3, 0.7]]))
    assert winner(fuse_late(a, b, 0.5)).tolist() == [-1]


# -- anytime decisions --------------------------------------------------------------------------------

def test_contact_decision_is_final_at_the_first_window_that_is_sure_and_stands_until_the_contact_ends():
    acc = DecisionAccumulator(3, "contact", n=0, correlation=0.0, confidence=0.99)
    sure_of_1 = np.log(np.array([0.1, 0.8, 0.1]))
    said = [acc.update(sure_of_1) for _ in range(4)]
    # pooled p(1) after n windows: 8^n / (8^n + 2): 0.8, 0.97, 0.996 -> final at the third
    assert [d.decided for d in said] == [False, False, True, True]
    assert said[2].windows == 3 and said[3].windows == 3 and said[3].label == 1
    # later windows that say otherwise do not undo the final decision of this contact
    assert acc.update(np.log(np.array([0.98, 0.01, 0.01]))).label == 1
    assert acc.update(sure_of_1, in_contact=False).label == -1          # the contact ended
    assert not acc.update(sure_of_1).decided                             # a new contact starts afresh


def test_a_confidence_threshold_needs_a_contact_scope():
    with pytest.raises(InputError, match="scope 'contact'"):
        DecisionAccumulator(3, "last", n=5, confidence=0.9)


# -- the model file -----------------------------------------------------------------------------------

BANK = whisker_bank(rows="AB")
CLASSES = ("rough", "smooth", "medium")


def _data(seed=0, n=60):
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(3), n)
    values = rng.gamma(2.0, 1.0, (3 * n, 1, 8)) * 100.0
    values[:, 0, :3] *= 1 + 0.6 * labels[:, None]
    return values, labels


@pytest.fixture(scope="module")
def model():
    values, labels = _data()
    return TextureModel.train(values, labels, CLASSES, BANK, ("Af",), 500, epochs=60, seed=1)


def test_trained_model_is_calibrated_on_held_out_windows_and_keeps_the_networks_decisions(model):
    values, labels = _data(seed=5)
    assert model.calibrated and model.calibration.fitted_on["folds"] == DEFAULT_CALIBRATION_FOLDS
    assert model.calibration.fitted_on["windows"] == 180
    np.testing.assert_array_equal(np.argmax(model.log_posteriors(values), axis=1), model.predict(values))
    # it deploys its calibration's fold networks (tests/test_ensemble.py); without folds, one network
    assert len(model.mlp.members) == DEFAULT_CALIBRATION_FOLDS
    plain = TextureModel.train(*_data(), CLASSES, BANK, ("Af",), 500, epochs=60, seed=1, calibration_folds=0)
    assert not plain.calibrated and not hasattr(plain.mlp, "members")


def test_calibration_and_novelty_round_trip_through_the_model_file(model, tmp_path):
    path = model.save(tmp_path / "m.npz")
    loaded = TextureModel.load(path)
    assert loaded.calibration == model.calibration
    values, _ = _data(seed=7)
    np.testing.assert_array_equal(loaded.log_posteriors(values), model.log_posteriors(values))
    np.testing.assert_array_equal(loaded.novelty_score(values), model.novelty_score(values))
    with np.load(path, allow_pickle=False) as npz:
        assert json.loads(str(npz["header"]))["version"] == MODEL_VERSION == 3


def _rewrite(path, edit_header=None, drop=(), arrays=None):
    with np.load(path, allow_pickle=False) as npz:
        header = json.loads(str(npz["header"]))
        parts = {k: npz[k] for k in npz.files if k != "header" and k not in drop}
    if edit_header:
        edit_header(header)
    parts.update(arrays or {})
    with open(path, "wb") as fh:
        np.savez(fh, header=np.array(json.dumps(header)), **parts)
    return path


def test_a_version_1_file_still_loads_and_is_said_to_be_uncalibrated(model, tmp_path):
    def to_v1(h):
        h["version"] = 1
        del h["calibration"], h["novelty"], h["networks"]

    one = model.mlp.members[0]                                  # a version 1 file holds one network
    path = _rewrite(model.save(tmp_path / "v1.npz"), to_v1, drop=("novelty_means", "novelty_precision",
                                                                   "novelty_quantiles"),
                    arrays=dict(zip(("w1", "b1", "w2", "b2"), one.params())))
    old = TextureModel.load(path)
    assert not old.calibrated and old.novelty is None
    values, _ = _data(seed=8)
    np.testing.assert_allclose(np.exp(old.log_posteriors(values)),
                               old.outputs(values) / old.outputs(values).sum(axis=1, keepdims=True), rtol=1e-9)
    with pytest.raises(ModelError, match="retrain"):
        old.novelty_score(values)


@pytest.mark.parametrize("edit, arrays, drop, message", [
    (lambda h: h["calibration"].update(temperature=-1.0), None, (), "temperature"),
    (lambda h: h["calibration"].update(method="isotonic"), None, (), "not known"),
    (lambda h: h["calibration"].update(correlation=2.0), None, (), "correlation"),
    (lambda h: h["calibration"].pop("scale"), None, (), "exactly the keys"),
    (lambda h: h.update(calibration=[1, 2]), None, (), "must be an object"),
    (lambda h: h.update(novelty="yes"), None, (), "true or false"),
    (None, None, ("novelty_precision",), "lacks"),
    (None, {"novelty_quantiles": np.tile(np.linspace(1, 0, len(NOVELTY_QUANTILES)), (NOVELTY_RUN, 1))}, (),
     "non-decreasing"),
    (None, {"novelty_quantiles": np.linspace(0, 1, len(NOVELTY_QUANTILES))}, (), "novelty_quantiles has shape"),
    (lambda h: h["novelty"].update(method="knn"), None, (), "novelty method 'knn' is not known"),
    (lambda h: h["novelty"].update(gain=[1.0] * 7), None, (), "list of 8 finite numbers"),
    (lambda h: h["novelty"].update(gain=[0.0] * 8), None, (), "gain' must be > 0"),
    (lambda h: h["novelty"].pop("offset"), None, (), "exactly the keys"),
    (None, {"novelty_means": np.zeros((2, 8))}, (), "novelty_means"),
    (lambda h: h.update(novelty=False), None, (), "says it has no novelty"),
    (lambda h: h.update(version=1), None, (), "unknown header key"),
])
def test_a_bad_calibration_in_a_model_file_is_refused_by_name(model, tmp_path, edit, arrays, drop, message):
    path = _rewrite(model.save(tmp_path / "bad.npz"), edit, drop, arrays)
    with pytest.raises(ModelError, match=message):
        TextureModel.load(path)


def test_an_asymmetric_precision_is_refused(model, tmp_path):
    p = model.novelty.precision.copy()
    p[0, 1] += 1.0
    path = _rewrite(model.save(tmp_path / "asym.npz"), arrays={"novelty_precision": p})
    with pytest.raises(ModelError, match="symmetric"):
        TextureModel.load(path)


def test_novelty_threshold_calls_the_asked_share_of_held_out_known_windows_unknown(model):
    values, labels = _data(seed=11, n=400)
    scores = model.novelty_score(values)
    called = np.mean(scores > model.novelty.threshold(0.05))
    assert 0.01 < called < 0.12
    far = values * 6.0                                              # a texture far louder than any known
    assert np.mean(model.novelty_score(far) > model.novelty.threshold(0.05)) > 0.9


def test_a_version_2_file_of_before_the_warp_still_loads_and_scores_the_standardised_inputs(model, tmp_path):
    """A version 2 file written before the novelty's warp says ``"novelty": true`` and holds one row
    of quantiles: it loads, scores the unwarped distance, and has no contact thresholds."""
    values, _ = _data(seed=7)
    x = model._inputs(values)
    means = np.stack([x[:3].mean(axis=0), x[3:6].mean(axis=0), x[6:9].mean(axis=0)])
    precision = np.diag(np.arange(1.0, 9.0))

    def unwarped(h):
        h["novelty"] = True

    path = _rewrite(model.save(tmp_path / "old.npz"), unwarped,
                    arrays={"novelty_means": means, "novelty_precision": precision,
                            "novelty_quantiles": np.linspace(0.0, 10.0, len(NOVELTY_QUANTILES))})
    old = TextureModel.load(path)
    assert old.novelty.gain is None and not old.novelty.pools
    d = x[:, None, :] - means[None]
    np.testing.assert_allclose(old.novelty_score(values), (d * d * np.arange(1.0, 9.0)).sum(axis=2).min(axis=1),
                               rtol=1e-12)
    assert old.novelty.threshold(0.05) == pytest.approx(9.5)
    with pytest.raises(InputError, match="no contact quantiles"):
        old.novelty.contact_threshold(0.05, 10)


def test_the_novelty_warp_is_the_logarithm_of_the_raw_inputs():
    rng = np.random.default_rng(0)
    raw = rng.gamma(2.0, 50.0, (200, 4)) + 20.0
    mean, scale = raw.mean(axis=0), raw.std(axis=0)
    gain, offset = novelty_warp(mean, scale)
    u = np.arcsinh(((raw - mean) / scale) * gain + offset)
    # asinh(v / floor) = log(2 v / floor) + O((floor / v)^2): up to a constant per input, log v
    np.testing.assert_allclose(u - np.log(raw), np.log(2.0 / (0.01 * mean)) + 0 * u, atol=2e-3)


def _novelty_data(rng, classes, n, shift=0.0):
    """Windows of textures with log-normal inputs: class k's log-mean is k in the first input,
    ``shift`` in the second (a texture the model never met: shift > 0)."""
    labels = np.repeat(np.arange(len(classes)), n)
    logs = rng.normal(0.0, 0.5, (len(labels), 3))
    logs[:, 0] += np.asarray(classes, dtype=float)[labels]
    logs[:, 1] += shift
    return np.exp(logs + 3.0), labels


def test_held_out_thresholds_come_from_known_windows_only_and_novel_contacts_pass_them():
    """Fitted on known textures alone, the window and contact thresholds call about the asked share of
    fresh known windows and contacts unknown; a texture between the known ones in the first input
    but off in the second is caught per contact far more often than per window (its windows overlap
    the known ones', its contacts' means do not)."""
    rng = np.random.default_rng(3)
    raw, y = _novelty_data(rng, [0, 2], 300)
    mean, scale = raw.mean(axis=0), raw.std(axis=0)
    folds = (np.arange(len(y)) % 300) * 10 // 300
    nov = fit_novelty((raw - mean) / scale, y, 2, folds, y, mean, scale)
    assert nov.pools and nov.quantiles.shape == (NOVELTY_RUN, len(NOVELTY_QUANTILES))
    # row 0 is the held-out window scores' quantiles, computed here apart from fit_novelty, on the raw
    # inputs' warp (asinh of the raw values over 1 % of their mean: their logarithm, up to a constant)
    u = np.arcsinh(raw / (0.01 * mean))
    held = np.empty(len(y))
    for f in range(10):
        test = folds == f
        means = np.stack([u[~test & (y == k)].mean(axis=0) for k in range(2)])
        r = u[~test] - means[y[~test]]
        cov = r.T @ r / (len(r) - 2)
        cov = 0.9 * cov + 0.1 * np.diag(np.diag(cov)) + 1e-6 * np.eye(3)
        d = u[test][:, None, :] - means[None]
        held[test] = np.einsum("nki,ij,nkj->nk", d, np.linalg.inv(cov), d).min(axis=1)
    np.testing.assert_allclose(nov.quantiles[0], np.quantile(held, NOVELTY_QUANTILES), rtol=1e-9)

    known, _ = _novelty_data(rng, [0, 2], 400)
    novel, _ = _novelty_data(rng, [1], 400, shift=0.6)
    xk, xn = (known - mean) / scale, (novel - mean) / scale
    assert 0.02 < np.mean(nov.score(xk) > nov.threshold(0.05)) < 0.09
    window_caught = np.mean(nov.score(xn) > nov.threshold(0.05))
    t = nov.contact_threshold(0.05, 10)
    contacts_known = [nov.pooled_score(xk[i:i + 10]) for i in range(0, len(xk), 10)]
    contacts_novel = [nov.pooled_score(xn[i:i + 10]) for i in range(0, len(xn), 10)]
    assert np.mean(np.array(contacts_known) > t) < 0.12
    assert np.mean(np.array(contacts_novel) > t) > 0.9 > 0.5 > window_caught
    assert nov.pooled_score(xn[:1]) == pytest.approx(float(nov.score(xn[:1])[0]))


def test_the_contact_threshold_refuses_what_is_no_contact(model):
    with pytest.raises(InputError, match="at least one window"):
        model.novelty.contact_threshold(0.05, 0)
    with pytest.raises(InputError, match="needs windows"):
        model.novelty.pooled_score(np.zeros((0, 8)))
    assert model.novelty.contact_threshold(0.05, 10 * NOVELTY_RUN) == model.novelty.contact_threshold(0.05, NOVELTY_RUN)


def test_a_model_file_written_before_calibration_loads_uncalibrated():
    """tests/data/model-v1.npz was written by this program at e879733 (format version 1), with the
    first five training windows and the outputs it gave them in model-v1-check.npy."""
    from pathlib import Path

    data = Path(__file__).parent / "data"
    old = TextureModel.load(data / "model-v1.npz")
    check = np.load(data / "model-v1-check.npy")
    values, outputs = check[:, :8].reshape(5, 1, 8), check[:, 8:]
    assert not old.calibrated and old.novelty is None
    np.testing.assert_allclose(old.outputs(values), outputs, rtol=1e-12)
    np.testing.assert_allclose(np.exp(old.log_posteriors(values)), outputs / outputs.sum(axis=1, keepdims=True),
                               rtol=1e-9)


def test_the_calibrations_fold_networks_stand_in_for_copies_trained_again(model, tmp_path):
    """A late fusion's weight needs held-out logits of the training windows: the model's own
    calibration already trained those fold networks on those windows; they must equal copies
    trained again, and be used only for the very windows and folds they were made on."""
    import dataclasses

    from supramodal.calibration import calibration_folds
    from supramodal.fused_model import out_of_fold_logits

    values, labels = _data()
    folds, _ = calibration_folds(labels, labels, DEFAULT_CALIBRATION_FOLDS)
    kept = out_of_fold_logits(model, values, labels, CLASSES, folds)
    again = out_of_fold_logits(dataclasses.replace(model, out_of_fold=None), values, labels, CLASSES, folds)
    np.testing.assert_allclose(kept, again, rtol=1e-9, atol=1e-9)
    assert model.out_of_fold.matches(values, labels, folds)
    assert not model.out_of_fold.matches(values * 1.0001, labels, folds)
    assert not model.out_of_fold.matches(values, labels, (folds + 1) % DEFAULT_CALIBRATION_FOLDS)
    assert TextureModel.load(model.save(tmp_path / "m.npz")).out_of_fold is None     # never in the file


@pytest.mark.parametrize("rho", [0.5, 0.99, 1 - 1e-4, 1 - 1e-8, 1 - 1e-11, 1 - 1e-15])
def test_effective_windows_against_extended_precision_up_to_rho_one(rho):
    """n^2 / sum_ij rho^|i-j|, at 50 digits; the closed form cancels near rho = 1 (a model file or
    a scene may hold any rho in [0, 1])."""
    from supramodal.calibration import effective_windows

    ns = np.array([1, 2, 7, 50])
    got = effective_windows(ns, rho)
    for n, g in zip(ns, got):
        ref = mpmath.mpf(int(n)) ** 2 / mpmath.fsum(mpmath.mpf(rho) ** abs(i - j) for i in range(n) for j in range(n))
        assert g == pytest.approx(float(ref), rel=1e-9)


def _plain_prefix_loss(runs, labels, rho, caps=None):
    """The log loss (smoothed targets) of every prefix of every run, each pooled on its own as a contact
    is (pool_log_posteriors): the plain loop the pooling fits vectorise."""
    eps = 1.0 / (sum(len(r) for r in runs) + 2)
    total, count = 0.0, 0
    for lp, label in zip(runs, labels):
        for m in range(1, len(lp) + 1):
            pooled = pool_log_posteriors(lp[:m], rho, caps)
            t = np.full(pooled.shape, eps / (len(pooled) - 1))
            t[label] = 1.0 - eps
            total -= float((t * pooled).sum())
            count += 1
    return total / count


def test_the_pooling_fits_find_the_least_loss_of_every_prefix_pooled_as_a_contact_is():
    """fit_pooling and fit_capped_pooling (which pool every prefix at once) against a plain search over
    the loss of each prefix pooled on its own: the fitted correlation is no worse than the plain
    search's, and the loss is the same function (runs of 1 to 30 windows, 4 classes)."""
    from scipy.optimize import minimize_scalar

    rng = np.random.default_rng(7)
    labels = [int(k) for k in rng.integers(0, 4, size=12)]
    runs = []
    for label in labels:
        z = rng.normal(size=(int(rng.integers(1, 31)), 4)) + np.eye(4)[label] * 1.2
        z += rng.normal(size=4) * 0.8                         # a per-run bias: windows of a run correlate
        runs.append(z - np.log(np.exp(z).sum(axis=1, keepdims=True)))
    rho = fit_pooling(runs, labels)
    plain = minimize_scalar(lambda r: _plain_prefix_loss(runs, labels, r), bounds=(0.0, 1.0), method="bounded",
                            options={"xatol": 1e-5})
    assert 0.0 < rho < 1.0
    assert _plain_prefix_loss(runs, labels, rho) <= plain.fun + 1e-9
    capped_rho, caps = fit_capped_pooling(runs, labels)
    assert fit_capped_pooling(runs, labels, plain_correlation=rho)[0] == capped_rho
    # with its caps, no correlation does better than the capped fit's, prefix by prefix
    fitted = _plain_prefix_loss(runs, labels, capped_rho, caps)
    assert min(_plain_prefix_loss(runs, labels, r, caps) for r in np.linspace(0.0, 1.0, 41)) >= fitted - 1e-7


def test_fit_pooling_keeps_each_run_with_its_label_when_one_is_empty():
    lp = np.log(np.array([[0.9, 0.1]] * 5))
    other = np.log(np.array([[0.1, 0.9]] * 5))
    with_empty = fit_pooling([lp, np.empty((0, 2)), other], [0, 1, 1])
    assert with_empty == pytest.approx(fit_pooling([lp, other], [0, 1]), abs=1e-6)


def test_a_vote_never_counts_a_tied_window_for_the_first_class_and_is_no_confidence_rule():
    acc = DecisionAccumulator(2, "last", n=5, method="vote")
    tied = np.log(np.array([0.5, 0.5]))
    assert acc.update(tied).label == -1 and acc.update(tied).label == -1
    with pytest.raises(InputError, match="method 'log'"):
        DecisionAccumulator(2, "contact", n=0, method="vote", confidence=0.9)


def test_a_final_contact_decision_stands_as_it_was_said_and_is_never_taken_while_mostly_unknown():
    from supramodal.decisions import UNKNOWN, Decider, DecisionRules

    d = Decider(("a", "b"), DecisionRules(scope="contact", n=0, method="log", confidence=0.9, unknown_below=0.95))
    unsure = np.log(np.array([0.94, 0.06]))          # each window unknown (below 0.95), pooled soon sure
    said = [d.decide(unsure).pooled for _ in range(4)]
    assert all(p.label == UNKNOWN and not p.decided for p in said)
    sure = np.log(np.array([0.99, 0.01]))
    said = [d.decide(sure).pooled for _ in range(8)]
    final = next(p for p in said if p.decided)
    assert final.label == "a" and all(p == final for p in said[said.index(final):])
    assert d.decide(np.log(np.array([0.01, 0.99]))).pooled == final     # a later window changes nothing
    assert d.summary()["contacts_decided"] == 1


@pytest.mark.parametrize("edit, message", [
    (lambda h: h["calibration"].update(temperature=1e300), "temperature"),
    (lambda h: h["calibration"]["fitted_on"].update(log_loss="small"), "finite number"),
    (lambda h: h["calibration"]["fitted_on"].update(windows=-3), "count"),
    (lambda h: h["calibration"]["fitted_on"].update(folds_by="chance"), "folds_by"),
])
def test_calibration_numbers_a_file_may_hold_are_bounded(model, tmp_path, edit, message):
    path = _rewrite(model.save(tmp_path / "bad.npz"), edit)
    with pytest.raises(ModelError, match=message):
        TextureModel.load(path)


# -- caps per pair of classes (issue 23: classes the network cannot tell apart) ----------------------

def _capped_reference(scores, caps, q=16):
    """cap_gaps at 50 digits: leads over the winner softly capped, d / (1 + (d / L) ** q) ** (1 / q)."""
    s = [mpmath.mpf(float(v)) for v in scores]
    k = max(range(len(s)), key=lambda i: s[i])
    led = [0 if j == k else (s[k] - s[j]) / (1 + ((s[k] - s[j]) / mpmath.mpf(float(caps[k][j]))) ** q) ** (mpmath.mpf(1) / q)
           for j in range(len(s))]
    lse = mpmath.log(mpmath.fsum(mpmath.exp(-v) for v in led))
    return [float(-v - lse) for v in led]


@pytest.mark.parametrize("scores", [[3.0, 1.0, -2.0], [-647.0, 46.0, 45.9], [0.2, 0.1, 40.0], [5.0, 5.0 - 1e-9, 0.0]])
def test_capped_posteriors_match_extended_precision(scores):
    caps = np.array([[0.0, 0.3, 5.0], [0.05, 0.0, 2.0], [7.0, 1e3, 0.0]])
    np.testing.assert_allclose(cap_gaps(np.array(scores), caps), _capped_reference(scores, caps), rtol=1e-12, atol=1e-12)


def test_caps_keep_every_windows_winner_and_every_tie():
    rng = np.random.default_rng(3)
    k = 6
    z = rng.normal(0, 40, (2000, k)) * rng.uniform(0.001, 10, (2000, 1))
    z[:50, 1] = z[:50, 4] = z[:50].max(axis=1) + 1.0                   # ties for the top
    caps = rng.uniform(1e-3, 5, (k, k))
    np.fill_diagonal(caps, 0.0)
    tight = np.where(np.eye(k, dtype=bool), 0.0, 1e-3)
    for cal in (Calibration(2.0, 10.0, 0.3, {}, caps, caps, 0.5), Calibration(1e4, 1e-3, 0.0, {}, tight, caps, 0.0)):
        lp = cal.log_posteriors(z)
        np.testing.assert_array_equal(winner(lp), winner(z))            # a tie stays a tie: -1
        assert np.all(winner(lp)[:50] == -1)
        np.testing.assert_allclose(np.exp(lp).sum(axis=1), 1.0, rtol=1e-12)
        assert np.isfinite(lp).all()
        pooled = cal.pool(lp[50:70])
        assert winner(pooled) == winner(pool_log_posteriors(lp[50:70], cal.correlation))


def _confusable(seed=0, runs=12, run=20):
    """Held-out logits of 4 classes: 2 and 3 told apart (sure and right), 0 and 1 not: the network
    is as sure, but picks one of the pair for a whole run of windows, either side with equal chance
    (its preference persists within a touch, as the two-sense world's microphone does)."""
    rng = np.random.default_rng(seed)
    z, y, groups, folds = [], [], [], []
    for r in range(runs * 4):
        label = r % 4
        side = label if label >= 2 else rng.integers(2)
        logits = rng.normal(-30, 8, (run, 4))
        logits[:, side] = rng.normal(30, 8, run)
        if label < 2 and rng.random() < 0.1:                            # a few windows pick the other side
            logits[:, [0, 1]] = logits[:, [1, 0]]
        z.append(logits)
        y += [label] * run
        groups += [r] * run
        folds += [r % 10] * run
    return np.vstack(z), np.array(y), np.array(groups), np.array(folds)


def test_two_classes_the_network_cannot_tell_apart_are_called_even_per_window_and_per_contact():
    """The calibrated posteriors of the pair approach 0.5 / 0.5 (the truth: either side is right half
    the time), per window and per contact, while the pair the network tells apart stays sure; one
    temperature for all (no caps) cannot do both. Winners are the network's."""
    z, y, groups, folds = _confusable()
    cal = fit_calibration(z, y, groups, folds=folds)
    plain = fit_calibration(z, y, groups, folds=folds, caps=False)
    assert cal.caps is not None and plain.caps is None and plain.contact_caps is None
    zt, yt, gt, _ = _confusable(seed=1)
    pair = yt < 2
    for c in (cal, plain):
        np.testing.assert_array_equal(winner(c.log_posteriors(zt)), winner(zt))
    p = np.exp(cal.log_posteriors(zt))
    assert abs(p[pair].max(axis=1).mean() - 0.5) < 0.05                # even within the pair
    assert p[pair][:, :2].sum(axis=1).min() > 0.97                      # and sure it is the pair
    assert p[~pair].max(axis=1).min() > 0.97                            # the other pair stays sure
    assert np.exp(plain.log_posteriors(zt))[pair].max(axis=1).mean() > 0.7   # what caps fix
    contacts = [np.flatnonzero(gt == g)[:10] for g in np.unique(gt)]
    top = np.array([np.exp(cal.pool(cal.log_posteriors(zt[r]))).max() for r in contacts])
    is_pair = np.array([yt[r[0]] < 2 for r in contacts])
    assert abs(top[is_pair].mean() - 0.5) < 0.05 and top[~is_pair].min() > 0.99
    right = np.array([winner(cal.pool(cal.log_posteriors(zt[r]))) == yt[r[0]] for r in contacts])
    assert 0.3 < right[is_pair].mean() < 0.7                            # what 0.5 claims, roughly


def test_capped_calibration_round_trips_and_bad_caps_are_refused_by_name(model, tmp_path):
    caps = ((0.0, 0.5, 3.0), (0.25, 0.0, 9.0), (2.0, 1e3, 0.0))
    capped = Calibration(model.calibration.temperature, model.calibration.scale, 0.4, {"windows": 3}, caps, caps, 0.2)
    d = json.loads(json.dumps(capped.to_dict()))
    assert d["method"] == "asinh-temperature" and Calibration.from_dict(d, InputError, 3) == capped
    plain = {k: v for k, v in d.items() if k not in ("caps", "contact_caps", "contact_correlation")}
    assert Calibration.from_dict(plain, InputError, 3).caps is None         # a file of before caps
    path = replace_calibration(model, capped).save(tmp_path / "capped.npz")
    loaded = TextureModel.load(path)
    assert loaded.calibration == capped
    values, _ = _data(seed=9)
    np.testing.assert_array_equal(loaded.log_posteriors(values), capped.log_posteriors(model.logits(values)))
    for key, value, message in [("caps", [[0, 1], [1, 0]], "3 x 3"), ("caps", [[0, -1, 1], [1, 0, 1], [1, 1, 0]], "lie in"),
                                ("contact_caps", [[1, 1, 1], [1, 0, 1], [1, 1, 0]], "zero diagonal"),
                                ("caps", [[0, True, 1], [1, 0, 1], [1, 1, 0]], "numbers"),
                                ("caps", [[0, 1e5, 1], [1, 0, 1], [1, 1, 0]], "lie in"), ("extra", 1, "exactly the keys"),
                                ("contact_correlation", 1.5, "contact_correlation must lie in")]:
        def edit(h, key=key, value=value):
            h["calibration"][key] = value
        with pytest.raises(ModelError, match=message):
            TextureModel.load(_rewrite(replace_calibration(model, capped).save(tmp_path / f"bad-{key}.npz"), edit))


def replace_calibration(model, calibration):
    import dataclasses
    return dataclasses.replace(model, calibration=calibration)
