"""Fig. 4: the A and f features of one vibrissa (A4, cf 630 Hz) for pure sines swept across its resonance.

Each sine (amplitude 1, starting at phase 0) goes through the whole whisker bank
for ``duration`` seconds; the windows of the first ``settle`` seconds (the
filter's onset) are dropped and the feature values of vibrissa ``channel`` are
averaged over the remaining (steady-state) windows.

How the curves are compared (the paper only shows them): each curve is divided
by its own maximum over the sweep, and its sharpness is measured on that
normalised curve as the width of the band where it stays at or above 1/sqrt(2)
of the maximum (-3 dB, the half-power criterion of a filter applied to both
features alike), ``Q = peak frequency / width``, and its range (max/min over the
sweep, in dB). A band that reaches an end of the sweep is reported open
(``width_3db`` None, ``closed`` False): that curve is flatter than the sweep
can measure.
"""

from __future__ import annotations

import numpy as np

from supramodal.banks import whisker_bank
from supramodal.errors import InputError
from supramodal.experiments.common import Plan, Run
from supramodal.features import DEFAULT_WINDOW, FEATURES
from supramodal.pipeline import extract_features

CHANNEL = "A4"
#: Full sweep: 241 log-spaced frequencies over two octaves centred on 630 Hz (0.58 % apart).
SWEEP = (315.0, 1260.0, 241)
QUICK_SWEEP = (315.0, 1260.0, 41)


def sine_responses(bank, channel: str, freqs, duration: float = 2.0, settle: float = 0.3, progress=None) -> dict:
    """Steady-state mean and standard deviation (over windows) of every feature of ``channel``, per frequency."""
    k = bank.names.index(channel)
    t = np.arange(int(round(duration * bank.fs))) / bank.fs
    skip = int(round(settle / DEFAULT_WINDOW))
    mean: dict[str, list[float]] = {f: [] for f in FEATURES}
    sd: dict[str, list[float]] = {f: [] for f in FEATURES}
    for i, freq in enumerate(freqs):
        w = extract_features(np.sin(2 * np.pi * freq * t), bank, FEATURES)
        steady = w.values[skip:, :, k]
        if len(steady) < 2:
            raise InputError(f"{duration} s leaves fewer than 2 steady windows after {settle} s of settling")
        for j, f in enumerate(FEATURES):
            mean[f].append(float(steady[:, j].mean()))
            sd[f].append(float(steady[:, j].std()))
        if progress and (i + 1) % 40 == 0:
            progress(f"fig4: {i + 1}/{len(freqs)} sines")
    return {"mean": mean, "sd": sd, "windows": int(len(w) - skip)}


def sharpness(freqs, values) -> dict:
    """Peak, -3 dB band, Q and range of a curve normalised by its maximum (see the module's notes)."""
    freqs = np.asarray(freqs, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    v = v / v.max()
    i = int(np.argmax(v))
    above = v >= 1 / np.sqrt(2)
    lo = i
    while lo > 0 and above[lo - 1]:
        lo -= 1
    hi = i
    while hi < len(v) - 1 and above[hi + 1]:
        hi += 1

    def cross(a, b):  # linear interpolation in dB between neighbours a (inside) and b (outside)
        da, db = 20 * np.log10(v[a]), 20 * np.log10(max(v[b], 1e-300))
        return float(freqs[a] + (freqs[b] - freqs[a]) * (-3.0103 - da) / (db - da))

    low = cross(lo, lo - 1) if lo > 0 else None
    high = cross(hi, hi + 1) if hi < len(v) - 1 else None
    width = None if low is None or high is None else high - low
    return {
        "peak_hz": float(freqs[i]), "low_hz": low, "high_hz": high, "width_3db": width,
        "q": None if width is None else float(freqs[i] / width), "closed": width is not None,
        "range_db": float(20 * np.log10(v.max() / max(v.min(), 1e-300))),
    }


def fig4(channel: str = CHANNEL, sweep=SWEEP, duration: float = 2.0, settle: float = 0.3, progress=None) -> dict:
    """Responses of vibrissa ``channel`` to pure sines across its resonance, normalised, with sharpness.

    Returns
    -------
    dict
        ``{"figure": "fig4", "channel", "cf", "b", "freqs", "features": {feature: {"mean", "sd",
        "normalised", "sharpness": {...}}}, "windows"}``; ``normalised`` is ``mean / max(mean)``.
    """
    bank = whisker_bank()
    freqs = np.geomspace(sweep[0], sweep[1], int(sweep[2]))
    if progress:
        progress(f"fig4: {len(freqs)} sines of {duration:g} s, {freqs[0]:g}..{freqs[-1]:g} Hz, vibrissa {channel}")
    r = sine_responses(bank, channel, freqs, duration, settle, progress)
    k = bank.names.index(channel)
    features = {}
    for f in FEATURES:
        m = np.asarray(r["mean"][f])
        features[f] = {"mean": r["mean"][f], "sd": r["sd"][f], "normalised": [float(v) for v in m / m.max()],
                       "sharpness": sharpness(freqs, m)}
    return {"figure": "fig4", "channel": channel, "cf": float(bank.cf[k]), "b": float(bank.b[k]),
            "freqs": [float(f) for f in freqs], "duration": duration, "settle": settle,
            "windows": r["windows"], "features": features}


def plan(quick: bool = False, **_) -> Plan:
    """One run: about a second for the full sweep, a fraction in quick mode."""
    key = ("fig4",)
    kwargs = {"sweep": QUICK_SWEEP, "duration": 1.0} if quick else {"sweep": SWEEP}
    return Plan([Run(key, fig4, kwargs, cost=2.0, seeded=False)], lambda results: results[key])
