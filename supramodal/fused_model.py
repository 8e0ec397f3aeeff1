"""The supramodal network (the paper's Sect. 5): one classifier on two senses' aligned windows.

An :class:`EarlyFusionModel` takes, for each pair of aligned windows, both senses' feature windows
(e.g. 20 whisker + 50 cochlea channels of Af), flattened and set side by side
(:func:`supramodal.fusion.early_inputs`), standardised with the training windows' mean and scale,
into one MLP trained with iRPROP-; winner-take-all as for one sense.

Its file is an ``.npz`` archive like a :class:`~supramodal.model.TextureModel`'s (read with
``allow_pickle=False``, every member bounded, every shape checked against the header), whose
header names the format ``supramodal-early-model`` and, under ``senses``, what each sense's
inputs are (bank, features, window, peak settings, and the sense's name), in input order.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from supramodal.errors import InputError
from supramodal.fusion import early_inputs
from supramodal.mlp import DEFAULT_EPOCHS, MLP, train_mlp
from supramodal.model import (SENSE_KEYS, ModelError, check_sense_fits, classes_from_header, network_from_arrays,
                              read_model_archive, save_model_archive, sense_from_header, sense_header)

EARLY_FORMAT = "supramodal-early-model"
EARLY_VERSION = 1


@dataclass(frozen=True)
class Sense:
    """What one sense's input windows are: its name and the pipeline settings that make them."""

    name: str
    bank: object
    features: tuple[str, ...]
    window_samples: int
    peak_mode: str = "maxima"
    peak_threshold: float = 0.0

    @classmethod
    def of(cls, name: str, pipeline) -> "Sense":
        """The sense a :class:`~supramodal.pipeline.FeaturePipeline` computes."""
        return cls(name, pipeline.bank, tuple(pipeline.features), pipeline.window_samples, pipeline.peaks.mode,
                   float(pipeline.peaks.threshold))

    @property
    def n_inputs(self) -> int:
        return len(self.features) * self.bank.channels

    def check_pipeline(self, pipeline) -> None:
        """Raise :class:`ModelError` naming what differs if ``pipeline`` does not make this sense's
        windows (checked as a one-sense model checks its pipeline)."""
        try:
            check_sense_fits((self.bank, self.features, self.window_samples, self.peak_mode, self.peak_threshold),
                             pipeline.bank, pipeline.features, pipeline.window_samples, pipeline.peaks.mode,
                             pipeline.peaks.threshold)
        except ModelError as exc:
            raise ModelError(f"sense {self.name!r}: {exc} (the model's senses feed [fusion] streams in their "
                             "order: are the two streams given the other way round?)") from None


@dataclass
class EarlyFusionModel:
    """One MLP on two senses' aligned feature windows.

    Attributes
    ----------
    senses : (Sense, Sense)
        In input order.
    classes : tuple of str
    mean, scale : ndarray, shape (inputs,)
        Standardisation of the concatenated inputs (from the training windows).
    mlp : MLP
    training : dict
        How it was trained (algorithm, epochs, seed, windows).
    """

    senses: tuple[Sense, Sense]
    classes: tuple[str, ...]
    mean: np.ndarray
    scale: np.ndarray
    mlp: MLP
    training: dict = field(default_factory=dict)

    @classmethod
    def train(cls, senses, values_a: np.ndarray, values_b: np.ndarray, labels, classes,
              epochs: int = DEFAULT_EPOCHS, seed: int = 0, hidden: int | None = None) -> "EarlyFusionModel":
        """Fit the scaling and the MLP on aligned windows: ``values_a[k]`` and ``values_b[k]`` cover
        the same time, shapes (n, features, channels) of each sense; ``labels`` (n,) index ``classes``."""
        senses = tuple(senses)
        x = early_inputs(cls._check(senses[0], values_a), cls._check(senses[1], values_b))
        mean = x.mean(axis=0)
        scale = x.std(axis=0)
        scale[scale == 0] = 1.0
        mlp, history = train_mlp((x - mean) / scale, np.asarray(labels), len(classes), hidden=hidden, epochs=epochs,
                                 seed=seed)
        info = {"algorithm": "iRPROP-", "epochs": len(history), "seed": seed, "final_mse": history[-1],
                "windows": int(len(x))}
        return cls(senses, tuple(classes), mean, scale, mlp, info)

    @staticmethod
    def _check(sense: Sense, values) -> np.ndarray:
        values = np.asarray(values, dtype=np.float64)
        expected = (len(sense.features), sense.bank.channels)
        if values.ndim != 3 or values.shape[1:] != expected:
            raise InputError(f"sense {sense.name!r}: feature windows must have shape (n, {expected[0]}, "
                             f"{expected[1]}), got {values.shape}")
        return values

    def outputs(self, values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
        """Output activations in [0, 1], shape (n, classes), for aligned windows of both senses."""
        x = early_inputs(self._check(self.senses[0], values_a), self._check(self.senses[1], values_b))
        return self.mlp.outputs((x - self.mean) / self.scale)

    # -- files ---------------------------------------------------------------------------------

    def header(self) -> dict:
        return {"format": EARLY_FORMAT, "version": EARLY_VERSION,
                "senses": [{"name": s.name, **sense_header(s.bank, s.features, s.window_samples, s.peak_mode,
                                                           s.peak_threshold)} for s in self.senses],
                "classes": list(self.classes), "layers": list(self.mlp.shape), "training": self.training}

    def save(self, path) -> Path:
        """Write the model to exactly ``path`` (an ``.npz`` archive); returns the path."""
        return save_model_archive(path, self.header(), self.mlp, self.mean, self.scale)

    @classmethod
    def load(cls, path) -> "EarlyFusionModel":
        """Read and validate an early-fusion model file; :class:`ModelError` says what is wrong."""
        path = Path(path)
        header, arrays = read_model_archive(path)

        def bad(msg):
            return ModelError(f"{path}: {msg}")

        if not isinstance(header, dict) or header.get("format") != EARLY_FORMAT:
            found = header.get("format") if isinstance(header, dict) else None
            raise bad(f"not a {EARLY_FORMAT} file (format is {found!r})"
                      + ("; it is a one-sense model: give it to a [[stream]], not to [fusion]"
                         if found == "supramodal-model" else ""))
        if type(header.get("version")) is not int or header["version"] != EARLY_VERSION:   # true == 1 in Python
            raise bad(f"format version {header.get('version')!r} is not supported (this program reads version "
                      f"{EARLY_VERSION}); retrain the model with this version")
        unknown = set(header) - {"format", "version", "senses", "classes", "layers", "training"}
        if unknown:
            raise bad(f"unknown header key(s) {sorted(unknown)}")
        raw = header.get("senses")
        if not (isinstance(raw, list) and len(raw) == 2 and all(isinstance(s, dict) for s in raw)):
            raise bad("'senses' must be a list of the two senses' descriptions")
        senses = []
        for i, s in enumerate(raw):
            extra = set(s) - {"name", *SENSE_KEYS}
            if extra or not isinstance(s.get("name"), str) or not s["name"]:
                raise bad(f"senses[{i}] must have a non-empty 'name' and the keys {list(SENSE_KEYS)} only")
            senses.append(Sense(s["name"], *sense_from_header(s, lambda m, i=i: bad(f"senses[{i}]: {m}"))))
        if senses[0].name == senses[1].name:
            raise bad(f"the two senses are both named {senses[0].name!r}")
        classes = classes_from_header(header, bad)
        n_in = senses[0].n_inputs + senses[1].n_inputs
        mlp, mean, scale = network_from_arrays(header, arrays, n_in, len(classes), bad,
                                               f"{senses[0].n_inputs} + {senses[1].n_inputs} inputs of the two senses")
        training = header.get("training", {})
        if not isinstance(training, dict):
            raise bad("'training' must be an object")
        return cls(tuple(senses), tuple(classes), mean, scale, mlp, training)
