"""What every experiment writes its results with: CSV rows, and PNG figures where matplotlib can be imported.

matplotlib is the extra ``plots``. The experiments use it, and :mod:`supramodal.experiments.report` (which
dispatches to them) too, so that neither imports the other for it.
"""

from __future__ import annotations

import csv
from pathlib import Path

from supramodal.interrupts import import_optional

__all__ = ["have_matplotlib", "pyplot", "save_figure", "write_csv"]


def have_matplotlib() -> bool:
    """Whether matplotlib can be imported (imported with Ctrl-C held: see :mod:`supramodal.interrupts`)."""
    return import_optional("matplotlib") is not None


def pyplot():
    """matplotlib.pyplot on the file backend (Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> Path:
    """Save at 110 dpi as a palette PNG (64 colours: the plots are line art; a tenth of the size)."""
    import io

    import matplotlib.pyplot as plt
    from PIL import Image

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, dpi=110, format="png")
    plt.close(fig)
    buf.seek(0)
    with Image.open(buf) as im:
        im.convert("RGB").quantize(colors=64).save(path, format="PNG", optimize=True)
    return path


def write_csv(path: Path, header, rows) -> Path:
    """Write ``rows`` under ``header`` to ``path`` as CSV (floats to 6 significant digits, None empty)."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for row in rows:
            w.writerow(["" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for v in row])
    return path
