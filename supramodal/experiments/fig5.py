"""Fig. 5: mean classification rate against the whisker bank's mean bandwidth B (5..500), three features.

The bandwidth is Slaney's ``B = 2 pi b`` (the paper's "bandwidth", quoted in Hz):
every channel's ``b`` is multiplied by one factor so that the mean B over the 20
vibrissae hits each grid value (``whisker_bank(mean_B=B)``). The true mean -3 dB
width is reported beside it. The texture set is the whisker reference set (Fig. 3a).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from supramodal.banks import half_power_width, slaney_bandwidth
from supramodal.experiments.common import Plan, Run, default_bank, estimate_cost, quick_set, rates_of
from supramodal.features import FEATURES
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.textures import reference_texture_set

#: Log-like grid from 5 to 500; 145 is the paper's default bank.
MEAN_B_GRID = (5.0, 10.0, 20.0, 30.0, 50.0, 75.0, 100.0, 145.0, 200.0, 300.0, 400.0, 500.0)
QUICK_GRID = (5.0, 30.0, 145.0, 500.0)
PAPER_FIG5 = "chance up to ~30, best near 200 (Af, A) or 300 (f), slow decline beyond"


def plan(quick: bool = False, epochs: int = DEFAULT_EPOCHS, grid=None, features=FEATURES, **_) -> Plan:
    """One run per mean B of the grid (default :data:`MEAN_B_GRID`, quick :data:`QUICK_GRID`)."""
    grid = tuple(float(b) for b in (grid or (QUICK_GRID if quick else MEAN_B_GRID)))
    ts = quick_set(reference_texture_set("whisker"), quick)
    banks = {B: default_bank(ts, mean_B=B) for B in grid}
    runs = [Run(("fig5", B), rates_of, {"texture_set": ts, "bank": banks[B], "features": tuple(features),
                                        "epochs": epochs}, estimate_cost(ts, banks[B], len(features), epochs))
            for B in grid]

    def assemble(results: dict) -> dict:
        out: dict[str, Any] = {"figure": "fig5", "texture_set": ts.name, "duration": ts.duration, "mean_B": list(grid),
               "mean_width_3db": [float(np.mean(half_power_width(banks[B].b))) for B in grid],
               "B_range": [[float(v) for v in (slaney_bandwidth(banks[B].b).min(), slaney_bandwidth(banks[B].b).max())]
                           for B in grid],
               "features": {}, "paper": PAPER_FIG5}
        for f in features:
            rs = [results[("fig5", B)]["features"][f] for B in grid]
            out["features"][f] = {"mean_rate": [r["mean_rate"] for r in rs],
                                  "per_texture": {n: [r["per_texture"][n] for r in rs] for n in ts.names}}
        out["timing"] = {"compute_seconds": sum(results[("fig5", B)]["timing"]["compute_seconds"] for B in grid)}
        return out

    return Plan(runs, assemble)
