"""Speed of the fast gammatone form against an earlier version of it, interleaved in one process.

    git show bccde39:supramodal/gammatone.py > /tmp/old_gammatone.py
    python3 -m benchmarks.fastform_speed /tmp/old_gammatone.py [repeats] [bank:block ...]

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
from supramodal.banks import cochlea_bank, whisker_bank

BLOCKS = (32, 441, 500, 4410)


def load(path: str):
    spec = importlib.util.spec_from_file_location("old_gammatone", path)
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


if __name__ == "__main__":
    main(sys.argv[1:])
