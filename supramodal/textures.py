"""Three-peak "sandpaper" textures after Neimark et al. 2003 (paper Sect. 4.1).

White Gaussian noise is shaped in the frequency domain: its spectrum is -3 dB
everywhere except around three peaks, the lowest at +6 dB and the other two at
+3 dB. The paper does not give the peaks' frequencies or widths; the project's
choices (docs/model.md):

* each peak is a Gaussian bump *in dB*: ``gain_dB(f) = floor + max_k (g_k - floor)
  exp(-(f - f_k)**2 / (2 sigma_k**2))``, with a full width at half height (in dB)
  of ``width * f_k`` (constant relative width, default 0.2);
* the noise is scaled so that the -3 dB floor has RMS 0.1 (full scale 1.0), far
  from clipping; textures are *not* normalised one by one, so that a texture's
  overall level stays part of its spectrum as the paper defines it.

A texture set is a JSON file (format ``supramodal-textures``, version 1)::

    {"format": "supramodal-textures", "version": 1, "name": "whisker-reference",
     "bank": "whisker", "fs": 5000, "duration": 40.0, "width": 0.2, "seed": 2010,
     "textures": [{"name": "T1", "peaks": [95.0, 210.0, 480.0]}, ...]}

``seed`` makes the noise of every texture reproducible (texture ``i`` of the set
draws from ``SeedSequence([seed, i])``).

A texture-set file is data: it is parsed as JSON only, within bounds (at most
:data:`MAX_TEXTURE_SET_BYTES`, nested at most :data:`MAX_TEXTURE_SET_DEPTH` deep,
at most :data:`MAX_TEXTURES` textures, each at most :data:`MAX_TEXTURE_SAMPLES`
samples long), and anything else is refused with a :class:`TextureSetError`
naming the file, the key and the limit.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from supramodal.errors import InputError
from supramodal.jsondata import read_json_file

TEXTURES_FORMAT = "supramodal-textures"
TEXTURES_VERSION = 1
PEAK_GAINS_DB = (6.0, 3.0, 3.0)
FLOOR_DB = -3.0
FLOOR_RMS = 0.1
#: Where random peaks are drawn for each bank, Hz: inside the bank's range.
PEAK_RANGES = {"whisker": (80.0, 750.0), "cochlea": (100.0, 10000.0)}
BANK_RATES = {"whisker": 5000.0, "cochlea": 44100.0}

#: Longest texture synthesised, samples (``duration * fs``): 2**24 is 3355 s at 5 kHz and
#: 380 s at 44.1 kHz (the reference sets use 40 s). Synthesis shapes the whole signal in
#: one FFT, about 40 bytes a sample at its peak: 0.7 GB at this bound.
MAX_TEXTURE_SAMPLES = 2**24
#: Most textures in one set.
MAX_TEXTURES = 256
#: Largest texture-set file read, bytes (checked before reading; a set of 256 textures takes ~20 kB).
MAX_TEXTURE_SET_BYTES = 2**20
#: Deepest nesting read: the format nests 3 levels (object, ``textures``, texture with its ``peaks``).
MAX_TEXTURE_SET_DEPTH = 8


class TextureSetError(InputError):
    """A texture-set file or description is refused; the message names the file, the key and the fix."""


@dataclass(frozen=True)
class Texture:
    """A texture: a name and three peak frequencies (Hz), ascending."""

    name: str
    peaks: tuple[float, float, float]


@dataclass(frozen=True)
class TextureSet:
    """Textures to synthesise together, with the rate, duration and noise seed."""

    name: str
    bank: str
    fs: float
    duration: float
    width: float
    seed: int
    textures: tuple[Texture, ...]

    @property
    def names(self) -> tuple[str, ...]:
        """The textures' names, in order."""
        return tuple(t.name for t in self.textures)

    def to_dict(self) -> dict:
        """Return the set as the JSON object of a texture-set file (:func:`load_texture_set` reads it)."""
        return {
            "format": TEXTURES_FORMAT, "version": TEXTURES_VERSION, "name": self.name, "bank": self.bank,
            "fs": self.fs, "duration": self.duration, "width": self.width, "seed": self.seed,
            "textures": [{"name": t.name, "peaks": list(t.peaks)} for t in self.textures],
        }

    def save(self, path) -> None:
        """Write the set to ``path`` as indented JSON (:meth:`to_dict`)."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    def synthesize(self, index: int, duration: float | None = None) -> np.ndarray:
        """Signal of texture ``index``, float64, shape (samples,)."""
        return synthesize(self.textures[index].peaks, self.fs, self.duration if duration is None else duration,
                          width=self.width, seed=np.random.SeedSequence([self.seed, index]))


def gain_db(f, peaks, width: float = 0.2) -> np.ndarray:
    """Spectral gain in dB at frequencies ``f`` (Hz) for three ascending peaks (Hz)."""
    f = np.asarray(f, dtype=np.float64)
    bump = np.zeros_like(f)
    for fk, gk in zip(peaks, PEAK_GAINS_DB):
        sigma = width * fk / (2 * np.sqrt(2 * np.log(2)))
        bump = np.maximum(bump, (gk - FLOOR_DB) * np.exp(-0.5 * ((f - fk) / sigma) ** 2))
    return FLOOR_DB + bump


def synthesize(peaks, fs: float, duration: float, width: float = 0.2, seed=None) -> np.ndarray:
    """White Gaussian noise shaped to the three-peak spectrum.

    Parameters
    ----------
    peaks : sequence of 3 float
        Peak frequencies, Hz, ascending, each in (0, fs/2).
    fs : float
        Sample rate, Hz.
    duration : float
        Seconds.
    width : float
        Relative full width at half height of each peak (in dB), as a fraction of its frequency.
    seed : int, SeedSequence or None

    Returns
    -------
    ndarray, shape (round(duration * fs),), float64
        The floor (-3 dB) has RMS :data:`FLOOR_RMS`.
    """
    _check_peaks(peaks, fs)
    n = texture_samples(duration, fs)
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal(n)
    spectrum = np.fft.rfft(noise)
    freqs = np.fft.rfftfreq(n, 1 / fs)
    # A unit-RMS white noise times 10**(floor/20) must come out at FLOOR_RMS.
    amplitude = 10 ** (gain_db(freqs, peaks, width) / 20) * (FLOOR_RMS / 10 ** (FLOOR_DB / 20))
    return np.fft.irfft(spectrum * amplitude, n)


def texture_samples(duration: float, fs: float) -> int:
    """Return the samples in ``duration`` seconds at ``fs`` Hz, ``round(duration * fs)``.

    Raises
    ------
    InputError
        If that is not between 1 and :data:`MAX_TEXTURE_SAMPLES`.
    """
    n = duration * fs
    if not (math.isfinite(n) and 0.5 <= n):
        raise InputError(f"duration {duration} s at {fs} Hz gives no sample; give a positive number of seconds")
    if n > MAX_TEXTURE_SAMPLES + 0.5:
        raise InputError(f"duration {duration:g} s at {fs:g} Hz is {n:.6g} samples, more than the "
                         f"{MAX_TEXTURE_SAMPLES} a texture may have (MAX_TEXTURE_SAMPLES: "
                         f"{MAX_TEXTURE_SAMPLES / fs:g} s at this rate); synthesise shorter textures")
    return int(round(n))


def _three(peaks: Sequence[float]) -> tuple[float, float, float]:
    """Three peak frequencies as a :class:`Texture` holds them (the caller made or checked three)."""
    low, middle, high = peaks
    return low, middle, high


def _check_peaks(peaks, fs) -> None:
    peaks = list(peaks)
    if len(peaks) != 3:
        raise InputError(f"a three-peak texture needs exactly 3 peak frequencies, got {len(peaks)}")
    if not all(np.isfinite(p) and 0 < p < fs / 2 for p in peaks):
        raise InputError(f"peak frequencies {peaks} must lie in (0, fs/2) = (0, {fs / 2:g}) Hz")
    if sorted(peaks) != peaks or len(set(peaks)) != 3:
        raise InputError(f"peak frequencies must be distinct and ascending (the lowest gets +6 dB), got {peaks}")


def random_texture_set(bank: str, n: int = 8, seed: int = 0, duration: float = 40.0, width: float = 0.2,
                       min_ratio: float = 1.2) -> TextureSet:
    """Draw ``n`` textures: three peaks log-uniform in the bank's range, each at least ``min_ratio`` apart."""
    if bank not in PEAK_RANGES:
        raise InputError(f"unknown bank {bank!r}: choose 'whisker' or 'cochlea'")
    lo, hi = PEAK_RANGES[bank]
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7E57]))
    textures: list[Texture] = []
    while len(textures) < n:
        # Round first, then check: the stored (rounded) peaks are the ones that must be min_ratio apart.
        peaks = [round(float(p), 1) for p in np.sort(np.exp(rng.uniform(np.log(lo), np.log(hi), 3)))]
        if all(b / a >= min_ratio for a, b in zip(peaks, peaks[1:])):
            textures.append(Texture(f"T{len(textures) + 1}", _three(peaks)))
    return TextureSet(f"{bank}-random-{seed}", bank, BANK_RATES[bank], duration, width, seed, tuple(textures))


def texture_set_from_dict(d, source: str = "texture set") -> TextureSet:
    """Validate a texture-set description (already parsed JSON) and build it."""
    def bad(msg):
        return TextureSetError(f"{source}: {msg}")

    if not isinstance(d, dict):
        raise bad("expected a JSON object")
    if d.get("format") != TEXTURES_FORMAT:
        raise bad(f"'format' must be {TEXTURES_FORMAT!r}, got {d.get('format')!r}")
    if d.get("version") != TEXTURES_VERSION:
        raise bad(f"'version' {d.get('version')!r} is not supported (expected {TEXTURES_VERSION})")
    known = {"format", "version", "name", "bank", "fs", "duration", "width", "seed", "textures"}
    unknown = set(d) - known
    if unknown:
        raise bad(f"unknown key(s) {sorted(unknown)}; allowed: {sorted(known)}")
    if d.get("bank") not in BANK_RATES:
        raise bad(f"'bank' must be 'whisker' or 'cochlea', got {d.get('bank')!r}")
    for key in ("fs", "duration", "width"):
        v = d.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < math.inf:
            raise bad(f"'{key}' must be a positive number, got {v!r}")
    try:
        texture_samples(float(d["duration"]), float(d["fs"]))
    except InputError as exc:
        raise bad(f"'duration': {exc}") from None
    if isinstance(d.get("seed"), bool) or not isinstance(d.get("seed"), int) or d["seed"] < 0:
        raise bad(f"'seed' must be a non-negative integer, got {d.get('seed')!r}")
    items = d.get("textures")
    if not isinstance(items, list) or len(items) < 2:
        raise bad("'textures' must be a list of at least 2 textures")
    if len(items) > MAX_TEXTURES:
        raise bad(f"'textures' lists {len(items)} textures, more than the {MAX_TEXTURES} a set may hold "
                  "(MAX_TEXTURES); split the set")
    textures = []
    for i, t in enumerate(items):
        if not isinstance(t, dict) or set(t) != {"name", "peaks"} or not isinstance(t["name"], str):
            raise bad(f"texture {i} must be an object with exactly 'name' (text) and 'peaks' (3 numbers)")
        peaks = t["peaks"]
        if not isinstance(peaks, list) or not all(isinstance(p, (int, float)) and not isinstance(p, bool)
                                                  for p in peaks):
            raise bad(f"texture {t['name']!r}: 'peaks' must be a list of 3 numbers")
        try:
            _check_peaks([float(p) for p in peaks], float(d["fs"]))
        except InputError as exc:
            raise bad(f"texture {t['name']!r}: {exc}") from None
        textures.append(Texture(t["name"], _three([float(p) for p in peaks])))
    names = [t.name for t in textures]
    if len(set(names)) != len(names):
        raise bad("texture names must be distinct")
    return TextureSet(str(d.get("name", source)), d["bank"], float(d["fs"]), float(d["duration"]),
                      float(d["width"]), int(d["seed"]), tuple(textures))


def load_texture_set(path) -> TextureSet:
    """Read a texture-set JSON file (validated; never executed)."""
    path = Path(path)
    try:
        d = read_json_file(path, max_bytes=MAX_TEXTURE_SET_BYTES, max_depth=MAX_TEXTURE_SET_DEPTH,
                           error=TextureSetError, limits=("MAX_TEXTURE_SET_BYTES", "MAX_TEXTURE_SET_DEPTH"))
    except FileNotFoundError:
        raise TextureSetError(f"no texture-set file at {path}") from None
    except IsADirectoryError:
        raise TextureSetError(f"{path} is a folder, not a texture-set file") from None
    return texture_set_from_dict(d, str(path))


def reference_texture_set(bank: str) -> TextureSet:
    """Return the reference set shipped with the package for ``bank`` ('whisker' or 'cochlea')."""
    if bank not in BANK_RATES:
        raise InputError(f"unknown bank {bank!r}: choose 'whisker' or 'cochlea'")
    text = resources.files("supramodal").joinpath("data", "textures", f"{bank}_reference.json").read_text()
    return texture_set_from_dict(json.loads(text), f"{bank}_reference.json")
