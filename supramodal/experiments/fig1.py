"""Fig. 1: transfer functions of the cochlea and whisker banks (gain in dB against log frequency).

Computed exactly, in closed form, from the filter the pipeline runs: the
sampled impulse response ``h[n] = Re(n**3 p**n) / g`` (``p`` the channel's pole,
``g`` its gain at ``fc``, see :mod:`supramodal.gammatone`) has the transform

    H(w) = (S(p e**-jw) + conj(S(p e**jw))) / (2 g),   S(q) = q (1 + 4q + q**2) / (1 - q)**4,

the sum of ``n**3 q**n`` over all ``n >= 0``: no truncation, no FFT grid.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq

from supramodal.banks import Bank, cochlea_bank, half_power_width, slaney_bandwidth, whisker_bank
from supramodal.experiments.common import Plan, Run
from supramodal.gammatone import gain_at_cf, pole_powers

METHOD = "closed form of the sampled impulse response's transform (exact, no truncation)"
#: Half power, as a gain.
HALF_POWER = 1 / np.sqrt(2)


def moment_sum(q):
    """``S(q)``: ``sum_{n>=0} n**3 q**n = q (1 + 4q + q**2) / (1 - q)**4`` for ``|q| < 1`` (complex)."""
    return q * (1 + 4 * q + q * q) / (1 - q) ** 4


def transfer_function(bank: Bank, freqs) -> np.ndarray:
    """Complex frequency response of every channel at ``freqs`` (Hz), unit gain at ``fc``.

    Returns
    -------
    ndarray, shape (channels, len(freqs)), complex
    """
    freqs = np.asarray(freqs, dtype=np.float64)
    p = pole_powers(bank, np.ones(1))           # shape (channels, 1)
    z = np.exp(1j * 2 * np.pi * freqs[None, :] / bank.fs)
    h = (moment_sum(p / z) + np.conj(moment_sum(p * z))) / 2
    return h / gain_at_cf(bank)[:, None]


def half_power_edges(bank: Bank, channel: int) -> tuple[float | None, float | None, float, float]:
    """Frequencies where a channel's gain crosses 1/sqrt(2) of its maximum, below and above its peak.

    Returns ``(low, high, peak_hz, peak_gain)``; ``low`` is None if the gain never falls that far between
    0 Hz and the peak (a wide, low channel), ``high`` likewise up to ``fs/2``.
    """
    one = Bank(bank.kind, bank.fs, bank.cf[channel : channel + 1], bank.b[channel : channel + 1],
               (bank.names[channel],))
    gain = lambda f: float(np.abs(transfer_function(one, [f])[0, 0]))
    cf, nyq = float(one.cf[0]), bank.fs / 2
    # The peak lies within a fraction of b of fc; refine it on a fine local grid.
    grid = np.linspace(max(cf - 2 * one.b[0], 1e-3), min(cf + 2 * one.b[0], nyq - 1e-3), 2001)
    g = np.abs(transfer_function(one, grid)[0])
    peak_hz, level = float(grid[np.argmax(g)]), float(g.max()) * HALF_POWER
    edge = lambda lo, hi: (brentq(lambda f: gain(f) - level, lo, hi, xtol=1e-9)
                           if (gain(lo) - level) * (gain(hi) - level) < 0 else None)
    return edge(1e-6, peak_hz), edge(peak_hz, nyq - 1e-6), peak_hz, float(g.max())


def bank_response(bank: Bank, freqs) -> dict:
    """Gain curves (dB) of a bank and each channel's bandwidth figures."""
    gain_db = 20 * np.log10(np.abs(transfer_function(bank, freqs)))
    channels = []
    for k in range(bank.channels):
        low, high, peak, peak_gain = half_power_edges(bank, k)
        channels.append({
            "name": bank.names[k], "cf": float(bank.cf[k]), "b": float(bank.b[k]),
            "B": float(slaney_bandwidth(bank.b[k])), "peak_hz": peak,
            "width_3db": None if low is None or high is None else high - low,
            "width_3db_formula": float(half_power_width(bank.b[k])),
            "max_gain_db": float(20 * np.log10(peak_gain)),
        })
    return {"fs": bank.fs, "freqs": [float(f) for f in freqs], "channels": channels,
            "gain_db": [[float(v) for v in row] for row in gain_db]}


def fig1(n_freqs: int = 600, f_min: float = 10.0, progress=None) -> dict:
    """Transfer functions of the paper's two banks: 50-channel cochlea and 20-vibrissa array.

    ``n_freqs`` log-spaced frequencies from ``f_min`` to just below each bank's Nyquist frequency.

    Returns
    -------
    dict
        ``{"figure": "fig1", "method", "banks": {"cochlea"|"whisker": {"fs", "freqs", "channels":
        [{"name", "cf", "b", "B", "peak_hz", "width_3db", "width_3db_formula", "max_gain_db"}],
        "gain_db": [[per frequency] per channel]}}}``.
    """
    out = {}
    for name, bank in (("cochlea", cochlea_bank()), ("whisker", whisker_bank())):
        if progress:
            progress(f"fig1: {name} bank, {bank.channels} channels")
        freqs = np.geomspace(f_min, bank.fs / 2 * 0.999, n_freqs)
        out[name] = bank_response(bank, freqs)
    return {"figure": "fig1", "method": METHOD, "banks": out}


def plan(quick: bool = False, **_) -> Plan:
    """One run (it takes well under a second; quick mode samples fewer frequencies)."""
    key = ("fig1",)
    run = Run(key, fig1, {"n_freqs": 120 if quick else 600}, cost=0.5, seeded=False)
    return Plan([run], lambda results: results[key])
