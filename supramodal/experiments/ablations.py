"""Measurements behind docs/results.md's explanations: where our figures differ from the paper, why.

Each is a plan (plain data, run by :mod:`.runner`) or a pure function;
``python -m supramodal.experiments.ablations [--quick] [--jobs N] [--seed S] [--out DIR]``
runs them all and writes ``ablations.json`` into ``--out`` (default ./out/ablations). None of
them changes a reference texture set, the training or the banks the figures use: they vary one
thing at a time beside them.

* ``cochlea_on_whisker_spectra``: the cochlea bank on the *whisker* random sets' spectra
  (same peak frequencies, 80..750 Hz, 44.1 kHz): is cochlear f strong because of the bank,
  or because the cochlear sets' peaks lie up to 10 kHz?
* ``peak_statistics``: peaks per 100 ms window and the spread of f across windows, per
  channel, for both banks: how many cycles each channel's f averages over.
* ``peak_width``: Fig. 5's sweep on the whisker reference set with narrower texture peaks
  (relative width 0.2 -> 0.05, 0.02): does a narrow filter still see a texture's peak?
* ``network_seeds``: Fig. 3a with several network seeds: the spread due to training alone.
* ``windows_from_rest``: Fig. 5's sweep with every 100 ms window filtered from rest (filter
  state zeroed at each window's start) instead of one continuous stream: a gammatone's
  envelope peaks ``(n-1) / (2 pi b) = 3 / B`` seconds after an onset, 100 ms at B = 30.
* ``rows``: Fig. 6b's whisker rows on the random whisker sets, in the order A..E and E..A.
* ``level_spread``: at a given mean B, how far apart the textures' mean A lie on each whisker
  channel (dB) against the spread of A from window to window within a texture.
* ``unscaled``: Fig. 3 (both reference sets) and Fig. 5 (a few B) with the raw feature values
  fed to the network, without the per-input standardisation the paper does not mention.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from supramodal.banks import MAX_CHANNELS, WHISKER_ROWS, Bank
from supramodal.experiments.common import (
    Plan,
    Run,
    classification_rates,
    default_bank,
    estimate_cost,
    progress_to_stderr,
    quick_set,
    rates_of,
    rates_per_feature,
)
from supramodal.experiments.runner import run_plans
from supramodal.features import DEFAULT_WINDOW, FEATURES
from supramodal.gammatone import GammatoneFilterbank
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.peaks import PeakExtractor
from supramodal.pipeline import extract_features, window_length
from supramodal.textures import BANK_RATES, random_texture_set, reference_texture_set
from supramodal.training import texture_features

ABLATION_SETS = 5
WIDTHS = (0.05, 0.02)
WIDTH_GRID = (5.0, 10.0, 30.0, 100.0, 145.0, 300.0, 500.0)
NETWORK_SEEDS = 5


def as_cochlea_set(texture_set):
    """Return the same textures (peaks, noise seed, duration, width) synthesised at 44.1 kHz for the cochlea."""
    return dataclasses.replace(texture_set, name=f"{texture_set.name}-at-44k1", bank="cochlea",
                               fs=BANK_RATES["cochlea"])


def cochlea_on_whisker_spectra(n_sets: int = ABLATION_SETS, seed: int = 0, quick: bool = False,
                               epochs: int = DEFAULT_EPOCHS) -> Plan:
    """Both banks on the whisker random sets ``seed..seed+n_sets-1`` (peaks in 80..750 Hz)."""
    runs = []
    for i in range(n_sets):
        ws = quick_set(random_texture_set("whisker", 8, seed=seed + i), quick)
        for ts in (ws, as_cochlea_set(ws)):
            bank = default_bank(ts)
            runs.append(Run(("ablation", "low-peaks", ts.bank, seed + i), rates_of,
                            {"texture_set": ts, "bank": bank, "features": FEATURES, "epochs": epochs},
                            estimate_cost(ts, bank, 3, epochs)))

    def assemble(results: dict) -> dict:
        out = {}
        for bank in ("whisker", "cochlea"):
            rates = {f: [results[("ablation", "low-peaks", bank, seed + i)]["features"][f]["mean_rate"]
                         for i in range(n_sets)] for f in FEATURES}
            out[bank] = {f: {"mean_rate": float(np.mean(v)), "sd": float(np.std(v, ddof=1)) if n_sets > 1 else 0.0,
                             "per_set": v} for f, v in rates.items()}
        return {"sets": [f"whisker-random-{seed + i}" for i in range(n_sets)], "banks": out}

    return Plan(runs, assemble)


def peak_statistics(bank_name: str, seconds: float = 10.0, texture: int = 0, progress=None) -> dict:
    """Per channel: mean peaks per 100 ms window, and the coefficient of variation of f across windows.

    On ``seconds`` of the bank's reference texture ``texture``.
    """
    ts = reference_texture_set(bank_name)
    bank = default_bank(ts)
    x = ts.synthesize(texture, duration=seconds)
    peaks = PeakExtractor(bank.channels)
    p = peaks.process(GammatoneFilterbank(bank).process(x))
    wlen = window_length(DEFAULT_WINDOW, bank.fs)
    n_win = len(x) // wlen
    counts = np.zeros((n_win, bank.channels))
    keep = (p.index + 1) // wlen < n_win
    np.add.at(counts, ((p.index[keep] + 1) // wlen, p.channel[keep]), 1)
    counts = counts[1:]                                              # drop the onset window
    f = extract_features(x, bank, ("f",)).feature("f")[1:]
    cv = f.std(axis=0) / f.mean(axis=0)
    return {"bank": bank_name, "texture": ts.names[texture], "seconds": seconds, "cf": [float(c) for c in bank.cf],
            "peaks_per_window": [float(v) for v in counts.mean(axis=0)], "f_cv": [float(v) for v in cv]}


def peak_width(widths=WIDTHS, grid=WIDTH_GRID, quick: bool = False, epochs: int = DEFAULT_EPOCHS) -> Plan:
    """Fig. 5's bandwidth sweep on the whisker reference set re-synthesised with narrower peaks."""
    runs = []
    base = quick_set(reference_texture_set("whisker"), quick)
    for w in widths:
        ts = dataclasses.replace(base, name=f"{base.name}-width-{w:g}", width=w)
        for B in grid:
            bank = default_bank(ts, mean_B=B)
            runs.append(Run(("ablation", "width", w, B), rates_of,
                            {"texture_set": ts, "bank": bank, "features": FEATURES, "epochs": epochs},
                            estimate_cost(ts, bank, 3, epochs)))

    def assemble(results: dict) -> dict:
        return {"mean_B": list(grid), "widths": {
            str(w): {f: [results[("ablation", "width", w, B)]["features"][f]["mean_rate"] for B in grid]
                     for f in FEATURES} for w in widths}}

    return Plan(runs, assemble)


def network_seeds(bank_name: str = "whisker", n_seeds: int = NETWORK_SEEDS, epochs: int = DEFAULT_EPOCHS,
                  quick: bool = False, progress=None) -> dict:
    """Fig. 3 on a bank's reference set with network seeds 0..n_seeds-1: mean, sd, min, max per feature."""
    ts = quick_set(reference_texture_set(bank_name), quick)
    bank = default_bank(ts)
    values, _ = texture_features(ts, bank, FEATURES, progress=progress)
    wlen = window_length(DEFAULT_WINDOW, bank.fs)
    out = {}
    for k, f in enumerate(FEATURES):
        rates = [classification_rates(values[:, :, k : k + 1], ts.names, bank, (f,), wlen, epochs=epochs,
                                      seed=s)["mean_rate"] for s in range(n_seeds)]
        out[f] = {"mean_rate": float(np.mean(rates)), "sd": float(np.std(rates, ddof=1)),
                  "min": float(min(rates)), "max": float(max(rates)), "rates": rates}
    return {"bank": bank_name, "texture_set": ts.name, "seeds": list(range(n_seeds)), "features": out}


def features_from_rest(texture_set, bank: Bank, features=FEATURES) -> np.ndarray:
    """Like :func:`~supramodal.training.texture_features`, but every window is filtered from rest.

    The bank is replicated once per window so that the windows of a texture go through a few
    filterbank calls, each window's samples into its own copy of the channels; at most
    :data:`~supramodal.banks.MAX_CHANNELS` channels per call (a bank's limit), so a 40 s texture is
    several calls.

    Returns
    -------
    ndarray, shape (textures, windows, features, channels)
    """
    wlen = window_length(DEFAULT_WINDOW, bank.fs)
    per_call = max(1, MAX_CHANNELS // bank.channels)                                # windows per filterbank call
    out = []
    for i in range(len(texture_set.textures)):
        x = texture_set.synthesize(i)
        n = len(x) // wlen
        windows = x[: n * wlen].reshape(n, wlen)
        parts = []
        for first in range(0, n, per_call):
            k = min(per_call, n - first)
            rep = Bank(bank.kind, bank.fs, np.tile(bank.cf, k), np.tile(bank.b, k),
                       tuple(f"{w}:{name}" for w in range(k) for name in bank.names))
            xs = np.repeat(windows[first:first + k], bank.channels, axis=0)          # (k * channels, wlen)
            v = extract_features(xs, rep, features, block=None).values              # (1, features, k * channels)
            parts.append(v[0].reshape(len(features), k, bank.channels).transpose(1, 0, 2))
        out.append(np.concatenate(parts))
    return np.stack(out)


def rates_from_rest(texture_set, bank: Bank, features=FEATURES, epochs: int = DEFAULT_EPOCHS, seed: int = 0,
                    progress=None) -> dict:
    """:func:`~supramodal.experiments.common.rates_of` with :func:`features_from_rest`."""
    values = features_from_rest(texture_set, bank, features)
    return {"features": rates_per_feature(values, texture_set.names, bank, features, epochs, seed, progress)}


def windows_from_rest(grid=WIDTH_GRID, quick: bool = False, epochs: int = DEFAULT_EPOCHS) -> Plan:
    """Fig. 5's sweep with every window filtered from rest, whisker reference set."""
    ts = quick_set(reference_texture_set("whisker"), quick)
    runs = []
    for B in grid:
        bank = default_bank(ts, mean_B=B)
        runs.append(Run(("ablation", "from-rest", B), rates_from_rest,
                        {"texture_set": ts, "bank": bank, "features": FEATURES, "epochs": epochs},
                        2 * estimate_cost(ts, bank, 3, epochs)))

    def assemble(results: dict) -> dict:
        return {"mean_B": list(grid), "features": {
            f: [results[("ablation", "from-rest", B)]["features"][f]["mean_rate"] for B in grid] for f in FEATURES}}

    return Plan(runs, assemble)


def rows(n_sets: int = ABLATION_SETS, seed: int = 0, quick: bool = False, epochs: int = DEFAULT_EPOCHS) -> Plan:
    """Fig. 6b (Af) on the random whisker sets, rows added in the order A..E and in the order E..A."""
    orders = {"A..E": WHISKER_ROWS, "E..A": WHISKER_ROWS[::-1]}
    groups = {o: ["".join(r[: k + 1]) for k in range(len(r))] for o, r in orders.items()}
    runs, seen = [], set()
    for i in range(n_sets):
        ts = quick_set(random_texture_set("whisker", 8, seed=seed + i), quick)
        for o in orders:
            for g in groups[o]:
                key = ("ablation", "rows", seed + i, "".join(sorted(g)))
                if key in seen:
                    continue
                seen.add(key)
                bank = default_bank(ts, rows=g)
                runs.append(Run(key, rates_of, {"texture_set": ts, "bank": bank, "features": ("Af",), "epochs": epochs},
                                estimate_cost(ts, bank, 1, epochs)))

    def assemble(results: dict) -> dict:
        out = {}
        for o in orders:
            per_set = [[results[("ablation", "rows", seed + i, "".join(sorted(g)))]["features"]["Af"]["mean_rate"]
                        for g in groups[o]] for i in range(n_sets)]
            out[o] = {"rows": groups[o], "mean_rate": [float(v) for v in np.mean(per_set, axis=0)],
                      "sd": [float(v) for v in np.std(per_set, axis=0, ddof=1)] if n_sets > 1 else None,
                      "per_set": per_set}
        return {"sets": [f"whisker-random-{seed + i}" for i in range(n_sets)], "orders": out}

    return Plan(runs, assemble)


LEVEL_B = (5.0, 145.0)


def level_spread(mean_B: float, quick: bool = False, progress=None) -> dict:
    """Per whisker channel at ``mean_B``, on the reference set: A's spread between and within textures.

    That is the range over textures of the mean of A (dB), the mean over textures of A's
    window-to-window standard deviation (dB, of 20 log10 A), and their ratio, a per-channel
    separability index.
    """
    ts = quick_set(reference_texture_set("whisker"), quick)
    bank = default_bank(ts, mean_B=mean_B)
    values, _ = texture_features(ts, bank, ("A",))
    a_db = 20 * np.log10(values[:, 1:, 0, :])                   # (textures, windows, channels), onset dropped
    means = a_db.mean(axis=1)
    spread = means.max(axis=0) - means.min(axis=0)
    within = a_db.std(axis=1).mean(axis=0)
    return {"mean_B": mean_B, "names": list(bank.names), "cf": [float(c) for c in bank.cf],
            "between_db": [float(v) for v in spread], "within_db": [float(v) for v in within],
            "ratio": [float(v) for v in spread / within]}


UNSCALED_B = (5.0, 30.0, 145.0, 300.0)


def unscaled(grid=UNSCALED_B, quick: bool = False, epochs: int = DEFAULT_EPOCHS) -> Plan:
    """Fig. 3 on both reference sets and Fig. 5 at ``grid``, networks trained on unscaled inputs."""
    configs = {}
    for name in ("whisker", "cochlea"):
        ts = quick_set(reference_texture_set(name), quick)
        configs[("ablation", "unscaled", "fig3", name)] = (ts, default_bank(ts))
    ws = quick_set(reference_texture_set("whisker"), quick)
    for B in grid:
        configs[("ablation", "unscaled", "fig5", B)] = (ws, default_bank(ws, mean_B=B))
    runs = [Run(key, rates_of, {"texture_set": ts, "bank": bank, "features": FEATURES, "epochs": epochs,
                                "standardise": False}, estimate_cost(ts, bank, 3, epochs))
            for key, (ts, bank) in configs.items()]

    def assemble(results: dict) -> dict:
        rate = lambda key, f: results[key]["features"][f]["mean_rate"]
        return {"fig3": {name: {f: rate(("ablation", "unscaled", "fig3", name), f) for f in FEATURES}
                         for name in ("whisker", "cochlea")},
                "fig5": {"mean_B": list(grid),
                         "features": {f: [rate(("ablation", "unscaled", "fig5", B), f) for B in grid]
                                      for f in FEATURES}}}

    return Plan(runs, assemble)


def plans(quick: bool = False, epochs: int = DEFAULT_EPOCHS) -> dict[str, Plan]:
    """Every ablation as a plan, keyed by name."""
    single = lambda key, fn, kwargs, cost: Plan([Run(key, fn, kwargs, cost, seeded=False)], lambda r: r[key])
    n_sets = 2 if quick else ABLATION_SETS
    return {
        "cochlea_on_whisker_spectra": cochlea_on_whisker_spectra(n_sets, quick=quick, epochs=epochs),
        "peak_statistics_whisker": single(("ablation", "peaks", "whisker"), peak_statistics,
                                          {"bank_name": "whisker", "seconds": 2.0 if quick else 10.0}, 2.0),
        "peak_statistics_cochlea": single(("ablation", "peaks", "cochlea"), peak_statistics,
                                          {"bank_name": "cochlea", "seconds": 2.0 if quick else 10.0}, 10.0),
        "peak_width": peak_width(grid=(5.0, 145.0) if quick else WIDTH_GRID, quick=quick, epochs=epochs),
        "windows_from_rest": windows_from_rest(grid=(5.0, 145.0) if quick else WIDTH_GRID, quick=quick, epochs=epochs),
        "rows": rows(n_sets, quick=quick, epochs=epochs),
        **{f"level_spread_{B:g}": single(("ablation", "levels", B), level_spread, {"mean_B": B, "quick": quick}, 3.0)
           for B in LEVEL_B},
        "unscaled": unscaled(grid=(5.0, 145.0) if quick else UNSCALED_B, quick=quick, epochs=epochs),
        "network_seeds_whisker": single(("ablation", "seeds", "whisker"), network_seeds,
                                        {"bank_name": "whisker", "quick": quick, "epochs": epochs}, 15.0),
    }


def main(argv=None) -> int:
    """Run every ablation and write ``ablations.json`` (see the module's docstring)."""
    parser = argparse.ArgumentParser(prog="python -m supramodal.experiments.ablations",
                                     description="Run the ablations behind docs/results.md; "
                                                 "write them as one JSON file.")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--jobs", type=int)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="out/ablations")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    results = run_plans(plans(quick=args.quick), jobs=args.jobs, seed=args.seed, progress=progress_to_stderr)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ablations.json").write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {out / 'ablations.json'} in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    # The module's own name, not __main__: spawned workers import the plans' functions by it.
    from supramodal.experiments.ablations import main as _main

    sys.exit(_main())
