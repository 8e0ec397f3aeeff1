"""Fit a bank, a window and features to a user's own recordings by grouped cross-validation.

``supramodal fit MANIFEST``: the bank's fit to the sensor and the window matter more than
anything else (a fingertip sensor at 2.2 kHz scores 38 % of windows on the whisker bank and 57 %
on the cochlea's denser low channels). This module sweeps, one parameter at a time from a base
and keeping the best value of each before the next (coordinate search: a plot per parameter,
and tens of cross-validations instead of thousands):

1. channels of an ERB-spaced gammatone bank at the recordings' own rate (no resampling),
2. the band's top and 3. bottom edge, 4. the bandwidth scale (every ``b`` times a factor),
5. the window, 6. the features (A, f, Af, all three),

each candidate scored by :func:`node.workflows.training.cross_validate_manifest` (folds by recording,
seeded: the fit is deterministic given its seed). The paper's whisker and cochlea banks (their
rates, the recordings resampled) are scored with the same window and features, for comparison.
Candidates of one step run in parallel processes.
"""

from __future__ import annotations

import csv
import warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from supramodal.bankfile import bank_from_description, save_bank
from supramodal.banks import Bank, cochlea_bank, whisker_bank
from supramodal.node.scene.band import BandWarning, channels_beyond_band
from supramodal.node.workflows.manifest import manifest_classes, read_manifest
from supramodal.node.workflows.reports import pyplot_or_none
from supramodal.node.workflows.training import cross_validate_manifest
from supramodal.replay.session import session_paths
from supramodal.replay.wavio import wav_info

__all__ = ["Candidate", "fit_manifest", "format_fit", "write_fit"]

#: The values each step tries (quick mode: the shorter lists), as (name, full, quick). ``name`` is a field of
#: :class:`Candidate` and its values are of that field's type, which differs from step to step (Any, not a union
#: every field would have to accept, so that ``replace(best, **{name: v})`` type-checks).
STEPS: tuple[tuple[str, tuple[Any, ...], tuple[Any, ...]], ...] = (
    ("channels", (10, 20, 30, 50), (10, 20)),
    ("f_high", (0.5, 0.7, 0.9), (0.5, 0.9)),          # fraction of the Nyquist frequency
    ("f_low", (0.001, 0.005, 0.02, 0.1), (0.005, 0.05)),   # fraction of the Nyquist frequency
    ("b_scale", (0.5, 1.0, 2.0), (0.5, 1.0, 2.0)),
    ("window", (0.05, 0.1, 0.2, 0.4), (0.1, 0.4)),    # seconds
    ("features", (("A",), ("f",), ("Af",), ("A", "f", "Af")), (("Af",), ("A", "f", "Af"))),
)


@dataclass(frozen=True)
class Candidate:
    """One setting: an ERB-spaced bank at ``fs`` and the pipeline's window and features."""

    fs: float
    channels: int = 20
    f_high: float = 0.9
    f_low: float = 0.02
    b_scale: float = 1.0
    window: float = 0.1
    features: tuple = ("Af",)

    def bank(self) -> Bank:
        """Return the candidate's bank: ``channels`` ERB-spaced filters at ``fs``, bandwidths scaled by ``b_scale``.

        ``f_low`` and ``f_high`` are fractions of the Nyquist frequency.
        """
        nyquist = self.fs / 2
        base = bank_from_description({"kind": "cochlea", "channels": self.channels, "f_low": self.f_low * nyquist,
                                      "f_high": self.f_high * nyquist, "fs": self.fs}, "fit")
        return Bank("custom", self.fs, base.cf, base.b * self.b_scale, base.names)


def _recording_rate(path: Path) -> int:
    wav = path if path.suffix.lower() == ".wav" else session_paths(path)[0]
    return wav_info(wav).rate


def _score(job):
    manifest, bank, window, features, k, epochs, seed, mapping = job
    with warnings.catch_warnings():
        # The paper's banks may reach above the recordings' band: format_fit says so once.
        warnings.simplefilter("ignore", BandWarning)
        r = cross_validate_manifest(manifest, bank, features, window, k, epochs=epochs, seed=seed, mapping=mapping)
    return {"window_accuracy": r["window_accuracy"], "recording_accuracy": r["recording_accuracy"]}


def fit_manifest(manifest, k: int = 5, epochs: int = 300, seed: int = 0, quick: bool = False, jobs: int = 1,
                 mapping="auto", progress=None) -> dict:
    """Sweep the settings (module docstring) on the manifest's recordings.

    Returns
    -------
    dict
        ``fs`` (the recordings' rate), ``rows`` (every candidate: step, value, window and
        recording accuracy mean and sd), ``best`` (the :class:`Candidate`'s fields and its
        scores), ``paper`` (the whisker and cochlea banks' scores with the best window and
        features).
    """
    recs = read_manifest(manifest)
    manifest_classes(recs, manifest)
    rates = sorted({_recording_rate(r.path) for r in recs})
    if len(rates) > 1 and progress:
        progress(f"fit: recordings at {rates} Hz; the banks run at {rates[-1]} Hz, the others resampled")
    best = Candidate(fs=float(rates[-1]))
    rows: list[dict] = []
    best_score = None

    def run(candidates_banks):
        batch = [(manifest, bank, c.window, c.features, k, epochs, seed, mapping) for c, bank in candidates_banks]
        if jobs > 1:
            with ProcessPoolExecutor(max_workers=jobs) as pool:
                return list(pool.map(_score, batch))
        return [_score(job) for job in batch]

    for name, full, short in STEPS:
        values = short if quick else full
        candidates = [replace(best, **{name: v}) for v in values]
        scores = run([(c, c.bank()) for c in candidates])
        for c, s in zip(candidates, scores):
            rows.append({"step": name, "value": getattr(c, name), **_flat(s)})
            if progress:
                progress(f"fit: {name} = {getattr(c, name)}: windows {s['window_accuracy']['mean']:.3f} "
                         f"+- {s['window_accuracy']['sd']:.3f}")
        i = max(range(len(scores)), key=lambda j: (scores[j]["window_accuracy"]["mean"],
                                                   scores[j]["recording_accuracy"]["mean"], -j))
        best, best_score = candidates[i], scores[i]
    paper = {}
    for label, bank in (("whisker", whisker_bank()), ("cochlea", cochlea_bank())):
        s = run([(best, bank)])[0]
        paper[label] = {**_flat(s), "beyond_band": int(channels_beyond_band(bank, min(rates)).size),
                        "channels": bank.channels}
        if progress:
            progress(f"fit: the paper's {label} bank: windows {s['window_accuracy']['mean']:.3f}")
    assert best_score is not None, "STEPS is not empty and each step sets best_score"
    return {"fs": best.fs, "k": k, "seed": seed, "rows": rows,
            "best": {**best.__dict__, "features": list(best.features), **_flat(best_score)}, "paper": paper}


def _flat(score: dict) -> dict:
    return {"window_mean": score["window_accuracy"]["mean"], "window_sd": score["window_accuracy"]["sd"],
            "recording_mean": score["recording_accuracy"]["mean"], "recording_sd": score["recording_accuracy"]["sd"]}


def format_fit(result: dict) -> str:
    """Return a fit's result as text: each step's value and accuracies, the best setting, the paper's banks.

    Accuracies are means +- standard deviations over the folds, per window and per recording; a paper's
    bank with channels above the recordings' band says how many.
    """
    b = result["best"]
    lines = [f"fit by grouped {result['k']}-fold cross-validation (seed {result['seed']}), "
             f"banks at {result['fs']:g} Hz",
             f"{'step':<10}{'value':>22}{'windows':>16}{'recordings':>16}"]
    for r in result["rows"]:
        value = "+".join(r["value"]) if isinstance(r["value"], tuple) else f"{r['value']:g}"
        lines.append(f"{r['step']:<10}{value:>22}{r['window_mean']:>9.3f} +-{r['window_sd']:.3f}"
                     f"{r['recording_mean']:>9.3f} +-{r['recording_sd']:.3f}")
    lines += ["", f"best: {b['channels']} channels, {b['f_low'] * result['fs'] / 2:g} .. "
                  f"{b['f_high'] * result['fs'] / 2:g} Hz, bandwidths x{b['b_scale']:g}, window {b['window']:g} s, "
                  f"features {'+'.join(b['features'])}: windows {b['window_mean']:.3f} +- {b['window_sd']:.3f}, "
                  f"recordings {b['recording_mean']:.3f} +- {b['recording_sd']:.3f}"]
    for name, p in result["paper"].items():
        empty = f"; {p['beyond_band']} of its {p['channels']} channels lie above the recordings' band" \
            if p["beyond_band"] else ""
        lines.append(f"the paper's {name} bank (same window, features): windows {p['window_mean']:.3f} +- "
                     f"{p['window_sd']:.3f}, recordings {p['recording_mean']:.3f} +- {p['recording_sd']:.3f}{empty}")
    return "\n".join(lines)


def write_fit(result: dict, folder: Path) -> list[Path]:
    """Write a fit's result into ``folder`` and return the files written.

    ``fit.csv`` (every candidate), ``bank.json`` (the best bank, for ``train --bank``) and, where
    matplotlib is installed, ``fit.png`` (accuracy against each parameter).
    """
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "fit.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["step", "value", "window_mean", "window_sd", "recording_mean", "recording_sd"])
        for r in result["rows"]:
            value = "+".join(r["value"]) if isinstance(r["value"], tuple) else r["value"]
            w.writerow([r["step"], value, r["window_mean"], r["window_sd"], r["recording_mean"], r["recording_sd"]])
    fields = {f: result["best"][f] for f in Candidate.__dataclass_fields__}
    best = Candidate(**{**fields, "features": tuple(fields["features"])})
    written = [folder / "fit.csv", save_bank(folder / "bank.json", best.bank())]
    plt = pyplot_or_none()
    if plt is None:
        return written
    steps = [s for s, _, _ in STEPS]
    fig, axes = plt.subplots(1, len(steps), figsize=(3 * len(steps), 3), sharey=True)
    for ax, step in zip(axes, steps):
        rows = [r for r in result["rows"] if r["step"] == step]
        labels = ["+".join(r["value"]) if isinstance(r["value"], tuple) else f"{r['value']:g}" for r in rows]
        x = np.arange(len(rows))
        ax.errorbar(x, [r["window_mean"] for r in rows], yerr=[r["window_sd"] for r in rows], fmt="o-", color="0.2",
                    capsize=3)
        ax.set_xticks(x, labels, rotation=45, fontsize=8)
        ax.set_title(step, fontsize=9)
    axes[0].set_ylabel("window accuracy (grouped CV)")
    for name, p in result["paper"].items():
        for ax in axes:
            ax.axhline(p["window_mean"], color="0.6", linestyle=":" if name == "whisker" else "--", linewidth=1)
    fig.suptitle("dotted: the paper's whisker bank, dashed: its cochlea (same window and features)", fontsize=9)
    fig.tight_layout()
    fig.savefig(folder / "fit.png", dpi=110)
    plt.close(fig)
    return written + [folder / "fit.png"]

