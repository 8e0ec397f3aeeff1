"""``python -m supramodal.benchmarks.filterbank``: re-executes itself with one BLAS/OpenMP thread, then runs."""

import sys

from supramodal.benchmarks import run_pinned

if __name__ == "__main__":
    run_pinned("supramodal.benchmarks.filterbank")
    from supramodal.benchmarks.filterbank.run import main

    sys.exit(main())
