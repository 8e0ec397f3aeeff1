"""A confusion matrix as files a user opens: CSV always, PNG where matplotlib is installed (extra ``plots``)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

__all__ = ["write_confusion"]


def write_confusion(labels, confusion, base: Path, title: str) -> list[Path]:
    """Write ``base.csv`` (counts; rows = truth, columns = predicted) and ``base.png`` (each row as
    shares of its windows, so a rare label reads as clearly as a common one).

    Returns the paths written (the PNG only where matplotlib can be imported).
    """
    counts = np.asarray(confusion, dtype=int)
    csv_path = base.with_name(base.name + ".csv")
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["truth \\ predicted", *labels])
        for name, row in zip(labels, counts):
            w.writerow([name, *row.tolist()])
    written = [csv_path]
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return written
    shares = counts / np.maximum(counts.sum(axis=1, keepdims=True), 1)
    n = len(labels)
    fig, ax = plt.subplots(figsize=(1.2 + 0.55 * n, 1.0 + 0.5 * n))
    ax.imshow(shares, cmap="Greys", vmin=0, vmax=1)
    for i in range(n):
        for j in range(n):
            ax.text(j, i, f"{shares[i, j]:.2f}", ha="center", va="center", fontsize=8,
                    color="white" if shares[i, j] > 0.5 else "black")
    ax.set_xticks(range(n), labels, rotation=45, ha="right")
    ax.set_yticks(range(n), labels)
    ax.set_xlabel("predicted")
    ax.set_ylabel("truth")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    png_path = base.with_name(base.name + ".png")
    fig.savefig(png_path, dpi=120)
    plt.close(fig)
    return written + [png_path]
