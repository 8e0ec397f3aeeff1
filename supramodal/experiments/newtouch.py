"""Trust on a new touch (issue 34): what the senses, their late fusion and "unknown" say about themselves.

They say it on a touch the models never met, on the two-sense world with per-touch gains.

Per set (:func:`supramodal.twosense.two_sense_set`, 8 textures): :data:`TOUCHES` touches of every
texture (:func:`supramodal.twosense.synthesize_touch`: each touch its own gain per vibrissa and its
own microphone level). The textures of heard pair 2 (``H2a``, ``H2b``) are left out of training: the
unknown ones. On the six others:

* Each sense's model is trained on touches 1-2, calibrated on held-out folds of whole touches
  (groups = texture and touch: the calibration the node fits when the recordings are separate
  touches). Beside it, the same network calibrated on folds that are spans of each texture's
  recordings (what it fits when a texture is one recording, and all the issue had): scored the
  same way, to show a calibration that does not hold on a new touch.
* The late fusion is learned on out-of-fold log-posteriors of touches 1-2, by the rule of issue 34
  (:func:`supramodal.fusion.learn_late_fusion`: bounded sharpness, the weight in its plateau's
  middle) and, for comparison, by the rule before it (:func:`late_fusion_before`).
* Scored on touch 3: accuracy, log loss, ECE and the share wrong of windows saying >= 0.99, per
  window; each sense beside its training estimate (its calibration's held-out log loss and
  accuracy); the false-unknown rate at 0.05 asked, per window and per contact of
  :data:`CONTACT_WINDOWS` windows, and the novelty's AUROC against the unknown textures' touch 3.
* The early fusion's network (:func:`train_early`), trained on both senses' windows of touches 1-2 and
  calibrated by touch as the senses are, scored on touch 3 beside them.
* Recalibration (:meth:`supramodal.model.TextureModel.recalibrated`): each sense recalibrated on the
  first half of touch 3, the networks and the fusion's weight and sharpness kept, scored on its
  second half (ECE, log loss, the false-unknown rate).
* With ``--more-touches K``, each sense's per-contact false-unknown rate also over K further new touches of
  every known texture, and how often one touch a texture, as touch 3, lands within :data:`UNKNOWN_RANGE`
  (:func:`more_touches_unknown`).

    supramodal experiment newtouch [--quick] [--sets N] [--seed S] [--touch-seconds S] [--more-touches K]
                                   [--augment] [--out DIR]
    python -m supramodal.experiments.newtouch [--quick] [--sets N] [--seed S]
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace

import numpy as np

from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.calibration import DEFAULT_CALIBRATION_FOLDS, fit_network_calibration, log_loss, winner
from supramodal.errors import InputError
from supramodal.experiments.calibration import auroc
from supramodal.experiments.common import AUGMENT_HELP, Run, augment_line
from supramodal.experiments.fusion import contact_runs
from supramodal.features import DEFAULT_WINDOW
from supramodal.fused_model import held_out_scores, learn_late_fusion_out_of_fold, senses_out_of_fold
from supramodal.fusion import LATE_WEIGHTS, fuse_late
from supramodal.logdomain import log_softmax
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.model import GainAugment, TextureModel, log_posteriors_of
from supramodal.pipeline import extract_features, window_length
from supramodal.twosense import synthesize_touch, two_sense_set

#: Touches of every texture: the models learn on all but the last, which scores them.
TOUCHES = 3
#: The textures left out of training (heard pair 2 of :func:`~supramodal.twosense.two_sense_set`).
UNKNOWN = ("H2a", "H2b")
SENSES = ("whiskers", "microphone")
#: The false-unknown rate asked (``[decision] unknown``).
ASKED_UNKNOWN = 0.05
#: The false-unknown rates on the new touch that issue 34 asks for at :data:`ASKED_UNKNOWN`.
UNKNOWN_RANGE = (0.03, 0.08)
#: Windows per contact for the contact-level unknown rate.
CONTACT_WINDOWS = 10
#: A window saying at least this is "sure" (the issue: at most 1 % of them wrong).
SURE = 0.99
FEATURES = ("Af",)


def touch_features(set_seed: int, seconds: float, progress=None) -> tuple[list[str], dict]:
    """Af windows of every texture's every touch, both senses aligned.

    Returns ``(names, {(texture index, touch): (whiskers (n, 1, 20), microphone (n, 1, 50))})``,
    n the same for every touch.
    """
    surfaces = two_sense_set(pairs=2, seed=set_seed)
    out = {}
    for i, s in enumerate(surfaces):
        for t in range(TOUCHES):
            out[i, t] = touch_windows(s, seconds, set_seed, i, t)
        if progress:
            progress(f"  set {set_seed}: {s.name}, {TOUCHES} touches ({i + 1}/{len(surfaces)})")
    n = min(len(v) for pair in out.values() for v in pair)
    return [s.name for s in surfaces], {k: (w[:n], m[:n]) for k, (w, m) in out.items()}


def touch_windows(surface, seconds: float, set_seed: int, index: int, touch: int) -> tuple[np.ndarray, np.ndarray]:
    """Return both senses' Af windows of one touch (:func:`supramodal.twosense.synthesize_touch`).

    Parameters
    ----------
    surface : Surface
        Texture ``index`` of set ``set_seed`` (:func:`supramodal.twosense.two_sense_set`).
    seconds : float
        The touch's length.
    set_seed, index, touch : int
        Which touch: its signals and gains derive from the three.

    Returns
    -------
    whiskers : ndarray, shape (n, 1, 20)
    microphone : ndarray, shape (m, 1, 50)
    """
    whiskers, mic = synthesize_touch(surface, seconds, set_seed, index, touch)
    return (extract_features(whiskers, whisker_bank(), FEATURES).values,
            extract_features(mic, cochlea_bank(), FEATURES).values)


@dataclass(frozen=True)
class TrainedSenses:
    """Both senses' models trained on touches 1 .. :data:`TOUCHES` - 1 of the known textures, and their late fusion.

    The models' calibration folds are by touch; the late fusion is learned on their out-of-fold
    windows (issue 34's rule).

    Attributes
    ----------
    classes : list of str
        The known textures, in the models' order.
    known : list of int
        Their indices into the set's textures.
    per : int
        Windows per touch.
    y, groups : ndarray, shape (n,)
        The training windows' labels and touches (texture and touch).
    values : list of ndarray
        Each sense's training windows, in :data:`SENSES` order.
    models : dict
        ``{sense: TextureModel}``.
    late : dict
        :func:`supramodal.fused_model.learn_late_fusion_out_of_fold`'s result.
    held, folds : list of ndarray, ndarray
        The senses' out-of-fold log-posteriors and their folds.
    """

    classes: list
    known: list
    per: int
    y: np.ndarray
    groups: np.ndarray
    values: list
    models: dict
    late: dict
    held: list
    folds: np.ndarray


def train_senses(names, feats, epochs: int, seed: int, progress=None, say: str = "",
                 augment: GainAugment | None = None) -> TrainedSenses:
    """Train :class:`TrainedSenses` on :func:`touch_features`' windows, leaving out :data:`UNKNOWN`.

    The windows are ``names``, ``feats``. ``say``: the progress lines' prefix. ``augment``: gain
    augmentation of every network's training windows, per vibrissa for the whiskers, one level for
    the microphone (one signal: a touch scales its every cochlea channel alike).
    """
    known = [i for i, n in enumerate(names) if n not in UNKNOWN]
    classes = [names[i] for i in known]
    per = len(feats[known[0], 0][0])
    training = range(TOUCHES - 1)
    y = np.concatenate([np.full(per, k) for k in range(len(known)) for _ in training])
    groups = np.concatenate([np.full(per, k * TOUCHES + t) for k in range(len(known)) for t in training])
    values = [np.concatenate([feats[i, t][s_i] for i in known for t in training]) for s_i in range(len(SENSES))]
    models = {}
    for sense, bank, v in zip(SENSES, (whisker_bank(), cochlea_bank()), values):
        if progress:
            progress(f"{say}the {sense} model, calibrated by touch")
        aug = None if augment is None else replace(augment, per_channel=augment.per_channel and sense == "whiskers")
        models[sense] = TextureModel.train(v, y, classes, bank, FEATURES, window_length(DEFAULT_WINDOW, bank.fs),
                                           epochs=epochs, seed=seed, groups=groups, augment=aug)
        assert models[sense].calibration is not None, "calibrated (the default)"
    if progress:
        progress(f"{say}the late fusion, on out-of-fold windows of touches 1-{TOUCHES - 1}")
    held, folds, _ = senses_out_of_fold(list(models.values()), values, y, classes, groups)
    late = learn_late_fusion_out_of_fold(held[0], held[1], y, folds)
    return TrainedSenses(classes, known, per, y, groups, values, models, late, held, folds)


def late_fusion_before(log_posteriors_a, log_posteriors_b, labels) -> tuple[float, float]:
    """Learn the late fusion by its rule before issue 34, for comparison.

    The weight right most often (ties: lower log loss, then nearer 0.5), its sharpness unbounded
    (up to e^5).
    """
    from scipy.optimize import minimize_scalar

    a, b, y = np.asarray(log_posteriors_a), np.asarray(log_posteriors_b), np.asarray(labels)
    candidates = []
    for w in LATE_WEIGHTS:
        mixed = w * a + (1.0 - w) * b
        r = minimize_scalar(lambda ls, mixed=mixed: log_loss(log_softmax(np.exp(ls) * mixed, axis=1), y),
                            bounds=(-7.0, 5.0), method="bounded", options={"xatol": 1e-4})
        s = float(np.exp(r.x))
        candidates.append((-float(np.mean(winner(mixed) == y)), log_loss(log_softmax(s * mixed, axis=1), y),
                           abs(w - 0.5), float(w), s))
    return min(candidates)[3:]


def _scores(lp, y) -> dict:
    return held_out_scores({"": lp}, y)[""]       # a window saying >= 0.99 (SURE) is sure


def _unknown(model: TextureModel, known, unknown, per_texture: int) -> dict:
    """Return the false-unknown rate at :data:`ASKED_UNKNOWN` on known textures, the unknown ones' rate, and AUROCs.

    The false-unknown rate is on windows of known textures (per window and per contact), the
    rate on the unknown textures likewise, and the novelty's AUROC per window and per contact.
    Contacts are :data:`CONTACT_WINDOWS` windows side by side (``contacts``) and, for the
    false-unknown rate, also starting at every window (``false_unknown_contact_every_start``: the same
    rate, measured on every contact a touch holds; side by side, 10 contacts a touch make it a count
    of 60, whose binomial spread alone is +-0.03 at 0.05).
    """
    nov = model.novelty
    assert nov is not None, "trained with calibration folds"
    xk, xu = model._inputs(known), model._inputs(unknown)
    wk, wu = nov.score(xk), nov.score(xu)
    ck, cu = _contact_scores(nov, xk, per_texture), _contact_scores(nov, xu, per_texture)
    every = _contact_scores(nov, xk, per_texture, step=1)
    t_w, t_c = nov.threshold(ASKED_UNKNOWN), nov.contact_threshold(ASKED_UNKNOWN, CONTACT_WINDOWS)
    touch = nov.touch
    return {"false_unknown_window": float(np.mean(wk > t_w)), "false_unknown_contact": float(np.mean(ck > t_c)),
            "false_unknown_contact_every_start": float(np.mean(every > t_c)),
            "unknown_found_window": float(np.mean(wu > t_w)), "unknown_found_contact": float(np.mean(cu > t_c)),
            "auroc_window": auroc(wu, wk), "auroc_contact": auroc(cu, ck), "contacts": int(len(ck)),
            "touch_spread": None if touch is None else touch.spread,
            "touch_spread_estimated": None if touch is None else touch.estimated}


def band_counts(total: int, band: tuple[float, float] = UNKNOWN_RANGE) -> tuple[int, int]:
    """Return the least and most counts ``k`` of ``total`` whose share ``k / total`` lies in ``band``, inclusive."""
    lo, hi = band
    return int(np.ceil(lo * total - 1e-9)), int(np.floor(hi * total + 1e-9))


def contact_scores(model: TextureModel, windows) -> np.ndarray:
    """Return the novelty scores (:meth:`~supramodal.calibration.Novelty.pooled_score`) of one touch's contacts.

    The contacts are :data:`CONTACT_WINDOWS` windows side by side (a shorter rest left out), as
    :func:`_unknown` counts them; ``windows`` are the touch's feature windows (n, 1, inputs).
    """
    assert model.novelty is not None, "trained with calibration folds"
    return _contact_scores(model.novelty, model._inputs(windows), len(windows))


def _contact_scores(nov, x, per_texture: int, step: int | None = None) -> np.ndarray:
    """Pooled scores of the contacts among standardised rows ``x`` stacked texture by texture (:func:`contact_runs`)."""
    return np.array([nov.pooled_score(x[r]) for r in contact_runs(np.arange(len(x)), per_texture, CONTACT_WINDOWS,
                                                                  step=step)])


def _counts_above(scores, threshold: float) -> list[list[int]]:
    """Per texture, per touch: its contacts whose score is above ``threshold`` (called unknown)."""
    return [[int(np.sum(np.asarray(c) > threshold)) for c in per_texture] for per_texture in scores]


def one_touch_draws(counts, contacts: int, band: tuple[float, float] = UNKNOWN_RANGE) -> float:
    """Chance that one touch drawn per texture gives a false-unknown rate per contact within ``band``.

    Parameters
    ----------
    counts : sequence of sequence of int
        Per texture, per touch of it: the touch's contacts called unknown. Each touch of a texture is
        drawn alike likely, the textures independently (a sense-set's touch 3 is one such draw).
    contacts : int
        Contacts in one touch, every touch alike.
    band : (float, float)
        The rates asked for, inclusive.

    Returns
    -------
    float
        ``P(lo <= K / N <= hi)``, ``K`` the draw's contacts called unknown and ``N`` = ``contacts`` times
        the textures: exact, by convolving the textures' distributions of counts.
    """
    pmf = np.ones(1)
    for per_touch in counts:
        pmf = np.convolve(pmf, np.bincount(np.asarray(per_touch, dtype=int), minlength=contacts + 1) / len(per_touch))
    least, most = band_counts(contacts * len(counts), band)
    return float(pmf[least:most + 1].sum())


def best_one_touch_draws(scores, band: tuple[float, float] = UNKNOWN_RANGE) -> float:
    """Return the largest chance that one touch a texture lands within ``band``, over every threshold.

    ``scores``: per texture, per touch of it, the contacts' novelty scores, every touch with as many
    contacts. The threshold is chosen knowing these touches, so no threshold fixed before them can do
    better on them: an upper bound on :func:`one_touch_draws` at any threshold.
    """
    touches = [[np.sort(np.asarray(c, dtype=np.float64)) for c in per_texture] for per_texture in scores]
    contacts = len(touches[0][0])
    every = np.concatenate([c for per_texture in touches for c in per_texture])
    # the counts change only at a score: below the least, every contact is called unknown
    candidates = np.concatenate([[-np.inf], np.unique(every)])
    best = 0.0
    for t in candidates:
        counts = [[contacts - int(np.searchsorted(c, t, side="right")) for c in per_texture] for per_texture in touches]
        best = max(best, one_touch_draws(counts, contacts, band))
    return best


def more_touches_unknown(trained: TrainedSenses, feats, set_seed: int, seconds: float, more: int, per: int,
                         progress=None, say: str = "") -> dict:
    """Measure the per-contact false-unknown rate on touch 3 and ``more`` further new touches of every known texture.

    Touch 3 is one draw of a new touch per texture; its rate moves with the draw, since a touch's gains move
    all its contacts together. Over many new touches, each sense's rate at its model's threshold is the one
    the model delivers; and :func:`one_touch_draws` says how often one draw, as touch 3, lands within
    :data:`UNKNOWN_RANGE`: at the model's threshold; at the ideal one for these touches (the ``1 -``
    :data:`ASKED_UNKNOWN` quantile of their own contacts' scores, whose rate over them is exactly the one
    asked); and at the best one for the band (:func:`best_one_touch_draws`: no threshold does better).

    Parameters
    ----------
    trained : TrainedSenses
    feats : dict
        :func:`touch_features`' windows (touch 3 among them).
    set_seed : int
    seconds : float
        Each touch's length.
    more : int
        Further new touches of every known texture (touches 4 .. ``more`` + 3).
    per : int
        Windows a touch (the further touches are cut to it, as :func:`touch_features` cuts every touch).
    progress : callable(str), optional
    say : str
        The progress lines' prefix.

    Returns
    -------
    dict
        ``{sense: {"touches", "contacts", "rate", "within", "threshold", "ideal_threshold", "within_ideal",
        "within_best", "counts"}}``; ``counts`` per known texture and touch (touch 3 first), the contacts
        called unknown at the model's threshold.
    """
    surfaces = two_sense_set(pairs=2, seed=set_seed)
    scores: dict = {sense: [] for sense in SENSES}
    for k, i in enumerate(trained.known):
        touches = [feats[i, TOUCHES - 1]] + [touch_windows(surfaces[i], seconds, set_seed, i, t)
                                             for t in range(TOUCHES, TOUCHES + more)]
        for s_i, sense in enumerate(SENSES):
            scores[sense].append([contact_scores(trained.models[sense], w[s_i][:per]) for w in touches])
        if progress:
            progress(f"{say}{more} more new touches of {trained.classes[k]} ({k + 1}/{len(trained.known)})")
    out = {}
    for sense, per_texture in scores.items():
        nov = trained.models[sense].novelty
        assert nov is not None, "trained with calibration folds"
        contacts = len(per_texture[0][0])
        every = np.concatenate([np.asarray(c) for touches in per_texture for c in touches])
        threshold = nov.contact_threshold(ASKED_UNKNOWN, CONTACT_WINDOWS)
        ideal = float(np.quantile(every, 1.0 - ASKED_UNKNOWN))
        counts, ideal_counts = _counts_above(per_texture, threshold), _counts_above(per_texture, ideal)
        out[sense] = {"touches": more + 1, "contacts": contacts, "rate": float(np.mean(every > threshold)),
                      "within": one_touch_draws(counts, contacts), "threshold": threshold,
                      "ideal_threshold": ideal, "within_ideal": one_touch_draws(ideal_counts, contacts),
                      "within_best": best_one_touch_draws(per_texture), "counts": counts}
    return out


def run_set(set_seed: int, seconds: float = 10.0, epochs: int = DEFAULT_EPOCHS, seed: int = 0,
            progress=None, augment: GainAugment | None = None, more_touches: int = 0) -> dict:
    """One set: see the module docstring.

    Plain data: per sense and fusion rule, ``training`` (the held-out estimate), ``touch3``,
    ``recalibrated`` (touch 3's second half) scores, ``unknown`` rates; with ``more_touches``, each sense's
    ``more_touches`` (:func:`more_touches_unknown`).
    """
    names, feats = touch_features(set_seed, seconds, progress)
    per = len(next(iter(feats.values()))[0])          # windows a touch, every touch alike
    half = per // 2
    if half < CONTACT_WINDOWS:                      # before the training, which would be for nothing
        raise InputError(f"{per} windows per touch leave too few for contacts of {CONTACT_WINDOWS} in each half of "
                         "touch 3: give longer touches (--touch-seconds)")
    t0 = time.process_time()
    trained = train_senses(names, feats, epochs, seed, progress, f"  set {set_seed}: ", augment)
    train_cpu = time.process_time() - t0
    known, classes = trained.known, trained.classes
    unknown = [i for i, n in enumerate(names) if n in UNKNOWN]
    new_touch = [TOUCHES - 1]

    def stack(senses_index, textures=known, rows=slice(None)):
        return np.concatenate([feats[i, t][senses_index][rows] for i in textures for t in new_touch])

    def labels(n):
        return np.repeat(np.arange(len(known)), n)

    y_test, y_first, y_second = labels(per), labels(half), labels(per - half)
    result: dict = {"set_seed": set_seed, "textures": classes, "unknown_textures": list(UNKNOWN),
                    "windows_per_touch": per, "senses": {}, "late": {}, "train_cpu_seconds": train_cpu}
    test_lp, recal_lp = {}, {}
    for s_i, sense in enumerate(SENSES):
        if progress:
            progress(f"  set {set_seed}: the {sense} model calibrated by span, and scored")
        model, train = trained.models[sense], trained.values[s_i]
        assert model.calibration is not None and model.out_of_fold is not None, "calibrated (the default)"
        # span folds' networks, augmented as the model's were; their calibration applied to the model's networks
        aug = model.augment
        span, _, _ = fit_network_calibration(train.reshape(len(train), -1), trained.y, len(classes), None,
                                             DEFAULT_CALIBRATION_FOLDS, epochs=epochs, seed=seed,
                                             augment=None if aug is None else aug.for_inputs(FEATURES,
                                                                                             model.bank.channels),
                                             patience=model.training.get("patience"))
        test = stack(s_i)
        test_lp[sense] = model.log_posteriors(test)
        estimate = model.calibration.log_posteriors(model.out_of_fold.logits)
        recal = model.recalibrated(stack(s_i, rows=slice(0, half)), y_first, what="touch 3, first half")
        second = stack(s_i, rows=slice(half, None))
        recal_lp[sense] = recal.log_posteriors(second)
        result["senses"][sense] = {
            "folds_by": model.calibration.fitted_on.get("folds_by"),
            "training": _scores(estimate, trained.y), "touch3": _scores(test_lp[sense], y_test),
            "span_training": {"log_loss": span.fitted_on["log_loss"],
                              "accuracy": span.fitted_on["held_out_accuracy"]},
            "span_touch3": _scores(log_posteriors_of(model.logits(test), span), y_test),
            "recalibrated": _scores(recal_lp[sense], y_second),
            "unknown": _unknown(model, test, stack(s_i, unknown), per),
            "unknown_recalibrated": _unknown(recal, second, stack(s_i, unknown, slice(half, None)), per - half)}
    rules = {"issue34": (trained.late["weight"], trained.late["sharpness"]),
             "before": late_fusion_before(trained.held[0], trained.held[1], trained.y)}
    for rule, (w, s) in rules.items():
        fused_test = fuse_late(test_lp["whiskers"], test_lp["microphone"], w, s)
        result["late"][rule] = {"weight": w, "sharpness": s, "touch3": _scores(fused_test, y_test),
                                "recalibrated": _scores(fuse_late(recal_lp["whiskers"], recal_lp["microphone"], w, s),
                                                        y_second)}
    result["late"]["issue34"]["training"] = _scores(trained.late["fused"], trained.y)
    if progress:
        progress(f"  set {set_seed}: the early fusion's network, calibrated by touch")
    t0 = time.process_time()
    early = train_early(trained, epochs, seed, augment)
    result["early"] = {"training": _scores(early.calibration.log_posteriors(early.out_of_fold.logits), trained.y),
                       "touch3": _scores(early.log_posteriors(stack(0), stack(1)), y_test),
                       "train_cpu_seconds": time.process_time() - t0}
    if more_touches:
        more = more_touches_unknown(trained, feats, set_seed, seconds, more_touches, per, progress,
                                    f"  set {set_seed}: ")
        for sense, v in more.items():
            result["senses"][sense]["more_touches"] = v
    return result


def train_early(trained: TrainedSenses, epochs: int, seed: int, augment: GainAugment | None = None):
    """Return the early fusion's network trained on both senses' windows of touches 1-2, calibrated by touch.

    ``augment``: as :func:`train_senses` gives each sense's (per vibrissa for the whiskers, one level for the
    microphone), each sense's columns by its own gains.
    """
    from supramodal.fused_model import EarlyFusionModel, Sense

    models = [trained.models[s] for s in SENSES]
    senses = [Sense(s, m.bank, m.features, m.window_samples, m.peak_mode, m.peak_threshold)
              for s, m in zip(SENSES, models)]
    pair = None if augment is None else tuple(m.augment for m in models)
    model = EarlyFusionModel.train(senses, trained.values[0], trained.values[1], trained.y, trained.classes,
                                   epochs=epochs, seed=seed, groups=trained.groups, augment=pair)
    assert model.calibration is not None and model.out_of_fold is not None, "calibrated (the default)"
    return model


#: Seconds of each touch (full, quick).
TOUCH_SECONDS = (10.0, 6.0)
#: The most further new touches of each texture ``--more-touches`` takes.
MAX_MORE_TOUCHES = 100
#: CPU seconds a further new touch costs per second of touch and texture (its signals and features, both senses):
#: measured 0.02-0.03 as the wall time added by ``--more-touches`` on 2 worker processes, at 10 s and 40 s.
MORE_TOUCH_CPU = 0.03
#: The longest touch the experiment makes: a set takes about 3 CPU-minutes per 60 s of touch (measured at 40 s),
#: and each touch's signals are held whole (the microphone's at 44.1 kHz).
MAX_TOUCH_SECONDS = 600.0


def run_newtouch(sets: int = 5, quick: bool = False, epochs: int = DEFAULT_EPOCHS, seed: int = 0, progress=None,
                 jobs: int | None = None, augment: GainAugment | None = None,
                 touch_seconds: float | None = None, more_touches: int = 0) -> dict:
    """:func:`run_set` over ``sets`` sets (seeds ``seed``, ``seed + 1``, ...) on ``jobs`` worker processes.

    ``touch_seconds``: each touch's length (default :data:`TOUCH_SECONDS`: 10 s, 6 s ``quick``). Longer touches
    give every figure more windows and contacts to count (40 s: 240 contacts a sense on touch 3, against 60), and
    the models more to learn from; the world is otherwise the same. ``more_touches``: further new touches of every
    known texture (0 .. :data:`MAX_MORE_TOUCHES`), on which each sense's per-contact false-unknown rate is also
    measured (:func:`more_touches_unknown`).
    """
    from supramodal.experiments.runner import run_all

    if sets < 1:
        raise InputError(f"--sets must be >= 1 for the new-touch experiment, got {sets}")
    seconds = TOUCH_SECONDS[1 if quick else 0] if touch_seconds is None else float(touch_seconds)
    if not (np.isfinite(seconds) and 0 < seconds <= MAX_TOUCH_SECONDS):
        raise InputError(f"--touch-seconds must be a number of seconds in (0, {MAX_TOUCH_SECONDS:g}], got "
                         f"{touch_seconds!r}")
    if isinstance(more_touches, bool) or int(more_touches) != more_touches or not 0 <= more_touches <= MAX_MORE_TOUCHES:
        raise InputError(f"--more-touches must be a whole number of touches in 0..{MAX_MORE_TOUCHES}, got "
                         f"{more_touches!r}: give fewer (each costs about {MORE_TOUCH_CPU:g} s of CPU per second of "
                         "touch and texture)")
    least = (2 * CONTACT_WINDOWS + 1) * DEFAULT_WINDOW
    if seconds < least:
        raise InputError(f"touches of {seconds:g} s leave too few windows for contacts of {CONTACT_WINDOWS} in each "
                         f"half of touch 3: give at least {least:g} s (--touch-seconds)")
    t0 = time.perf_counter()
    runs = [Run(("newtouch", seed + k), run_set, {"set_seed": seed + k, "seconds": seconds, "epochs": epochs,
                                                   "seed": seed, "augment": augment, "more_touches": int(more_touches)},
                (8 + 6 * MORE_TOUCH_CPU * more_touches) * seconds, seeded=False)
            for k in range(sets)]
    results = list(run_all(runs, jobs=jobs, seed=seed, progress=progress).values())
    return {"figure": "newtouch", "seconds": seconds, "touches": TOUCHES, "asked_unknown": ASKED_UNKNOWN,
            "contact_windows": CONTACT_WINDOWS, "sure": SURE, "sets": results,
            "augment": None if augment is None else augment.to_dict(), "more_touches": int(more_touches),
            "compute_seconds": time.perf_counter() - t0}


def _sure(r: dict) -> str:
    if not r["sure_count"]:
        return "- (0 sure)"
    return f"{r['sure_wrong']:.3f} of {r['sure_count']}"


def _every(u: dict) -> str:
    v = u.get("false_unknown_contact_every_start")
    return "-" if v is None else f"{v:.3f}"


def _within(values) -> str:
    """Return ``k of n sense-sets (min..max)``, k of the sense-sets' rates ``values`` in :data:`UNKNOWN_RANGE`.

    A value None (not measured) is left out.
    """
    lo, hi = UNKNOWN_RANGE
    values = [x for x in values if x is not None]
    inside = sum(lo <= x <= hi for x in values)
    return f"{inside} of {len(values)} sense-sets" + (f" ({min(values):.3f}..{max(values):.3f})" if values else "")


def pooled_contacts(result: dict) -> str:
    """Return the per-contact false-unknown rate of every sense-set together, and what a count can say.

    The count of contacts called unknown in a sense-set is binomial if the rate is the one asked: the
    line gives the pooled rate with its 95 % (Clopper-Pearson) interval, and the chance that one
    sense-set of its contacts lands in :data:`UNKNOWN_RANGE`, and every sense-set, at exactly the rate
    asked.
    """
    from scipy.stats import binom, binomtest

    asked = result["asked_unknown"]
    pairs = [(round(v["unknown"]["false_unknown_contact"] * v["unknown"]["contacts"]), v["unknown"]["contacts"])
             for r in result["sets"] for v in r["senses"].values() if v["unknown"].get("contacts")]
    if not pairs:
        return ""
    k, n = sum(c for c, _ in pairs), sum(m for _, m in pairs)
    low, high = binomtest(k, n, asked).proportion_ci(0.95)
    lo, hi = UNKNOWN_RANGE

    def inside(m: int) -> float:
        """P(lo <= X / m <= hi) for X ~ Binomial(m, asked)."""
        least, most = band_counts(m)
        return float(binom.cdf(most, m, asked) - binom.cdf(least - 1, m, asked))

    sizes = sorted({m for _, m in pairs})
    each = ", ".join(f"{inside(m):.2f} at {m} contacts" for m in sizes)
    return (f"per contact, every sense-set together: {k} of {n} known contacts called unknown, {k / n:.3f} "
            f"(95 % interval {low:.3f}..{high:.3f}); at exactly {asked:g}, a sense-set lands within {lo:g}..{hi:g} "
            f"with probability {each}, all {len(pairs)} with {float(np.prod([inside(m) for _, m in pairs])):.3f}")


def more_touches_lines(result: dict) -> list[str]:
    """Return the table's lines of :func:`more_touches_unknown`: the rate over many new touches, one draw's chance."""
    got = [(r["set_seed"], sense, v["more_touches"]) for r in result["sets"] for sense, v in r["senses"].items()
           if "more_touches" in v]
    if not got:
        return []
    lo, hi = UNKNOWN_RANGE
    more = got[0][2]["touches"] - 1
    lines = ["", f"Per contact on touch 3 and {more} more new touches of each known texture "
             f"({got[0][2]['contacts']} contacts a touch): the rate at the model's threshold over all of them, and "
             f"the chance that one touch a texture, as touch 3, lands within {lo:g}..{hi:g}: at the model's "
             "threshold, at the ideal one for these touches (the quantile of their own contacts' scores that "
             "calls the rate asked), and at the best one for the band (chosen knowing these touches: no "
             "threshold does better on them)", "",
             "| set | sense | rate over the new touches | touches with none called unknown | one touch a texture "
             "within the band: model's threshold | ideal threshold | best threshold |", "|---|---|---|---|---|---|---|"]
    for set_seed, sense, m in got:
        zero = float(np.mean([c == 0 for touches in m["counts"] for c in touches]))
        lines.append(f"| {set_seed} | {sense} | {m['rate']:.3f} | {zero:.2f} | {m['within']:.2f} | "
                     f"{m['within_ideal']:.2f} | {m['within_best']:.2f} |")
    per_touch = np.array([c / m["contacts"] for _, _, m in got for touches in m["counts"] for c in touches])
    chances = {name: float(np.prod([m[key] for _, _, m in got]))
               for name, key in (("models'", "within"), ("ideal", "within_ideal"), ("best", "within_best"))}
    return lines + ["", f"per contact over touch 3 and {more} more: {_within(m['rate'] for *_, m in got)} within "
                    f"{lo:g}..{hi:g}; of the {len(per_touch)} touches and senses, {np.mean(per_touch == 0):.2f} had no "
                    f"contact called unknown, the most {per_touch.max():.2f}",
                    f"one touch a texture within {lo:g}..{hi:g} per contact, every one of the {len(got)} sense-sets: "
                    "probability " + ", ".join(f"{v:.2g} at the {name} thresholds" for name, v in chances.items())]


def newtouch_table(result: dict) -> str:
    """Return the experiment's figures as Markdown, one row per set and method."""
    lines = [f"{len(result['sets'])} two-sense sets, 6 known textures (+2 unknown), {result['touches']} touches of "
             f"{result['seconds']:g} s each; trained on touches 1-{result['touches'] - 1}, scored on touch "
             f"{result['touches']}; per window. Training estimate: held-out folds of the training touches.", "",
             "| set | method | training estimate: right, log loss | touch 3: right | log loss | ECE | "
             f"saying >= {result['sure']:g}, wrong | recalibrated on its first half: ECE, log loss |",
             "|---|---|---|---|---|---|---|---|"]
    for r in result["sets"]:
        for sense, v in r["senses"].items():
            for label, train, test in ((f"{sense} (folds by touch)", v["training"], v["touch3"]),
                                       (f"{sense} (folds by span)", v["span_training"], v["span_touch3"])):
                rc = v["recalibrated"] if "touch" in label else None
                lines.append(f"| {r['set_seed']} | {label} | {train['accuracy']:.3f}, {train['log_loss']:.3f} | "
                             f"{test['accuracy']:.3f} | {test['log_loss']:.3f} | {test['ece']:.3f} | {_sure(test)} | "
                             + (f"{rc['ece']:.3f}, {rc['log_loss']:.3f} |" if rc else "- |"))
        for rule, v in r["late"].items():
            t = v["touch3"]
            train = v.get("training")
            est = f"{train['accuracy']:.3f}, {train['log_loss']:.3f}" if train else "-"
            name = "the new-touch rule" if rule == "issue34" else "the rule before"
            lines.append(f"| {r['set_seed']} | late, {name} (weight "
                         f"{v['weight']:.2f}, sharpness {v['sharpness']:.3g}) | {est} | {t['accuracy']:.3f} | "
                         f"{t['log_loss']:.3f} | {t['ece']:.3f} | {_sure(t)} | {v['recalibrated']['ece']:.3f}, "
                         f"{v['recalibrated']['log_loss']:.3f} |")
        if "early" in r:            # results of before it have none
            train, t = r["early"]["training"], r["early"]["touch3"]
            lines.append(f"| {r['set_seed']} | early fusion (folds by touch) | {train['accuracy']:.3f}, "
                         f"{train['log_loss']:.3f} | {t['accuracy']:.3f} | {t['log_loss']:.3f} | {t['ece']:.3f} | "
                         f"{_sure(t)} | - |")
    lines += ["", f"Unknown at {result['asked_unknown']:g} asked (contacts of {result['contact_windows']} windows): "
              "false-unknown rate on touch 3 of the known textures, and after recalibration on its second half; "
              "AUROC against the unknown textures' touch 3", "",
              "| set | sense | false unknown, windows | contacts | contacts at every start | recalibrated: windows | "
              "contacts | contacts at every start | AUROC windows | contacts | touch spread allowed (estimated) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["sets"]:
        for sense, v in r["senses"].items():
            u, ur = v["unknown"], v["unknown_recalibrated"]
            spread = "-" if u.get("touch_spread") is None else (
                f"{u['touch_spread']:.3f} ("
                + ("-" if u["touch_spread_estimated"] is None else f"{u['touch_spread_estimated']:.3f}") + ")")
            lines.append(f"| {r['set_seed']} | {sense} | {u['false_unknown_window']:.3f} | "
                         f"{u['false_unknown_contact']:.3f} | {_every(u)} | {ur['false_unknown_window']:.3f} | "
                         f"{ur['false_unknown_contact']:.3f} | {_every(ur)} | {u['auroc_window']:.4f} | "
                         f"{u['auroc_contact']:.4f} | {spread} |")
    unknowns = [v["unknown"] for r in result["sets"] for v in r["senses"].values()]
    lines += ["", "false-unknown rate (0.05 asked) within 0.03..0.08 on touch 3: "
              + "; ".join(f"{what} {_within(u.get(key) for u in unknowns)}"
                          for what, key in (("per window", "false_unknown_window"),
                                            ("per contact", "false_unknown_contact"),
                                            ("per contact at every start", "false_unknown_contact_every_start")))]
    pooled = pooled_contacts(result)
    if pooled:
        lines.append(pooled)
    lines += more_touches_lines(result)
    checks = []
    for r in result["sets"]:
        better = min(v["touch3"]["log_loss"] for v in r["senses"].values())
        checks.append(r["late"]["issue34"]["touch3"]["log_loss"] <= better)
    lines += ["", f"late fusion (the new-touch rule) log loss on touch 3 <= the better sense's: {sum(checks)} of "
              f"{len(checks)} sets"]
    cpu = [r["train_cpu_seconds"] for r in result["sets"] if "train_cpu_seconds" in r]
    if cpu:
        lines.append(f"training CPU of a set's senses and fusion (this process): {min(cpu):.1f}..{max(cpu):.1f} s")
    early = [r["early"]["train_cpu_seconds"] for r in result["sets"] if "early" in r]
    if early:
        lines.append(f"training CPU of a set's early-fusion network (this process): {min(early):.1f}.."
                     f"{max(early):.1f} s")
    lines.append(augment_line(result))
    return "\n".join(lines)


def _rows(result: dict) -> list[dict]:
    """One row per set and method: the figures of :func:`newtouch_table` as plain columns."""
    rows = []
    for r in result["sets"]:
        methods = {f"{sense}": (v["training"], v["touch3"], v["recalibrated"]) for sense, v in r["senses"].items()}
        methods |= {f"{sense} (folds by span)": (v["span_training"], v["span_touch3"], None)
                    for sense, v in r["senses"].items()}
        methods |= {f"late ({'new-touch rule' if rule == 'issue34' else rule})": (v.get("training"), v["touch3"],
                                                                                 v["recalibrated"])
                    for rule, v in r["late"].items()}
        if "early" in r:
            methods["early"] = (r["early"]["training"], r["early"]["touch3"], None)
        for name, (train, test, recal) in methods.items():
            rows.append({"set": r["set_seed"], "method": name,
                         "estimate_accuracy": None if train is None else train["accuracy"],
                         "estimate_log_loss": None if train is None else train["log_loss"],
                         **{f"touch3_{k}": test[k]
                            for k in ("accuracy", "log_loss", "ece", "sure_count", "sure_wrong")},
                         "recalibrated_ece": None if recal is None else recal["ece"],
                         "recalibrated_log_loss": None if recal is None else recal["log_loss"]})
    return rows


def write_newtouch(result: dict, out) -> list:
    """Write ``newtouch.csv`` (one row per set and method) and, with matplotlib, ``newtouch.png``.

    The PNG shows each method's log loss and ECE on the new touch, and after recalibration. With
    ``--more-touches``, also ``newtouch_unknown.png``: each new touch's per-contact false-unknown rate.
    """
    import csv
    from pathlib import Path

    from supramodal.experiments.plotting import have_matplotlib, pyplot

    out = Path(out)
    rows = _rows(result)
    with open(out / "newtouch.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    written = [out / "newtouch.csv"]
    if not have_matplotlib():
        return written
    plt = pyplot()
    methods = list(dict.fromkeys(r["method"] for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
    x = np.arange(len(methods))
    for ax, (key, label) in zip(axes, (("log_loss", "log loss (nats)"), ("ece", "ECE"))):
        for k, (col, name, shade) in enumerate(((f"touch3_{key}", "new touch", "0.35"),
                                               (f"recalibrated_{key}", "recalibrated on half of it", "0.7"))):
            means = [np.mean([r[col] for r in rows if r["method"] == m and r[col] is not None] or [np.nan])
                     for m in methods]
            ax.bar(x + (k - 0.5) * 0.38, means, 0.38, label=name, color=shade)
        ax.set_xticks(x, methods, rotation=30, ha="right", fontsize=7)
        ax.set_ylabel(label)
    axes[1].axhline(0.05, color="k", lw=0.8, ls=":")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"trust on a new touch: {len(result['sets'])} two-sense sets, mean over sets", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "newtouch.png", dpi=120)
    plt.close(fig)
    written.append(out / "newtouch.png")
    if any("more_touches" in v for r in result["sets"] for v in r["senses"].values()):
        written.append(_plot_more_touches(result, out / "newtouch_unknown.png"))
    return written


def _plot_more_touches(result: dict, path):
    """Plot each new touch's per-contact false-unknown rate, per sense-set, beside the band asked; return ``path``."""
    from supramodal.experiments.plotting import pyplot, save_figure

    plt = pyplot()
    got = [(f"set {r['set_seed']}\n{sense}", v["more_touches"]) for r in result["sets"]
           for sense, v in r["senses"].items() if "more_touches" in v]
    fig, ax = plt.subplots(figsize=(10, 3.4))
    lo, hi = UNKNOWN_RANGE
    ax.axhspan(lo, hi, color="0.85", label=f"asked: {lo:g}..{hi:g}")
    jitter = np.random.default_rng(0)
    for x, (_, m) in enumerate(got):
        rates = np.array([c for touches in m["counts"] for c in touches]) / m["contacts"]
        ax.plot(x + jitter.uniform(-0.25, 0.25, len(rates)), rates, ".", color="0.35", ms=3,
                label="one touch" if x == 0 else None)
        ax.plot([x - 0.35, x + 0.35], [m["rate"]] * 2, "k-", lw=2, label="over all the new touches" if x == 0 else None)
    ax.set_xticks(range(len(got)), [name for name, _ in got], fontsize=7)
    ax.set_ylabel("share of a touch's contacts\ncalled unknown")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title(f"false unknown per contact ({result['asked_unknown']:g} asked) on {got[0][1]['touches']} new "
                 f"touches of each known texture, {result['seconds']:g} s each", fontsize=9)
    return save_figure(fig, path)


def main(argv=None) -> int:
    """Run the experiment from the command line (:func:`~supramodal.experiments.common.two_sense_sets_main`)."""
    from supramodal.experiments.common import two_sense_sets_main

    return two_sense_sets_main(argv, "newtouch", __doc__.splitlines()[0], run_newtouch, newtouch_table,
                               "6 s touches (default 10 s)", augment=AUGMENT_HELP)


if __name__ == "__main__":
    sys.exit(main())
