"""``supramodal bench``: error against run time, drift over long streams, the whole node.

Benchmark code, not a product path: the peer designs live in
:mod:`supramodal.benchmarks.filterbank.peers` and nowhere else. Three parts:

a. every filterbank backend (fast float64 and float32, reference float64) and
   peer (scipy.signal.gammatone 'iir' + lfilter, Slaney's cascade + sosfilt, in
   float64 and float32) x block size x bank: real-time factor on one core and
   maximum relative error against the float64 reference, with the Pareto front;
b. deviation from the reference after 1 s, 1 min, 10 min and 60 min of stream;
c. the whole node: pipeline to decisions per backend (real-time factor, decisions'
   agreement with the float64 reference), and the threaded node itself.

Run it with ``supramodal bench [--quick] [--out DIR] [--json]``: the command runs
``python -m supramodal.benchmarks.filterbank`` in a child process with BLAS and OpenMP pinned to
one thread (``python -m supramodal.benchmarks.filterbank`` re-executes itself so pinned if they
are not).
"""

from supramodal.benchmarks import PINNED_THREADS

__all__ = ["PINNED_THREADS"]
