"""The usual gammatone designs, streamed the usual way: benchmark peers only, never a product path.

Both take one scipy call per channel per block with the filter state carried
from block to block, which is how code built on detly's ``gammatone`` package or
on brian2hears-style cascades streams a filterbank:

* ``"scipy-iir"``: ``scipy.signal.gammatone(cf, 'iir', fs=fs)``, an 8th-order
  ``(b, a)`` run by ``scipy.signal.lfilter``. scipy derives the bandwidth from
  ``cf`` itself (``1.019 * (cf / 9.26449 + 24.7)``, the cochlea's); for a bank with
  other bandwidths (the whiskers) the same formulas are evaluated with the bank's
  ``b`` (:func:`scipy_iir_design`, checked equal to scipy's output where the
  bandwidths agree).
* ``"slaney"``: Slaney's four-biquad cascade (Apple TR #35, 1993; MakeERBFilters
  and ERBFilterBank of the Auditory Toolbox), run by ``scipy.signal.sosfilt``.

float32 peers round their coefficients and run their recursions in float32, as a
float32 user of these designs would.
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Callable

import numpy as np
from scipy.signal import gammatone, lfilter, sosfilt

from supramodal.banks import Bank
from supramodal.errors import InputError
from supramodal.gammatone import FilterbankBase

PEERS = ("scipy-iir", "slaney")


def scipy_iir_design(cf: float, b: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """scipy.signal.gammatone's 'iir' formulas with the bandwidth parameter ``b`` (Hz) given."""
    T = 1.0 / fs
    bw = 2 * math.pi * b
    fr = 2 * cf * math.pi * T
    bwT = bw * T
    g1 = -2 * cmath.exp(2j * fr) * T
    g2 = 2 * cmath.exp(-bwT + 1j * fr) * T
    g3 = math.sqrt(3 + 2 ** (3 / 2)) * math.sin(fr)
    g4 = math.sqrt(3 - 2 ** (3 / 2)) * math.sin(fr)
    g5 = cmath.exp(2j * fr)
    g = g1 + g2 * (math.cos(fr) - g4)
    g *= g1 + g2 * (math.cos(fr) + g4)
    g *= g1 + g2 * (math.cos(fr) - g3)
    g *= g1 + g2 * (math.cos(fr) + g3)
    g /= (-2 / math.exp(2 * bwT) - 2 * g5 + 2 * (1 + g5) / math.exp(bwT)) ** 4
    g = abs(g)
    num = [T**4 / g,
           -4 * T**4 * math.cos(fr) / math.exp(bwT) / g,
           6 * T**4 * math.cos(2 * fr) / math.exp(2 * bwT) / g,
           -4 * T**4 * math.cos(3 * fr) / math.exp(3 * bwT) / g,
           T**4 * math.cos(4 * fr) / math.exp(4 * bwT) / g]
    den = [1.0,
           -8 * math.cos(fr) / math.exp(bwT),
           4 * (4 + 3 * math.cos(2 * fr)) / math.exp(2 * bwT),
           -8 * (6 * math.cos(fr) + math.cos(3 * fr)) / math.exp(3 * bwT),
           2 * (18 + 16 * math.cos(2 * fr) + math.cos(4 * fr)) / math.exp(4 * bwT),
           -8 * (6 * math.cos(fr) + math.cos(3 * fr)) / math.exp(5 * bwT),
           4 * (4 + 3 * math.cos(2 * fr)) / math.exp(6 * bwT),
           -8 * math.cos(fr) / math.exp(7 * bwT),
           math.exp(-8 * bwT)]
    return np.array(num), np.array(den)


def scipy_uses_bank_bandwidths(bank: Bank) -> bool:
    """Tell whether scipy's own ERB gives the bank's ``b`` (so scipy's function is called as is)."""
    return bool(np.allclose(1.019 * (bank.cf / 9.26449 + 24.7), bank.b, rtol=1e-12, atol=0))


def slaney_sos(cf: float, b: float, fs: float) -> np.ndarray:
    """Slaney's MakeERBFilters for one channel as 4 second-order sections (unit gain at cf).

    ``B = 2 pi b`` (MakeERBFilters' ``1.019 * 2 pi * ERB``), ``T = 1 / fs``.
    """
    T = 1.0 / fs
    B = 2 * math.pi * b
    arg = 2 * cf * math.pi * T
    c, s, e = math.cos(arg), math.sin(arg), math.exp(B * T)
    r3p, r3m = math.sqrt(3 + 2**1.5), math.sqrt(3 - 2**1.5)
    A0, A2, B0 = T, 0.0, 1.0
    B1 = -2 * c / e
    B2 = math.exp(-2 * B * T)
    A11 = -(2 * T * c / e + 2 * r3p * T * s / e) / 2
    A12 = -(2 * T * c / e - 2 * r3p * T * s / e) / 2
    A13 = -(2 * T * c / e + 2 * r3m * T * s / e) / 2
    A14 = -(2 * T * c / e - 2 * r3m * T * s / e) / 2
    z4 = cmath.exp(4j * cf * math.pi * T)
    z2 = cmath.exp(-(B * T) + 2j * cf * math.pi * T)
    gain = abs((-2 * z4 * T + 2 * z2 * T * (c - r3m * s))
               * (-2 * z4 * T + 2 * z2 * T * (c + r3m * s))
               * (-2 * z4 * T + 2 * z2 * T * (c - r3p * s))
               * (-2 * z4 * T + 2 * z2 * T * (c + r3p * s))
               / (-2 / math.exp(2 * B * T) - 2 * z4 + 2 * (1 + z4) / e) ** 4)
    return np.array([
        [A0 / gain, A11 / gain, A2 / gain, B0, B1, B2],
        [A0, A12, A2, B0, B1, B2],
        [A0, A13, A2, B0, B1, B2],
        [A0, A14, A2, B0, B1, B2],
    ])


class _PerChannelPeer(FilterbankBase):
    """One scipy call per channel per block, state carried: ``_call(c, x) -> y``."""

    _call: Callable[[int, np.ndarray], np.ndarray]     # each peer's own (a method)

    def __init__(self, bank: Bank, dtype=np.float64, nonfinite: str = "raise") -> None:
        super().__init__(bank, dtype, nonfinite)
        self.reset()

    def _fresh(self):
        return type(self)(self.bank, self.dtype)

    def _filter(self, x: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        y = np.empty((self.channels, x.shape[-1]), dtype=self.dtype) if out is None else out
        for c in range(self.channels):
            y[c] = self._call(c, x if x.ndim == 1 else x[c])
        return y


class ScipyGammatonePeer(_PerChannelPeer):
    """scipy.signal.gammatone(cf, 'iir', fs) + lfilter, per channel, state carried."""

    backend = "scipy-iir"

    def __init__(self, bank: Bank, dtype=np.float64, nonfinite: str = "raise") -> None:
        if scipy_uses_bank_bandwidths(bank):
            designs = [gammatone(float(cf), "iir", fs=bank.fs) for cf in bank.cf]
        else:
            designs = [scipy_iir_design(float(cf), float(b), bank.fs) for cf, b in zip(bank.cf, bank.b)]
        dt = np.dtype(dtype)
        self._ba = [(np.asarray(b, dtype=dt), np.asarray(a, dtype=dt)) for b, a in designs]
        super().__init__(bank, dtype, nonfinite)

    def reset(self) -> None:
        """Zero every channel's filter state."""
        self._zi = [np.zeros(8, dtype=self.dtype) for _ in range(self.channels)]

    def _call(self, c: int, x: np.ndarray) -> np.ndarray:
        b, a = self._ba[c]
        y, self._zi[c] = lfilter(b, a, x, zi=self._zi[c])
        return y


class SlaneyPeer(_PerChannelPeer):
    """Slaney's 4-biquad cascade + sosfilt, per channel, state carried."""

    backend = "slaney"

    def __init__(self, bank: Bank, dtype=np.float64, nonfinite: str = "raise") -> None:
        self._sos = [slaney_sos(float(cf), float(b), bank.fs).astype(dtype) for cf, b in zip(bank.cf, bank.b)]
        super().__init__(bank, dtype, nonfinite)

    def reset(self) -> None:
        """Zero every channel's filter state."""
        self._zi = [np.zeros((4, 2), dtype=self.dtype) for _ in range(self.channels)]

    def _call(self, c: int, x: np.ndarray) -> np.ndarray:
        y, self._zi[c] = sosfilt(self._sos[c], x, zi=self._zi[c])
        return y


def make_peer(bank: Bank, name: str, dtype=np.float64) -> FilterbankBase:
    """Return a peer filterbank by name (``"scipy-iir"`` or ``"slaney"``)."""
    if name == "scipy-iir":
        return ScipyGammatonePeer(bank, dtype)
    if name == "slaney":
        return SlaneyPeer(bank, dtype)
    raise InputError(f"unknown peer {name!r}; peers are {', '.join(PEERS)}")
