"""The fast form's algorithm written plainly: per channel, per sub-block, loops and no rescaling.

Slow and obviously right; the tests check that ``supramodal.gammatone.GammatoneFilterbank``
computes the same thing to rounding. With ``S_j = sum_(t>=1) t**j p**t x[n-t]`` (``j = 0..3``),
the moments of the past at the start ``n`` of a sub-block of ``m`` samples:

* output ``y[n+d] = g Re(p**d sum_j C(3, j) d**(3-j) S_j + sum_(i<=d) (d-i)**3 p**(d-i) x[n+i])``
  (``(d + t)**3`` expanded binomially), ``g`` the unit-gain factor;
* next state ``S'_j = p**m sum_r C(j, r) m**(j-r) S_r + sum_(i<m) (m-i)**j p**(m-i) x[n+i]``.

Pole powers come from the closed form in long double (phase reduced modulo one turn), the gain
from :func:`supramodal.gammatone.gain_at_cf`.
"""

from math import comb

import numpy as np

from supramodal.gammatone import gain_at_cf

LD = np.longdouble
TWO_PI = 2 * np.arccos(LD(-1))


def pole_power(cf: float, b: float, fs: float, d: int) -> complex:
    """``p**d``, ``p = exp((-2 pi b + 2j pi cf) / fs)``, from the closed form."""
    turns = np.fmod(LD(cf) * LD(d) / LD(fs), LD(1))
    mag = np.exp(-TWO_PI * LD(b) * LD(d) / LD(fs))
    return complex(float(mag * np.cos(TWO_PI * turns)), float(mag * np.sin(TWO_PI * turns)))


class PlainGammatone:
    """Streaming filterbank, one channel and one sub-block of ``m`` samples at a time."""

    def __init__(self, bank, m: int) -> None:
        self.bank, self.m = bank, m
        self.gain = 1.0 / gain_at_cf(bank)
        self.state = np.zeros((bank.channels, 4), dtype=complex)
        self.powers = [[pole_power(cf, b, bank.fs, d) for d in range(m + 1)] for cf, b in zip(bank.cf, bank.b)]

    def process(self, x) -> np.ndarray:
        """Filter a block, shape (L,) (fed to every channel) or (channels, L); returns (channels, L)."""
        x = np.asarray(x, dtype=float)
        C, L = self.bank.channels, x.shape[-1]
        y = np.zeros((C, L))
        for c in range(C):
            xc = x if x.ndim == 1 else x[c]
            for start in range(0, L, self.m):
                sub = xc[start : start + self.m]
                y[c, start : start + len(sub)] = self._subblock(c, sub)
        return y

    def _subblock(self, c: int, x: np.ndarray) -> np.ndarray:
        p, S, l = self.powers[c], self.state[c], len(x)
        out = np.zeros(l)
        for d in range(l):
            past = sum(comb(3, j) * d ** (3 - j) * S[j] for j in range(4))
            now = sum((d - i) ** 3 * p[d - i] * x[i] for i in range(d + 1))
            out[d] = self.gain[c] * (p[d] * past + now).real
        new = np.zeros(4, dtype=complex)
        for j in range(4):
            carried = sum(comb(j, r) * l ** (j - r) * S[r] for r in range(j + 1))
            new[j] = p[l] * carried + sum((l - i) ** j * p[l - i] * x[i] for i in range(l))
        self.state[c] = new
        return out
