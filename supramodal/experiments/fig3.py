"""Fig. 3: classification rate of 8 textures with each feature alone, for one bank or both."""

from __future__ import annotations

import numpy as np

from supramodal.banks import Bank
from supramodal.errors import InputError
from supramodal.experiments.common import BANKS, Plan, Run, default_bank, estimate_cost, quick_set, rates_of
from supramodal.features import FEATURES
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.textures import TextureSet, random_texture_set, reference_texture_set

#: The paper's mean rates (Fig. 3), for the side-by-side tables.
PAPER_FIG3 = {
    "whisker": {"Af": 0.904, "A": 0.895, "f": 0.415},
    "cochlea": {"Af": 0.925, "A": 0.954, "f": 0.260},
}


def fig3(texture_set: TextureSet, features=FEATURES, epochs: int = DEFAULT_EPOCHS, seed: int = 0,
         progress=None, bank: Bank | None = None) -> dict:
    """Rates of one texture set, each feature on its own.

    Parameters
    ----------
    bank : Bank, optional
        Default: the set's own bank (:func:`~supramodal.experiments.common.default_bank`).

    Returns
    -------
    dict
        ``{"bank", "texture_set", "textures": {name: peaks}, "features": {feature:
        {"mean_rate", "per_texture"}}, "timing": {...}}``.
    """
    bank = default_bank(texture_set) if bank is None else bank
    if progress:
        progress(f"fig3 {bank.kind}: computing features of {len(texture_set.textures)} textures "
                 f"x {texture_set.duration:g} s ({texture_set.name})")
    rates = rates_of(texture_set, bank, features, epochs=epochs, seed=seed, progress=progress)
    return {
        "bank": bank.kind,
        "texture_set": texture_set.name,
        "textures": {t.name: list(t.peaks) for t in texture_set.textures},
        "features": rates["features"],
        "timing": rates["timing"],
    }


def summarize_sets(runs: list[dict], label: str) -> dict:
    """Mean and spread of :func:`fig3` results over several texture sets of one bank.

    ``features[f]["mean_rate"]`` is the mean of the sets' mean rates and ``"sd"`` their
    standard deviation (ddof=1; 0 for one set); the per-set results are kept under ``"sets"``.
    """
    features = list(runs[0]["features"])
    summary = {}
    for f in features:
        rates = np.array([r["features"][f]["mean_rate"] for r in runs])
        names = runs[0]["features"][f]["per_texture"]
        summary[f] = {
            "mean_rate": float(rates.mean()),
            "sd": float(rates.std(ddof=1)) if len(runs) > 1 else 0.0,
            "per_texture": {n: float(np.mean([r["features"][f]["per_texture"][n] for r in runs])) for n in names},
        }
    timing = {k: sum(r["timing"][k] for r in runs) for k in ("signal_seconds", "compute_seconds")}
    return {"bank": runs[0]["bank"], "texture_set": label, "features": summary, "sets": runs, "timing": timing}


def random_sets_label(n_sets: int, seed: int) -> str:
    """Return the label of ``n_sets`` random sets of seeds ``seed ..``, e.g. ``"5 random sets, seeds 0..4"``."""
    return f"{n_sets} random sets, seeds {seed}..{seed + n_sets - 1}"


def plan(banks=BANKS, texture_set: TextureSet | None = None, reference: bool = True, sets: int = 0,
         seed: int = 0, quick: bool = False, epochs: int = DEFAULT_EPOCHS, features=FEATURES) -> Plan:
    """Fig. 3 runs: each bank's reference set (or ``texture_set``) and/or ``sets`` random sets.

    Random set ``i`` of a bank is ``random_texture_set(bank, 8, seed=seed + i)``; in quick
    mode every set is shortened to :data:`~supramodal.experiments.common.QUICK_DURATION` s.

    The assembled result has the shape of :func:`fig3` for one bank and its reference set
    alone, that of :func:`summarize_sets` for one bank and random sets alone, and otherwise
    ``{"figure": "fig3", "banks": {bank: fig3 result}, "random_sets": {bank: summary}}``.
    """
    banks = tuple(banks)
    if texture_set is not None and banks != (texture_set.bank,):
        raise InputError(f"texture set {texture_set.name!r} is for the {texture_set.bank} bank, not {list(banks)}: "
                         f"pass --bank {texture_set.bank}")
    if sets < 0:
        raise InputError(f"--sets must be >= 0, got {sets}")
    runs, labels = [], {}
    for bank in banks:
        sets_of_bank: list[tuple[tuple[str | int, ...], TextureSet]] = []
        if reference:
            sets_of_bank.append((("fig3", bank, "reference"),
                                 texture_set if texture_set is not None else reference_texture_set(bank)))
        for i in range(sets):
            ts = random_texture_set(bank, 8, seed=seed + i)
            sets_of_bank.append((("fig3", bank, "random", seed + i), ts))
        for key, ts in sets_of_bank:
            ts = quick_set(ts, quick)
            cost = estimate_cost(ts, default_bank(ts), len(features), epochs)
            runs.append(Run(key, fig3, {"texture_set": ts, "features": tuple(features), "epochs": epochs}, cost))
        labels[bank] = random_sets_label(sets, seed)

    def assemble(results: dict) -> dict:
        ref = {b: results[("fig3", b, "reference")] for b in banks if reference}
        rnd = {b: summarize_sets([results[("fig3", b, "random", seed + i)] for i in range(sets)], labels[b])
               for b in banks if sets}
        if len(banks) == 1 and not (reference and sets):
            return ref[banks[0]] if reference else rnd[banks[0]]
        out = {"figure": "fig3", "banks": ref}
        if rnd:
            out["random_sets"] = rnd
        out["paper"] = {b: PAPER_FIG3[b] for b in banks}
        return out

    return Plan(runs, assemble)
