"""Fusion of the two senses on the two-sense synthetic world, with calibrated posteriors (issue 23).

Whiskers alone, microphone alone, late fusion and early fusion (the supramodal network), over
random texture sets.

Per set (:func:`supramodal.twosense.two_sense_set`, 8 textures): each texture's contact is
synthesised for both senses; Af windows of 100 ms from the whisker bank (20 channels, 5 kHz) and
the cochlea (50 channels, 44.1 kHz), aligned by index (offline, both start at the contact). The
first :data:`~supramodal.training.TRAIN_FRACTION` of every texture's windows train, the rest test.

* Each sense: a :class:`~supramodal.model.TextureModel`, calibrated as ``supramodal train``
  calibrates it (on out-of-fold windows of its training part).
* Late fusion, as ``train --fusion late`` learns it: its weight and sharpness
  (:func:`supramodal.fusion.learn_late_fusion`) are learned on *held-out* log-posteriors of the
  training windows, each window's from a copy of the sense's model trained on the other grouped
  folds (:func:`supramodal.fused_model.senses_out_of_fold`), never from the sense models' own
  training windows; its contact pooling on the same held-out windows, fused
  (:func:`supramodal.fused_model.fused_pooling`).
* Early fusion: the supramodal network (:class:`~supramodal.fused_model.EarlyFusionModel`, one MLP
  on both senses' standardised windows side by side), calibrated like a sense model on the
  out-of-fold windows of the concatenated inputs.

Reported on the test windows: accuracy per window and per contact (a run of
:data:`CONTACT_WINDOWS` test windows, pooled by each method's calibrated pooling), and the
calibration of both (log loss, Brier score, ECE, and the share wrong of the decisions that say at
least 0.99).

    supramodal experiment fusion [--quick] [--sets N] [--seed S] [--out DIR]
    python -m supramodal.experiments.fusion [--quick] [--sets N] [--seed S]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.calibration import DEFAULT_CALIBRATION_FOLDS, calibration_report, pool_log_posteriors, winner
from supramodal.errors import InputError
from supramodal.experiments.common import Run
from supramodal.features import DEFAULT_WINDOW
from supramodal.fused_model import EarlyFusionModel, Sense, fused_pooling, senses_out_of_fold
from supramodal.fusion import fuse_late, learn_late_fusion
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.model import TextureModel
from supramodal.pipeline import extract_features, window_length
from supramodal.training import TRAIN_FRACTION
from supramodal.twosense import synthesize_contact, two_sense_set

METHODS = ("whiskers", "microphone", "late", "early")
#: Windows pooled into one contact decision (1 s).
CONTACT_WINDOWS = 10
#: A decision that says at least this is "sure" (the issue's figure: at most 1 % of them wrong).
SURE = 0.99
FEATURES = ("Af",)


def set_features(set_seed: int, seconds: float, progress=None):
    """Per texture, aligned Af windows of both senses: (names, whiskers (T, n, 20), mic (T, n, 50))."""
    surfaces = two_sense_set(pairs=2, seed=set_seed)
    wb, cb = whisker_bank(), cochlea_bank()
    fw, fm = [], []
    for i, s in enumerate(surfaces):
        w, m = synthesize_contact(s, seconds, seed=[set_seed, i])
        fw.append(extract_features(w, wb, FEATURES).values[:, 0])
        fm.append(extract_features(m, cb, FEATURES).values[:, 0])
        if progress:
            progress(f"  set {set_seed}: {s.name} ({i + 1}/{len(surfaces)})")
    n = min(min(len(v) for v in fw), min(len(v) for v in fm))
    return [s.name for s in surfaces], np.stack([v[:n] for v in fw]), np.stack([v[:n] for v in fm])


def contact_runs(labels, per_texture: int, length: int = CONTACT_WINDOWS, step: int | None = None) -> list[np.ndarray]:
    """Return the indices of the contacts among test windows stacked texture by texture (``per_texture`` each).

    A contact is a run of ``length`` consecutive windows of one texture (a shorter rest is left
    out), one every ``step`` windows (default ``length``: contacts side by side; 1: a contact
    starting at every window, overlapping).
    """
    step = length if step is None else step
    runs = []
    for start in range(0, len(labels), per_texture):
        for k in range(0, per_texture - length + 1, step):
            runs.append(np.arange(start + k, start + k + length))
    return runs


def pooled_contacts(log_posteriors, runs, correlation: float, caps=None) -> np.ndarray:
    """Each run's pooled log-posteriors, (runs, classes).

    Pooled by :func:`supramodal.calibration.pool_log_posteriors`, with a calibration's contact
    ``caps`` where it has them.
    """
    return np.array([pool_log_posteriors(log_posteriors[r], correlation, caps) for r in runs])


def run_set(set_seed: int, seconds: float = 20.0, epochs: int = DEFAULT_EPOCHS, seed: int = 0, progress=None) -> dict:
    """Accuracy and calibration of each method on one set; see the module docstring.

    Returns
    -------
    dict
        ``set_seed``, ``textures``, the late fusion learned (``late_weight`` of the whiskers,
        ``late_sharpness``, ``late_correlation``) and the held-out accuracies it was learned on
        (``held_out``); per method the test accuracy per ``window`` and per ``contact``, and
        ``calibration[method][scope]``, a :func:`supramodal.calibration.calibration_report`.
    """
    names, fw, fm = set_features(set_seed, seconds, progress)
    T, n = fw.shape[:2]
    n_train = int(round(TRAIN_FRACTION * n))
    if not 0 < n_train < n:
        raise InputError(f"{n} windows per texture cannot be split into training and test windows: "
                         "synthesise longer contacts")

    def part(values, rows):
        v = values[:, rows]
        return v.reshape(-1, *v.shape[2:])

    y_train = np.repeat(np.arange(T), n_train)
    y_test = np.repeat(np.arange(T), n - n_train)
    banks = {"whiskers": whisker_bank(), "microphone": cochlea_bank()}
    train = {"whiskers": part(fw, slice(0, n_train))[:, None], "microphone": part(fm, slice(0, n_train))[:, None]}
    test = {"whiskers": part(fw, slice(n_train, n))[:, None], "microphone": part(fm, slice(n_train, n))[:, None]}
    models, test_lp, pooling = {}, {}, {}
    for name, bank in banks.items():
        if progress:
            progress(f"  set {set_seed}: training the {name} model and its calibration")
        model = models[name] = TextureModel.train(train[name], y_train, names, bank, FEATURES,
                                                  window_length(DEFAULT_WINDOW, bank.fs), epochs=epochs, seed=seed)
        test_lp[name] = model.log_posteriors(test[name])
        assert model.calibration is not None, "trained with calibration folds (the default)"
        pooling[name] = model.calibration.contact_pooling
    if progress:
        progress(f"  set {set_seed}: held-out log-posteriors of both senses for the late fusion")
    held, folds, _ = senses_out_of_fold(list(models.values()), list(train.values()), y_train, names,
                                        k=DEFAULT_CALIBRATION_FOLDS, seed=seed)
    weight, sharpness = learn_late_fusion(held[0], held[1], y_train)
    fused_held = fuse_late(held[0], held[1], weight, sharpness)
    pooling["late"] = (fused_pooling(fused_held, y_train, folds), None)
    test_lp["late"] = fuse_late(test_lp["whiskers"], test_lp["microphone"], weight, sharpness)
    if progress:
        progress(f"  set {set_seed}: training the early-fusion network and its calibration")
    senses = [Sense(name, bank, FEATURES, window_length(DEFAULT_WINDOW, bank.fs)) for name, bank in banks.items()]
    early = EarlyFusionModel.train(senses, train["whiskers"], train["microphone"], y_train, names, epochs=epochs,
                                   seed=seed)
    test_lp["early"] = early.log_posteriors(test["whiskers"], test["microphone"])
    assert early.calibration is not None, "trained with calibration folds (the default)"
    pooling["early"] = early.calibration.contact_pooling

    contacts = contact_runs(y_test, n - n_train)
    y_contact = np.array([y_test[r[0]] for r in contacts])
    calibration = {}
    for m in METHODS:
        calibration[m] = {"window": calibration_report(test_lp[m], y_test, sure=SURE),
                          "contact": calibration_report(pooled_contacts(test_lp[m], contacts, *pooling[m]), y_contact,
                                                        sure=SURE)}
    return {"set_seed": set_seed, "textures": names, "late_weight": weight, "late_sharpness": sharpness,
            "late_correlation": pooling["late"][0], "test_windows_per_texture": n - n_train,
            "held_out": {m: float(np.mean(winner(lp) == y_train)) for m, lp in zip(banks, held)}
            | {"late": float(np.mean(winner(fused_held) == y_train))},
            "window": {m: calibration[m]["window"]["accuracy"] for m in METHODS},
            "contact": {m: calibration[m]["contact"]["accuracy"] for m in METHODS},
            "calibration": calibration}


def spread(values) -> dict:
    """Mean and sd (ddof 1; 0 for one value) of a list of numbers."""
    v = np.array(values, dtype=np.float64)
    return {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "min": float(v.min()), "max": float(v.max())}


def merge_reports(reports: list[dict]) -> dict:
    """One :func:`~supramodal.calibration.calibration_report` of the decisions of several, as if scored together.

    Means are weighted by count, reliability bins summed, sure decisions counted.
    """
    n = np.array([r["n"] for r in reports], dtype=np.float64)
    counts = np.sum([r["reliability"]["count"] for r in reports], axis=0)
    conf = np.sum([[c * (m or 0.0) for c, m in zip(r["reliability"]["count"], r["reliability"]["confidence"])]
                   for r in reports], axis=0)
    right = np.sum([[c * (a or 0.0) for c, a in zip(r["reliability"]["count"], r["reliability"]["accuracy"])]
                    for r in reports], axis=0)
    sure = int(sum(r["sure_count"] for r in reports))
    sure_wrong = sum(round(r["sure_wrong"] * r["sure_count"]) for r in reports if r["sure_count"])
    mean_conf = [float(s / c) if c else None for s, c in zip(conf, counts)]
    accuracy = [float(s / c) if c else None for s, c in zip(right, counts)]
    ece = float(sum(c / counts.sum() * abs(a - m) for c, a, m in zip(counts, accuracy, mean_conf)
                    if c and a is not None and m is not None))      # None exactly where c is 0
    return {"n": int(n.sum()),
            **{k: float(np.dot(n, [r[k] for r in reports]) / n.sum()) for k in ("accuracy", "log_loss", "brier")},
            "ece": ece, "sure": reports[0]["sure"], "sure_count": sure,
            "sure_wrong": sure_wrong / sure if sure else None,
            "reliability": {"edges": reports[0]["reliability"]["edges"], "count": counts.astype(int).tolist(),
                            "confidence": mean_conf, "accuracy": accuracy}}


def summarize(results: list[dict], seconds: float) -> dict:
    """:func:`run_set` results of several sets, summarised.

    Per method and scope the accuracy's and ECE's mean and spread over sets, and every set's
    decisions scored together (``pooled``).
    """
    best = [max(r["window"]["whiskers"], r["window"]["microphone"]) for r in results]
    summary: dict[str, dict[str, dict[str, object]]] = {}
    for m in METHODS:
        summary[m] = {}
        for kind in ("window", "contact"):
            reports = [r["calibration"][m][kind] for r in results]
            summary[m][kind] = {**spread([r[kind][m] for r in results]),
                                "ece": spread([c["ece"] for c in reports]), "pooled": merge_reports(reports)}
    return {"figure": "fusion", "seconds": seconds, "contact_windows": CONTACT_WINDOWS, "sure": SURE, "sets": results,
            "summary": summary,
            "late_fusion": {k: spread([r[k] for r in results]) for k in ("late_weight", "late_sharpness",
                                                                        "late_correlation")},
            "gain_over_better_sense": {m: spread([r["window"][m] - b for r, b in zip(results, best)])
                                       for m in ("late", "early")}}


def run_fusion(sets: int = 5, quick: bool = False, epochs: int = DEFAULT_EPOCHS, seed: int = 0,
               progress=None, jobs: int | None = None) -> dict:
    """:func:`run_set` over ``sets`` sets (seeds ``seed``, ``seed + 1``, ...), and their summary.

    The networks' seed is ``seed`` itself; ``quick``: 8 s contacts (default 20 s). The sets run over
    ``jobs`` worker processes (default: all cores; :func:`supramodal.experiments.runner.run_all`,
    single-threaded BLAS: a set trains some 30 small networks, which threaded BLAS slows many times
    on a busy machine); the results do not depend on ``jobs``. Returns the per-set results and
    :func:`summarize`'s figures.
    """
    from supramodal.experiments.runner import run_all

    if sets < 1:
        raise InputError(f"--sets must be >= 1 for the two-sense fusion, got {sets}")
    seconds = 8.0 if quick else 20.0
    t0 = time.perf_counter()
    runs = [Run(("fusion", seed + k), run_set, {"set_seed": seed + k, "seconds": seconds, "epochs": epochs,
                                                 "seed": seed}, 1.5 * seconds, seeded=False) for k in range(sets)]
    results = list(run_all(runs, jobs=jobs, seed=seed, progress=progress).values())
    if progress:
        for r in results:
            progress(f"set {r['set_seed']}: " + ", ".join(f"{m} {r['window'][m]:.3f}" for m in METHODS)
                     + f" (late weight of the whiskers {r['late_weight']:.2f}, sharpness {r['late_sharpness']:.2f})")
    return {**summarize(results, seconds), "compute_seconds": time.perf_counter() - t0}


def fusion_table(result: dict) -> str:
    """Return the experiment's summary as Markdown."""
    s = result["summary"]
    lines = [f"{len(result['sets'])} two-sense sets of 8 textures, {result['seconds']:g} s contacts; test windows of "
             f"100 ms and contacts of {result['contact_windows']} windows; mean +- sd over sets; ECE (15 bins) and "
             f"the share wrong of the decisions saying >= {result['sure']:g} over every set's decisions together", "",
             "| method | windows | contacts | ECE windows | ECE contacts | wrong of sure windows | "
             "wrong of sure contacts |", "|---|---|---|---|---|---|---|"]
    for m in METHODS:
        w, c = s[m]["window"], s[m]["contact"]
        lines.append(f"| {m} | {w['mean']:.3f} +- {w['sd']:.3f} | {c['mean']:.3f} +- {c['sd']:.3f} | "
                     f"{w['pooled']['ece']:.3f} | {c['pooled']['ece']:.3f} | {sure_cell(w['pooled'])} | "
                     f"{sure_cell(c['pooled'])} |")
    lines.append("")
    lf = result["late_fusion"]
    lines.append(f"late fusion learned on held-out windows: weight of the whiskers {lf['late_weight']['mean']:.2f} "
                 f"({lf['late_weight']['min']:.2f}..{lf['late_weight']['max']:.2f}), sharpness "
                 f"{lf['late_sharpness']['mean']:.2f}, contact correlation {lf['late_correlation']['mean']:.2f}")
    for m, g in result["gain_over_better_sense"].items():
        lines.append(f"{m} fusion over the better single sense, per window: {g['mean'] * 100:+.1f} points "
                     f"(sd {g['sd'] * 100:.1f}, at least {g['min'] * 100:+.1f})")
    return "\n".join(lines)


def sure_cell(report: dict) -> str:
    """``wrong / sure`` decisions of a report as a share and a count, e.g. ``0.000 (0 of 312)``."""
    if not report["sure_count"]:
        return "- (0 sure)"
    wrong = round(report["sure_wrong"] * report["sure_count"])
    return f"{report['sure_wrong']:.3f} ({wrong} of {report['sure_count']})"


def main(argv=None) -> int:
    """Run the experiment from the command line (:func:`~supramodal.experiments.common.two_sense_sets_main`)."""
    from supramodal.experiments.common import two_sense_sets_main

    return two_sense_sets_main(argv, "fusion", __doc__.splitlines()[0], run_fusion, fusion_table,
                               "8 s contacts (default 20 s)")


if __name__ == "__main__":
    sys.exit(main())
