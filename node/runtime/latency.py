"""Decision latencies in constant memory: a log-spaced histogram, exact count and maximum.

The node records one latency per window, for as long as it runs (a week at 10 windows/s is
six million). Keeping them all grows memory without bound; this keeps a fixed histogram whose
bins are 1 % wide, so a percentile read from it is within 1 % of the exact one (the maximum and
the count are exact). Not thread-safe: the node's processing thread owns it.
"""

from __future__ import annotations

import math

import numpy as np

from supramodal.errors import InputError

__all__ = ["LatencyHistogram"]


class LatencyHistogram:
    """Latencies in milliseconds, counted in log-spaced bins of relative width ``resolution``.

    Parameters
    ----------
    low_ms, high_ms : float
        Range of the bins (default 1 us .. 1000 s); a value below or above lands in the first or
        last bin (its percentile then reads as the bin's edge; the maximum stays exact).
    resolution : float
        Relative width of a bin (default 0.01): percentiles are within this of the exact ones.
    """

    def __init__(self, low_ms: float = 1e-3, high_ms: float = 1e6, resolution: float = 0.01) -> None:
        self._log_low = math.log(low_ms)
        self._step = math.log1p(resolution)
        n = int(math.ceil((math.log(high_ms) - self._log_low) / self._step)) + 1
        self._counts = np.zeros(n, dtype=np.int64)
        self.count = 0
        self.max = -math.inf

    def add(self, ms: float) -> None:
        """Count one latency (milliseconds; 0 or negative counts in the first bin)."""
        i = 0 if ms <= 0 else int((math.log(ms) - self._log_low) / self._step)
        self._counts[min(max(i, 0), self._counts.size - 1)] += 1
        self.count += 1
        self.max = max(self.max, ms)

    def percentile(self, q: float) -> float:
        """Return the ``q``-th percentile (0..100), ms, as numpy's ``method="lower"``, to within ``resolution``.

        numpy's ``"lower"`` is the recorded value at rank ``floor(q/100 (count - 1))``; the value returned
        is the geometric centre of the bin holding it, at most the maximum.
        """
        if not self.count:
            raise InputError("no latency recorded: a percentile needs at least one")
        rank = q / 100 * (self.count - 1)
        i = int(np.searchsorted(np.cumsum(self._counts), math.floor(rank) + 1))
        return min(math.exp(self._log_low + (i + 0.5) * self._step), self.max)

    def summary(self) -> dict[str, float] | None:
        """``{"p50", "p99", "max", "count"}`` in ms, or None with no latency recorded."""
        if not self.count:
            return None
        return {"p50": self.percentile(50), "p99": self.percentile(99), "max": self.max, "count": self.count}
