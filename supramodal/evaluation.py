"""What a user needs to trust a model.

How accuracy grows with the windows pooled, how soon a touch is decided at a confidence
threshold, and which channels carry the decision. Pure numpy on a model's outputs; no files, no
devices.
"""

from __future__ import annotations

import numpy as np

from supramodal.calibration import winner
from supramodal.decisions import DecisionAccumulator
from supramodal.errors import InputError

__all__ = ["ANYTIME_THRESHOLDS", "DETECT_WITHIN", "POOLED_WINDOWS", "anytime_sweep", "change_detections",
           "pooled_accuracy", "permutation_importance"]

#: Numbers of consecutive windows whose pooled decision ``evaluate`` reports (and the whole recording).
POOLED_WINDOWS = (1, 2, 5, 10)
#: Confidence thresholds of the anytime decisions ``evaluate`` and ``experiment calibration`` report.
ANYTIME_THRESHOLDS = (0.5, 0.7, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995, 0.999)
#: A change of texture counts as detected when it is signalled within this many windows of its
#: boundary (the boundary's window the first).
DETECT_WITHIN = 5


def pooled_accuracy(log_posteriors_by_recording, truths, n: int) -> tuple[float | None, int]:
    """Accuracy of decisions pooled over ``n`` consecutive windows, as the node pools a contact.

    Each recording's windows are cut into runs of ``n`` from its start (a shorter rest is left
    out); a run's decision is the class of the largest summed log-posterior
    (:class:`~supramodal.decisions.DecisionAccumulator`'s ``"log"`` method).

    Parameters
    ----------
    log_posteriors_by_recording : sequence of ndarray, each (windows, classes)
        The model's log-posteriors for each recording's windows, in time order.
    truths : sequence of int
        Each recording's class index.
    n : int
        Windows per run, >= 1.

    Returns
    -------
    accuracy : float or None
        Share of runs decided right; None when no recording holds ``n`` windows.
    runs : int
        How many runs were decided.
    """
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise InputError(f"windows pooled must be an integer >= 1, got {n!r}")
    hits = runs = 0
    for logp, truth in zip(log_posteriors_by_recording, truths):
        logp = np.asarray(logp, dtype=np.float64)
        m = len(logp) // n
        if m == 0:
            continue
        score = logp[: m * n].reshape(m, n, -1).sum(axis=1)
        hits += int(np.count_nonzero(winner(score) == truth))       # a tie is no decision: not a hit
        runs += m
    return (hits / runs if runs else None), runs


def change_detections(truths, signalled) -> tuple[list[tuple[int, int | None]], int]:
    """Score the texture changes signalled within one contact against the truth.

    A *boundary* is a window whose true texture differs from the window before it. Its detection is
    the first change signalled from that window up to (not including) the next boundary; the delay
    is ``detection - boundary + 1`` windows (signalled in the boundary's own window: 1). Every other
    change signalled is a false one (before the first boundary, or a second within one segment).

    Parameters
    ----------
    truths : sequence
        The true texture of each of the contact's windows, in order (consecutive windows, no
        lift-off between them).
    signalled : iterable of int
        The windows (indices into ``truths``) at which a change was signalled.

    Returns
    -------
    boundaries : list of (int, int or None)
        Per boundary, its window and the window of its detection (None: not signalled before the
        next boundary or the contact's end).
    false : int
        Changes signalled that detect no boundary.
    """
    n = len(truths)
    at = sorted(int(t) for t in signalled)
    if any(not 0 <= t < n for t in at):
        raise InputError(f"a change signalled outside the contact's {n} windows: {at}")
    starts = [b for b in range(1, n) if truths[b] != truths[b - 1]]
    out: list[tuple[int, int | None]] = []
    for b, end in zip(starts, starts[1:] + [n]):
        out.append((b, next((t for t in at if b <= t < end), None)))
    return out, len(at) - sum(t is not None for _, t in out)


def permutation_importance(outputs, windows: np.ndarray, truth: np.ndarray, repeats: int = 5,
                           seed: int = 0) -> np.ndarray:
    """How much window accuracy each channel carries: the drop when its features are shuffled.

    Channel ``c``'s feature values (every feature of it) are permuted across the windows,
    breaking their link with the labels while keeping their distribution; the drop in
    accuracy, averaged over ``repeats`` permutations, is the channel's importance.

    Parameters
    ----------
    outputs : callable
        ``outputs(windows) -> (n, classes)``, scores whose largest value per row is the decision,
        e.g. :meth:`TextureModel.log_posteriors` (a tie is no decision).
    windows : ndarray, shape (n, features, channels)
    truth : ndarray of int, shape (n,)
    repeats : int, optional
        Permutations per channel (default 5).
    seed : int, optional
        Seed of the permutations (default 0).

    Returns
    -------
    ndarray, shape (channels,)
        Accuracy lost per channel (0 = the decision does not use it; can be slightly negative
        by chance).
    """
    windows = np.asarray(windows)
    truth = np.asarray(truth)
    rng = np.random.default_rng(seed)
    base = float(np.mean(winner(outputs(windows)) == truth))
    drop = np.zeros(windows.shape[2])
    for c in range(windows.shape[2]):
        for _ in range(repeats):
            shuffled = windows.copy()
            shuffled[:, :, c] = windows[rng.permutation(len(windows)), :, c]
            drop[c] += base - float(np.mean(winner(outputs(shuffled)) == truth))
    return drop / repeats


def anytime_sweep(log_posteriors, labels, runs, correlation: float, thresholds=ANYTIME_THRESHOLDS,
                  caps=None) -> list[dict]:
    """Contacts decided as soon as their pooled confidence reaches each threshold.

    Parameters
    ----------
    log_posteriors : ndarray, shape (windows, classes)
        Calibrated log-posteriors of test windows.
    labels : ndarray of int, shape (windows,)
    runs : list of ndarray
        Each contact's windows, in time order (one texture each).
    correlation : float
        The pooling's window correlation (the model's).
    thresholds : sequence of float in (0, 1)
    caps : array-like (classes, classes) or None
        The pooling's caps per pair of classes. A calibrated model's pooling is
        ``correlation, caps = model.calibration.contact_pooling``, as the node pools.

    Returns
    -------
    list of dict
        Per threshold: ``confidence``, ``contacts``, ``decided`` (how many reached it),
        ``right`` (decided and right), ``windows`` (the windows each decided contact took),
        ``median_windows`` (None if none was decided) and ``end_right``: contacts whose
        decision at their last window (the final one, or the pooled one if never final) is right.
    """
    lp = np.asarray(log_posteriors, dtype=np.float64)
    y = np.asarray(labels)
    out = []
    for c in thresholds:
        windows, right, end_right = [], 0, 0
        for r in runs:
            acc = DecisionAccumulator(lp.shape[1], "contact", 0, "log", correlation, c, caps=caps)
            for t in r:
                d = acc.update(lp[t])
            if d.decided:
                windows.append(d.windows)
                right += int(d.label == y[r[0]])
            end_right += int(d.label == y[r[0]])
        out.append({"confidence": float(c), "contacts": len(runs), "decided": len(windows), "right": right,
                    "windows": windows, "median_windows": float(np.median(windows)) if windows else None,
                    "end_right": end_right})
    return out
