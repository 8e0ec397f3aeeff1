"""Fig. 6: mean classification rate (Af) against the number of channels, cochlea and whiskers.

* Cochlea: ``cochlea_bank(n=N)``, N channels ERB-spaced (Slaney) over 20 Hz..20 kHz, so fewer
  channels cover the same range more sparsely; cochlea reference set (Fig. 3b).
* Whiskers: whole rows of four vibrissae added in the order A, AB, ABC, ABCD, ABCDE (the
  paper's "arc by arc", MODEL-NOTES section 2); whisker reference set (Fig. 3a); default bandwidths.

The full cochlear grid is every N from 1 to 20, where the rate moves, then every 5 channels
to 60, where it has long saturated: 28 banks instead of 60, which would more than double
the cost of ``experiment all`` (a 60-channel run costs as much as the 1..10 runs together).
"""

from __future__ import annotations

from supramodal.banks import WHISKER_ROWS, Bank
from supramodal.experiments.common import Plan, Run, default_bank, estimate_cost, quick_set, rates_of
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.textures import reference_texture_set

COCHLEA_GRID = tuple(range(1, 21)) + tuple(range(25, 61, 5))
QUICK_COCHLEA_GRID = (1, 3, 10)
#: Whisker groups, cumulative rows in this order.
WHISKER_GROUPS = tuple("".join(WHISKER_ROWS[: k + 1]) for k in range(len(WHISKER_ROWS)))
FEATURE = "Af"
THRESHOLD = 0.80
PAPER_FIG6 = "over 80 % from 20 cochlear channels and from 2 whisker groups (Af)"


def first_at_or_above(xs, rates, threshold: float = THRESHOLD):
    """Smallest x from which every rate is >= threshold (None if the last one is below)."""
    best = None
    for x, r in zip(reversed(xs), reversed(rates)):
        if r < threshold:
            break
        best = x
    return best


def plan(quick: bool = False, epochs: int = DEFAULT_EPOCHS, cochlea_grid=None, **_) -> Plan:
    """One run per cochlear bank size and per whisker group, Af only."""
    grid = tuple(int(n) for n in (cochlea_grid or (QUICK_COCHLEA_GRID if quick else COCHLEA_GRID)))
    sets = {b: quick_set(reference_texture_set(b), quick) for b in ("cochlea", "whisker")}
    banks: dict[tuple[str, str, int | str], Bank] = {("fig6", "cochlea", n): default_bank(sets["cochlea"], n=n)
                                                     for n in grid}
    banks.update({("fig6", "whisker", g): default_bank(sets["whisker"], rows=g) for g in WHISKER_GROUPS})
    runs = [Run(key, rates_of, {"texture_set": sets[key[1]], "bank": bank, "features": (FEATURE,), "epochs": epochs},
                estimate_cost(sets[key[1]], bank, 1, epochs)) for key, bank in banks.items()]

    def assemble(results: dict) -> dict:
        rate = lambda key: results[key]["features"][FEATURE]["mean_rate"]
        coch = [rate(("fig6", "cochlea", n)) for n in grid]
        whisk = [rate(("fig6", "whisker", g)) for g in WHISKER_GROUPS]
        return {
            "figure": "fig6", "feature": FEATURE, "threshold": THRESHOLD, "paper": PAPER_FIG6,
            "cochlea": {"texture_set": sets["cochlea"].name, "duration": sets["cochlea"].duration,
                        "channels": list(grid), "mean_rate": coch,
                        "first_at_or_above_threshold": first_at_or_above(grid, coch)},
            "whisker": {"texture_set": sets["whisker"].name, "duration": sets["whisker"].duration,
                        "rows": list(WHISKER_GROUPS), "groups": list(range(1, len(WHISKER_GROUPS) + 1)),
                        "channels": [4 * len(g) for g in WHISKER_GROUPS], "mean_rate": whisk,
                        "first_at_or_above_threshold": first_at_or_above(range(1, len(whisk) + 1), whisk)},
            "timing": {"compute_seconds": sum(r["timing"]["compute_seconds"] for r in results.values())},
        }

    return Plan(runs, assemble)
