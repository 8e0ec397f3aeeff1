"""Tables, CSV files and plots of experiment results. matplotlib is optional (extra ``plots``)."""

from __future__ import annotations

import csv
from pathlib import Path

from supramodal.experiments.fig3 import PAPER_FIG3


def have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def fig3_table(result: dict) -> str:
    """Per-texture and mean rates of each feature, beside the paper's means."""
    feats = list(result["features"])
    names = list(result["features"][feats[0]]["per_texture"])
    lines = [f"Fig. 3, {result['bank']} bank, {result['texture_set']}",
             f"{'texture':<10}" + "".join(f"{f:>9}" for f in feats)]
    for n in names:
        lines.append(f"{n:<10}" + "".join(f"{result['features'][f]['per_texture'][n]:>9.3f}" for f in feats))
    lines.append(f"{'mean':<10}" + "".join(f"{result['features'][f]['mean_rate']:>9.3f}" for f in feats))
    if any("sd" in result["features"][f] for f in feats):
        lines.append(f"{'sd':<10}" + "".join(f"{result['features'][f].get('sd', 0.0):>9.3f}" for f in feats))
    paper = PAPER_FIG3.get(result["bank"], {})
    lines.append(f"{'paper':<10}" + "".join(f"{paper.get(f, float('nan')):>9.3f}" for f in feats))
    t = result.get("timing")
    if t and t.get("signal_seconds"):
        lines.append(f"pipeline compute: {t['compute_seconds']:.2f} s for {t['signal_seconds']:.0f} s of signal "
                     f"({t['compute_seconds'] / t['signal_seconds']:.4f} s per s)")
    return "\n".join(lines)


def write_fig3(result: dict, out: Path) -> list[Path]:
    """Write ``fig3_<bank>.csv`` (and ``.png`` where matplotlib is installed) into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    feats = list(result["features"])
    names = list(result["features"][feats[0]]["per_texture"])
    csv_path = out / f"fig3_{result['bank']}.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["bank", "feature", "texture", "rate"])
        for f in feats:
            for n in names:
                w.writerow([result["bank"], f, n, f"{result['features'][f]['per_texture'][n]:.4f}"])
            w.writerow([result["bank"], f, "mean", f"{result['features'][f]['mean_rate']:.4f}"])
            if "sd" in result["features"][f]:
                w.writerow([result["bank"], f, "sd", f"{result['features'][f]['sd']:.4f}"])
    written = [csv_path]
    if have_matplotlib():
        written.append(_plot_fig3(result, out / f"fig3_{result['bank']}.png"))
    return written


def _plot_fig3(result: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    feats = list(result["features"])
    names = list(result["features"][feats[0]]["per_texture"])
    fig, ax = plt.subplots(figsize=(8, 3.6))
    width = 0.8 / len(feats)
    shades = {"Af": "0.25", "A": "0.55", "f": "0.8"}
    for k, f in enumerate(feats):
        rates = [result["features"][f]["per_texture"][n] for n in names]
        ax.bar(np.arange(len(names)) + (k - (len(feats) - 1) / 2) * width, rates, width,
               color=shades.get(f, None), edgecolor="k", linewidth=0.5,
               label=f"{f} (mean {result['features'][f]['mean_rate']:.2f})")
    ax.axhline(1 / len(names), color="r", linestyle=":", linewidth=1, label="chance")
    ax.set_xticks(range(len(names)), names)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("classification rate")
    ax.set_title(f"Fig. 3, {result['bank']} bank: {result['texture_set']}")
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
