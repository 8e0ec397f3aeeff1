"""Fig. 3: classification rate of 8 textures with each feature alone, for one bank."""

from __future__ import annotations

import numpy as np

from supramodal.experiments.common import (DEFAULT_EPOCHS, classification_rates, default_bank,
                                           texture_features)
from supramodal.features import FEATURES
from supramodal.pipeline import window_length
from supramodal.textures import TextureSet, random_texture_set

#: The paper's mean rates (Fig. 3), for the side-by-side tables.
PAPER_FIG3 = {
    "whisker": {"Af": 0.904, "A": 0.895, "f": 0.415},
    "cochlea": {"Af": 0.925, "A": 0.954, "f": 0.260},
}


def fig3(texture_set: TextureSet, features=FEATURES, epochs: int = DEFAULT_EPOCHS, seed: int = 0,
         progress=None) -> dict:
    """Rates of one texture set, each feature on its own.

    Returns
    -------
    dict
        ``{"bank", "texture_set", "textures": {name: peaks}, "features": {feature:
        {"mean_rate", "per_texture"}}, "timing": {...}}``.
    """
    bank = default_bank(texture_set)
    if progress:
        progress(f"fig3 {bank.kind}: computing features of {len(texture_set.textures)} textures "
                 f"x {texture_set.duration:g} s ({texture_set.name})")
    values, timing = texture_features(texture_set, bank, features, progress=progress)
    wlen = window_length(0.1, bank.fs)
    results = {}
    for k, feature in enumerate(features):
        if progress:
            progress(f"fig3 {bank.kind}: training and testing on {feature}")
        results[feature] = classification_rates(values[:, :, k : k + 1], texture_set.names, bank, (feature,),
                                                wlen, epochs=epochs, seed=seed)
    return {
        "bank": bank.kind,
        "texture_set": texture_set.name,
        "textures": {t.name: list(t.peaks) for t in texture_set.textures},
        "features": results,
        "timing": timing,
    }


def fig3_random_sets(bank: str, n_sets: int, seed: int = 0, features=FEATURES, epochs: int = DEFAULT_EPOCHS,
                     progress=None) -> dict:
    """Fig. 3 over ``n_sets`` random texture sets (seeds ``seed .. seed + n_sets - 1``): mean and sd.

    The per-set results are kept under ``"sets"``; ``features[f]["mean_rate"]`` is the mean of
    the sets' mean rates and ``"sd"`` their standard deviation (ddof=1).
    """
    if n_sets < 1:
        raise ValueError(f"--sets must be >= 1, got {n_sets}")
    runs = []
    for i in range(n_sets):
        ts = random_texture_set(bank, 8, seed=seed + i)
        if progress:
            progress(f"fig3 {bank}: random set {i + 1}/{n_sets} (seed {seed + i})")
        runs.append(fig3(ts, features, epochs=epochs, seed=seed, progress=progress))
    summary = {}
    for f in features:
        rates = np.array([r["features"][f]["mean_rate"] for r in runs])
        names = runs[0]["features"][f]["per_texture"]
        summary[f] = {
            "mean_rate": float(rates.mean()),
            "sd": float(rates.std(ddof=1)) if n_sets > 1 else 0.0,
            "per_texture": {n: float(np.mean([r["features"][f]["per_texture"][n] for r in runs])) for n in names},
        }
    timing = {k: sum(r["timing"][k] for r in runs) for k in ("signal_seconds", "compute_seconds")}
    return {"bank": bank, "texture_set": f"{n_sets} random sets, seeds {seed}..{seed + n_sets - 1}",
            "features": summary, "sets": runs, "timing": timing}
