"""Decisions of two senses fused, late and early.

Late: a weighted sum of per-sense log-posteriors. Early: one network on both senses' aligned
feature vectors, the supramodal network of the paper's Sect. 5.

Pure functions on arrays of aligned windows: window k of one sense covers the same time as window
k of the other (pairing windows of live streams on a common clock is the node's job).
"""

from __future__ import annotations

import numpy as np

from supramodal.calibration import log_loss
from supramodal.errors import InputError
from supramodal.logdomain import log_softmax

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


def sharpness_bound(weight: float) -> float:
    """Return the largest sharpness a late fusion of ``weight`` may learn: ``1 / max(w, 1 - w)``.

    At the bound the sense that counts more enters the fused log-posteriors at full strength,
    ``s w = 1``, and no sense ever beyond: the fusion may be as sure as the two senses' calibrated
    posteriors multiplied (naive Bayes, at ``w = 0.5`` and ``s = 2``), never surer. Beyond it, a
    sharpness learned on windows where both senses are right says 1.00 on every window, the wrong
    ones too, on a touch those windows did not come from (issue 34: 118.6 learned, every wrong fused
    window at 1.00, the fused log loss worse than one sense's alone).
    """
    return 1.0 / max(weight, 1.0 - weight)


def learn_late_fusion(log_posteriors_a: np.ndarray, log_posteriors_b: np.ndarray, labels: np.ndarray
                      ) -> tuple[float, float]:
    """``(weight, sharpness)`` of :func:`fuse_late` learned on held-out windows.

    For each weight of :data:`LATE_WEIGHTS` the sharpness that minimises the fused log loss, up to
    :func:`sharpness_bound`; the weight kept is the middle of the plateau around the best: the
    weights whose fused log loss is within one standard error (of the per-window difference) of the
    lowest, contiguous with it. A weight at the plateau's edge may stand beside a cliff that a new
    touch crosses (issue 34: 0.05..0.55 right on 0.990..0.998 of windows, 0.65 on 0.842); its middle
    is about as good on these windows and farther from the cliff. The weights 0 and 1 (one sense alone,
    at most as sure as its calibration) are candidates, so on these windows the best weight's log loss
    is never above the better sense's, and the weight kept is within one standard error of it.

    The windows must be held out from both senses' networks (out-of-fold windows): on their own
    training windows both are nearly always right and say nothing of each other's worth.
    """
    a, b = np.asarray(log_posteriors_a, dtype=np.float64), np.asarray(log_posteriors_b, dtype=np.float64)
    y = np.asarray(labels)
    if len(y) == 0 or a.shape != b.shape or a.shape[0] != len(y):
        raise InputError(f"learning a late fusion needs held-out windows of both senses and their labels, got "
                         f"{a.shape}, {b.shape} and {y.shape}")
    sharpness, losses = [], []
    for w in LATE_WEIGHTS:
        mixed = w * a + (1.0 - w) * b
        s = _fit_sharpness(mixed, y, sharpness_bound(w))
        sharpness.append(s)
        losses.append(-log_softmax(s * mixed, axis=1)[np.arange(len(y)), y])
    middle = plateau_middle(losses)
    return float(LATE_WEIGHTS[middle]), sharpness[middle]


def plateau_middle(losses) -> int:
    """Return the middle of the plateau around the best of several candidates.

    Each candidate is given by its losses on the same windows (a sequence of arrays (n,),
    candidates in order of a parameter). The plateau is the candidates whose mean loss is within
    one standard error (of the per-window difference) of the lowest, contiguous with it; of two
    middles, the one nearer the best is returned.
    """
    best = int(np.argmin([np.mean(loss) for loss in losses]))
    plateau = [_within_one_error(np.asarray(loss), np.asarray(losses[best])) for loss in losses]
    lo = hi = best
    while lo > 0 and plateau[lo - 1]:
        lo -= 1
    while hi < len(plateau) - 1 and plateau[hi + 1]:
        hi += 1
    return min({(lo + hi) // 2, (lo + hi + 1) // 2}, key=lambda k: abs(k - best))


def _within_one_error(loss: np.ndarray, best: np.ndarray) -> bool:
    """Whether the windows' losses ``loss`` are, on average, within one standard error of ``best``'s."""
    d = loss - best
    return bool(d.mean() <= (d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else 0.0))


def _fit_sharpness(mixed: np.ndarray, labels: np.ndarray, upper: float) -> float:
    from scipy.optimize import minimize_scalar

    r = minimize_scalar(lambda ls: log_loss(log_softmax(np.exp(ls) * mixed, axis=1), labels),
                        bounds=(-7.0, float(np.log(upper))), method="bounded", options={"xatol": 1e-4})
    # the bounded search never returns its bounds: where the loss falls all the way, take the bound itself
    inside = float(np.exp(r.x))
    at_bound = log_loss(log_softmax(upper * mixed, axis=1), labels)
    return float(upper) if at_bound <= log_loss(log_softmax(inside * mixed, axis=1), labels) else inside


def early_inputs(values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
    """Both senses' aligned windows side by side, shape (windows, inputs_a + inputs_b).

    That is the supramodal network's input (e.g. 20 whisker + 50 cochlea channels of Af).
    """
    a = np.asarray(values_a).reshape(len(values_a), -1)
    b = np.asarray(values_b).reshape(len(values_b), -1)
    if len(a) != len(b):
        raise InputError(f"early fusion needs aligned windows: {len(a)} and {len(b)}")
    return np.concatenate([a, b], axis=1)
