"""Confidence that means what it says (issue 23), measured.

Calibrated posteriors per window and per contact, late and early fusion of two senses, unknown
textures, and decisions taken as soon as they are sure.

Four measurements, each on held-out windows (the last quarter of every texture's windows,
:func:`supramodal.training.split`; Af features, each bank's default channels):

1. **Calibration** (:func:`score_set`): on the whisker and cochlea reference sets and on random
   texture sets, a :class:`~supramodal.model.TextureModel` trained as ``supramodal train`` trains it
   (its calibration fitted on out-of-fold windows of its training part) is scored per window and per
   contact (:data:`CONTACT_WINDOWS` consecutive test windows of one texture, pooled by the model's
   :meth:`~supramodal.calibration.Calibration.pool`): accuracy, log loss, Brier score, ECE
   (15 bins), and the share wrong of the decisions saying at least :data:`SURE`; beside them the
   uncalibrated posteriors (the normalised outputs; contacts pooled by their plain sum).
2. **Two senses** (:func:`supramodal.experiments.fusion.run_set`): each sense alone, late fusion
   learned on held-out windows, early fusion calibrated; accuracy and calibration of each.
3. **Unknown textures** (:func:`leave_out_fold`): leave :data:`LEFT_OUT` textures of a reference set
   out of training, every fold; how well the model's novelty score and the doubt ``1 - max p``
   tell the left-out textures' test windows from the known ones' (AUROC, per window and per
   contact), and the known textures' accuracy when windows beyond the novelty threshold of a
   :data:`FALSE_UNKNOWN` false-unknown rate are called unknown.
4. **Anytime decisions** (:func:`anytime_sweep`): contacts of up to :data:`ANYTIME_WINDOWS` test
   windows fed one by one to a :class:`~supramodal.decisions.DecisionAccumulator` with a
   confidence threshold; the share of contacts decided, the share of those right and the
   median number of windows it took, against the threshold (:data:`ANYTIME_THRESHOLDS`).

Run by ``supramodal experiment calibration [--quick] [--sets N] [--seed S] [--jobs N] [--out DIR]
[--json]``: a Markdown table on stdout, ``calibration.csv``, ``reliability.csv``, ``unknown.csv``,
``anytime.csv`` and (with matplotlib) ``calibration.png`` and ``anytime.png`` in ``--out``. The
networks of the texture sets are seeded from the experiment's seed and the run (as every figure's);
the two-sense sets use the experiment's seed itself, as ``experiment fusion`` does, so that their
figures are that experiment's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.stats import rankdata

from supramodal.calibration import calibration_report, normalised_log_posteriors, winner
from supramodal.errors import InputError
from supramodal.evaluation import ANYTIME_THRESHOLDS, anytime_sweep
from supramodal.experiments import fusion
from supramodal.experiments.common import BANKS, QUICK_DURATION, Plan, Run, default_bank, quick_set
from supramodal.experiments.fusion import (
    CONTACT_WINDOWS,
    SURE,
    contact_runs,
    merge_reports,
    pooled_contacts,
    spread,
    sure_cell,
)
from supramodal.features import DEFAULT_WINDOW
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.model import TextureModel
from supramodal.pipeline import window_length
from supramodal.textures import TextureSet, random_texture_set, reference_texture_set
from supramodal.training import split, texture_features

FEATURES = ("Af",)
#: Most windows of one contact in the anytime decisions (2 s of 100 ms windows).
ANYTIME_WINDOWS = 20
#: Confidence thresholds of the anytime decisions.
#: The threshold the issue names.
ANYTIME_CONFIDENCE = 0.99
#: Textures left out of training per fold of the unknown-texture test.
LEFT_OUT = 2
#: False-unknown rate of known windows at which the novelty threshold is set.
FALSE_UNKNOWN = 0.05
#: Random texture sets per bank and two-sense sets (default; in quick mode).
DEFAULT_SETS = 5
QUICK_SETS = 1
#: Seconds of contact per texture of the two-sense sets (quick mode: as ``experiment fusion --quick``).
TWO_SENSE_SECONDS = 20.0
QUICK_TWO_SENSE_SECONDS = 8.0
#: The issue's targets ("Done when").
TARGET_ECE = 0.05
TARGET_SURE_WRONG = 0.01
TARGET_LATE_GAIN = 0.10
TARGET_EARLY = 0.90
TARGET_AUROC = 0.90
TARGET_DROP = 0.03
TARGET_ANYTIME = 0.99


# -- the pieces --------------------------------------------------------------------------------------

def auroc(unknown, known) -> float:
    """Area under the ROC curve of a score that should be larger for ``unknown`` than for ``known``.

    That is the chance that an unknown item scores above a known one (ties count half).
    """
    u = np.asarray(unknown, dtype=np.float64)
    k = np.asarray(known, dtype=np.float64)
    if u.size == 0 or k.size == 0:
        raise InputError(f"an AUROC needs unknown and known items, got {u.size} and {k.size}")
    ranks = rankdata(np.concatenate([u, k]))
    return float((ranks[:u.size].sum() - u.size * (u.size + 1) / 2) / (u.size * k.size))


def merge_sweeps(sweeps: list[list[dict]]) -> list[dict]:
    """:func:`anytime_sweep` results of several sets, their contacts counted together."""
    out = []
    for rows in zip(*sweeps):
        windows = [w for r in rows for w in r["windows"]]
        out.append({"confidence": rows[0]["confidence"],
                    **{k: int(sum(r[k] for r in rows)) for k in ("contacts", "decided", "right", "end_right")},
                    "windows": windows, "median_windows": float(np.median(windows)) if windows else None})
    return out


def _features(texture_set: TextureSet, progress):
    bank = default_bank(texture_set)
    if progress:
        progress(f"{bank.kind}: features of {len(texture_set.textures)} textures x {texture_set.duration:g} s "
                 f"({texture_set.name})")
    values, timing = texture_features(texture_set, bank, FEATURES)
    return values, bank, window_length(DEFAULT_WINDOW, bank.fs), timing


def score_set(texture_set: TextureSet, epochs: int = DEFAULT_EPOCHS, seed: int = 0, progress=None) -> dict:
    """Calibration per window and per contact, and anytime decisions, of one texture set; see the module.

    Returns
    -------
    dict
        ``bank``, ``texture_set``, ``calibration`` (the model's, as stored), ``window`` and
        ``contact``: ``{"calibrated" | "uncalibrated" [| "summed"]: calibration report}``
        (``summed``: calibrated windows, contacts pooled by their plain sum), ``anytime``
        (:func:`anytime_sweep`: contacts side by side), ``anytime_every_start`` (the same with a
        contact starting at every test window that leaves room for one), ``timing``.
    """
    values, bank, wlen, timing = _features(texture_set, progress)
    x_train, y_train, x_test, y_test = split(values)
    if progress:
        progress(f"{bank.kind}: training and calibrating on {len(y_train)} windows")
    model = TextureModel.train(x_train, y_train, texture_set.names, bank, FEATURES, wlen, epochs=epochs, seed=seed)
    per_texture = len(y_test) // len(texture_set.names)
    contacts = contact_runs(y_test, per_texture, CONTACT_WINDOWS)
    if not contacts:
        raise InputError(f"{per_texture} test windows per texture make no contact of {CONTACT_WINDOWS}: "
                         "synthesise longer textures")
    y_contact = y_test[[r[0] for r in contacts]]
    lp = model.log_posteriors(x_test)
    raw = normalised_log_posteriors(model.logits(x_test))
    assert model.calibration is not None                  # trained with calibration folds (the default)
    rho, caps = model.calibration.contact_pooling         # the node's pooling (DecisionAccumulator)
    anytime = contact_runs(y_test, per_texture, min(ANYTIME_WINDOWS, per_texture))
    every_start = contact_runs(y_test, per_texture, min(ANYTIME_WINDOWS, per_texture), step=1)
    return {"bank": bank.kind, "texture_set": texture_set.name, "calibration": model.calibration.to_dict(),
            "test_windows_per_texture": per_texture,
            "window": {"calibrated": calibration_report(lp, y_test, sure=SURE),
                       "uncalibrated": calibration_report(raw, y_test, sure=SURE)},
            "contact": {"calibrated": calibration_report(
                pooled_contacts(lp, contacts, rho, caps), y_contact, sure=SURE),
                        "uncalibrated": calibration_report(pooled_contacts(raw, contacts, 0.0), y_contact, sure=SURE),
                        "summed": calibration_report(pooled_contacts(lp, contacts, 0.0), y_contact, sure=SURE)},
            "anytime": anytime_sweep(lp, y_test, anytime, rho, caps=caps),
            "anytime_every_start": anytime_sweep(lp, y_test, every_start, rho, caps=caps),
            "timing": timing}


def leave_out_fold(texture_set: TextureSet, fold: int, epochs: int = DEFAULT_EPOCHS, seed: int = 0,
                   progress=None) -> dict:
    """Leave textures ``LEFT_OUT * fold ..`` out of training; detect unknown textures on every texture's test windows.

    See the module.

    A window is unknown when its novelty score (:meth:`~supramodal.calibration.Novelty.score`) is
    beyond the model's threshold for a :data:`FALSE_UNKNOWN` rate of held-out known windows; a
    contact when its pooled novelty (:meth:`~supramodal.calibration.Novelty.pooled_score`) is beyond
    the threshold for that rate of held-out known contacts of its length. Both thresholds come from
    the model's held-out windows of its known textures alone.

    Returns
    -------
    dict
        ``bank``, ``fold``, ``left_out`` (names); ``window`` and ``contact``: ``auroc_novelty``,
        ``auroc_doubt`` (``1 - max p``; of a contact, of its pooled posteriors),
        ``auroc_supervised`` (the reference: a network trained on every texture, the left-out ones
        too, scoring their summed posterior; of a contact, its windows' mean),
        ``auroc_mean_novelty`` (a contact's mean window novelty, the score of before; windows: the
        novelty itself), ``false_unknown`` (share of known test windows or contacts beyond the
        threshold) and ``unknown_caught`` (the same share of unknown ones), ``threshold``; the known
        test windows' or contacts' ``accuracy`` without rejection, ``accuracy_with_rejection`` (one
        called unknown counts as wrong), ``accuracy_of_accepted`` (of those not called unknown),
        ``drop`` (accuracy minus accuracy with rejection) and ``accepted_drop`` (accuracy minus
        accuracy of accepted).
    """
    names = texture_set.names
    out = list(range(LEFT_OUT * fold, LEFT_OUT * fold + LEFT_OUT))
    if fold < 0 or out[-1] >= len(names) or len(names) - LEFT_OUT < 2:
        raise InputError(f"fold {fold} leaves textures {out} out of a set of {len(names)}")
    known = [k for k in range(len(names)) if k not in out]
    values, bank, wlen, _ = _features(texture_set, progress)
    x_train, y_train, _, _ = split(values[known])
    if progress:
        progress(f"{bank.kind}: training without {', '.join(names[k] for k in out)}")
    model = TextureModel.train(x_train, y_train, [names[k] for k in known], bank, FEATURES, wlen, epochs=epochs,
                               seed=seed)
    all_train, all_labels, x_test, y_test = split(values)
    # A reference no novelty score can be expected to beat: a network of the same shape trained on all the
    # textures, the left-out ones included, scoring a window by its posterior of the left-out
    # classes. Where even it cannot tell a left-out texture's windows from the known ones', the
    # features of one window do not hold the difference.
    if progress:
        progress(f"{bank.kind}: the supervised reference, trained with {', '.join(names[k] for k in out)}")
    seen = TextureModel.train(all_train, all_labels, names, bank, FEATURES, wlen, epochs=epochs, seed=seed,
                              calibration_folds=0)
    seen_score = np.exp(seen.log_posteriors(x_test)[:, out]).sum(axis=1)
    assert model.calibration is not None and model.novelty is not None      # trained with calibration folds
    index = {k: i for i, k in enumerate(known)}
    contacts = contact_runs(y_test, len(y_test) // len(names), CONTACT_WINDOWS)
    lp = model.log_posteriors(x_test)
    novelty = model.novelty_score(x_test)
    inputs = model._inputs(x_test)
    first = [r[0] for r in contacts]
    scopes = {"window": {"labels": y_test, "log_posteriors": lp, "novelty": novelty, "mean_novelty": novelty,
                         "supervised": seen_score,
                         "threshold": model.novelty.threshold(FALSE_UNKNOWN)},
              "contact": {"labels": y_test[first],
                          "log_posteriors": pooled_contacts(lp, contacts, *model.calibration.contact_pooling),
                          "novelty": np.array([model.novelty.pooled_score(inputs[r]) for r in contacts]),
                          "mean_novelty": np.array([novelty[r].mean() for r in contacts]),
                          "supervised": np.array([seen_score[r].mean() for r in contacts]),
                          "threshold": model.novelty.contact_threshold(FALSE_UNKNOWN, CONTACT_WINDOWS)}}
    result = {"bank": bank.kind, "texture_set": texture_set.name, "fold": fold, "left_out": [names[k] for k in out]}
    for scope, d in scopes.items():
        y, lps, nov, t = d["labels"], d["log_posteriors"], d["novelty"], d["threshold"]
        unknown = np.isin(y, out)
        doubt = 1.0 - np.exp(lps.max(axis=1))
        right = winner(lps[~unknown]) == np.array([index[k] for k in y[~unknown]])
        rejected = nov[~unknown] > t
        accuracy, kept = float(right.mean()), float((right & ~rejected).mean())
        accepted = float(right[~rejected].mean()) if (~rejected).any() else None
        result[scope] = {"auroc_novelty": auroc(nov[unknown], nov[~unknown]),
                         "auroc_mean_novelty": auroc(d["mean_novelty"][unknown], d["mean_novelty"][~unknown]),
                         "auroc_doubt": auroc(doubt[unknown], doubt[~unknown]),
                         "auroc_supervised": auroc(d["supervised"][unknown], d["supervised"][~unknown]),
                         "false_unknown": float(np.mean(rejected)),
                         "unknown_caught": float(np.mean(nov[unknown] > t)),
                         "n_unknown": int(unknown.sum()), "n_known": int((~unknown).sum()), "threshold": float(t),
                         "accuracy": accuracy, "accuracy_with_rejection": kept, "accuracy_of_accepted": accepted,
                         "drop": accuracy - kept,
                         "accepted_drop": accuracy - (accepted if accepted is not None else 0.0)}
    return result


# -- the plan -------------------------------------------------------------------------------------------

def _cost(texture_set: TextureSet, per: float) -> float:
    return per * texture_set.duration / 40.0 + 0.5


def plan(quick: bool = False, epochs: int = DEFAULT_EPOCHS, seed: int = 0, sets: int | None = None) -> Plan:
    """Return the runs of ``experiment calibration``.

    Per bank its reference set, ``sets`` random sets (seeds ``seed ..``) and every leave-out fold of the
    reference set; ``sets`` two-sense sets (seeds ``seed ..``). Quick mode: textures of
    :data:`~supramodal.experiments.common.QUICK_DURATION` s, two-sense contacts of
    :data:`QUICK_TWO_SENSE_SECONDS` s, :data:`QUICK_SETS` sets by default.
    """
    n_sets = (QUICK_SETS if quick else DEFAULT_SETS) if sets is None else sets
    if isinstance(n_sets, bool) or not isinstance(n_sets, int) or n_sets < 1:
        raise InputError(f"--sets must be >= 1 for experiment calibration (random texture sets per bank and "
                         f"two-sense sets), got {sets!r}")
    seconds = QUICK_TWO_SENSE_SECONDS if quick else TWO_SENSE_SECONDS
    runs = []
    per_bank_cost = {"whisker": 4.0, "cochlea": 25.0}
    for bank in BANKS:
        ref = quick_set(reference_texture_set(bank), quick)
        runs.append(Run(("calibration", bank, "reference"), score_set, {"texture_set": ref, "epochs": epochs},
                        _cost(ref, per_bank_cost[bank])))
        for i in range(n_sets):
            ts = quick_set(random_texture_set(bank, 8, seed=seed + i), quick)
            runs.append(Run(("calibration", bank, "random", seed + i), score_set, {"texture_set": ts, "epochs": epochs},
                            _cost(ts, per_bank_cost[bank])))
        for f in range(len(ref.textures) // LEFT_OUT):
            runs.append(Run(("calibration", bank, "leave-out", f), leave_out_fold,
                            {"texture_set": ref, "fold": f, "epochs": epochs}, _cost(ref, 0.8 * per_bank_cost[bank])))
    for i in range(n_sets):
        runs.append(Run(("calibration", "two-sense", seed + i), fusion.run_set,
                        {"set_seed": seed + i, "seconds": seconds, "epochs": epochs, "seed": seed},
                        1.5 * seconds, seeded=False))

    def assemble(results: dict) -> dict:
        out: dict[str, Any] = {"figure": "calibration", "quick": quick, "epochs": epochs, "seed": seed,
               "duration": QUICK_DURATION if quick else None, "contact_windows": CONTACT_WINDOWS,
               "anytime_windows": ANYTIME_WINDOWS, "sure": SURE, "false_unknown": FALSE_UNKNOWN,
               "thresholds": list(ANYTIME_THRESHOLDS), "reference": {}, "random_sets": {}, "leave_out": {}}
        for bank in BANKS:
            out["reference"][bank] = results[("calibration", bank, "reference")]
            out["random_sets"][bank] = summarize_sets([results[("calibration", bank, "random", seed + i)]
                                                       for i in range(n_sets)], seed)
            folds = [results[k] for k in results if k[:3] == ("calibration", bank, "leave-out")]
            out["leave_out"][bank] = summarize_folds(folds)
        out["two_sense"] = fusion.summarize([results[("calibration", "two-sense", seed + i)] for i in range(n_sets)],
                                            seconds)
        return out

    return Plan(runs, assemble)


def summarize_sets(results: list[dict], seed: int) -> dict:
    """:func:`score_set` results of random sets, summarised.

    Per scope and posteriors, every set's decisions together (``pooled``) and the spread over
    sets of the accuracy and the ECE; anytime merged.
    """
    summary: dict[str, dict] = {}
    for scope in ("window", "contact"):
        summary[scope] = {}
        for variant in results[0][scope]:
            reports = [r[scope][variant] for r in results]
            summary[scope][variant] = {"pooled": merge_reports(reports),
                                       "accuracy": spread([c["accuracy"] for c in reports]),
                                       "ece": spread([c["ece"] for c in reports])}
    return {"bank": results[0]["bank"], "label": f"{len(results)} random sets, seeds {seed}..{seed + len(results) - 1}",
            "sets": results, **summary, "anytime": merge_sweeps([r["anytime"] for r in results]),
            "anytime_every_start": merge_sweeps([r["anytime_every_start"] for r in results])}


def summarize_folds(folds: list[dict]) -> dict:
    """Leave-out folds of one bank, and the worst of each figure over them (``{scope}_{figure}``)."""
    worst = {f"{scope}_{k}": min(f[scope][k] for f in folds) for scope in ("window", "contact")
             for k in ("auroc_novelty", "auroc_mean_novelty", "auroc_doubt", "auroc_supervised")}
    worst |= {f"{scope}_{k}": max(f[scope][k] for f in folds) for scope in ("window", "contact")
              for k in ("drop", "accepted_drop")}
    return {"folds": folds, "worst": worst}


# -- the table -------------------------------------------------------------------------------------------

def _groups(result: dict):
    """Return the reports and ECEs of every texture-set group and two-sense method, one tuple each.

    Each is (name, window report, contact report, uncalibrated window report, uncalibrated
    contact report, per-set window ECEs, per-set contact ECEs).
    """
    rows = []
    for bank in BANKS:
        r = result["reference"][bank]
        rows.append((f"{bank} reference", r["window"]["calibrated"], r["contact"]["calibrated"],
                     r["window"]["uncalibrated"], r["contact"]["uncalibrated"], None, None))
    for bank in BANKS:
        s = result["random_sets"][bank]
        rows.append((f"{bank}, {len(s['sets'])} random sets", s["window"]["calibrated"]["pooled"],
                     s["contact"]["calibrated"]["pooled"], s["window"]["uncalibrated"]["pooled"],
                     s["contact"]["uncalibrated"]["pooled"], s["window"]["calibrated"]["ece"],
                     s["contact"]["calibrated"]["ece"]))
    two = result["two_sense"]
    for m in fusion.METHODS:
        s = two["summary"][m]
        rows.append((f"two senses: {m}", s["window"]["pooled"], s["contact"]["pooled"], None, None,
                     s["window"]["ece"], s["contact"]["ece"]))
    return rows


def _arrow(before, after, spec=".3f") -> str:
    after = format(after + 0.0, spec)          # + 0.0: no "-0.000" for a log loss of -0.0
    return after if before is None else f"{format(before + 0.0, spec)} -> {after}"


def _calibration_rows(result: dict, scope: int) -> list[str]:
    lines = ["| held-out | n | accuracy | mean confidence | log loss | Brier | ECE | ECE per set (max) | "
             "says >= 0.99: wrong |", "|---|---|---|---|---|---|---|---|---|"]
    for name, *reports, ece_w, ece_c in _groups(result):
        cal, raw = reports[scope], reports[scope + 2]
        ece = (ece_w, ece_c)[scope]
        lines.append(
            f"| {name} | {cal['n']} | {cal['accuracy']:.3f} | "
            f"{_arrow(raw and mean_confidence(raw), mean_confidence(cal))} | "
            f"{_arrow(raw and raw['log_loss'], cal['log_loss'])} | "
            f"{_arrow(raw and raw['brier'], cal['brier'])} | {_arrow(raw and raw['ece'], cal['ece'])} | "
            f"{'-' if ece is None else format(ece['max'], '.3f')} | "
            + (f"{sure_cell(raw)} -> " if raw else "") + f"{sure_cell(cal)} |")
    return lines


def mean_confidence(report: dict) -> float:
    """Return the mean top posterior of a calibration report's decisions (from its reliability bins).

    Above the accuracy, the decisions overclaim; below it, they underclaim.
    """
    rel = report["reliability"]
    return sum(c * (m or 0.0) for c, m in zip(rel["count"], rel["confidence"])) / report["n"]


def done_when(result: dict) -> list[tuple[str, str, list[str]]]:
    """Return the issue's "Done when" figures: (what, measured, what misses it) per line.

    The line holds where the last is empty.
    """
    out = []
    groups = [g for g in _groups(result) if not g[0].startswith(tuple(f"{b}," for b in BANKS))]
    for k, label in ((0, "per window"), (1, "per contact")):
        values = [(g[0], g[1 + k]["ece"]) for g in groups]
        out.append((f"ECE {label} <= {TARGET_ECE}", ", ".join(f"{n} {v:.3f}" for n, v in values),
                    [n for n, v in values if v > TARGET_ECE]))
    sure = [(g[0], g[1]["sure_wrong"], g[1]["sure_count"]) for g in groups]
    out.append((f"windows saying >= {SURE}: at most {TARGET_SURE_WRONG:.0%} wrong",
                ", ".join(f"{n} {'-' if w is None else format(w, '.3f')} of {c}" for n, w, c in sure),
                [n for n, w, _ in sure if w is not None and w > TARGET_SURE_WRONG]))
    two = result["two_sense"]
    gain = two["gain_over_better_sense"]["late"]
    out.append((f"two senses: late fusion >= better sense + {TARGET_LATE_GAIN * 100:.0f} points per window",
                f"{gain['mean'] * 100:+.1f} points (each set at least {gain['min'] * 100:+.1f})",
                [] if gain["min"] >= TARGET_LATE_GAIN else ["a set"]))
    early = two["summary"]["early"]["window"]
    out.append((f"two senses: early fusion >= {TARGET_EARLY} per window",
                f"{early['mean']:.3f} (each set at least {early['min']:.3f})",
                [] if early["min"] >= TARGET_EARLY else ["a set"]))
    lo = result["leave_out"]
    for scope in ("window", "contact"):
        out.append((f"unknown textures, every fold: AUROC >= {TARGET_AUROC} (novelty score, per {scope})",
                    ", ".join(f"{b} worst fold {worst[scope + '_auroc_novelty']:.3f} (a network trained with the "
                              f"left-out textures: worst fold {worst[scope + '_auroc_supervised']:.3f})"
                              for b, worst in ((b, lo[b]["worst"]) for b in BANKS)),
                    [b for b in BANKS if lo[b]["worst"][scope + "_auroc_novelty"] < TARGET_AUROC]))
    for scope in ("window", "contact"):
        for key, how in (("accepted_drop", f"of the known {scope}s still answered"),
                         ("drop", f"a known {scope} called unknown counted wrong")):
            out.append((f"known textures' accuracy falls <= {TARGET_DROP * 100:.0f} points at {FALSE_UNKNOWN:.0%} "
                        f"false unknown, per {scope} ({how})",
                        ", ".join(f"{b} worst fold {lo[b]['worst'][scope + '_' + key] * 100:+.1f} points"
                                  for b in BANKS),
                        [b for b in BANKS if lo[b]["worst"][scope + "_" + key] > TARGET_DROP]))
    # A contact may start at any window: 40 contacts side by side can only say 40 of 40 or a miss
    # (one wrong is 2.5 %); a contact starting at every test window measures the rate to ~0.2 %.
    for key, how in (("anytime_every_start", "a contact starting at every test window"),
                     ("anytime", "contacts side by side")):
        rows = {b: _at(result["reference"][b][key], ANYTIME_CONFIDENCE) for b in BANKS}
        out.append((f"anytime decisions at {ANYTIME_CONFIDENCE}: >= {TARGET_ANYTIME} of the decided contacts right "
                    f"({how})",
                    ", ".join(f"{b} {_share(r['right'], r['decided'])} ({r['right']} of {r['decided']} decided; "
                              f"{r['decided']} of {r['contacts']} contacts decided, median "
                              f"{_fmt(r['median_windows'], 'g')} windows)" for b, r in rows.items()),
                    [b for b, r in rows.items()
                     if not (r["decided"] and r["right"] >= TARGET_ANYTIME * r["decided"])]))
    return out


def _at(sweep: list[dict], confidence: float) -> dict:
    return next(r for r in sweep if r["confidence"] == confidence)


def _share(k: int, n: int) -> str:
    return f"{k / n:.3f}" if n else "-"


def _fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def calibration_table(result: dict) -> str:
    """Return the experiment's figures as Markdown: the issue's "Done when", then each measurement."""
    two = result["two_sense"]
    head = (f"Test windows of 100 ms (the last 25 % of each texture; "
            f"{'quick: ' + format(result['duration'], 'g') + ' s textures' if result['quick'] else '40 s textures'}), "
            f"contacts of {result['contact_windows']} windows; {len(two['sets'])} two-sense set(s) of "
            f"{two['seconds']:g} s contacts; 'a -> b': uncalibrated -> calibrated")
    lines = [head, "", "| the issue's \"done when\" | measured | holds? |", "|---|---|---|"]
    lines += [f"| {w} | {m} | {'**no**: ' + ', '.join(miss) if miss else 'yes'} |" for w, m, miss in done_when(result)]
    lines += ["", "Calibration per window", ""] + _calibration_rows(result, 0)
    lines += ["", f"Calibration per contact ({result['contact_windows']} windows pooled; uncalibrated: summed "
              "log-posteriors)", ""] + _calibration_rows(result, 1)
    lines += ["", fusion.fusion_table(two)]
    lines += ["", f"Unknown textures: {LEFT_OUT} of 8 left out of training per fold; test windows of all 8 "
              f"(thresholds: {FALSE_UNKNOWN:.0%} false unknown on held-out training windows, and on held-out "
              f"contacts of {result['contact_windows']} windows); 'window / contact'", "",
              "| bank | left out | AUROC novelty | AUROC mean window novelty (contact) | AUROC 1 - max p | "
              "AUROC, trained with them (reference) | "
              "false unknown | unknown caught | known accuracy: all -> with rejection (accepted) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for bank in BANKS:
        for f in result["leave_out"][bank]["folds"]:
            w, c = f["window"], f["contact"]
            lines.append(f"| {bank} | {', '.join(f['left_out'])} | "
                         f"{w['auroc_novelty']:.3f} / {c['auroc_novelty']:.3f} | "
                         f"{c['auroc_mean_novelty']:.3f} | {w['auroc_doubt']:.3f} / {c['auroc_doubt']:.3f} | "
                         f"{w['auroc_supervised']:.3f} / {c['auroc_supervised']:.3f} | "
                         f"{w['false_unknown']:.3f} / {c['false_unknown']:.3f} | "
                         f"{w['unknown_caught']:.3f} / {c['unknown_caught']:.3f} | "
                         + " / ".join(f"{v['accuracy']:.3f} -> {v['accuracy_with_rejection']:.3f} "
                                      f"({_fmt(v['accuracy_of_accepted'], '.3f')})" for v in (w, c)) + " |")
    lines += ["", f"Anytime decisions: contacts of up to {result['anytime_windows']} windows, decided at the first "
              "window whose pooled confidence reaches the threshold: right of decided / decided of all / median "
              "windows to decide", "",
              "| threshold | " + " | ".join(_sweep_names(result)) + " |", "|---|" + "---|" * len(_sweep_names(result))]
    sweeps = _sweeps(result)
    for i, c in enumerate(result["thresholds"]):
        cells = [f"{_share(s[i]['right'], s[i]['decided'])} / {_share(s[i]['decided'], s[i]['contacts'])} / "
                 f"{_fmt(s[i]['median_windows'], 'g')}" for s in sweeps.values()]
        lines.append(f"| {c:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _sweeps(result: dict) -> dict:
    out = {}
    for key, how in (("anytime", ""), ("anytime_every_start", ", every start")):
        out.update({f"{b} reference{how}": result["reference"][b][key] for b in BANKS})
        out.update({f"{b}, {len(result['random_sets'][b]['sets'])} random sets{how}": result["random_sets"][b][key]
                    for b in BANKS})
    return out


def _sweep_names(result: dict) -> list[str]:
    return list(_sweeps(result))


# -- files -------------------------------------------------------------------------------------------------

def write_calibration(result: dict, out, notice=None) -> list:
    """Write the experiment's CSV files and, with matplotlib, its PNGs into ``out``; return the paths written.

    ``calibration.csv``, ``reliability.csv``, ``unknown.csv``, ``anytime.csv`` and, with
    matplotlib, ``calibration.png`` (reliability diagrams) and ``anytime.png``; without
    matplotlib, ``notice`` (a callable taking one line) says that no PNG was written.
    """
    from pathlib import Path

    from supramodal.experiments.plotting import have_matplotlib, write_csv

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    metrics = ("n", "accuracy", "log_loss", "brier", "ece", "sure_count", "sure_wrong")
    rows, bins = [], []
    for name, kind, seed, method, scope, variant, rep in _reports(result):
        rows.append([name, kind, seed, method, scope, variant] + [rep[k] for k in metrics])
        r = rep["reliability"]
        for b in range(len(r["count"])):
            bins.append([name, kind, seed, method, scope, variant, r["edges"][b], r["edges"][b + 1], r["count"][b],
                         r["confidence"][b], r["accuracy"][b]])
    key = ["set", "kind", "set_seed", "method", "scope", "posteriors"]
    paths = [write_csv(out / "calibration.csv", key + list(metrics), rows),
             write_csv(out / "reliability.csv", key + ["bin_low", "bin_high", "count", "confidence", "accuracy"], bins)]
    unknown = [[b, f["fold"], " ".join(f["left_out"]), scope]
               + [f[scope][k] for k in ("auroc_novelty", "auroc_mean_novelty", "auroc_doubt", "auroc_supervised",
                                        "false_unknown",
                                        "unknown_caught", "threshold", "accuracy", "accuracy_with_rejection",
                                        "accuracy_of_accepted")]
               for b in BANKS for f in result["leave_out"][b]["folds"] for scope in ("window", "contact")]
    paths.append(write_csv(out / "unknown.csv", ["bank", "fold", "left_out", "scope", "auroc_novelty",
                                            "auroc_mean_window_novelty", "auroc_doubt", "auroc_supervised",
                                            "false_unknown",
                                            "unknown_caught", "novelty_threshold", "known_accuracy",
                                            "known_accuracy_with_rejection", "known_accuracy_of_accepted"], unknown))
    anytime = [[name, r["confidence"], r["contacts"], r["decided"], r["right"],
                r["right"] / r["decided"] if r["decided"] else None, r["decided"] / r["contacts"],
                r["median_windows"], float(np.mean(r["windows"])) if r["windows"] else None, r["end_right"]]
               for name, sweep in _sweeps(result).items() for r in sweep]
    paths.append(write_csv(out / "anytime.csv", ["set", "confidence", "contacts", "decided", "right",
                                                 "right_of_decided", "decided_of_all", "median_windows",
                                                 "mean_windows", "right_at_end"],
                      anytime))
    if have_matplotlib():
        paths += [_plot_reliability(result, out / "calibration.png"), _plot_anytime(result, out / "anytime.png")]
    elif notice:
        notice("matplotlib is not installed: no calibration.png or anytime.png written (pip install '.[plots]')")
    return paths


def _reports(result: dict):
    """(set, kind, set seed, method, scope, posteriors, report) of every calibration report of a result."""
    for bank in BANKS:
        r = result["reference"][bank]
        for scope in ("window", "contact"):
            for variant, rep in r[scope].items():
                yield f"{bank} reference", "reference", None, "model", scope, variant, rep
        for k, r in enumerate(result["random_sets"][bank]["sets"]):
            for scope in ("window", "contact"):
                for variant, rep in r[scope].items():
                    yield f"{bank} random", "random", result["seed"] + k, "model", scope, variant, rep
    for r in result["two_sense"]["sets"]:
        for m in fusion.METHODS:
            for scope in ("window", "contact"):
                yield "two senses", "two-sense", r["set_seed"], m, scope, "calibrated", r["calibration"][m][scope]


#: Fewest decisions a bin of a reliability diagram needs to be drawn (fewer say little).
PLOT_MIN_BIN = 5


def _plot_reliability(result: dict, path):
    from supramodal.experiments.plotting import pyplot, save_figure

    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(10, 8.4))
    groups = _groups(result)
    sets = [g for g in groups if not g[0].startswith("two senses")]
    two = [g for g in groups if g[0].startswith("two senses")]
    styles = [("k", "o"), ("C1", "s"), ("0.5", "^"), ("C0", "v"), ("C2", "D"), ("C3", "P")]
    for row, scope in enumerate(("window", f"contact ({result['contact_windows']} windows)")):
        for col, (chosen, title) in enumerate(((sets, "texture sets"), (two, "two senses"))):
            ax = axes[row, col]
            ax.plot([0, 1], [0, 1], color="0.7", linewidth=0.8)
            for (name, *reports, _, _), (colour, marker) in zip(chosen, styles):
                for rep, raw in ((reports[row], False), (reports[row + 2], True)):
                    if rep is not None:
                        _reliability_line(ax, rep, colour, "x" if raw else marker, ":" if raw else "-",
                                          f"{name.removeprefix('two senses: ')}{' uncalibrated' if raw else ''} "
                                          f"(ECE {rep['ece']:.3f})")
            ax.set_xlim(0, 1.01)
            ax.set_ylim(0, 1.01)
            ax.set_xlabel("confidence (top posterior), 15 bins")
            ax.set_ylabel("share right")
            ax.set_title(f"({'abcd'[2 * row + col]}) {title}, per {scope}", fontsize=10)
            ax.grid(True, linewidth=0.3)
            ax.legend(fontsize=6.5, loc="upper left")
    fig.suptitle(f"Reliability of held-out decisions (bins of at least {PLOT_MIN_BIN}; marker area ~ count)",
                 fontsize=10)
    return save_figure(fig, path)


def _reliability_line(ax, report: dict, colour, marker, line, label) -> None:
    rel = report["reliability"]
    pts = [(c, a, n) for c, a, n in zip(rel["confidence"], rel["accuracy"], rel["count"]) if n >= PLOT_MIN_BIN]
    if not pts:
        return
    x, y, n = (np.array(v) for v in zip(*pts))
    ax.plot(x, y, color=colour, linestyle=line, linewidth=0.9, alpha=0.6 if line == ":" else 1.0, label=label)
    ax.scatter(x, y, s=6 + 60 * np.sqrt(n / n.sum()), color=colour, marker=marker, zorder=3)


def _plot_anytime(result: dict, path):
    from supramodal.experiments.plotting import pyplot, save_figure

    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
    styles = [("k", "o", "-"), ("C1", "s", "-"), ("k", "^", "--"), ("C1", "v", "--"),
              ("0.5", "o", "-"), ("C3", "s", "-"), ("0.5", "^", "--"), ("C3", "v", "--")]
    lowest = 1.0
    for (name, sweep), (colour, marker, line) in zip(_sweeps(result).items(), styles):
        x = -np.log10(1.0 - np.array([r["confidence"] for r in sweep]))
        values = ([r["right"] / r["decided"] if r["decided"] else np.nan for r in sweep],
                  [r["decided"] / r["contacts"] for r in sweep],
                  [np.nan if r["median_windows"] is None else r["median_windows"] for r in sweep])
        for ax, v in zip(axes, values):
            ax.plot(x, v, color=colour, marker=marker, linestyle=line, markersize=4, label=name)
        lowest = min(lowest, np.nanmin(np.concatenate([values[0], values[1]], dtype=float), initial=1.0))
    titles = ("(a) decided contacts right", "(b) contacts decided at all",
              "(c) median windows to decide (of 100 ms)")
    for ax, title in zip(axes, titles):
        ticks = result["thresholds"]
        ax.set_xticks(-np.log10(1.0 - np.array(ticks)), [f"{t:g}" for t in ticks], fontsize=7)
        ax.set_xlabel("confidence threshold")
        ax.set_title(title, fontsize=10)
        ax.grid(True, linewidth=0.3)
    axes[0].axhline(TARGET_ANYTIME, color="r", linewidth=0.6, linestyle=":")
    for ax in axes[:2]:
        ax.set_ylim(min(0.5, lowest - 0.05), 1.01)
        ax.set_ylabel("share of contacts")
    axes[1].legend(fontsize=7, loc="lower left")
    fig.suptitle(f"Anytime decisions: contacts of up to {result['anytime_windows']} test windows", fontsize=10)
    return save_figure(fig, path)
