"""Decisions of two senses fused: late (weighted sum of per-sense log-posteriors) and early (one
network on both senses' aligned feature vectors, the supramodal network of the paper's Sect. 5).

Pure functions on arrays of aligned windows: window k of one sense covers the same time as window
k of the other (pairing windows of live streams on a common clock is the node's job).
"""

from __future__ import annotations

import numpy as np

from supramodal.decisions import posteriors
from supramodal.errors import InputError
from supramodal.mlp import train_mlp

#: Weights of the first sense tried when learning late fusion (the second gets 1 - w).
LATE_WEIGHTS = np.linspace(0.0, 1.0, 21)


def fuse_late(outputs_a: np.ndarray, outputs_b: np.ndarray, weight: float) -> np.ndarray:
    """Fused log-posteriors ``w log p_a + (1 - w) log p_b``, shape (windows, classes).

    ``outputs_*`` are the two networks' output activations for the same windows, shape
    (windows, classes); the fused decision is the argmax, and pooling sums rows, as for one sense.
    """
    a, b = np.asarray(outputs_a), np.asarray(outputs_b)
    if a.shape != b.shape or a.ndim != 2:
        raise InputError(f"the two senses' outputs must have one shape (windows, classes), got {a.shape} and {b.shape}")
    if not 0.0 <= weight <= 1.0:
        raise InputError(f"the late-fusion weight must lie in [0, 1], got {weight!r}")
    return weight * np.log(posteriors(a)) + (1.0 - weight) * np.log(posteriors(b))


def learn_late_weight(outputs_a: np.ndarray, outputs_b: np.ndarray, labels: np.ndarray) -> float:
    """The weight of :data:`LATE_WEIGHTS` whose fused decisions are right most often on
    ``labels`` (windows held out from the networks' training: on their own training windows both
    networks are near perfect and say nothing of each other's worth); ties go to the weight
    nearest 0.5."""
    labels = np.asarray(labels)
    scores = [np.mean(np.argmax(fuse_late(outputs_a, outputs_b, w), axis=1) == labels) for w in LATE_WEIGHTS]
    best = max(scores)
    return float(min((w for w, s in zip(LATE_WEIGHTS, scores) if s == best), key=lambda w: abs(w - 0.5)))


class Standardised:
    """An MLP on standardised, flattened feature windows (the scaling from the training windows).

    Parameters
    ----------
    values : ndarray, shape (windows, ...)
        Training windows (any trailing shape: flattened).
    labels : ndarray of int, shape (windows,)
    n_classes : int
    epochs, seed
        As :func:`supramodal.mlp.train_mlp`.
    """

    def __init__(self, values, labels, n_classes: int, epochs: int, seed: int) -> None:
        x = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
        self.mean = x.mean(axis=0)
        self.scale = x.std(axis=0)
        self.scale[self.scale == 0] = 1.0
        self.mlp, _ = train_mlp((x - self.mean) / self.scale, np.asarray(labels), n_classes, epochs=epochs, seed=seed)

    def outputs(self, values) -> np.ndarray:
        x = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
        return self.mlp.outputs((x - self.mean) / self.scale)


def early_inputs(values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
    """Both senses' aligned windows side by side, shape (windows, inputs_a + inputs_b): the
    supramodal network's input (e.g. 20 whisker + 50 cochlea channels of Af)."""
    a = np.asarray(values_a).reshape(len(values_a), -1)
    b = np.asarray(values_b).reshape(len(values_b), -1)
    if len(a) != len(b):
        raise InputError(f"early fusion needs aligned windows: {len(a)} and {len(b)}")
    return np.concatenate([a, b], axis=1)
