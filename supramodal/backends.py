"""Filterbank backends behind one interface: the plain reference and the fast exact form.

Every backend is a :class:`~supramodal.gammatone.FilterbankBase`: built from a
bank, a dtype and a non-finite policy; ``process(block) -> (channels, L)``,
``reset()``, ``impulse_response(n)``, the counters ``samples_processed``,
``nonfinite_count`` and ``out_of_range_count``, and the input range ``max_input``
(the same for every backend of a bank and dtype: samples beyond it are refused or
replaced and counted, as NaN are). Make one with :func:`make_filterbank`.

* ``"fast"``: :class:`~supramodal.gammatone.GammatoneFilterbank`, the block
  state-space form (every channel in a few matrix products), float64 or float32.
* ``"reference"``: :class:`ReferenceFilterbank`, simple and obviously right,
  slow: per channel, the complex pole filter ``(p z^-1 + 4 p^2 z^-2 + p^3 z^-3) /
  (1 - p z^-1)^4`` as four first-order sections run by ``scipy.signal.lfilter``
  with their states carried from block to block. float64 only. It is the ground
  truth for the error figures of long streams (docs/bench), where convolving with
  the analytic impulse response would cost too much. Its sections stay below
  ``state_gain`` times the input (about 2), so alone it could take inputs up to
  ~1e307; it is held to the fast form's ``max_input`` (~7e219) so that both accept
  the same streams.
"""

from __future__ import annotations

import numpy as np

from supramodal.banks import Bank
from supramodal.errors import InputError
from supramodal.gammatone import FilterbankBase, GammatoneFilterbank, gain_at_cf, pole_powers

BACKENDS = ("fast", "reference")


class ReferenceFilterbank(FilterbankBase):
    """Per channel, ``Re`` of the complex filter ``g (p z^-1 + 4 p^2 z^-2 + p^3 z^-3) / (1 - p z^-1)^4``.

    Its impulse response is exactly ``g Re(n**3 p**n)``, the sampled gammatone
    normalised at ``fc`` (``g = 1 / gain_at_cf``). The numerator and the first
    pole go in one ``lfilter`` call, the three other poles in one call each: four
    calls per channel per block, every section a first-order recursion (well
    conditioned, unlike the direct form of the fourfold pole). float64 only.
    """

    backend = "reference"

    def __init__(self, bank: Bank, dtype=np.float64, nonfinite: str = "raise") -> None:
        if np.dtype(dtype) != np.float64:
            raise InputError(f"the reference backend is float64 only, got dtype {np.dtype(dtype)}")
        super().__init__(bank, dtype, nonfinite)
        p = pole_powers(bank, np.arange(4.0))                      # p**0 .. p**3, (C, 4)
        g = 1.0 / gain_at_cf(bank)
        self._num = [np.array([0.0, g[c] * p[c, 1], 4 * g[c] * p[c, 2], g[c] * p[c, 3]]) for c in range(bank.channels)]
        self._den = [np.array([1.0, -p[c, 1]]) for c in range(bank.channels)]
        self.reset()

    def reset(self) -> None:
        """Return to rest: zero every channel's filter delays, as if no sample had been seen."""
        # Per channel: the numerator section's 3 delays, then one delay per further pole.
        self._zi = [[np.zeros(3, complex), np.zeros(1, complex), np.zeros(1, complex), np.zeros(1, complex)]
                    for _ in range(self.channels)]

    def _fresh(self) -> ReferenceFilterbank:
        return ReferenceFilterbank(self.bank)

    def _filter(self, x: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        from scipy.signal import lfilter  # here: scipy.signal takes 0.6 s to import, and the fast form needs none

        C, L = self.channels, x.shape[-1]
        y = np.empty((C, L)) if out is None else out
        one = np.ones(1)
        for c in range(C):
            xc = x if x.ndim == 1 else x[c]
            zi = self._zi[c]
            s, zi[0] = lfilter(self._num[c], self._den[c], xc.astype(complex), zi=zi[0])
            for k in (1, 2, 3):
                s, zi[k] = lfilter(one, self._den[c], s, zi=zi[k])
            y[c] = s.real
        return y


def make_filterbank(bank: Bank, backend: str = "fast", dtype=np.float64, nonfinite: str = "raise",
                    **kwargs) -> FilterbankBase:
    """Return a filterbank of the named backend (``"fast"`` or ``"reference"``).

    ``kwargs`` go to the backend (``subblock`` for the fast form).
    """
    if backend == "fast":
        return GammatoneFilterbank(bank, dtype=dtype, nonfinite=nonfinite, **kwargs)
    if backend == "reference":
        if kwargs:
            raise InputError(f"the reference backend takes no options, got {sorted(kwargs)}")
        return ReferenceFilterbank(bank, dtype=dtype, nonfinite=nonfinite)
    raise InputError(f"unknown filterbank backend {backend!r}; backends are {', '.join(BACKENDS)}")
