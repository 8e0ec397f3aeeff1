"""Filterbank definitions: the cochlea and the whisker array as plain data.

A :class:`Bank` is what every other part of the model needs to know about a
filterbank: its sample rate, the centre frequency and bandwidth parameter of
each channel, and the channels' names. It holds no state and does no signal
processing.

Conventions (see docs/model.md)
-------------------------------
* ``erb(fc) = fc / q_ear + b_min`` in Hz (Glasberg & Moore 1990 form).
* The gammatone's bandwidth parameter is ``b = 1.019 * erb(fc)`` in Hz, the ``b``
  of the impulse response ``t**3 exp(-2 pi b t) cos(2 pi fc t)``.
* The paper's "bandwidth" figures are Slaney's ``B = 2 pi b`` (rad/s, quoted as
  Hz): see :func:`slaney_bandwidth`. The true -3 dB width is
  :func:`half_power_width`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from supramodal.checks import is_number
from supramodal.errors import InputError

#: Glasberg & Moore (1990) constants used by the cochlea.
COCHLEA_Q_EAR = 9.26449
COCHLEA_B_MIN = 24.7
#: The paper's choice for the whiskers (Sect. 2).
WHISKER_Q_EAR = 35.0
WHISKER_B_MIN = 15.0
#: Factor between the ERB and the gammatone's b for order 4 (Patterson et al.).
ERB_TO_B = 1.019

#: Reconstructed whisker resonance table (Hz), rows A..E, arcs 1..4.
#: A RECONSTRUCTION, not Neimark et al.'s measured table (which is not public
#: text): it meets every figure the paper quotes (A4 = 630 Hz, lowest 82 Hz,
#: highest 749 Hz, mean 270 Hz, hence B from 111 to 233 with mean 145) and its
#: shape follows the whisker lengths of the average rat. See docs/model.md.
WHISKER_TABLE: dict[str, tuple[float, float, float, float]] = {
    "A": (105.0, 158.0, 340.0, 630.0),
    "B": (85.0, 146.0, 251.0, 749.0),
    "C": (82.0, 136.0, 240.0, 560.0),
    "D": (86.0, 130.0, 222.0, 420.0),
    "E": (99.0, 147.0, 255.0, 560.0),
}
WHISKER_ROWS = tuple(WHISKER_TABLE)
WHISKER_RATE = 5000.0
COCHLEA_RATE = 44100.0
#: Most channels a bank may have (the cochlea has 50, the whiskers 20): a bound on what a scene or
#: a model file can make the node allocate.
MAX_CHANNELS = 1024
#: Highest sample rate a bank runs at, Hz (audio interfaces reach 768 kHz): a bound on what a scene,
#: a bank file or a model file can make the node resample and filter.
MAX_RATE = 1e6


def _real(value, what: str) -> np.ndarray:
    """``value`` as a float64 array, or an InputError naming ``what`` (complex, text, None...)."""
    a = np.asarray(value)
    if a.dtype.kind not in "fiu":
        raise InputError(f"{what} must be real numbers (Hz), got {a.dtype} values: {value!r:.60}")
    return a.astype(np.float64)


@dataclass(frozen=True)
class Bank:
    """A gammatone filterbank as plain data.

    Parameters
    ----------
    kind : str
        ``"cochlea"``, ``"whisker"`` or ``"custom"``.
    fs : float
        Sample rate, Hz.
    cf : ndarray, shape (channels,)
        Centre frequencies, Hz; each in (0, fs/2).
    b : ndarray, shape (channels,)
        Bandwidth parameters of the impulse response, Hz; each > 0.
    names : tuple of str
        One name per channel (``"A4"`` for a whisker, ``"ch07"`` for the cochlea).

    Raises
    ------
    InputError
        Empty bank, mismatched lengths, non-finite values, ``fs <= 0``,
        ``cf <= 0``, ``cf >= fs/2`` or ``b <= 0``.
    """

    kind: str
    fs: float
    cf: np.ndarray
    b: np.ndarray
    names: tuple[str, ...]

    def __post_init__(self) -> None:
        cf, b = _real(self.cf, "centre frequencies cf"), _real(self.b, "bandwidths b")
        fs = _real(self.fs, "sample rate fs")
        if fs.size != 1:
            raise InputError(f"sample rate fs must be one number of Hz, got {fs.size} values")
        cf, b, rate = cf.reshape(-1), b.reshape(-1), float(fs.reshape(-1)[0])
        names = tuple(str(n) for n in self.names)
        if not np.isfinite(rate) or rate <= 0 or rate > MAX_RATE:
            raise InputError(f"sample rate fs must be a positive number of Hz, at most {MAX_RATE:g} (MAX_RATE), "
                             f"got {self.fs!r}")
        if cf.size == 0:
            raise InputError("a bank needs at least one channel; got an empty list of centre frequencies")
        if cf.size > MAX_CHANNELS:
            raise InputError(f"a bank has at most {MAX_CHANNELS} channels (MAX_CHANNELS); "
                             f"this one has {cf.size} channels")
        if b.size != cf.size or len(names) != cf.size:
            raise InputError(
                f"cf, b and names must have one entry per channel; got {cf.size}, {b.size} and {len(names)}"
            )
        if not (np.all(np.isfinite(cf)) and np.all(np.isfinite(b))):
            raise InputError("centre frequencies and bandwidths must be finite numbers (found NaN or Inf)")
        bad = np.flatnonzero((cf <= 0) | (cf >= rate / 2))
        if bad.size:
            k = int(bad[0])
            raise InputError(
                f"centre frequency of channel {names[k]} is {cf[k]:g} Hz, outside (0, fs/2) = (0, {rate / 2:g}) Hz: "
                "lower it or raise the sample rate"
            )
        bad = np.flatnonzero(b <= 0)
        if bad.size:
            k = int(bad[0])
            raise InputError(f"bandwidth parameter b of channel {names[k]} is {b[k]:g} Hz; it must be > 0")
        if len(set(names)) != len(names):
            raise InputError("channel names must be unique")
        cf.flags.writeable = False
        b.flags.writeable = False
        object.__setattr__(self, "cf", cf)
        object.__setattr__(self, "b", b)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "fs", rate)

    @property
    def channels(self) -> int:
        """Number of channels."""
        return int(self.cf.size)

    def to_dict(self) -> dict:
        """JSON-ready description, enough to rebuild the bank exactly (floats round-trip)."""
        return {
            "kind": self.kind,
            "fs": self.fs,
            "cf": [float(v) for v in self.cf],
            "b": [float(v) for v in self.b],
            "names": list(self.names),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Bank:
        """Inverse of :meth:`to_dict`; raises InputError on a malformed description."""
        try:
            return cls(kind=str(d["kind"]), fs=float(d["fs"]), cf=np.asarray(d["cf"], float),
                       b=np.asarray(d["b"], float), names=tuple(d["names"]))
        except (KeyError, TypeError) as exc:
            raise InputError(f"malformed bank description: {exc!r}; expected keys kind, fs, cf, b, names") from exc

    def matches(self, other: Bank) -> bool:
        """Tell whether both banks filter identically (same rate, cf and b to 1e-12, same names)."""
        return (
            self.channels == other.channels
            and bool(np.isclose(self.fs, other.fs, rtol=1e-12, atol=0))
            and np.allclose(self.cf, other.cf, rtol=1e-12, atol=0)
            and np.allclose(self.b, other.b, rtol=1e-12, atol=0)
            and self.names == other.names
        )


def erb(fc, q_ear: float = COCHLEA_Q_EAR, b_min: float = COCHLEA_B_MIN):
    """Equivalent rectangular bandwidth ``fc / q_ear + b_min``, Hz."""
    return np.asarray(fc, dtype=np.float64) / q_ear + b_min


def slaney_bandwidth(b):
    """Return the paper's bandwidth figure ``B = 2 pi b`` (rad/s, quoted as "Hz" in the paper)."""
    return 2 * np.pi * np.asarray(b, dtype=np.float64)


def half_power_width(b, order: int = 4):
    """Return the true -3 dB width of an order-``order`` gammatone of bandwidth parameter ``b``, Hz.

    For a gammatone the magnitude near fc is ``(1 + ((f - fc)/b)**2) ** (-order/2)``,
    so the half-power width is ``2 b sqrt(2**(1/order) - 1)`` (0.87 b at order 4).
    """
    return 2 * np.asarray(b, dtype=np.float64) * np.sqrt(2 ** (1 / order) - 1)


def erb_space(f_low: float, f_high: float, n: int, q_ear: float = COCHLEA_Q_EAR,
              b_min: float = COCHLEA_B_MIN) -> np.ndarray:
    """Slaney's ERBSpace: ``n`` centre frequencies equally spaced on the ERB scale.

    ``cf_k = -c + exp(k/n * (ln(f_low + c) - ln(f_high + c))) * (f_high + c)``,
    ``c = q_ear * b_min``, ``k = 1..n``: descending from just below ``f_high`` down
    to ``f_low`` (``f_high`` itself is excluded, ``f_low`` included), as in
    Slaney's Auditory Toolbox.

    Returns
    -------
    ndarray, shape (n,)
        Centre frequencies in Hz, descending.
    """
    if n < 1:
        raise InputError(f"the number of channels must be >= 1, got {n}")
    if not (0 < f_low < f_high):
        raise InputError(f"need 0 < f_low < f_high, got f_low={f_low}, f_high={f_high}")
    c = q_ear * b_min
    k = np.arange(1, n + 1)
    return -c + np.exp(k / n * (np.log(f_low + c) - np.log(f_high + c))) * (f_high + c)


def cochlea_bank(n: int = 50, f_low: float = 20.0, f_high: float = 20000.0,
                 fs: float = COCHLEA_RATE) -> Bank:
    """Return the paper's cochlea: ``n`` channels ERB-spaced over [f_low, f_high), Glasberg-Moore bandwidths.

    Channels are ordered by ascending centre frequency (``ch00`` lowest).
    """
    if not (isinstance(n, (int, np.integer)) and 1 <= n <= MAX_CHANNELS):
        raise InputError(f"a cochlea has 1..{MAX_CHANNELS} channels (MAX_CHANNELS); got {n!r}")
    for key, v in (("f_low", f_low), ("f_high", f_high), ("fs", fs)):
        if not (is_number(v) and v > 0):
            raise InputError(f"{key} must be a positive number of Hz, got {v!r}")
    if not f_low < f_high <= fs / 2:
        raise InputError(f"f_high = {f_high:g} Hz lies outside (f_low, fs/2] = ({f_low:g}, {fs / 2:g}] Hz: the band "
                         "must rise and end at or below the Nyquist frequency; lower f_high (or f_low), or raise fs")
    cf = np.sort(erb_space(f_low, f_high, n))
    b = ERB_TO_B * erb(cf, COCHLEA_Q_EAR, COCHLEA_B_MIN)
    names = tuple(f"ch{k:02d}" for k in range(n))
    return Bank("cochlea", fs, cf, b, names)


def whisker_bank(rows: Sequence[str] | str = WHISKER_ROWS, mean_B: float | None = None,
                 fs: float = WHISKER_RATE) -> Bank:
    """Return the whisker array: the reconstructed table's vibrissae, row by row.

    Parameters
    ----------
    rows : sequence of str or str
        Rows to include, a subset of ``"ABCDE"`` (default all five: 20 channels).
        Channel order is row by row in the order given, arcs 1..4 within a row.
    mean_B : float, optional
        If given, every channel's ``b`` is multiplied by one factor so that the
        mean of Slaney's ``B = 2 pi b`` equals ``mean_B`` (the paper's Fig. 5
        sweep). By default the paper's ``q_ear = 35, b_min = 15`` apply (mean B
        about 145 over all 20 channels).
    fs : float
        Sample rate, Hz (default 5000).
    """
    rows = tuple(rows)
    if not rows:
        raise InputError("choose at least one whisker row from A, B, C, D, E")
    unknown = [r for r in rows if r not in WHISKER_TABLE]
    if unknown:
        raise InputError(f"unknown whisker row(s) {unknown}; rows are {', '.join(WHISKER_ROWS)}")
    if len(set(rows)) != len(rows):
        raise InputError(f"whisker rows repeat in {rows}")
    cf = np.array([f for r in rows for f in WHISKER_TABLE[r]], dtype=np.float64)
    names = tuple(f"{r}{arc}" for r in rows for arc in range(1, 5))
    b = ERB_TO_B * erb(cf, WHISKER_Q_EAR, WHISKER_B_MIN)
    if mean_B is not None:
        if not (np.isfinite(mean_B) and mean_B > 0):
            raise InputError(f"mean_B must be a positive number, got {mean_B!r}")
        b = b * (mean_B / float(np.mean(slaney_bandwidth(b))))
    return Bank("whisker", fs, cf, b, names)


def bank_by_name(name: str, **kwargs) -> Bank:
    """``"whisker"`` or ``"cochlea"`` with that bank's keyword arguments."""
    if name == "whisker":
        return whisker_bank(**kwargs)
    if name == "cochlea":
        return cochlea_bank(**kwargs)
    raise InputError(f"unknown bank {name!r}: choose 'whisker' or 'cochlea'")
