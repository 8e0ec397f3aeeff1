"""Fusion of the two senses on the two-sense synthetic world: whiskers alone, microphone alone, late
fusion and early fusion (the supramodal network), over random texture sets.

Per set (:func:`supramodal.twosense.two_sense_set`, 8 textures): each texture's contact is
synthesised for both senses; Af windows of 100 ms from the whisker bank (20 channels, 5 kHz) and
the cochlea (50 channels, 44.1 kHz), aligned by index (offline, both start at the contact). The
first :data:`~supramodal.training.TRAIN_FRACTION` of every texture's windows trains, the rest
tests. Of the training windows, the first 80 % train the networks and the last 20 % choose the
late-fusion weight (:func:`supramodal.fusion.learn_late_weight`). Reported on the test windows: the
share of windows right, and the share of contacts right, a contact being a run of 10 test windows
(1 s) pooled by summed log-posteriors.

    supramodal experiment fusion [--quick] [--sets N] [--seed S] [--out DIR]
    python -m supramodal.experiments.fusion [--quick] [--sets N] [--seed S]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.decisions import posteriors
from supramodal.fusion import Standardised, early_inputs, fuse_late, learn_late_weight
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.pipeline import extract_features
from supramodal.training import TRAIN_FRACTION
from supramodal.twosense import synthesize_contact, two_sense_set

METHODS = ("whiskers", "microphone", "late", "early")
#: Windows pooled into one contact decision (1 s).
CONTACT_WINDOWS = 10


def set_features(set_seed: int, seconds: float, progress=None):
    """Per texture, aligned Af windows of both senses: (names, whiskers (T, n, 20), mic (T, n, 50))."""
    surfaces = two_sense_set(pairs=2, seed=set_seed)
    wb, cb = whisker_bank(), cochlea_bank()
    fw, fm = [], []
    for i, s in enumerate(surfaces):
        w, m = synthesize_contact(s, seconds, seed=[set_seed, i])
        fw.append(extract_features(w, wb, ("Af",)).values[:, 0])
        fm.append(extract_features(m, cb, ("Af",)).values[:, 0])
        if progress:
            progress(f"  set {set_seed}: {s.name} ({i + 1}/{len(surfaces)})")
    n = min(min(len(v) for v in fw), min(len(v) for v in fm))
    return [s.name for s in surfaces], np.stack([v[:n] for v in fw]), np.stack([v[:n] for v in fm])


def _pooled_accuracy(log_post: np.ndarray, labels: np.ndarray, per_texture: int) -> float:
    """Contacts of CONTACT_WINDOWS consecutive test windows of one texture, pooled."""
    hits = runs = 0
    for t in range(len(log_post) // per_texture):
        rows = log_post[t * per_texture:(t + 1) * per_texture]
        for k in range(0, per_texture - CONTACT_WINDOWS + 1, CONTACT_WINDOWS):
            hits += int(np.argmax(rows[k:k + CONTACT_WINDOWS].sum(axis=0)) == labels[t * per_texture])
            runs += 1
    return hits / runs


def run_set(set_seed: int, seconds: float = 20.0, epochs: int = DEFAULT_EPOCHS, seed: int = 0, progress=None) -> dict:
    """Window and contact accuracy of each method on one set; see the module docstring."""
    names, fw, fm = set_features(set_seed, seconds, progress)
    T, n = fw.shape[:2]
    n_train = int(round(TRAIN_FRACTION * n))
    n_fit = int(round(0.8 * n_train))
    parts = {"fit": slice(0, n_fit), "weight": slice(n_fit, n_train), "test": slice(n_train, n)}

    def take(values, part):
        v = values[:, parts[part]]
        return v.reshape(-1, *v.shape[2:]), np.repeat(np.arange(T), v.shape[1])

    nets = {}
    for name, values in (("whiskers", fw), ("microphone", fm), ("early", early_inputs(
            fw.reshape(T * n, -1), fm.reshape(T * n, -1)).reshape(T, n, -1))):
        x, y = take(values, "fit")
        nets[name] = Standardised(x, y, T, epochs, seed)
    out = {}
    for part in ("weight", "test"):
        xw, y = take(fw, part)
        xm, _ = take(fm, part)
        xe, _ = take(early_inputs(fw.reshape(T * n, -1), fm.reshape(T * n, -1)).reshape(T, n, -1), part)
        out[part] = (y, nets["whiskers"].outputs(xw), nets["microphone"].outputs(xm), nets["early"].outputs(xe))
    y, ow, om, _ = out["weight"]
    weight = learn_late_weight(ow, om, y)
    y, ow, om, oe = out["test"]
    logs = {"whiskers": np.log(posteriors(ow)), "microphone": np.log(posteriors(om)),
            "late": fuse_late(ow, om, weight), "early": np.log(posteriors(oe))}
    per_texture = n - n_train
    return {"set_seed": set_seed, "textures": names, "late_weight": weight, "test_windows_per_texture": per_texture,
            "window": {m: float(np.mean(np.argmax(logs[m], axis=1) == y)) for m in METHODS},
            "contact": {m: _pooled_accuracy(logs[m], y, per_texture) for m in METHODS}}


def run_fusion(sets: int = 5, quick: bool = False, epochs: int = DEFAULT_EPOCHS, seed: int = 0,
               progress=None) -> dict:
    """:func:`run_set` over ``sets`` sets (seeds ``seed``, ``seed + 1``, ...); ``quick``: 8 s contacts
    (default 20 s). Returns the per-set results and, per method, mean and sd over sets."""
    seconds = 8.0 if quick else 20.0
    t0 = time.perf_counter()
    results = []
    for k in range(sets):
        r = run_set(seed + k, seconds, epochs, seed, progress)
        results.append(r)
        if progress:
            progress(f"set {seed + k}: " + ", ".join(f"{m} {r['window'][m]:.3f}" for m in METHODS)
                     + f" (late weight of the whiskers {r['late_weight']:.2f})")

    def spread(values):
        v = np.array(values)
        return {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0}

    best = [max(r["window"]["whiskers"], r["window"]["microphone"]) for r in results]
    return {"figure": "fusion", "seconds": seconds, "contact_windows": CONTACT_WINDOWS, "sets": results,
            "summary": {m: {kind: spread([r[kind][m] for r in results]) for kind in ("window", "contact")}
                        for m in METHODS},
            "gain_over_better_sense": {m: spread([r["window"][m] - b for r, b in zip(results, best)])
                                       for m in ("late", "early")},
            "compute_seconds": time.perf_counter() - t0}


def fusion_table(result: dict) -> str:
    """The experiment's summary as Markdown."""
    s = result["summary"]
    lines = [f"{len(result['sets'])} two-sense sets of 8 textures, {result['seconds']:g} s contacts; test windows of "
             f"100 ms and contacts of {result['contact_windows']} windows; mean +- sd over sets", "",
             "| method | windows | contacts |", "|---|---|---|"]
    for m in METHODS:
        w, c = s[m]["window"], s[m]["contact"]
        lines.append(f"| {m} | {w['mean']:.3f} +- {w['sd']:.3f} | {c['mean']:.3f} +- {c['sd']:.3f} |")
    lines.append("")
    for m, g in result["gain_over_better_sense"].items():
        lines.append(f"{m} fusion over the better single sense, per window: {g['mean'] * 100:+.1f} points "
                     f"(sd {g['sd'] * 100:.1f})")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m supramodal.experiments.fusion", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="8 s contacts and 2 sets (default: 20 s, --sets)")
    p.add_argument("--sets", type=int, default=5, help="random two-sense texture sets (default 5)")
    p.add_argument("--seed", type=int, default=0, help="first set's seed and the networks' seed (default 0)")
    p.add_argument("--epochs", type=int, default=DEFAULT_EPOCHS, help=f"iRPROP- epochs (default {DEFAULT_EPOCHS})")
    args = p.parse_args(argv)
    progress = lambda m: print(m, file=sys.stderr, flush=True)    # noqa: E731
    result = run_fusion(2 if args.quick else args.sets, args.quick, args.epochs, args.seed, progress)
    print(fusion_table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
