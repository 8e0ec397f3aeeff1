"""``python -m supramodal.benchmarks.filterbank``: re-executes itself with one BLAS/OpenMP thread, then runs."""

import os
import sys

from supramodal.benchmarks.filterbank import PINNED_THREADS

if __name__ == "__main__":
    if any(os.environ.get(k) != v for k, v in PINNED_THREADS.items()):
        os.execve(sys.executable, [sys.executable, "-m", "supramodal.benchmarks.filterbank", *sys.argv[1:]],
                  {**os.environ, **PINNED_THREADS})
    from supramodal.benchmarks.filterbank.run import main

    sys.exit(main())
