"""Repeatable features after long silence: the worst difference between chunkings of one replay.

A burst of noise, 6 s of exact zeros, a second burst, through the paper's two banks in 20 random
chunkings (seeded) and in one call. The figure per bank is the worst, over chunkings, windows and
the three features, of ``max over channels |x - x_ref| / max over channels |x_ref|`` for the window
(the relative difference of a window's feature vector), with the pipeline gathering blocks and
without. ``--no-floor`` sets :data:`supramodal.peaks.PEAK_FLOOR` to 0, the behaviour before the
floor: peaks of ring-down residue (~1e-300) then depend on where blocks end.

    python -m supramodal.benchmarks.silence_repeatability [--no-floor] [--chunkings 20]
"""

from __future__ import annotations

import argparse

import numpy as np

import supramodal.peaks
from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.features import FEATURES, concat_windows
from supramodal.pipeline import FeaturePipeline


def sound_silence_sound(fs: float, silent: float = 6.0, seed: int = 3) -> np.ndarray:
    """0.5 s of noise (sd 0.3), ``silent`` seconds of exact zeros, 0.5 s of noise; shape (n,)."""
    rng = np.random.default_rng(seed)
    n = int(0.5 * fs)
    return np.concatenate([0.3 * rng.standard_normal(n), np.zeros(int(silent * fs)), 0.3 * rng.standard_normal(n)])


def window_difference(got: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per window, the relative difference of its feature vector; shapes (windows, channels)."""
    scale = np.abs(ref).max(axis=1)
    diff = np.abs(got - ref).max(axis=1)
    return np.where(scale > 0, diff / np.where(scale > 0, scale, 1.0), diff)


def worst_over_chunkings(bank, gather: bool, chunkings: int, seed: int = 11) -> tuple[float, int]:
    """``(worst relative difference, window where it is)`` over ``chunkings`` random chunkings."""
    x = sound_silence_sound(bank.fs)
    ref = FeaturePipeline(bank, gather=gather).run(x)
    rng = np.random.default_rng(seed)
    worst, where = 0.0, -1
    for _ in range(chunkings):
        top = int(rng.choice([7, 64, 441, 2000, 5000]))
        pipe = FeaturePipeline(bank, gather=gather)
        out, i = [], 0
        while i < x.size:
            step = int(rng.integers(1, top + 1))
            out.append(pipe.process(x[i:i + step]))
            i += step
        out.append(pipe.finish())
        got = concat_windows(out, FEATURES, bank.channels)
        for name in FEATURES:
            d = window_difference(got.feature(name), ref.feature(name))
            if d.max() > worst:
                worst, where = float(d.max()), int(d.argmax())
    return worst, where


def main(argv=None) -> int:
    """Print, per bank and way of gathering, the worst window difference over random chunkings; return 0."""
    p = argparse.ArgumentParser(prog="python -m supramodal.benchmarks.silence_repeatability",
                                description=__doc__.splitlines()[0])
    p.add_argument("--no-floor", action="store_true", help="measure without the peak floor (default: with it)")
    p.add_argument("--chunkings", type=int, default=20, help="random chunkings per case (default 20)")
    args = p.parse_args(argv)
    if args.no_floor:
        supramodal.peaks.PEAK_FLOOR = 0.0
    print(f"peak floor {supramodal.peaks.PEAK_FLOOR:g}; {args.chunkings} chunkings; "
          "0.5 s noise, 6 s zeros, 0.5 s noise")
    print(f"{'bank':10} {'gather':7} {'worst window difference':>24} {'at window':>10}")
    for bank in (whisker_bank(), cochlea_bank()):
        for gather in (True, False):
            worst, where = worst_over_chunkings(bank, gather, args.chunkings)
            print(f"{bank.kind:10} {str(gather):7} {worst:24.2e} {where:10d}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
