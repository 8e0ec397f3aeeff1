"""Decisions of two senses fused: late (weighted sum of per-sense log-posteriors) and early (one
network on both senses' aligned feature vectors, the supramodal network of the paper's Sect. 5).

Pure functions on arrays of aligned windows: window k of one sense covers the same time as window
k of the other (pairing windows of live streams on a common clock is the node's job).
"""

from __future__ import annotations

import numpy as np
from scipy.special import log_softmax

from supramodal.calibration import log_loss, winner
from supramodal.errors import InputError

#: Weights of the first sense tried when learning late fusion (the second gets 1 - w).
LATE_WEIGHTS = np.linspace(0.0, 1.0, 21)


def fuse_late(log_posteriors_a: np.ndarray, log_posteriors_b: np.ndarray, weight: float,
              sharpness: float = 1.0) -> np.ndarray:
    """Fused log-posteriors ``log_softmax(s (w log p_a + (1 - w) log p_b))``, shape (windows, classes).

    ``log_posteriors_*`` are the two senses' (calibrated) log-posteriors of the same windows,
    shape (windows, classes), e.g. :meth:`supramodal.model.TextureModel.log_posteriors`. The
    weight ``w`` sets which sense counts more (the decision depends on it alone); the sharpness
    ``s`` > 0 tempers the fused confidence (learned with the weight on held-out windows by
    :func:`learn_late_fusion`; 1 = the weighted product as it stands).
    """
    a, b = np.asarray(log_posteriors_a, dtype=np.float64), np.asarray(log_posteriors_b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise InputError(f"the two senses' log-posteriors must have one shape (windows, classes), got {a.shape} "
                         f"and {b.shape}")
    if not 0.0 <= weight <= 1.0:
        raise InputError(f"the late-fusion weight must lie in [0, 1], got {weight!r}")
    if not (np.isfinite(sharpness) and sharpness > 0):
        raise InputError(f"the late-fusion sharpness must be a finite number > 0, got {sharpness!r}")
    return log_softmax(sharpness * (weight * a + (1.0 - weight) * b), axis=1)


def learn_late_fusion(log_posteriors_a: np.ndarray, log_posteriors_b: np.ndarray, labels: np.ndarray
                      ) -> tuple[float, float]:
    """``(weight, sharpness)`` of :func:`fuse_late` learned on held-out windows.

    The weight is the one of :data:`LATE_WEIGHTS` whose fused decisions are right most often
    (ties: the lower fused log loss, then the weight nearest 0.5); the sharpness then minimises
    the fused log loss. The windows must be held out from both senses' networks (out-of-fold
    windows): on their own training windows both are nearly always right and say nothing of
    each other's worth.
    """
    a, b = np.asarray(log_posteriors_a, dtype=np.float64), np.asarray(log_posteriors_b, dtype=np.float64)
    y = np.asarray(labels)
    if len(y) == 0 or a.shape != b.shape or a.shape[0] != len(y):
        raise InputError(f"learning a late fusion needs held-out windows of both senses and their labels, got "
                         f"{a.shape}, {b.shape} and {y.shape}")
    candidates = []
    for w in LATE_WEIGHTS:
        mixed = w * a + (1.0 - w) * b
        right = float(np.mean(winner(mixed) == y))
        s = _fit_sharpness(mixed, y)
        candidates.append((-right, log_loss(log_softmax(s * mixed, axis=1), y), abs(w - 0.5), float(w), s))
    _, _, _, weight, sharpness = min(candidates)
    return weight, sharpness


def _fit_sharpness(mixed: np.ndarray, labels: np.ndarray) -> float:
    from scipy.optimize import minimize_scalar

    r = minimize_scalar(lambda ls: log_loss(log_softmax(np.exp(ls) * mixed, axis=1), labels), bounds=(-7.0, 5.0),
                        method="bounded", options={"xatol": 1e-4})
    return float(np.exp(r.x))


def early_inputs(values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
    """Both senses' aligned windows side by side, shape (windows, inputs_a + inputs_b): the
    supramodal network's input (e.g. 20 whisker + 50 cochlea channels of Af)."""
    a = np.asarray(values_a).reshape(len(values_a), -1)
    b = np.asarray(values_b).reshape(len(values_b), -1)
    if len(a) != len(b):
        raise InputError(f"early fusion needs aligned windows: {len(a)} and {len(b)}")
    return np.concatenate([a, b], axis=1)
