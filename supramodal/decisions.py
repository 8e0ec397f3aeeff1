"""Decisions over time: per window, over the last N windows, or over the current contact.

A robot decides per touch, not per 100 ms. The classifier's outputs for one
window are turned into a distribution ``p_k = o_k / sum(o)`` (the logistic
outputs need not sum to 1); the accumulated decision is the argmax of

* ``"log"``: the summed log-posteriors ``sum_t log p_k(t)`` (naive-Bayes pooling), or
* ``"vote"``: the count of windows each class won (ties go to the larger summed output),

over the last ``n`` windows (``scope="last"``) or over every window since the
current contact began (``scope="contact"``). A contact is a run of consecutive
windows whose input RMS is at least ``threshold``; a window below it ends the
contact and resets the accumulation.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from supramodal.errors import InputError

SCOPES = ("window", "last", "contact")
METHODS = ("log", "vote")
#: Defaults of a decision (the scene's [decision] section takes them from here).
DEFAULT_SCOPE = "window"
DEFAULT_POOLED = 10
DEFAULT_METHOD = "log"
DEFAULT_CONTACT_THRESHOLD = 0.01
_EPS = 1e-12


@dataclass(frozen=True)
class Decision:
    """One decision.

    Attributes
    ----------
    label : int
        Winning class index, or -1 when out of contact.
    confidence : float
        The winner's share: ``p_label`` for one window; for an accumulated
        decision, the normalised posterior of the winner (``"log"``) or its
        fraction of the votes (``"vote"``).
    windows : int
        How many windows the decision is based on (0 when out of contact).
    """

    label: int
    confidence: float
    windows: int


def posteriors(outputs: np.ndarray) -> np.ndarray:
    """Output activations (n, classes) -> rows that sum to 1."""
    o = np.clip(np.asarray(outputs, dtype=np.float64), _EPS, None)
    return o / o.sum(axis=-1, keepdims=True)


def window_decision(outputs: np.ndarray) -> Decision:
    """Winner-take-all on one window's outputs, shape (classes,)."""
    p = posteriors(outputs)
    k = int(np.argmax(p))
    return Decision(k, float(p[k]), 1)


class DecisionAccumulator:
    """Pools per-window outputs into a decision over several windows.

    Parameters
    ----------
    n_classes : int
    scope : {"window", "last", "contact"}
        ``"window"`` decides each window alone (the paper's setting).
    n : int
        Windows pooled for ``scope="last"`` (default :data:`DEFAULT_POOLED`, 1 s of 100 ms windows);
        for ``"contact"``, the most windows kept (0 = unlimited).
    method : {"log", "vote"}
    """

    def __init__(self, n_classes: int, scope: str = DEFAULT_SCOPE, n: int = DEFAULT_POOLED,
                 method: str = DEFAULT_METHOD) -> None:
        if scope not in SCOPES:
            raise InputError(f"decision scope must be one of {SCOPES}, got {scope!r}")
        if method not in METHODS:
            raise InputError(f"decision method must be one of {METHODS}, got {method!r}")
        if scope == "last" and n < 1:
            raise InputError(f"scope 'last' needs n >= 1 windows, got {n}")
        if n < 0:
            raise InputError(f"n must be >= 0, got {n}")
        self.n_classes = int(n_classes)
        self.scope, self.method = scope, method
        maxlen = n if scope == "last" else (n or None)
        self._history: deque[np.ndarray] = deque(maxlen=maxlen)

    def reset(self) -> None:
        """Forget every pooled window (a contact ended)."""
        self._history.clear()

    def update(self, outputs: np.ndarray, in_contact: bool = True) -> Decision:
        """Add one window's outputs (classes,) and return the current decision."""
        outputs = np.asarray(outputs, dtype=np.float64)
        if outputs.shape != (self.n_classes,):
            raise InputError(f"expected {self.n_classes} outputs, got shape {outputs.shape}")
        if self.scope == "window":
            return window_decision(outputs)
        if self.scope == "contact" and not in_contact:
            self.reset()
            return Decision(-1, 0.0, 0)
        self._history.append(posteriors(outputs))
        p = np.array(self._history)
        if self.method == "log":
            score = np.log(p).sum(axis=0)
            k = int(np.argmax(score))
            post = np.exp(score - score.max())
            return Decision(k, float(post[k] / post.sum()), len(p))
        votes = np.bincount(np.argmax(p, axis=1), minlength=self.n_classes).astype(float)
        tie = votes == votes.max()
        k = int(np.argmax(np.where(tie, p.sum(axis=0), -np.inf)))
        return Decision(k, float(votes[k] / len(p)), len(p))


class ContactDetector:
    """Marks each window as in contact or not from the input's RMS, streaming.

    Parameters
    ----------
    window_samples : int
        Same windows as the feature pipeline.
    threshold : float
        RMS (full scale 1.0) at or above which a window is in contact (default
        :data:`DEFAULT_CONTACT_THRESHOLD`).
    """

    def __init__(self, window_samples: int, threshold: float = DEFAULT_CONTACT_THRESHOLD) -> None:
        if not (np.isfinite(threshold) and threshold >= 0):
            raise InputError(f"contact threshold must be a non-negative RMS, got {threshold!r}")
        self.window_samples = int(window_samples)
        self.threshold = float(threshold)
        self._energy = 0.0
        self._filled = 0

    def process(self, x: np.ndarray) -> np.ndarray:
        """Feed input samples, shape (L,) or (channels, L); return one bool per window completed."""
        x = np.asarray(x, dtype=np.float64)
        sq = (x * x).mean(axis=0) if x.ndim == 2 else x * x
        flags = []
        i = 0
        while i < sq.size:
            take = min(self.window_samples - self._filled, sq.size - i)
            self._energy += float(sq[i : i + take].sum())
            self._filled += take
            i += take
            if self._filled == self.window_samples:
                flags.append(np.sqrt(self._energy / self.window_samples) >= self.threshold)
                self._energy, self._filled = 0.0, 0
        return np.array(flags, dtype=bool)
