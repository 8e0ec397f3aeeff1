"""A two-sense world without hardware: one surface, felt by the whiskers and heard by a microphone.

A surface is a texture of the kind :mod:`supramodal.textures` synthesises (noise shaped by three
spectral peaks) plus a friction sound: three peaks above the whiskers' band, which the contact
makes audible but the whiskers, sampled at 5 kHz and tuned below 1 kHz, never feel. The whisker
array gets the vibration; the microphone gets the vibration (weaker), the friction sound, and the
robot's motor noise, loud and low, which masks the vibration's peaks in the microphone.

The sets are built so that fusion has something to do (issue 11): textures come in pairs that
share everything but one part,

* **heard pairs** share their vibration and differ in the friction sound: the whiskers cannot tell
  them apart, the microphone can;
* **felt pairs** share their friction sound and differ in the vibration's peaks, under the motor
  noise's band: the whiskers can, the microphone hardly.

So each sense alone confuses some pairs that the other separates. Pure numpy; the clocks, offsets
and jitter of real sources belong to the node, not to this module.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from supramodal.errors import InputError
from supramodal.textures import synthesize

#: Whisker array rate and microphone rate, Hz.
WHISKER_RATE = 5000.0
MIC_RATE = 44100.0
#: The motor's noise in the microphone: three low peaks, Hz, low-passed at MOTOR_CUTOFF (a motor
#: hums, it does not hiss), and its level against the vibration.
MOTOR_PEAKS = (90.0, 180.0, 360.0)
MOTOR_CUTOFF = 1000.0
MOTOR_GAIN = 10.0
#: Level of the vibration in the microphone against the whiskers' (the contact is mostly felt).
VIBRATION_IN_MIC = 0.3
#: Level of the friction sound in the microphone.
FRICTION_GAIN = 1.0
#: Relative width of every peak (as in :func:`supramodal.textures.synthesize`).
WIDTH = 0.2
#: Vibrissae of the array (the whisker bank's channels): on a touch each meets the surface on its own.
WHISKERS = 20
#: How much a touch differs from the next, as the sd of the natural logarithm of a gain: each
#: vibrissa's coupling to the surface (its angle, its force), drawn for every vibrissa and every touch.
WHISKER_TOUCH_SPREAD = 0.03
#: The same for the microphone's level (its distance to the contact, which a touch changes).
MIC_TOUCH_SPREAD = 0.03


@dataclass(frozen=True)
class Surface:
    """One texture as both senses meet it.

    Attributes
    ----------
    name : str
    vibration : tuple of 3 float
        Peaks of the contact vibration, Hz (below 1 kHz: the whiskers' band).
    friction : tuple of 3 float
        Peaks of the friction sound, Hz (above 2.5 kHz: beyond the whisker array's Nyquist).
    """

    name: str
    vibration: tuple[float, float, float]
    friction: tuple[float, float, float]


def two_sense_set(pairs: int = 2, seed: int = 0) -> tuple[Surface, ...]:
    """``2 * pairs`` heard-pair textures and ``2 * pairs`` felt-pair textures (see the module).

    Parameters
    ----------
    pairs : int
        Pairs of each kind, >= 1 (default 2: eight textures).
    seed : int
        Draws every peak (default 0); the same seed gives the same set.

    Returns
    -------
    tuple of Surface
        Named ``H1a, H1b, ...`` (heard pairs) and ``F1a, F1b, ...`` (felt pairs).
    """
    if isinstance(pairs, bool) or not isinstance(pairs, int) or pairs < 1:
        raise InputError(f"pairs must be an integer >= 1, got {pairs!r}")
    rng = np.random.default_rng(seed)

    def vibration():
        # three peaks spread over the whisker bank's 80-800 Hz, 1.3x apart at least
        base = rng.uniform(100.0, 180.0)
        return tuple(round(base * f, 1) for f in np.cumprod([1.0, *rng.uniform(1.5, 2.2, 2)]))

    def friction():
        base = rng.uniform(3000.0, 4500.0)
        return tuple(round(base * f, 1) for f in (1.0, 1.6, 2.4))

    out = []
    for p in range(1, pairs + 1):
        v, f = vibration(), friction()
        out.append(Surface(f"H{p}a", v, f))
        out.append(Surface(f"H{p}b", v, tuple(round(x * 1.35, 1) for x in f)))   # differs only in the sound
    for p in range(1, pairs + 1):
        v, f = vibration(), friction()
        out.append(Surface(f"F{p}a", v, f))
        out.append(Surface(f"F{p}b", tuple(round(x * 1.12, 1) for x in v), f))   # differs only in the feel
    return tuple(out)


def synthesize_contact(surface: Surface, seconds: float, seed=None) -> tuple[np.ndarray, np.ndarray]:
    """Synthesize the whisker vibration and the microphone signal of ``seconds`` of contact with ``surface``.

    Returns
    -------
    whiskers : ndarray, shape (round(seconds * WHISKER_RATE),)
        The vibration at :data:`WHISKER_RATE` (mono: every vibrissa meets the same surface).
    mic : ndarray, shape (round(seconds * MIC_RATE),)
        Vibration (times :data:`VIBRATION_IN_MIC`) + friction sound + motor noise at
        :data:`MIC_RATE`.
    """
    ss = np.random.SeedSequence(seed)
    s_w, s_v, s_f, s_m = ss.spawn(4)
    whiskers = synthesize(surface.vibration, WHISKER_RATE, seconds, WIDTH, s_w)
    mic = (VIBRATION_IN_MIC * synthesize(surface.vibration, MIC_RATE, seconds, WIDTH, s_v)
           + FRICTION_GAIN * synthesize(surface.friction, MIC_RATE, seconds, WIDTH, s_f)
           + MOTOR_GAIN * _motor(seconds, s_m))
    return whiskers, mic


@dataclass(frozen=True)
class TouchGains:
    """What sets one touch apart from another touch of the same surface (issue 34).

    A real array never meets a surface twice at the same angle and force, so a model that
    learned one touch's coupling as a cue of the texture meets a new touch it has not calibrated
    for.

    Attributes
    ----------
    whiskers : ndarray, shape (WHISKERS,)
        Each vibrissa's gain on this touch.
    microphone : float
        The microphone's gain on this touch.
    """

    whiskers: np.ndarray
    microphone: float


def touch_gains(seed) -> TouchGains:
    """One touch's gains, log-normal around 1 (:data:`WHISKER_TOUCH_SPREAD`, :data:`MIC_TOUCH_SPREAD`).

    Drawn from ``seed`` (anything :class:`numpy.random.SeedSequence` takes).
    """
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    whiskers = np.exp(rng.normal(0.0, WHISKER_TOUCH_SPREAD, WHISKERS))
    return TouchGains(whiskers, float(np.exp(rng.normal(0.0, MIC_TOUCH_SPREAD))))


def synthesize_touch(surface: Surface, seconds: float, set_seed: int, index: int, touch: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Touch number ``touch`` (0, 1, ...) of texture ``index`` of set ``set_seed``: both senses' signals.

    Each with that touch's own gains (:func:`touch_gains`).

    Returns
    -------
    whiskers : ndarray, shape (WHISKERS, round(seconds * WHISKER_RATE))
        One signal per vibrissa (the vibration times the vibrissa's gain), for the whisker bank's
        one-signal-per-channel input.
    mic : ndarray, shape (round(seconds * MIC_RATE),)
        As :func:`synthesize_contact`, times the touch's microphone gain.
    """
    ss = np.random.SeedSequence([set_seed, index, touch])
    s_w, s_v, s_f, s_m = ss.spawn(4)
    g = touch_gains([set_seed, index, touch, 1])
    whiskers = g.whiskers[:, None] * synthesize(surface.vibration, WHISKER_RATE, seconds, WIDTH, s_w)[None, :]
    mic = g.microphone * (VIBRATION_IN_MIC * synthesize(surface.vibration, MIC_RATE, seconds, WIDTH, s_v)
                          + FRICTION_GAIN * synthesize(surface.friction, MIC_RATE, seconds, WIDTH, s_f)
                          + MOTOR_GAIN * _motor(seconds, s_m))
    return whiskers, mic


def synthesize_slide(surfaces, order, seconds: float, set_seed: int, touch: int) -> tuple[np.ndarray, np.ndarray]:
    """One touch that slides across several surfaces without lifting off, both senses.

    ``seconds`` of each of ``surfaces[i]`` for ``i`` in ``order``, back to back (each stretch is that
    texture's :func:`synthesize_touch`, touch ``touch``), both senses. The texture changes at every multiple
    of ``seconds``; the contact never ends.

    Returns
    -------
    whiskers : ndarray, shape (WHISKERS, len(order) * round(seconds * WHISKER_RATE))
    mic : ndarray, shape (len(order) * round(seconds * MIC_RATE),)
    """
    parts = [synthesize_touch(surfaces[i], seconds, set_seed, int(i), touch) for i in order]
    return np.concatenate([w for w, _ in parts], axis=1), np.concatenate([m for _, m in parts])


def _motor(seconds: float, seed) -> np.ndarray:
    """Motor noise at :data:`MIC_RATE`: the three-peak texture low-passed.

    The low pass is a 4th-order Butterworth at :data:`MOTOR_CUTOFF`, so that the noise masks the
    vibration's band and leaves the friction sound's.
    """
    from scipy.signal import butter, sosfilt  # here: scipy.signal takes 0.6 s to import

    sos = butter(4, MOTOR_CUTOFF, fs=MIC_RATE, output="sos")
    return sosfilt(sos, synthesize(MOTOR_PEAKS, MIC_RATE, seconds, WIDTH, seed))


#: The two senses of a surface, as a source of the node names them.
SENSES = ("whiskers", "microphone")
#: Seconds of contact per texture a sense's model is trained on (as ``experiment fusion``).
TRAIN_SECONDS = 20.0


@dataclass(frozen=True)
class OneSense:
    """One sense of a two-sense set, shaped as a texture set: what the training helpers take.

    A texture set has ``name``, ``fs``, ``duration``, ``textures``, ``names`` and ``synthesize``.

    Contact ``index`` with ``take`` k is one draw of the world, the same for both senses: the
    whisker signal of ``OneSense(..., "whiskers")`` and the microphone signal of
    ``OneSense(..., "microphone")`` with the same arguments are the two sides of one contact.

    Parameters
    ----------
    surfaces : tuple of Surface
        The set (:func:`two_sense_set`).
    sense : {"whiskers", "microphone"}
    duration : float
        Seconds per contact (default :data:`TRAIN_SECONDS`).
    seed : int
        The set's seed (contacts are drawn from ``[seed, index, take]``).
    take : int
        Which contact of each texture (default 0, the training contacts; a node's source plays
        take 1, contacts its model has never met).
    """

    surfaces: tuple
    sense: str
    duration: float = TRAIN_SECONDS
    seed: int = 0
    take: int = 0

    def __post_init__(self) -> None:
        if self.sense not in SENSES:
            raise InputError(f"a two-sense source's sense is one of {SENSES}, got {self.sense!r}")

    @property
    def name(self) -> str:
        """The set's name, with its seed and sense."""
        return f"two-sense set {self.seed} ({self.sense})"

    @property
    def fs(self) -> float:
        """The sense's sample rate, Hz."""
        return WHISKER_RATE if self.sense == "whiskers" else MIC_RATE

    @property
    def textures(self) -> tuple:
        """The set's surfaces."""
        return self.surfaces

    @property
    def names(self) -> tuple[str, ...]:
        """The surfaces' names, in order."""
        return tuple(s.name for s in self.surfaces)

    def synthesize(self, index: int, duration: float | None = None) -> np.ndarray:
        """Synthesize the sense's signal of contact ``index``, float64, shape (samples,)."""
        whiskers, mic = synthesize_contact(self.surfaces[index], self.duration if duration is None else duration,
                                           seed=[self.seed, index, self.take])
        return whiskers if self.sense == "whiskers" else mic
