"""Speed and error of the fast gammatone form against an earlier version of it, in one process.

    git show bccde39:supramodal/gammatone.py > /tmp/old_gammatone.py
    python3 -m supramodal.benchmarks.fastform_speed /tmp/old_gammatone.py [repeats] [bank:block ...]
    python3 -m supramodal.benchmarks.fastform_speed --errors /tmp/old_gammatone.py

The second form prints the impulse-response error (against ``reference_impulse_response``, long
double) of both versions on short blocks and mixed banks (docs/stability.md's table).

Prints, per bank, block length and dtype, the minimum time per block of each version over many
interleaved rounds (the machine may be busy: minima of interleaved rounds are what is compared)
and the ratio new / old.
"""

from __future__ import annotations

import importlib.util
import sys
import time

import numpy as np

from supramodal import gammatone as new_module
from supramodal.banks import Bank, cochlea_bank, whisker_bank

BLOCKS = (32, 441, 500, 4410)


def load(path: str):
    """Import the gammatone module at ``path`` (the earlier version) as ``old_gammatone``."""
    spec = importlib.util.spec_from_file_location("old_gammatone", path)
    assert spec is not None and spec.loader is not None, f"{path}: no module loader for this file"
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def time_per_block(fb, blocks, calls: int) -> float:
    """Seconds per block for ``calls`` consecutive blocks (one timed round)."""
    t0 = time.perf_counter()
    for i in range(calls):
        fb.process(blocks[i % len(blocks)], prepared=True)
    return (time.perf_counter() - t0) / calls


def main(argv: list[str]) -> None:
    """Print the best time per block of both versions, per bank, block length and dtype, and their ratio.

    Parameters
    ----------
    argv : list of str
        The old module's path, then optionally the rounds (default 30) and ``bank:block``
        cases to run (default all), as on the command line.
    """
    old_module = load(argv[0])
    repeats = int(argv[1]) if len(argv) > 1 else 30
    only = set(argv[2:])
    rng = np.random.default_rng(0)
    print(f"{'bank':8} {'block':>6} {'dtype':8} {'old us':>9} {'new us':>9} {'new/old':>8}")
    for name, bank in (("cochlea", cochlea_bank()), ("whisker", whisker_bank())):
        for L in BLOCKS:
            if only and f"{name}:{L}" not in only:
                continue
            for dtype in (np.float64, np.float32):
                blocks = [rng.standard_normal(L).astype(dtype) for _ in range(8)]
                fbs = {"old": old_module.GammatoneFilterbank(bank, dtype=dtype),
                       "new": new_module.GammatoneFilterbank(bank, dtype=dtype)}
                calls = max(4, 20000 // L)
                best = {k: np.inf for k in fbs}
                for fb in fbs.values():
                    time_per_block(fb, blocks, calls)                  # build plans, warm caches
                for _ in range(repeats):
                    for k, fb in fbs.items():
                        best[k] = min(best[k], time_per_block(fb, blocks, calls))
                print(f"{name:8} {L:6d} {np.dtype(dtype).name:8} {best['old'] * 1e6:9.1f} "
                      f"{best['new'] * 1e6:9.1f} {best['new'] / best['old']:8.3f}", flush=True)


ERROR_CASES = {
    "cochlea": (cochlea_bank, 15.0),
    "192 kHz, cf 86.4 kHz, b 1 Hz": (
        lambda: Bank("custom", 192000.0, np.array([86400.0]), np.array([1.0]), ("c",)), 8.0),
    "5 kHz, b 0.9 Hz beside b 49 kHz": (
        lambda: Bank("custom", 5000.0, np.array([30.0, 2000.0]), np.array([0.9, 49000.0]), ("narrow", "wide")), 15.0),
    "44.1 kHz, b 5 Hz beside b 440 kHz": (
        lambda: Bank("custom", 44100.0, np.array([1000.0, 10000.0]), np.array([5.0, 440000.0]), ("narrow", "wide")),
        15.0),
}
ERROR_BLOCKS = {"1": (1, 1), "2": (2, 2), "5": (5, 5), "32": (32, 32), "441": (441, 441), "1..5": (1, 5)}


def errors(old_module) -> None:
    """Print the worst impulse-response error of both versions against the long-double reference.

    One line per version and case of :data:`ERROR_CASES`, for each block pattern of
    :data:`ERROR_BLOCKS` (channels with ``b < fs`` only).
    """
    from supramodal.gammatone import reference_impulse_response, relative_error
    for name, (make, time_constants) in ERROR_CASES.items():
        bank = make()
        n = int(time_constants * bank.fs / (2 * np.pi * bank.b.min()))
        ref = reference_impulse_response(bank, n)
        for label, module in (("old", old_module), ("new", new_module)):
            row = []
            for block, (lo, hi) in ERROR_BLOCKS.items():
                rng = np.random.default_rng(0)
                fb = module.GammatoneFilterbank(bank)
                x = np.zeros(n)
                x[0] = 1.0
                out, i = [], 0
                while i < n:
                    s = int(rng.integers(lo, hi + 1))
                    out.append(fb.process(x[i : i + s]))
                    i += s
                y = np.concatenate(out, axis=1)
                worst = max(relative_error(y[c], ref[c]) for c in range(bank.channels) if bank.b[c] < bank.fs)
                row.append(f"{block}: {worst:.1e}")
            print(f"{label} {name} (n={n}): " + ", ".join(row), flush=True)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--errors"]:
        errors(load(sys.argv[2]))
    else:
        main(sys.argv[1:])
