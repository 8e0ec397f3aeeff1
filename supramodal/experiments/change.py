"""Re-deciding when the texture changes within a contact (issue 34), on the two-sense world with touches.

A whisker array and a microphone slide from surface to surface without lifting off.

Per set (:func:`supramodal.twosense.two_sense_set`; the six textures of
:mod:`supramodal.experiments.newtouch`, ``H2a`` and ``H2b`` left out): each sense's model trained on
touches 1-2 (calibrated by touch), the late fusion learned on their out-of-fold windows (issue 34's
rule) with its contact pooling, and each stream's change threshold fitted for one false change per minute
on the out-of-fold windows of touches 1-2 (:func:`supramodal.decisions.fit_change_threshold`: each held-out
touch a still one; never on the touches scored). Scored with :class:`supramodal.decisions.Decider` as a
scene's ``[decision] scope = "contact", n = 0, confidence = 0.99, change = 1`` decides (one false change
per minute allowed) with that threshold, per stream and fused:

* **Slides**: :data:`SLIDES` touches (slide ``r`` is touch ``4 + r`` of every texture: each its own
  signals and gains) that cross all six textures in a random order, :data:`SEGMENT` seconds each,
  without a lift-off: a change is *detected* when the decider
  signals one within :data:`DETECT_WITHIN` windows of the boundary (the boundary's window counts as
  the first); its delay in windows; the share of detections that name the new texture.
* **Still touches**: touch 3 of every texture, one texture throughout: every change signalled is a
  false one; false changes per minute, there and in the slides away from any boundary.
* **Anytime after a change and after a lift-off**: the share of segments after the first of a slide
  whose decision (the final one where the 0.99 was reached, else the pooled one at the segment's end)
  names the texture, beside the same for the very same segments decided as contacts of their own, as
  if the robot had lifted off before each (a fresh decision from the segment's first window).

With ``augment`` (``--augment``), every network trains also on gain-augmented copies of its training
windows, as :mod:`supramodal.experiments.newtouch`'s do (:class:`supramodal.model.GainAugment`: per
vibrissa for the whiskers, one level for the microphone); the thresholds are then fitted on the
augmented networks' out-of-fold windows.

The table gives every set's figures together, then each set's (the thresholds fitted too).

    supramodal experiment change [--quick] [--sets N] [--seed S] [--augment] [--out DIR]
    python -m supramodal.experiments.change [--quick] [--sets N] [--seed S] [--augment]
"""

from __future__ import annotations

import sys
import time
from typing import Any, cast

import numpy as np

from supramodal.decisions import (
    Decider,
    DecisionRules,
    PooledDecision,
    TextureChange,
    fit_change_threshold,
    windows_per_change,
)
from supramodal.errors import InputError
from supramodal.evaluation import DETECT_WITHIN, change_detections
from supramodal.experiments.common import AUGMENT_HELP, Run, augment_line
from supramodal.experiments.newtouch import FEATURES, TOUCHES, touch_features, train_senses
from supramodal.features import DEFAULT_WINDOW
from supramodal.fused_model import fused_pooling
from supramodal.fusion import fuse_late
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.model import GainAugment
from supramodal.pipeline import extract_features
from supramodal.twosense import synthesize_slide, two_sense_set

#: Seconds of each texture in a slide.
SEGMENT = 3.0
#: Slides per set.
SLIDES = 4
#: False changes per minute allowed (``[decision] change``).
CHANGE_RATE = 1.0
#: The final decision's confidence (``[decision] confidence``).
CONFIDENCE = 0.99
STREAMS = ("whiskers", "microphone", "late")


def rules() -> DecisionRules:
    """Return the ``[decision]`` every stream decides by here."""
    return DecisionRules(scope="contact", n=0, confidence=CONFIDENCE, change=CHANGE_RATE)


def decide(log_posteriors, classes, correlation: float, caps,
           threshold: float | None = None) -> list[PooledDecision]:
    """One contact's windows through a fresh :class:`Decider`: each window's pooled decision.

    ``threshold``: its change threshold (None: the bound).
    """
    d = Decider(classes, rules(), correlation, caps=caps, window_seconds=DEFAULT_WINDOW, change_threshold=threshold)
    return [cast(PooledDecision, d.decide(lp).pooled) for lp in log_posteriors]


def fitted_thresholds(trained, pooling: dict) -> dict:
    """Each stream's change threshold (:func:`~supramodal.decisions.fit_change_threshold`) for :data:`CHANGE_RATE`.

    Fitted on the out-of-fold windows of the training touches (``trained``: a
    :class:`~supramodal.experiments.newtouch.TrainedSenses`), each touch a still one; ``pooling``:
    ``{stream: (rho, caps)}``.
    """
    held = {"whiskers": trained.held[0], "microphone": trained.held[1], "late": trained.late["fused"]}
    groups = np.asarray(trained.groups)
    touches = [np.flatnonzero(groups == g) for g in dict.fromkeys(groups.tolist())]     # in time order
    n = windows_per_change(CHANGE_RATE, DEFAULT_WINDOW)
    return {s: fit_change_threshold([held[s][i] for i in touches], [int(trained.y[i[0]]) for i in touches], n,
                                    *pooling[s]) for s in STREAMS}


def _said(pooled: list[PooledDecision]) -> str | None:
    """Return a contact's decision: its final one where it was reached, else the pooled one at its end."""
    final = [p for p in pooled if p.decided]
    return (final[0] if final else pooled[-1]).label


def run_set(set_seed: int, seconds: float = 10.0, epochs: int = DEFAULT_EPOCHS, seed: int = 0,
            progress=None, augment: GainAugment | None = None) -> dict:
    """One set: see the module docstring (``augment``: the networks' gain augmentation, None: none).

    Per stream: ``boundaries``, ``detected``, ``delays`` (windows), ``to_new`` (first changes in a segment
    naming its texture), ``false_changes`` and ``minutes`` (still touches), ``false_in_slides`` and
    ``slide_minutes``, ``after_change`` and ``after_lift_off`` (segments right, of), ``threshold`` (fitted).
    """
    names, feats = touch_features(set_seed, seconds, progress)
    trained = train_senses(names, feats, epochs, seed, progress, f"  set {set_seed}: ", augment)
    known, classes, models, late = trained.known, trained.classes, trained.models, trained.late
    banks = {sense: m.bank for sense, m in models.items()}
    seg = int(round(SEGMENT / DEFAULT_WINDOW))
    if trained.per < seg:
        raise InputError(f"touches of {seconds:g} s are shorter than a slide's segments of {SEGMENT:g} s")
    pooling = {sense: m.calibration.contact_pooling for sense, m in models.items() if m.calibration is not None}
    pooling["late"] = (fused_pooling(late["fused"], trained.y, trained.folds, trained.groups), None)
    thresholds = fitted_thresholds(trained, pooling)
    deciding = {s: (*pooling[s], thresholds[s]) for s in STREAMS}

    def stream_lps(whisker_values, mic_values) -> dict:
        lw = models["whiskers"].log_posteriors(whisker_values)
        lm = models["microphone"].log_posteriors(mic_values)
        n = min(len(lw), len(lm))
        return {"whiskers": lw[:n], "microphone": lm[:n],
                "late": fuse_late(lw[:n], lm[:n], late["weight"], late["sharpness"])}

    out: dict[str, dict[str, Any]] = {
        s: {"boundaries": 0, "detected": 0, "delays": [], "to_new": 0, "false_changes": 0, "minutes": 0.0,
            "false_in_slides": 0, "slide_minutes": 0.0, "after_change": [0, 0], "after_lift_off": [0, 0],
            "threshold": thresholds[s]}
        for s in STREAMS}
    # still touches: touch 3 of every texture, one contact each
    for i in known:
        lps = stream_lps(feats[i, TOUCHES - 1][0], feats[i, TOUCHES - 1][1])
        for s in STREAMS:
            pooled = decide(lps[s], classes, *deciding[s])
            out[s]["false_changes"] += sum(p.change is not None for p in pooled)
            out[s]["minutes"] += len(pooled) * DEFAULT_WINDOW / 60.0
    surfaces = two_sense_set(pairs=2, seed=set_seed)
    rng = np.random.default_rng([set_seed, 34])
    for r in range(SLIDES):
        order = [known[k] for k in rng.permutation(len(known))]
        if progress:
            progress(f"  set {set_seed}: slide {r + 1}/{SLIDES} across {[names[i] for i in order]}")
        w, m = synthesize_slide(surfaces, order, SEGMENT, set_seed, TOUCHES + r)
        lps = stream_lps(extract_features(w, banks["whiskers"], FEATURES).values,
                         extract_features(m, banks["microphone"], FEATURES).values)
        for s in STREAMS:
            pooled = decide(lps[s], classes, *deciding[s])
            truths = [names[order[min(t // seg, len(order) - 1)]] for t in range(len(pooled))]
            boundaries, false = change_detections(truths, [t for t, p in enumerate(pooled) if p.change is not None])
            for at, t in boundaries:
                out[s]["boundaries"] += 1
                if t is not None:
                    out[s]["delays"].append(t - at + 1)
                    out[s]["detected"] += t - at + 1 <= DETECT_WITHIN
                    out[s]["to_new"] += cast(TextureChange, pooled[t].change).to == truths[at]
                # the segment's decision, from the pooled decisions of its own windows (after the change, if found)
                said = _said(pooled[at if t is None else t:at + seg])
                out[s]["after_change"][0] += said == truths[at]
                out[s]["after_change"][1] += 1
                fresh = _said(decide(lps[s][at:at + seg], classes, *deciding[s]))      # as after a lift-off
                out[s]["after_lift_off"][0] += fresh == truths[at]
                out[s]["after_lift_off"][1] += 1
            out[s]["false_in_slides"] += false
            out[s]["slide_minutes"] += len(pooled) * DEFAULT_WINDOW / 60.0
    return {"set_seed": set_seed, "textures": classes, "late_weight": late["weight"],
            "late_sharpness": late["sharpness"], "streams": out}


def summarize(results: list[dict]) -> dict:
    """Every set's counts together, per stream (``threshold``: the mean of the sets' fitted ones)."""
    out = {}
    for s in STREAMS:
        rows = [r["streams"][s] for r in results]
        boundaries = sum(r["boundaries"] for r in rows)
        delays = [d for r in rows for d in r["delays"]]
        after = [sum(r["after_change"][k] for r in rows) for k in (0, 1)]
        lift = [sum(r["after_lift_off"][k] for r in rows) for k in (0, 1)]
        out[s] = {"boundaries": boundaries, "detected": sum(r["detected"] for r in rows) / boundaries,
                  "found": len(delays) / boundaries,
                  "to_new": sum(r["to_new"] for r in rows) / max(1, len(delays)),
                  "median_delay": float(np.median(delays)) if delays else None,
                  "false_per_minute": sum(r["false_changes"] for r in rows) / sum(r["minutes"] for r in rows),
                  "false_per_minute_slides": sum(r["false_in_slides"] for r in rows)
                  / sum(r["slide_minutes"] for r in rows),
                  "after_change": after[0] / after[1], "after_lift_off": lift[0] / lift[1],
                  "segments": after[1], "lift_off_contacts": lift[1],
                  "threshold": float(np.mean([r["threshold"] for r in rows]))}
    return out


def run_change(sets: int = 5, quick: bool = False, epochs: int = DEFAULT_EPOCHS, seed: int = 0, progress=None,
               jobs: int | None = None, augment: GainAugment | None = None) -> dict:
    """:func:`run_set` over ``sets`` sets on ``jobs`` worker processes; ``quick``: 6 s still touches.

    ``augment``: every network's gain augmentation (None: none).
    """
    from supramodal.experiments.runner import run_all

    if sets < 1:
        raise InputError(f"--sets must be >= 1 for the change experiment, got {sets}")
    seconds = 6.0 if quick else 10.0
    t0 = time.perf_counter()
    runs = [Run(("change", seed + k), run_set, {"set_seed": seed + k, "seconds": seconds, "epochs": epochs,
                                                 "seed": seed, "augment": augment},
                (10 if augment is None else 14) * seconds, seeded=False) for k in range(sets)]
    results = list(run_all(runs, jobs=jobs, seed=seed, progress=progress).values())
    return {"figure": "change", "seconds": seconds, "segment": SEGMENT, "slides": SLIDES,
            "detect_within": DETECT_WITHIN, "change_rate": CHANGE_RATE, "confidence": CONFIDENCE, "sets": results,
            "augment": None if augment is None else augment.to_dict(),
            "summary": summarize(results), "compute_seconds": time.perf_counter() - t0}


def change_table(result: dict) -> str:
    """Return the experiment's figures as Markdown."""
    lines = [f"{len(result['sets'])} two-sense sets, 6 textures; slides of {result['segment']:g} s per texture "
             f"({result['slides']} a set, touches 4-{3 + result['slides']}), still touches of {result['seconds']:g} s "
             "(touch 3); [decision] "
             f"scope = \"contact\", confidence = {result['confidence']:g}, change = {result['change_rate']:g} per "
             "minute", "",
             f"| stream | changes detected within {result['detect_within']} windows | at all (in the segment) | "
             "naming the new texture | median delay (windows) | false changes per minute, still | in slides | "
             "segments right after a change | the same segments after a lift-off |",
             "|---|---|---|---|---|---|---|---|---|"]
    for s, v in result["summary"].items():
        delay = "-" if v["median_delay"] is None else f"{v['median_delay']:g}"
        lines.append(f"| {s} | {v['detected']:.3f} of {v['boundaries']} | {v['found']:.3f} | {v['to_new']:.3f} | "
                     f"{delay} | "
                     f"{v['false_per_minute']:.2f} | {v['false_per_minute_slides']:.2f} | {v['after_change']:.3f} of "
                     f"{v['segments']} | {v['after_lift_off']:.3f} of {v['lift_off_contacts']} |")
    lines += ["", "Each set (change threshold: fitted on the training touches' out-of-fold windows, log-odds):", "",
              f"| set | stream | change threshold | detected within {result['detect_within']} windows | "
              "false changes per minute, still | segments right after a change | after a lift-off |",
              "|---|---|---|---|---|---|---|"]
    for r in result["sets"]:
        for s, v in summarize([r]).items():
            lines.append(f"| {r['set_seed']} | {s} | {v['threshold']:.2f} | {v['detected']:.3f} of {v['boundaries']} | "
                         f"{v['false_per_minute']:.2f} | {v['after_change']:.3f} | {v['after_lift_off']:.3f} |")
    lines += ["", augment_line(result)]
    return "\n".join(lines)


def write_change(result: dict, out) -> list:
    """``change.csv``: one row per stream, the summary's figures."""
    import csv
    from pathlib import Path

    path = Path(out) / "change.csv"
    rows = [{"stream": s, **v} for s, v in result["summary"].items()]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return [path]


def main(argv=None) -> int:
    """Run the experiment from the command line (:func:`~supramodal.experiments.common.two_sense_sets_main`)."""
    from supramodal.experiments.common import two_sense_sets_main

    return two_sense_sets_main(argv, "change", __doc__.splitlines()[0], run_change, change_table,
                               "6 s still touches (default 10 s)", augment=AUGMENT_HELP)


if __name__ == "__main__":
    sys.exit(main())
