"""Confidence that means what it says: calibrated posteriors, their measures, and novelty.

Calibrated posteriors of one window and of a contact, the measures of calibration, and a
novelty score for textures the model never met.

The network (:mod:`supramodal.mlp`) ends in logistic units trained towards 0 and 1 with FANN's
tanh error, which drives their pre-activations (the *logits* ``z``) to hundreds: the outputs of
the losing classes are exactly 0.0 in float64 and ``o / sum(o)`` says 1.00 whether the window is
right or wrong. Everything here works on the logits, in the log domain, and never clips.

Window posteriors
    Uncalibrated (a model file without a calibration): the normalised outputs
    ``p_k = o_k / sum_j o_j`` with ``o = sigmoid(z)``, computed as ``log sigmoid(z)`` minus their
    log-sum-exp (:func:`normalised_log_posteriors`): the same numbers as before where they were
    representable, and finite everywhere.

    Calibrated (:class:`Calibration`): ``p = softmax(a * asinh(z / c))``, two numbers fitted by
    minimising the log loss of held-out windows (:func:`fit_window_calibration`). ``asinh`` is odd
    and increasing, so the winner of every window is the network's (the paper's winner-take-all
    is unchanged); it is linear for ``|z| << c`` and logarithmic beyond, so the few logits in the
    hundreds no longer decide the temperature of all the others. As ``c`` grows the map becomes
    plain temperature scaling ``softmax(z / T)`` with ``T = c / a``, which it contains.

Contact posteriors
    The windows of one touch are not independent: summing their log-posteriors (naive Bayes)
    counts the same evidence many times. The pooled posterior of ``n`` windows is
    ``softmax(g(n) * sum_t log p_t)`` with ``g(n) = n_eff(n) / n``, where ``n_eff`` is the
    effective number of independent windows among ``n`` whose correlation decays with their
    distance as ``rho ** lag`` (a first-order autoregressive model; the classical
    ``n / (1 + 2 sum_k (1 - k / n) rho ** k)``): ``rho = 0`` is naive Bayes, ``rho -> 1`` the mean of
    the windows (as sure as one window), and for ``0 < rho < 1`` the evidence still grows without
    bound, ``(1 - rho) / (1 + rho)`` window's worth per window, as a stationary touch should. ``rho``
    is fitted on held-out runs of consecutive windows (:func:`fit_pooling`). Scaling by
    ``g(n) > 0`` keeps the pooled winner that of the plain sum.

Unknown textures
    :class:`Novelty`: the squared Mahalanobis distance of the logarithm of a window's inputs to the
    nearest class mean (one covariance shared by the classes, shrunk towards its diagonal); for a
    contact, that of the mean of its windows, times their number (evidence that grows with the
    contact). A model trained now measures both under each class's predictive covariance for a new
    touch, whose gains move all its windows alike (:class:`TouchSpread`). Each comes with its
    distribution on held-out windows and contacts of known textures only, so that a threshold is a
    false-unknown rate.

Pure numpy/scipy; the models (:mod:`supramodal.model`, :mod:`supramodal.fused_model`) fit and
store these, the node applies them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from supramodal.errors import InputError
from supramodal.logdomain import log_softmax, logsumexp
from supramodal.mlp import EARLY_STOP_PATIENCE

__all__ = [
    "CALIBRATION_METHOD", "CHANGES_KEPT", "DEFAULT_CALIBRATION_FOLDS", "HeldOutChanges", "ECE_BINS",
    "NOVELTY_METHOD", "NOVELTY_TOUCH_METHOD", "NOVELTY_TOUCH_SPREAD", "Calibration", "HeldOutLogits",
    "Novelty", "TouchSpread", "calibration_of_held_out", "fold_tasks", "fold_work", "held_out_folds",
    "joint_stop_epochs", "train_fold_networks",
    "brier_score", "calibration_line", "calibration_report", "cap_gaps", "confusion_caps", "fit_capped_pooling",
    "fit_capped_window_calibration", "effective_windows", "expected_calibration_error", "fewest_groups_of_a_label",
    "fit_novelty", "fit_pooling", "fit_window_calibration", "log_loss", "log_sigmoid", "normalised_log_posteriors",
    "novelty_warp", "pool_log_posteriors", "reliability", "touch_spread", "winner",
]

#: Name of the window map stored in model files. Its optional keys ``caps`` and ``contact_caps``
#: (:func:`cap_gaps`) are new; a program of before them refuses a file that has them (exact keys).
CALIBRATION_METHOD = "asinh-temperature"
#: Sharpness ``q`` of the soft minimum ``d / (1 + (d / L) ** q) ** (1 / q)`` of a gap ``d`` and its
#: cap ``L``: within a few per cent of ``min(d, L)``, and strictly increasing in ``d``.
CAP_SHARPNESS = 16.0
#: Least cap (nats) a pair's out-of-fold counts may set, before the fitted factor: a pair whose
#: winner is as often the other class keeps a winner, barely.
CAP_FLOOR = 0.05
#: Range of a stored cap (nats).
CAP_BOUNDS = (1e-3, 1e4)
#: Range of the fitted factor of the counts' caps (:func:`confusion_caps`): a cap bounds the evidence
#: of the windows or contacts that deserve the most, so it never lies below the held-out odds of the
#: decisions for that class on average (factor 1). Fitted factors on the two-sense world: 1.4 to 2.4.
FACTOR_BOUNDS = (1.0, 1e2)
#: Grouped folds whose held-out windows fit a model's calibration, and so the networks a calibrated model
#: deploys (the one home of this default): the fold networks themselves, as an ensemble, so that the
#: calibration is fitted on the deployed networks' own held-out logits (and applied to their mean). Three: two
#: cost less, but a network of half the windows was sure and wrong on a new touch; three on the whisker
#: reference gave ECE 0.045 and log loss 0.474 against 0.038 and 0.535 for ten folds beside a network of all
#: the windows (the design before 2026-11-30, five times the CPU; docs/model.md, "The deployed networks").
DEFAULT_CALIBRATION_FOLDS = 3
#: Range of the window map's two numbers (``a`` and ``c``): where the fit looks, and what a model
#: file may hold.
MAP_BOUNDS = (1e-3, 1e4)
#: Bins of the expected calibration error and of the reliability diagram.
ECE_BINS = 15
#: Consecutive held-out windows of one recording that make one run when the pooling is fitted
#: (2 s of 100 ms windows); every prefix of a run, 1 .. this many windows, is scored.
POOLING_RUN = 20
#: Fraction of the covariance's diagonal mixed into it (shrinkage) for the novelty score.
NOVELTY_SHRINK = 0.1
#: Quantiles of the held-out novelty scores kept in a model: 0, 0.5, ..., 100 %.
NOVELTY_QUANTILES = np.linspace(0.0, 1.0, 201)


# -- log-domain posteriors ---------------------------------------------------------------------

def log_sigmoid(z) -> np.ndarray:
    """``log(1 / (1 + exp(-z)))`` without overflow or underflow to -inf (for finite ``z``)."""
    z = np.asarray(z, dtype=np.float64)
    return -np.logaddexp(0.0, -z)


def normalised_log_posteriors(logits) -> np.ndarray:
    """Log of the normalised outputs ``o_k / sum_j o_j``, ``o = sigmoid(logits)``, along the last axis.

    The uncalibrated posteriors of a model file without a calibration, finite for finite logits
    (an output of exactly 0.0 in float64 still has its logarithm here).
    """
    ls = log_sigmoid(logits)
    return ls - logsumexp(ls, axis=-1, keepdims=True)


def winner(log_posteriors) -> np.ndarray:
    """Winner-take-all per row of ``log_posteriors`` (..., classes): the class index, or -1 on a tie.

    A tie is a largest value shared by several classes: it is no decision, and it is never
    broken by the classes' order.
    """
    lp = np.asarray(log_posteriors, dtype=np.float64)
    k = np.argmax(lp, axis=-1)
    tied = np.count_nonzero(lp == lp.max(axis=-1, keepdims=True), axis=-1) > 1
    return np.where(tied, -1, k)


def effective_windows(n, correlation: float) -> np.ndarray:
    """Independent windows worth ``n`` consecutive windows whose correlation at lag ``k`` is ``correlation ** k``.

    That is ``n / (1 + 2 sum_{k=1}^{n-1} (1 - k/n) rho^k)``, in closed form.

    1 for ``n = 1`` whatever ``rho``; ``n`` for ``rho = 0``; 1 for ``rho = 1``.
    """
    n = np.asarray(n, dtype=np.float64)
    r = float(correlation)
    if r <= 0.0:
        return n.copy()
    if r >= 1.0:
        return np.ones_like(n)
    if 1.0 - r < 1e-3:
        # The closed form cancels catastrophically near rho = 1 (two terms of order 1/(1 - rho)^2):
        # sum the series itself, which is then short of no precision.
        return np.vectorize(lambda m: m / (1 + 2 * float(np.sum((1 - np.arange(1, m) / m) * r ** np.arange(1, m)))),
                            otypes=[np.float64])(n)
    # sum_{k=1}^{n-1} (1 - k/n) r^k = r / (1 - r) - r (1 - r^n) / (n (1 - r)^2)
    s = r / (1 - r) - r * (1 - r ** n) / (n * (1 - r) ** 2)
    return n / (1 + 2 * s)


def pool_log_posteriors(log_posteriors, correlation: float, caps=None) -> np.ndarray:
    """Pooled log-posteriors of the windows ``log_posteriors`` (n, classes) of one contact, shape (classes,).

    The pool is ``log_softmax(g(n) sum_t log p_t)``, ``g(n) = effective_windows(n, correlation) / n``;
    with ``caps`` (a calibration's contact caps), :func:`cap_gaps` of it instead.
    """
    lp = np.asarray(log_posteriors, dtype=np.float64)
    n = lp.shape[0]
    if n == 0:
        raise InputError("pooling needs at least one window")
    pooled = lp.sum(axis=0) * (effective_windows(n, correlation) / n)
    return log_softmax(pooled) if caps is None else cap_gaps(pooled, caps)


def cap_gaps(scores, caps) -> np.ndarray:
    """Log-posteriors ``log_softmax`` of ``scores`` (..., classes), each row's gaps to its winner capped.

    The caps are per pair of classes.

    With ``k`` the row's winner (its largest score) and ``d_j = s_k - s_j >= 0`` its lead over
    class ``j``, the lead becomes ``d_j / (1 + (d_j / L_kj) ** q) ** (1 / q)`` (``q`` =
    :data:`CAP_SHARPNESS`): ``d_j`` where it is well below the cap ``L_kj = caps[k, j] > 0``, about
    ``L_kj`` beyond. The odds of the winner against ``j`` are then at most ``exp(L_kj)``.

    A lead stays > 0 when it was > 0 and 0 when it was 0, and grows with ``d_j``: every row keeps
    its winner, and a tie stays a tie (whichever tied class is taken as ``k``, the tied classes
    keep leads of 0).
    """
    s = np.asarray(scores, dtype=np.float64)
    L = np.array(caps, dtype=np.float64)
    np.fill_diagonal(L, 1.0)                        # a class against itself: its lead is 0 whatever the cap
    k = np.argmax(s, axis=-1)
    d = np.take_along_axis(s, k[..., None], axis=-1) - s
    with np.errstate(divide="ignore"):
        log_ratio = np.log(d) - np.log(L[k])        # d = 0: -inf, the lead stays 0; the diagonal: d = 0
    capped = d * np.exp(-np.logaddexp(0.0, CAP_SHARPNESS * log_ratio) / CAP_SHARPNESS)
    return log_softmax(-capped, axis=-1)


def confusion_caps(predicted, labels, n_classes: int) -> np.ndarray:
    """Caps per pair of classes from held-out decisions: ``L[k, j] = log((N[k, k] + 1) / (N[j, k] + 1))``.

    ``N[t, p]`` is the count of held-out decisions for ``p`` of class ``t`` (Laplace's +1); each
    cap is at least :data:`CAP_FLOOR`, the diagonal 0 (no cap of a class against itself).

    ``exp(L[k, j])`` estimates the odds of ``k`` against ``j`` among the decisions for ``k``: about 1
    for a pair the model cannot tell apart, large for a pair it never confuses.
    """
    n = np.zeros((n_classes, n_classes))
    np.add.at(n, (np.asarray(labels), np.asarray(predicted)), 1.0)
    caps = np.maximum(np.log((np.diag(n)[:, None] + 1.0) / (n.T + 1.0)), CAP_FLOOR)
    np.fill_diagonal(caps, 0.0)
    return caps


class _Prefixes:
    """Every prefix of every run of log-posteriors, summed once.

    Pooling them at a given correlation is then one vectorised step: the pooling fits
    (:func:`fit_pooling`, :func:`fit_capped_pooling`) pool them at thousands of correlations,
    and a loop over runs made those fits most of a model's training time.

    Parameters
    ----------
    runs : sequence of ndarray, each (windows >= 1, classes)
    """

    def __init__(self, runs) -> None:
        self.sums = np.concatenate([np.cumsum(lp, axis=0) for lp in runs])
        #: Each prefix's length (its number of windows), float64, shape (prefixes,).
        self.lengths = np.concatenate([np.arange(1, len(lp) + 1, dtype=np.float64) for lp in runs])
        self._n = np.arange(1, len(max(runs, key=len)) + 1, dtype=np.float64)
        self._at = self.lengths.astype(np.intp) - 1

    def pooled(self, correlation: float) -> np.ndarray:
        """Return the pooled log-posteriors of every prefix (prefixes, classes): ``log_softmax(g(n) sum_t log p_t)``."""
        g = effective_windows(self._n, correlation) / self._n
        return log_softmax(self.sums * g[self._at][:, None], axis=1)


# -- fitting -------------------------------------------------------------------------------------

def _window_map(logits, temperature: float, scale: float) -> np.ndarray:
    return np.arcsinh(np.asarray(logits, dtype=np.float64) / scale) * temperature


#: Starts ``(log a, log c)`` of the window map's fit (those of the Nelder-Mead fit of before): where the
#: map is near the identity, near a temperature of 10 and in between. Each is a quasi-Newton descent of
#: a few dozen evaluations; the best end is kept (the loss has a long, flat valley towards plain
#: temperature scaling, ``c`` -> infinity, where descents from different starts may stop apart).
_MAP_STARTS = ((0.0, 0.0), (0.0, math.log(10.0)), (math.log(3.0), math.log(30.0)))
#: Largest logit a fit takes: ``z / c`` stays finite for every ``c`` it tries (>= ``MAP_BOUNDS[0]``).
_LARGEST_LOGIT = float(np.finfo(np.float64).max) * MAP_BOUNDS[0] / 2
#: Largest ``q log(d / L)`` of :func:`_capped_loss`: its exponential stays finite.
_LARGEST_EXP = 700.0
#: Options of the quasi-Newton fits (``scipy.optimize.minimize``'s SLSQP, whose quasi-Newton steps
#: keep within the bounds): a step that changes the loss (about 1 nat) by less than ``ftol`` ends it.
_QUASI_NEWTON = {"ftol": 1e-12, "maxiter": 500}


def _capped_loss(d, log_caps, target) -> tuple[float, np.ndarray, np.ndarray]:
    """Smoothed log loss of :func:`cap_gaps`' posteriors from the leads, and its derivatives.

    The arrays are laid out (classes, n), one column per decision: sums over the classes are then
    sums of rows, which numpy does at the speed of the elementwise operations.

    Parameters
    ----------
    d : ndarray, shape (classes, n)
        Each decision's leads ``d_j >= 0`` of its winner over class ``j`` (0 at the winner).
    log_caps : ndarray, shape (classes, n)
        The log of each lead's cap ``L_kj`` (any finite value where ``d_j`` is 0).
    target : ndarray, shape (classes, n)
        Targets whose columns sum to 1 (:func:`_smoothed_targets`).

    Returns
    -------
    loss : float
        ``-mean_i sum_j t_ij log p_ij``, ``log p`` the log-posteriors :func:`cap_gaps` makes of these leads.
    by_lead, by_log_cap : ndarray, shape (classes, n)
        The loss's derivatives by each ``d_ij`` and each ``log L_ij``.
    """
    n = d.shape[1]
    with np.errstate(divide="ignore"):
        x = np.log(d)                               # d = 0: -inf, and then x = 0: a lead of 0 stays 0
    x -= log_caps
    x *= CAP_SHARPNESS
    np.minimum(x, _LARGEST_EXP, out=x)              # never reached by a window map (d / L < 1.5e10)
    np.exp(x, out=x)                                # (d / L) ** q
    soft = np.log1p(x)
    shrink = np.exp(soft * (-1.0 / CAP_SHARPNESS))  # the capped lead over the lead
    h = d * shrink
    e = np.exp(-h)                                  # the winner's h is 0: every column sums to >= 1
    total = e.sum(axis=0)
    loss = float(((target * h).sum() + np.log(total).sum()) / n)
    by_h = (target - e / total) / n
    inv = 1.0 / (1.0 + x)
    # dh/dd = (h / d) / (1 + (d / L) ** q) and dh/dlog L = h (d / L) ** q / (1 + (d / L) ** q)
    return loss, by_h * shrink * inv, by_h * h * x * inv


class _WinnersCaps:
    """The caps ``f * base`` of each decision's winner over every class, as the capped losses take them.

    ``log base`` of each decision's winner is computed once (laid out (classes, n), as :func:`_capped_loss`
    takes it); :meth:`loss` caps the leads ``d`` at ``f`` times it, clipped to :data:`CAP_BOUNDS`.
    """

    def __init__(self, base: np.ndarray, winners: np.ndarray) -> None:
        filled = np.array(base, dtype=np.float64)
        np.fill_diagonal(filled, 1.0)               # a class against itself: its lead is 0
        self.log_base = np.ascontiguousarray(np.log(filled)[winners].T)
        self.lo, self.hi = (math.log(v) for v in CAP_BOUNDS)

    def loss(self, d, log_f: float, target) -> tuple[float, np.ndarray, float]:
        """Return :func:`_capped_loss` of leads ``d`` at caps ``f * base``, its derivatives by ``d`` and ``log f``."""
        raw = self.log_base + log_f
        loss, by_d, by_log_cap = _capped_loss(d, np.clip(raw, self.lo, self.hi), target)
        free = (raw > self.lo) & (raw < self.hi)    # a cap at its bound does not move with f
        return loss, by_d, float((by_log_cap * free).sum())


class _MapLoss:
    """The smoothed log loss of a window map on fixed held-out logits, with its gradient.

    The map is ``softmax(a * asinh(z / c))``, or with ``base`` caps ``cap_gaps(a * asinh(z / c),
    clip(f * base))`` (:func:`_bounded_caps`). Parameters are ``(log a, log c)`` or ``(log a, log c,
    log f)``; :meth:`__call__` gives the loss and its gradient at once, as a quasi-Newton fit
    (``jac=True``) asks. What does not change between evaluations (the targets, each row's winner,
    the log of its caps) is computed once here, laid out (classes, n) (:func:`_capped_loss`).

    Each row's winner is that of its logits: the map is increasing, so it is the winner of its
    scores (:func:`cap_gaps` takes it from the scores; the two differ only where rounding ties
    two scores, whose lead is then 0 against either).
    """

    def __init__(self, z: np.ndarray, y: np.ndarray, base: np.ndarray | None = None) -> None:
        if np.abs(z).max() > _LARGEST_LOGIT:
            raise InputError(f"logits beyond +-{_LARGEST_LOGIT:.3g} cannot be calibrated "
                             f"(the largest here: {np.abs(z).max():.3g}); a network's are hundreds at most")
        self.z = np.ascontiguousarray(z.T)
        self.n = len(z)
        self.target = np.ascontiguousarray(_smoothed_targets(y, z.shape[1]).T)
        self.at = (np.argmax(z, axis=1), np.arange(self.n))     # each row's winner, in the (classes, n) layout
        self.caps = None if base is None else _WinnersCaps(base, self.at[0])

    def __call__(self, p) -> tuple[float, np.ndarray]:
        """Return the loss and its gradient at ``p`` (logs of ``a``, ``c`` and, with caps, ``f``)."""
        a, c = math.exp(p[0]), math.exp(p[1])
        u = np.arcsinh(self.z / c)
        slope = np.tanh(u)                              # -c du/dc = w / sqrt(1 + w^2), w = z / c
        if self.caps is None:
            s = u * a
            top = s[self.at]                            # each row's largest score (its winner's)
            e = np.exp(s - top)
            total = e.sum(axis=0)
            loss = float((np.log(total).sum() + top.sum() - (self.target * s).sum()) / self.n)
            by_s = (e / total - self.target) / self.n
            return loss, np.array([(by_s * s).sum(), -a * (by_s * slope).sum()])
        d = u[self.at] - u
        d *= a
        np.maximum(d, 0.0, out=d)                       # >= 0 already, but for rounding
        loss, by_d, by_log_f = self.caps.loss(d, p[2], self.target)
        slope -= slope[self.at]
        return loss, np.array([(by_d * d).sum(), a * (by_d * slope).sum(), by_log_f])


def _fit(loss, starts, bounds):
    """Return the best end of quasi-Newton descents of ``loss`` (a :class:`_MapLoss`-like callable) from ``starts``.

    SLSQP with the analytic gradient: with bounds alone its steps are BFGS's, kept within them. Not
    L-BFGS-B: scipy's (1.17) calls LAPACK on its few numbers at every step, and in a process whose
    OpenBLAS keeps two threads each step cost 4.5 ms (2 busy cores), ten times the loss on 2400
    windows; none with one thread. A loss that is not finite raises :class:`InputError` (the logits'
    bound, :class:`_MapLoss`, should leave none).
    """
    from scipy.optimize import minimize  # here: it takes 0.3 s to import, and only a fit needs it

    best = None
    for start in starts:
        r = minimize(loss, np.array(start, dtype=np.float64), jac=True, method="SLSQP", bounds=bounds,
                     options=_QUASI_NEWTON)
        if not np.isfinite(r.fun):
            raise InputError("the calibration's loss is not finite: are the logits finite and of a sane size?")
        if best is None or r.fun < best.fun:
            best = r
    assert best is not None                     # starts were given
    return best


def fit_window_calibration(logits, labels) -> tuple[float, float]:
    """Fit ``(a, c)`` of ``softmax(a * asinh(z / c))`` minimising the log loss of ``labels``.

    The log loss (smoothed targets, :func:`_smoothed_targets`) is minimised by a quasi-Newton method (SLSQP) on
    ``(log a, log c)`` with its analytic gradient, from each of three starts, the best kept.

    Parameters
    ----------
    logits : ndarray, shape (n, classes)
        The network's logits of held-out windows (never its own training windows: on those it
        is nearly always right, and the fit would learn to be sure).
    labels : ndarray of int, shape (n,)

    Returns
    -------
    (float, float)
        ``a`` (the sharpness, > 0) and ``c`` (the scale of the logits where the map turns from
        linear to logarithmic, > 0), each within ``[1e-3, 1e4]``.
    """
    z = np.asarray(logits, dtype=np.float64)
    y = np.asarray(labels)
    _check_scored(z, y, "logits")
    lo, hi = (math.log(v) for v in MAP_BOUNDS)
    best = _fit(_MapLoss(z, y), _MAP_STARTS, [(lo, hi)] * 2)
    a, c = np.exp(np.clip(best.x, lo, hi))
    return float(a), float(c)


def fit_capped_window_calibration(logits, labels, start: tuple[float, float] | None = None
                                  ) -> tuple[float, float, np.ndarray]:
    """Fit ``(a, c, caps)`` of the capped window map ``cap_gaps(a * asinh(z / c), caps)``.

    The fit minimises the log loss of ``labels`` (held-out windows, as
    :func:`fit_window_calibration`), by a quasi-Newton method on ``(log a, log c, log f)`` with the analytic
    gradient.

    ``caps = f * confusion_caps(...)`` of the held-out windows' own winners; ``a``, ``c`` and the
    factor ``f`` (in :data:`FACTOR_BOUNDS`) are fitted together, so that the temperature no longer
    has to compromise between the pairs the network tells apart and those it cannot: the caps
    hold the latter near even odds, and the temperature serves the former.

    Parameters
    ----------
    logits, labels
        As :func:`fit_window_calibration`'s.
    start : (float, float), optional
        ``(a, c)`` of the plain map fitted to these windows, where the caller has it: one descent
        from there, with ``f`` at ``exp(0.5)``. Default: the plain map's three starts, each with
        that ``f``, the best kept.

    Returns
    -------
    (float, float, ndarray (classes, classes))
        ``caps`` has a zero diagonal and each other entry within :data:`CAP_BOUNDS`.
    """
    z = np.asarray(logits, dtype=np.float64)
    y = np.asarray(labels)
    _check_scored(z, y, "logits")
    base = confusion_caps(np.argmax(z, axis=1), y, z.shape[1])
    lo, hi = (math.log(v) for v in MAP_BOUNDS)
    flo, fhi = (math.log(v) for v in FACTOR_BOUNDS)
    starts = _MAP_STARTS if start is None else [tuple(math.log(min(max(v, MAP_BOUNDS[0]), MAP_BOUNDS[1]))
                                                      for v in start)]
    best = _fit(_MapLoss(z, y, base), [(*s, 0.5) for s in starts], [(lo, hi)] * 2 + [(flo, fhi)])
    a, c = np.exp(np.clip(best.x[:2], lo, hi))
    f = math.exp(min(max(float(best.x[2]), flo), fhi))
    return float(a), float(c), _bounded_caps(base * f)


def _bounded_caps(caps) -> np.ndarray:
    caps = np.clip(caps, *CAP_BOUNDS)
    np.fill_diagonal(caps, 0.0)
    return caps


def _smoothed_targets(labels, n_classes: int) -> np.ndarray:
    """Targets of the calibration's log loss: ``1 - eps`` on the true class and ``eps`` shared by the others.

    ``eps = 1 / (n + 2)`` (Laplace's rule of succession for ``n`` windows).

    Without it, held-out windows that are all right make the most likely calibration infinitely
    sure, and the first wrong window in use costs without bound; with it, ``n`` right windows
    out of ``n`` allow a confidence of about ``1 - 1 / (n + 2)``.
    """
    y = np.asarray(labels)
    eps = 1.0 / (len(y) + 2)
    t = np.full((len(y), n_classes), eps / (n_classes - 1))
    t[np.arange(len(y)), y] = 1.0 - eps
    return t


def fit_pooling(runs, labels) -> float:
    """Fit the correlation ``rho`` in [0, 1] of :func:`pool_log_posteriors`.

    ``rho`` minimises the log loss of every prefix of every run.

    Parameters
    ----------
    runs : sequence of ndarray, each (windows, classes)
        Calibrated log-posteriors of consecutive held-out windows of one recording.
    labels : sequence of int
        Each run's class.
    """
    from scipy.optimize import minimize_scalar  # here: it takes 0.3 s to import, and only a fit needs it

    kept = [(np.asarray(r, dtype=np.float64), lab) for r, lab in zip(runs, labels) if len(r)]
    if not kept:
        raise InputError("fitting the pooling needs at least one run of held-out windows")
    runs = [r for r, _ in kept]
    y = np.concatenate([np.full(len(r), lab) for r, lab in kept])
    target = _smoothed_targets(y, runs[0].shape[1])
    prefixes = _Prefixes(runs)
    r = minimize_scalar(lambda rho: -(target * prefixes.pooled(rho)).sum(axis=1).mean(), bounds=(0.0, 1.0),
                        method="bounded", options={"xatol": 1e-5})
    return float(r.x)


def fit_capped_pooling(runs, labels, plain_correlation: float | None = None) -> tuple[float, np.ndarray]:
    """Fit the correlation ``rho`` and the contact caps of a capped pooling ``cap_gaps(g(n) sum_t log p_t, caps)``.

    They minimise the log loss of every prefix of every run, by a quasi-Newton method (as
    :func:`fit_window_calibration`) on ``(rho, log f)`` with the analytic gradient, from
    ``plain_correlation`` and ``f = exp(0.5)``.

    The caps are a factor ``f`` (fitted with ``rho``) times :func:`confusion_caps` of the winners of the
    runs' prefixes of two windows or more, pooled with :func:`fit_pooling`'s correlation. A pair
    the network confuses within a whole touch (its preference within the pair persists from
    window to window) keeps odds near even however long the contact; a pair whose windows err
    independently is told apart by its contacts and keeps large caps.

    Parameters as :func:`fit_pooling`, and ``plain_correlation``: :func:`fit_pooling`'s result for
    these runs where the caller has it (default: fitted here). Returns ``(rho, caps)``, ``caps``
    (classes, classes) with a zero diagonal and each other entry within :data:`CAP_BOUNDS`.
    """
    rho0 = fit_pooling(runs, labels) if plain_correlation is None else float(plain_correlation)
    kept = [(np.asarray(r, dtype=np.float64), lab) for r, lab in zip(runs, labels) if len(r)]
    runs = [r for r, _ in kept]
    y = np.concatenate([np.full(len(r), lab) for r, lab in kept])
    n_classes = runs[0].shape[1]
    prefixes = _Prefixes(runs)
    pooled = prefixes.pooled(rho0)
    several = prefixes.lengths >= 2
    base = confusion_caps(np.argmax(pooled[several], axis=1), y[several], n_classes)
    flo, fhi = (math.log(v) for v in FACTOR_BOUNDS)
    best = _fit(_PoolLoss(prefixes, y, base), [(min(max(rho0, 0.0), 1.0), 0.5)], [(0.0, 1.0), (flo, fhi)])
    rho = min(max(float(best.x[0]), 0.0), 1.0)
    return rho, _bounded_caps(base * math.exp(min(max(float(best.x[1]), flo), fhi)))


def _pooling_slope(n_max: int, correlation: float) -> np.ndarray:
    """``d g(n) / d rho`` of ``g(n) = effective_windows(n, rho) / n`` for ``n = 1 .. n_max``, shape (n_max,).

    ``g = 1 / (1 + 2 s)`` with ``s = sum_{k=1}^{n-1} (1 - k/n) rho^k``, so ``dg/drho = -2 s' g^2``, and
    ``s' = sum_k k rho^(k-1) - (1/n) sum_k k^2 rho^(k-1)`` is summed as a series for every ``n`` at once
    (its terms are >= 0 for ``rho`` in [0, 1]: no cancellation near ``rho = 1``, where the closed
    form of ``s`` cancels).
    """
    r = min(max(float(correlation), 0.0), 1.0)
    n = np.arange(1, n_max + 1, dtype=np.float64)
    k = n[:-1]
    terms = k * r ** (k - 1)
    first = np.concatenate(([0.0], np.cumsum(terms)))
    second = np.concatenate(([0.0], np.cumsum(k * terms)))
    g = effective_windows(n, r) / n
    return -2.0 * (first - second / n) * g * g


class _PoolLoss:
    """The smoothed log loss of a capped pooling of every prefix, with its gradient in ``(rho, log f)``.

    The pooled scores of a prefix are ``g(n) S`` (``S`` the sum of its windows' log-posteriors, :class:`_Prefixes`),
    so its leads over its winner are ``g(n)`` times those of ``S``, computed once here; each
    evaluation scales them and caps them (:func:`_capped_loss`), as :func:`cap_gaps` does with the
    pooled log-posteriors (whose leads these are, but for rounding).
    """

    def __init__(self, prefixes: _Prefixes, y: np.ndarray, base: np.ndarray) -> None:
        s = prefixes.sums
        k = np.argmax(s, axis=1)                     # the pooled winner: g(n) > 0 keeps it
        rows = np.arange(len(s))
        self.lead = np.ascontiguousarray(np.maximum(s[rows, k][:, None] - s, 0.0).T)
        self.target = np.ascontiguousarray(_smoothed_targets(y, s.shape[1]).T)
        self.caps = _WinnersCaps(base, k)
        self.n, self.at = prefixes._n, prefixes._at

    def __call__(self, p) -> tuple[float, np.ndarray]:
        """Return the loss and its gradient at ``p = (rho, log f)``."""
        rho = min(max(float(p[0]), 0.0), 1.0)
        g = (effective_windows(self.n, rho) / self.n)[self.at]
        loss, by_d, by_log_f = self.caps.loss(self.lead * g, p[1], self.target)
        by_g = (by_d * self.lead).sum(axis=0)
        return loss, np.array([(by_g * _pooling_slope(len(self.n), rho)[self.at]).sum(), by_log_f])


def _check_scored(values, labels, what: str) -> None:
    if values.ndim != 2 or values.shape[0] == 0 or values.shape[1] < 2:
        raise InputError(f"{what} must have shape (n >= 1, classes >= 2), got {values.shape}")
    if labels.shape != (values.shape[0],) or labels.dtype.kind not in "iu":
        raise InputError(f"labels must be {values.shape[0]} integers, got {labels.dtype} {labels.shape}")
    if labels.min() < 0 or labels.max() >= values.shape[1]:
        raise InputError(f"labels must lie in 0..{values.shape[1] - 1}")
    if not np.isfinite(values).all():
        raise InputError(f"{what} contain NaN or Inf")


# -- the calibration a model keeps -----------------------------------------------------------

#: Held-out change statistics a calibration keeps, the largest (:class:`HeldOutChanges`).
CHANGES_KEPT = 1024


@dataclass(frozen=True)
class HeldOutChanges:
    """What a change detector's statistic did on a calibration's held-out windows.

    A node can then set its threshold for any rate of false changes
    (:func:`supramodal.decisions.change_threshold`).

    Attributes
    ----------
    windows : int
        Held-out windows measured (>= 1).
    largest : tuple of float
        Their largest statistics, in decreasing order, each at least 0 (a threshold is never below 0, so
        a lower statistic counts as 0; a window before the detector's first test has none, -inf): all
        of them, or the :data:`CHANGES_KEPT` largest.
    """

    windows: int
    largest: tuple[float, ...]

    def __post_init__(self) -> None:
        w = self.windows
        if isinstance(w, bool) or not isinstance(w, (int, np.integer)) or w < 1:
            raise InputError(f"held-out changes: windows must be a count >= 1, got {w!r}")
        try:
            a = np.array(self.largest, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError("held-out changes: largest must be a list of numbers") from None
        if a.ndim != 1 or len(a) != min(int(w), CHANGES_KEPT):
            raise InputError(f"held-out changes: largest must hold min(windows, {CHANGES_KEPT}) numbers, got "
                             f"{a.shape} for {w} windows")
        if not np.isfinite(a).all() or np.any(np.diff(a) > 0) or np.any(a < 0):
            raise InputError("held-out changes: largest must be finite numbers >= 0 in decreasing order")
        object.__setattr__(self, "windows", int(w))
        object.__setattr__(self, "largest", tuple(float(v) for v in a))

    @classmethod
    def of(cls, statistics) -> HeldOutChanges:
        """From every held-out window's statistic (any order; -inf where a window had none)."""
        stats = np.sort(np.maximum(np.asarray(statistics, dtype=np.float64), 0.0))[::-1]
        return cls(len(stats), tuple(stats[:CHANGES_KEPT]))

    def to_dict(self) -> dict:
        """Return the record as the JSON object a model file's calibration holds (``changes``)."""
        return {"windows": self.windows, "largest": list(self.largest)}


@dataclass(frozen=True)
class Calibration:
    """A model's fitted map from logits to window posteriors, and its pooling over a contact.

    Attributes
    ----------
    temperature : float
        ``a`` of ``softmax(a * asinh(z / c))`` (> 0).
    scale : float
        ``c`` (> 0), in units of the logits.
    correlation : float
        ``rho`` of :func:`pool_log_posteriors`, in [0, 1].
    fitted_on : dict
        How it was fitted: ``folds``, ``windows``, ``runs``, and the held-out log loss before
        and after (plain data, kept in the model file).
    caps, contact_caps : tuple of tuples of float, or None
        The caps per pair of classes (:func:`cap_gaps`) of a window's and of a contact's
        posteriors, ``caps[k][j]`` that of a decision for ``k`` against ``j``: zero diagonal,
        every other entry within :data:`CAP_BOUNDS`. None: no caps (a model file of before them,
        or a fit where they did not earn their numbers: :func:`fit_calibration`).
    changes : HeldOutChanges or None
        A change detector's statistic on the held-out windows (the model's, where it was trained
        with this version), for a node's change threshold at the rate a scene asks; None: the
        detector's bound.
    contact_correlation : float or None
        ``rho`` of the capped contact pooling, in [0, 1]: given exactly when ``contact_caps`` is.
        :attr:`correlation` stays that of the plain pooling (of the capped windows), for a
        pooling that does not apply the contact caps; the two are fitted apart, each for its
        own pooling (:attr:`contact_pooling`).
    """

    temperature: float
    scale: float
    correlation: float
    fitted_on: dict = field(default_factory=dict)
    caps: tuple | None = None
    contact_caps: tuple | None = None
    contact_correlation: float | None = None
    changes: HeldOutChanges | None = None

    def __post_init__(self) -> None:
        lo, hi = MAP_BOUNDS
        for name in ("temperature", "scale"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (lo * (1 - 1e-9) <= v <= hi * (1 + 1e-9)):
                raise InputError(f"calibration {name} must be a number in [{lo:g}, {hi:g}], got {v!r}")
        c = self.correlation
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not (0.0 <= c <= 1.0):
            raise InputError(f"calibration correlation must lie in [0, 1], got {c!r}")
        for name in ("caps", "contact_caps"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, _checked_caps(v, name))
        r = self.contact_correlation
        if (r is None) != (self.contact_caps is None):
            raise InputError("a calibration's contact caps come with their contact correlation, and only they")
        if r is not None and (isinstance(r, bool) or not isinstance(r, (int, float)) or not (0.0 <= r <= 1.0)):
            raise InputError(f"calibration contact_correlation must lie in [0, 1], got {r!r}")
        if self.caps is not None and self.contact_caps is not None and len(self.caps) != len(self.contact_caps):
            raise InputError(f"calibration caps are for {len(self.caps)} classes, its contact caps for "
                             f"{len(self.contact_caps)}")

    @property
    def capped(self) -> bool:
        """Whether the window or contact posteriors are capped per pair of classes."""
        return self.caps is not None or self.contact_caps is not None

    def log_posteriors(self, logits) -> np.ndarray:
        """Calibrated log-posteriors of windows with these ``logits`` (..., classes)."""
        scores = _window_map(logits, self.temperature, self.scale)
        if self.caps is None:
            return log_softmax(scores, axis=-1)
        self._check_classes(scores.shape[-1])
        return cap_gaps(scores, self.caps)

    @property
    def contact_pooling(self) -> tuple[float, tuple | None]:
        """``(rho, caps)`` of this calibration's contact pooling (:func:`pool_log_posteriors`).

        The capped one where it has contact caps, else ``(correlation, None)``.
        """
        if self.contact_caps is None or self.contact_correlation is None:    # both or neither (__post_init__)
            return self.correlation, None
        return self.contact_correlation, self.contact_caps

    def pool(self, log_posteriors) -> np.ndarray:
        """Calibrated log-posteriors of one contact from its windows' (n, classes)."""
        return pool_log_posteriors(log_posteriors, *self.contact_pooling)

    def _check_classes(self, n: int) -> None:
        if self.caps is not None and n != len(self.caps):
            raise InputError(f"this calibration's caps are for {len(self.caps)} classes, got {n}")

    def to_dict(self) -> dict:
        """Return the calibration as a model header's ``calibration`` object (:meth:`from_dict` reads it)."""
        d = {"method": CALIBRATION_METHOD, "temperature": self.temperature, "scale": self.scale,
             "correlation": self.correlation, "fitted_on": self.fitted_on}
        for name in ("caps", "contact_caps"):
            if getattr(self, name) is not None:
                d[name] = [list(r) for r in getattr(self, name)]
        if self.contact_correlation is not None:
            d["contact_correlation"] = self.contact_correlation
        if self.changes is not None:
            d["changes"] = self.changes.to_dict()
        return d

    @classmethod
    def from_dict(cls, d, bad, n_classes: int | None = None) -> Calibration:
        """From a model header's ``calibration`` object; ``bad(message)`` makes the error to raise.

        ``n_classes``: the model's classes, which caps must match.
        """
        if not isinstance(d, dict):
            raise bad("'calibration' must be an object")
        keys = {"method", "temperature", "scale", "correlation", "fitted_on"}
        optional = {"caps", "contact_caps", "contact_correlation", "changes"}
        if not keys <= set(d) <= keys | optional:
            raise bad(f"'calibration' must have exactly the keys {sorted(keys)}, and may have {sorted(optional)}; "
                      f"has {sorted(d)}")
        if d["method"] != CALIBRATION_METHOD:
            raise bad(f"calibration method {d['method']!r} is not known (this program reads {CALIBRATION_METHOD!r})")
        if not isinstance(d["fitted_on"], dict):
            raise bad("'calibration.fitted_on' must be an object")
        for key, value in d["fitted_on"].items():
            if key in _FITTED_COUNTS and not (type(value) is int and value >= 0):
                raise bad(f"'calibration.fitted_on.{key}' must be a count, got {value!r}")
            if key in _FITTED_NUMBERS and (isinstance(value, bool) or not isinstance(value, (int, float))
                                           or not math.isfinite(value)):
                raise bad(f"'calibration.fitted_on.{key}' must be a finite number, got {value!r}")
            if key == "folds_by" and value not in ("recording", "span"):
                raise bad(f"'calibration.fitted_on.folds_by' must be \"recording\" or \"span\", got {value!r}")
        caps = [d.get("caps"), d.get("contact_caps")]
        for i, (name, v) in enumerate(zip(("caps", "contact_caps"), caps)):
            if v is None:
                continue
            if (not isinstance(v, list) or not all(isinstance(r, list) for r in v)
                    or not all(not isinstance(e, bool) and isinstance(e, (int, float)) for r in v for e in r)):
                raise bad(f"'calibration.{name}' must be a list of lists of numbers")
            if n_classes is not None and (len(v) != n_classes or any(len(r) != n_classes for r in v)):
                raise bad(f"'calibration.{name}' must be {n_classes} x {n_classes} (the model's classes)")
            caps[i] = tuple(tuple(float(e) for e in r) for r in v)
        changes = d.get("changes")
        if changes is not None and (not isinstance(changes, dict) or set(changes) != {"windows", "largest"}
                                    or not isinstance(changes["largest"], list)
                                    or not all(not isinstance(e, bool) and isinstance(e, (int, float))
                                               for e in changes["largest"])):
            raise bad("'calibration.changes' must be an object with exactly the keys windows (a count) and "
                      "largest (a list of numbers)")
        try:
            return cls(d["temperature"], d["scale"], d["correlation"], d["fitted_on"], caps=caps[0],
                       contact_caps=caps[1], contact_correlation=d.get("contact_correlation"),
                       changes=None if changes is None else HeldOutChanges(changes["windows"],
                                                                           tuple(changes["largest"])))
        except InputError as exc:
            raise bad(str(exc)) from None


def _checked_caps(v, name: str) -> tuple:
    """``v`` as a tuple of tuples of floats, checked.

    It must be square, of >= 2 classes, with a zero diagonal and every other entry a finite
    number within :data:`CAP_BOUNDS`.
    """
    try:
        a = np.array(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"calibration {name} must be a square table of numbers") from None
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] < 2:
        raise InputError(f"calibration {name} must be a square table of >= 2 classes, got shape {a.shape}")
    lo, hi = CAP_BOUNDS
    off = a[~np.eye(len(a), dtype=bool)]
    if not np.all(np.diag(a) == 0.0):
        raise InputError(f"calibration {name} must have a zero diagonal")
    if not (np.isfinite(off).all() and np.all(off >= lo * (1 - 1e-9)) and np.all(off <= hi * (1 + 1e-9))):
        raise InputError(f"calibration {name} must lie in [{lo:g}, {hi:g}] off the diagonal")
    return tuple(tuple(float(e) for e in r) for r in a)


#: What :func:`fit_calibration` and :func:`fit_network_calibration` record in ``fitted_on``: counts
#: and numbers, checked when a model file is read (free text elsewhere is kept as it is).
_FITTED_COUNTS = ("windows", "runs", "run_windows", "folds")
_FITTED_NUMBERS = ("log_loss_uncalibrated", "log_loss", "held_out_accuracy")


def fit_calibration(logits, labels, groups, run: int = POOLING_RUN, folds=None, caps: bool = True) -> Calibration:
    """Fit a :class:`Calibration` on held-out windows.

    Parameters
    ----------
    logits : ndarray, shape (n, classes)
        Out-of-fold logits: each window's from a network that did not train on its group.
    labels : ndarray of int, shape (n,)
    groups : sequence, length n
        Each window's recording (or held-out block); windows of one group are consecutive in
        time and in order. Runs of ``run`` consecutive windows of one group fit the pooling.
    folds : sequence, length n, optional
        Each window's fold (which network gave its logits): a run never crosses from one fold
        to another. A contact in use is seen by one network throughout, whose errors persist from
        window to window; a run stitched from two fold networks' windows is less correlated than
        that, and a pooling fitted on it overclaims (two-sense world, whiskers: ECE per contact
        0.088 with stitched runs, 0.051 with runs of one fold).
    caps : bool
        Try caps per pair of classes on the window and on the contact posteriors
        (:func:`fit_capped_window_calibration`, :func:`fit_capped_pooling`; the default). Each is
        kept only where it earns its number: where it lowers the held-out log loss (windows; every
        prefix of every run for the contact caps) by more than Akaike's criterion charges for the
        one number fitted to that loss, the caps' factor: ``1 / n`` nats per decision (``n``
        windows or prefixes; the caps themselves are counts of held-out decisions, not fitted to
        the loss). False: the map and pooling of before them.
    """
    z = np.asarray(logits, dtype=np.float64)
    y = np.asarray(labels)
    _check_scored(z, y, "logits")
    n_classes = z.shape[1]
    charge = 1.0 / len(y)
    a, c = fit_window_calibration(z, y)
    lp = log_softmax(_window_map(z, a, c), axis=1)
    window_caps = contact_caps = contact_rho = None
    if caps:
        target = _smoothed_targets(y, n_classes)
        ca, cc, capped_caps = fit_capped_window_calibration(z, y, start=(a, c))
        capped = cap_gaps(_window_map(z, ca, cc), capped_caps)
        if (target * (capped - lp)).sum(axis=1).mean() > charge:
            a, c, window_caps, lp = ca, cc, capped_caps, capped
    runs, run_labels = [], []
    groups = np.asarray(groups)
    folds = np.zeros(len(y), dtype=int) if folds is None else np.asarray(folds)
    for g in dict.fromkeys(groups.tolist()):
        idx = np.flatnonzero(groups == g)
        for block in np.split(idx, np.flatnonzero(np.diff(folds[idx]) != 0) + 1):
            for s in range(0, len(block), run):
                part = block[s:s + run]
                runs.append(lp[part])
                run_labels.append(int(y[part[0]]))
    rho = fit_pooling(runs, run_labels)
    if caps:
        capped_rho, capped_caps = fit_capped_pooling(runs, run_labels, plain_correlation=rho)
        prefix_y = np.concatenate([np.full(len(r), lab) for r, lab in zip(runs, run_labels)])
        target = _smoothed_targets(prefix_y, n_classes)
        prefixes = _Prefixes(runs)
        gain = (target * (cap_gaps(prefixes.pooled(capped_rho), capped_caps)
                          - prefixes.pooled(rho))).sum(axis=1).mean()
        if gain > 1.0 / len(prefix_y):
            contact_caps, contact_rho = capped_caps, capped_rho
    rows = np.arange(len(y))
    before = float(-normalised_log_posteriors(z)[rows, y].mean())
    after = float(-lp[rows, y].mean())
    return Calibration(a, c, rho, {"windows": int(len(y)), "runs": len(runs), "run_windows": int(run),
                                   "log_loss_uncalibrated": round(before, 6), "log_loss": round(after, 6)},
                       caps=None if window_caps is None else _rows(window_caps),
                       contact_caps=None if contact_caps is None else _rows(contact_caps),
                       contact_correlation=contact_rho)


def _rows(caps) -> tuple:
    return tuple(tuple(float(e) for e in r) for r in np.asarray(caps))


# -- novelty ---------------------------------------------------------------------------------------

#: Name of the novelty score of this version in a model header (a version 2 file written before it
#: says ``"novelty": true``: the same distance on the standardised inputs themselves, windows only).
NOVELTY_METHOD = "asinh-mahalanobis"
#: Fraction of each input's typical size (its mean on the training windows; its scale where the mean is
#: 0) below which the novelty's logarithmic warp turns linear: ``asinh(v / floor)`` is ``log(2 v / floor)`` for
#: the feature values that occur, and stays finite at 0 and for negative values.
NOVELTY_FLOOR = 0.01
#: Longest contact whose pooled novelty has its own held-out quantiles (windows); a longer contact
#: is judged by this length's.
NOVELTY_RUN = POOLING_RUN
#: Fewest held-out contacts a length needs for quantiles of its own (a length with fewer repeats the
#: row of the one before).
NOVELTY_MIN_CONTACTS = 20
#: Largest spread (sd of the natural logarithm of a touch's gains) a novelty score allows for, and a model
#: file may say: gains of e^10 are no touch's (a training's estimate is held to it; a file beyond it is refused).
NOVELTY_MAX_TOUCH_SPREAD = 10.0
#: Most windows or touches a class's mean may say it was fitted on (a file's counts, checked on load).
NOVELTY_MAX_COUNT = 2**53
#: Name of the novelty score that allows for a new touch (:class:`TouchSpread`; issue 34).
NOVELTY_TOUCH_METHOD = "asinh-mahalanobis-touch"
#: Least spread (sd of the natural logarithm) of a touch's gains that a novelty score allows for,
#: whatever its training recordings show: two or three touches of each texture estimate it poorly
#: (a microphone's level is one number a touch: on the two-sense world, whose spread is 0.03, six
#: textures' two touches said 0.012 to 0.031). The default spread of :class:`supramodal.model.GainAugment`.
NOVELTY_TOUCH_SPREAD = 0.03


def _group_of_two_parts(groups, parts) -> bool:
    """Whether some gain group (>= 0) of ``groups`` has inputs of two ``parts`` (one gain is one sensor's)."""
    seen: dict[int, int] = {}
    return any(seen.setdefault(g, p) != p for g, p in zip(groups, parts) if g >= 0)


def gain_structure(groups) -> np.ndarray:
    """``G`` (inputs, inputs) of per-input gain ``groups`` (-1: no gain): 1 where two inputs share a gain."""
    g = np.asarray(groups)
    return ((g[:, None] == g[None, :]) & (g[:, None] >= 0)).astype(np.float64)


@dataclass(frozen=True)
class TouchSpread:
    """How far a touch's windows lie from their texture's mean by the touch alone: the novelty's allowance.

    Each touch of a surface has gains of its own (each vibrissa's coupling, the microphone's distance):
    in the novelty's logarithmic inputs ``u`` a gain ``g`` adds ``log g`` to its inputs, the same to every
    window of the touch. The touch's offset from its texture's mean is modelled as Gaussian with
    covariance ``spread ** 2 * G``, ``G[i, j] = 1`` where inputs ``i`` and ``j`` share a gain (same
    group, ``>= 0``), else 0. A class mean fitted on ``m`` touches (``touches``) and ``N`` windows
    (``windows``) of its texture then predicts a new touch's mean of ``n`` windows up to the covariance
    ``W (1 / n + 1 / N) + (1 + 1 / m) spread ** 2 G`` (``W``: the windows' covariance within one
    recording), and :class:`Novelty` measures the distance under it.

    Attributes
    ----------
    spread : float
        The sd of a touch's log gains allowed for (>= 0).
    groups : tuple of int
        Per input: the gain it shares (inputs of one group share one), -1 for an input no gain scales.
    windows, touches : tuple of int
        Per class: the windows and the recordings (touches) its mean was fitted on.
    estimated : float or None
        The spread the training recordings showed (None: they could not: fewer than two recordings of
        every texture); ``spread`` is the larger of it and the least allowed.
    parts : tuple of int
        Per input: the sensor (part) whose gains it has, where the inputs are of several sensors whose touches
        vary each by its own spread (an early fusion's two senses); empty: one spread for all (``spread``).
    part_spreads, part_estimated : tuple
        Per part, its ``spread`` and ``estimated`` (empty without :attr:`parts`); ``spread`` and
        ``estimated`` are then the largest of them (what is said in one number).
    """

    spread: float
    groups: tuple[int, ...]
    windows: tuple[int, ...]
    touches: tuple[int, ...]
    estimated: float | None = None
    parts: tuple[int, ...] = ()
    part_spreads: tuple[float, ...] = ()
    part_estimated: tuple[float | None, ...] = ()

    def structure(self) -> np.ndarray:
        """``G`` (inputs, inputs): 1 where two inputs share a gain (:func:`gain_structure` of :attr:`groups`)."""
        return gain_structure(self.groups)

    def covariance(self) -> np.ndarray:
        """Return the touch's covariance of its offset, ``D G D`` (inputs, inputs), ``D`` each input's part's spread."""
        if not self.parts:
            return self.structure() * self.spread ** 2
        d = np.asarray(self.part_spreads, dtype=np.float64)[np.asarray(self.parts)]
        return self.structure() * np.outer(d, d)

    def to_dict(self) -> dict:
        """Return what a model file's header keeps of it (plain JSON values)."""
        d: dict = {"spread": float(self.spread),
                   "estimated": None if self.estimated is None else float(self.estimated),
                   "groups": [int(v) for v in self.groups], "windows": [int(v) for v in self.windows],
                   "touches": [int(v) for v in self.touches]}
        if self.parts:
            d.update(parts=[int(v) for v in self.parts], part_spreads=[float(v) for v in self.part_spreads],
                     part_estimated=[None if v is None else float(v) for v in self.part_estimated])
        return d

    @classmethod
    def from_dict(cls, d, n_in: int, n_classes: int, bad) -> TouchSpread:
        """Return the spread a header says (:meth:`to_dict`), every value checked; ``bad(message)`` makes the error."""
        keys = ["estimated", "groups", "spread", "touches", "windows"]
        with_parts = sorted(keys + ["part_estimated", "part_spreads", "parts"])
        if not isinstance(d, dict) or sorted(d) not in (keys, with_parts):
            raise bad(f"'novelty.touch' must be an object of exactly the keys {keys} (and, for inputs of several "
                      f"sensors, parts, part_spreads and part_estimated), got {d!r}")

        def number(v) -> bool:
            return (not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
                    and 0 <= v <= NOVELTY_MAX_TOUCH_SPREAD)

        def integers(v, n: int, least: int, most: int) -> bool:
            return (isinstance(v, list) and len(v) == n
                    and all(not isinstance(e, bool) and isinstance(e, int) and least <= e <= most for e in v))

        if not number(d["spread"]) or not (d["estimated"] is None or number(d["estimated"])):
            raise bad(f"'novelty.touch' spread and estimated must be finite numbers >= 0 and <= "
                      f"{NOVELTY_MAX_TOUCH_SPREAD:g} (estimated may be null), got {d['spread']!r} and "
                      f"{d['estimated']!r}")
        if not integers(d["groups"], n_in, -1, n_in):
            raise bad(f"'novelty.touch.groups' must be a list of {n_in} integers >= -1 and <= {n_in}")
        for key in ("windows", "touches"):
            if not integers(d[key], n_classes, 1, NOVELTY_MAX_COUNT):
                raise bad(f"'novelty.touch.{key}' must be a list of {n_classes} integers >= 1 and <= 2**53")
        parts: tuple = ()
        spreads: tuple = ()
        estimated: tuple = ()
        if "parts" in d:
            k = len(d["part_spreads"]) if isinstance(d["part_spreads"], list) else 0
            if not (2 <= k <= n_in and integers(d["parts"], n_in, 0, k - 1)
                    and all(number(v) for v in d["part_spreads"]) and isinstance(d["part_estimated"], list)
                    and len(d["part_estimated"]) == k and all(v is None or number(v) for v in d["part_estimated"])):
                raise bad(f"'novelty.touch' parts must give each of the {n_in} inputs a part 0..k-1, part_spreads "
                          f"k >= 2 finite numbers 0..{NOVELTY_MAX_TOUCH_SPREAD:g} and part_estimated k of them or "
                          f"null, got {d['parts']!r}, {d['part_spreads']!r} and {d['part_estimated']!r}")
            if len(set(d["parts"])) != k:
                raise bad(f"'novelty.touch' parts: every part of the {k} of part_spreads must have inputs")
            if _group_of_two_parts(d["groups"], d["parts"]):
                raise bad("'novelty.touch' parts: the inputs of one gain group must be of one part")
            parts, spreads = tuple(d["parts"]), tuple(float(v) for v in d["part_spreads"])
            estimated = tuple(None if v is None else float(v) for v in d["part_estimated"])
            known = [v for v in estimated if v is not None]
            if d["spread"] != max(spreads) or d["estimated"] != (max(known) if known else None):
                raise bad("'novelty.touch' spread and estimated must be the largest of part_spreads and "
                          f"part_estimated, got {d['spread']!r} and {d['estimated']!r}")
        return cls(float(d["spread"]), tuple(d["groups"]), tuple(d["windows"]), tuple(d["touches"]),
                   None if d["estimated"] is None else float(d["estimated"]), parts, spreads, estimated)


@dataclass(frozen=True)
class Novelty:
    """How far windows lie from every known texture.

    A window's score is the squared Mahalanobis distance of its warped inputs ``u`` to the nearest
    class mean: under one covariance shared by the classes, shrunk towards its diagonal (a model file
    of before :attr:`touch`), or, with :attr:`touch`, under each class's predictive covariance of a
    new touch (:class:`TouchSpread`). The warp
    ``u = asinh(gain * x + offset)`` of the standardised inputs ``x`` is the logarithm of the raw
    feature values (:data:`NOVELTY_FLOOR`): the peak features are positive and heavy-tailed, and a
    Gaussian fits their logarithm better (leave-2-textures-out on the whisker reference set, worst
    fold: AUROC per window 0.648 on ``x``, 0.666 on the logarithm; per contact 0.785 -> 0.853).

    A contact's score (:meth:`pooled_score`) asks whether its windows together come from one known
    texture: ``n`` times the distance of the mean of its ``n`` warped windows to the nearest class
    mean. For a known texture the mean's distance shrinks as the windows' noise averages out; for
    a texture the model never met it tends to the distance of that texture's own mean, so the score
    grows with the contact (the evidence accumulates instead of being averaged away, as a mean of
    the windows' scores does: there the windows' own spread, the same for known and unknown
    textures, dominates).

    Attributes
    ----------
    means : ndarray, shape (classes, inputs)
        Class means of ``u``.
    precision : ndarray, shape (inputs, inputs)
        Inverse of the shared, shrunk covariance of ``u``.
    quantiles : ndarray, shape (len(NOVELTY_QUANTILES),) or (NOVELTY_RUN, len(NOVELTY_QUANTILES))
        The score's quantiles on held-out windows of known textures, increasing; with two
        dimensions, row ``n - 1`` those of the pooled score of held-out contacts of ``n`` windows
        (row 0: single windows). The threshold for a false-unknown rate ``r`` is the ``1 - r``
        quantile.
    gain, offset : ndarray, shape (inputs,), or None
        The warp; None: ``u = x`` (a model file of before the warp).
    touch : TouchSpread or None
        The allowance for a new touch (issue 34): the distances are then measured under each class's
        predictive covariance for a new touch's mean of ``n`` windows (:class:`TouchSpread`), ``precision``
        the inverse of ``W``, the windows' covariance within a recording. None: under ``W / n``, the
        class means taken as exact (a model file of before it).
    """

    means: np.ndarray
    precision: np.ndarray
    quantiles: np.ndarray
    gain: np.ndarray | None = None
    offset: np.ndarray | None = None
    touch: TouchSpread | None = None

    def warped(self, x) -> np.ndarray:
        """``u`` of standardised input rows ``x`` (n, inputs)."""
        x = np.asarray(x, dtype=np.float64)
        return x if self.gain is None else np.arcsinh(x * self.gain + self.offset)

    def distances(self, u) -> np.ndarray:
        """Squared Mahalanobis distances of warped rows ``u`` (n, inputs) to each class mean, (n, classes)."""
        d = np.asarray(u, dtype=np.float64)[:, None, :] - self.means[None, :, :]
        return np.einsum("nki,ij,nkj->nk", d, self.precision, d)

    def class_scores(self, u, n: int = 1) -> np.ndarray:
        """Scores (m, classes) of means ``u`` (m, inputs) of ``n`` warped windows each, against every class.

        Without :attr:`touch`, ``n`` times the squared Mahalanobis distance under ``W``; with it,
        the squared distance under the class's predictive covariance of such a mean (:class:`TouchSpread`).
        """
        if self.touch is None:
            return n * self.distances(u)
        d = np.asarray(u, dtype=np.float64)[None, :, :] - self.means[:, None, :]        # (classes, m, inputs)
        # a product by class (BLAS) and a sum: einsum's three-operand loop cost 30 times as much
        return np.sum(np.matmul(d, self._touch_precisions(n)) * d, axis=2).T

    def _touch_precisions(self, n: int) -> np.ndarray:
        """Return the classes' precisions (classes, inputs, inputs) of a new touch's mean of ``n`` windows."""
        cache = self.__dict__.setdefault("_precisions", {})      # derived from frozen fields: kept beside them
        if n not in cache:
            t = self.touch
            assert t is not None
            within = self.__dict__.get("_within")
            if within is None:
                within = np.linalg.inv(self.precision)
                within = self.__dict__.setdefault("_within", (within + within.T) / 2)
            g = t.covariance()
            p = np.stack([np.linalg.inv(within * (1.0 / n + 1.0 / nk) + (1.0 + 1.0 / mk) * g)
                          for nk, mk in zip(t.windows, t.touches)])
            p = (p + p.transpose(0, 2, 1)) / 2
            if n > NOVELTY_RUN:                     # a long contact's: not kept (one per length would pile up)
                return p
            cache[n] = p
        return cache[n]

    def score(self, x) -> np.ndarray:
        """Novelty of standardised input rows ``x`` (n, inputs), shape (n,)."""
        return self.class_scores(self.warped(x)).min(axis=1)

    def pooled_score(self, x) -> float:
        """Novelty of one contact, its standardised input rows ``x`` (n >= 1, inputs) in any order.

        The score is ``min_k`` of :meth:`class_scores` of the mean of its ``u`` (without
        :attr:`touch`: ``n * min_k d_k(mean of u)``); one window's equals :meth:`score`.
        """
        u = self.warped(x)
        if u.ndim != 2 or len(u) == 0:
            raise InputError(f"a contact's novelty needs windows (n >= 1, inputs), got shape {u.shape}")
        return float(self.class_scores(u.mean(axis=0, keepdims=True), len(u)).min())

    @property
    def pools(self) -> bool:
        """Whether contacts have held-out quantiles of their own (:meth:`contact_threshold`)."""
        return self.quantiles.ndim == 2

    def threshold(self, false_unknown: float) -> float:
        """Return the score above which a window is unknown.

        At that threshold a share ``false_unknown`` of held-out windows of known textures would
        be called unknown.
        """
        return self._threshold(false_unknown, 1)

    def contact_threshold(self, false_unknown: float, windows: int) -> float:
        """Return the :meth:`pooled_score` above which a contact of ``windows`` windows is unknown.

        At that threshold a share ``false_unknown`` of held-out contacts of known textures that
        long would be (beyond :data:`NOVELTY_RUN` windows, that length's threshold). A model
        without pooled quantiles (:attr:`pools` false) raises :class:`InputError`.
        """
        if not self.pools:
            raise InputError("this novelty score has no contact quantiles (a model file of before them): "
                             "retrain the model with `supramodal train`")
        if isinstance(windows, bool) or int(windows) != windows or windows < 1:
            raise InputError(f"a contact has at least one window, got {windows!r}")
        return self._threshold(false_unknown, int(windows))

    def _threshold(self, false_unknown: float, windows: int) -> float:
        if not (0.0 < false_unknown < 1.0):
            raise InputError(f"the false-unknown rate must lie in (0, 1), got {false_unknown!r}")
        q = self.quantiles[min(windows, len(self.quantiles)) - 1] if self.pools else self.quantiles
        return float(np.interp(1.0 - false_unknown, NOVELTY_QUANTILES, q))

    # -- in a model file: the header's ``novelty`` value and the arrays ``novelty_*``

    def header(self) -> bool | dict:
        """Return the header's ``novelty`` value.

        ``true`` for the unwarped score of before (what such a file said), else the method and
        the warp (a program of before refuses it rather than misread it).
        """
        if self.gain is None or self.offset is None:       # the warp is both or neither
            return True
        warp = {"gain": [float(v) for v in self.gain], "offset": [float(v) for v in self.offset]}
        if self.touch is None:
            return {"method": NOVELTY_METHOD, **warp}
        return {"method": NOVELTY_TOUCH_METHOD, **warp, "touch": self.touch.to_dict()}

    def arrays(self) -> dict:
        """Return the arrays a model file holds (``novelty_means``, ``novelty_precision``, ``novelty_quantiles``)."""
        return {"novelty_means": self.means, "novelty_precision": self.precision, "novelty_quantiles": self.quantiles}

    @classmethod
    def from_parts(cls, flag, arrays: dict, n_in: int, n_classes: int, bad) -> Novelty | None:
        """Return the novelty of a model file from its header's ``novelty`` value and its arrays, each validated.

        None when the header says false. ``bad(message)`` makes the error to raise.
        """
        names = ("novelty_means", "novelty_precision", "novelty_quantiles")
        present = [k for k in names if k in arrays]
        if flag is False:
            if present:
                raise bad(f"the file holds {present} but its header says it has no novelty score")
            return None
        if flag is not True and not isinstance(flag, dict):
            raise bad(f"'novelty' must be true or false, or an object with the method {NOVELTY_METHOD!r}, "
                      f"got {flag!r}")
        gain = offset = touch = None
        if isinstance(flag, dict):
            method = flag.get("method")
            if "method" in flag and method not in (NOVELTY_METHOD, NOVELTY_TOUCH_METHOD):
                raise bad(f"novelty method {method!r} is not known (this program reads {NOVELTY_METHOD!r} "
                          f"and {NOVELTY_TOUCH_METHOD!r})")
            keys = ["gain", "method", "offset"] + (["touch"] if method == NOVELTY_TOUCH_METHOD else [])
            if sorted(flag) != keys:
                raise bad(f"'novelty' must have exactly the keys {keys}, has {sorted(flag)}")
            if method == NOVELTY_TOUCH_METHOD:
                touch = TouchSpread.from_dict(flag["touch"], n_in, n_classes, bad)
            warp = []
            for key in ("gain", "offset"):
                v = flag[key]
                if (not isinstance(v, list) or len(v) != n_in
                        or not all(not isinstance(e, bool) and isinstance(e, (int, float)) and math.isfinite(e)
                                   for e in v)):
                    raise bad(f"'novelty.{key}' must be a list of {n_in} finite numbers")
                warp.append(np.array(v, dtype=np.float64))
            gain, offset = warp
            if np.any(gain <= 0):
                raise bad("'novelty.gain' must be > 0 everywhere")
        missing = [k for k in names if k not in arrays]
        if missing:
            raise bad(f"the header says the model has a novelty score, but the file lacks {missing}")
        rows = (NOVELTY_RUN, len(NOVELTY_QUANTILES)) if gain is not None else NOVELTY_QUANTILES.shape
        shapes = {"novelty_means": (n_classes, n_in), "novelty_precision": (n_in, n_in), "novelty_quantiles": rows}
        for k, want in shapes.items():
            a = arrays[k]
            if a.dtype.kind != "f" or a.shape != want:
                raise bad(f"array {k} has shape {a.shape} and dtype {a.dtype}; expected float {want}")
            if not np.isfinite(a).all():
                raise bad(f"array {k} contains NaN or Inf")
        q = arrays["novelty_quantiles"].astype(np.float64)
        if np.any(np.diff(q, axis=-1) < 0) or np.any(q[..., 0] < 0):
            raise bad("array novelty_quantiles must be non-negative and non-decreasing")
        precision = arrays["novelty_precision"].astype(np.float64)
        if not np.allclose(precision, precision.T, rtol=1e-9, atol=1e-12):
            raise bad("array novelty_precision must be symmetric")
        try:
            np.linalg.cholesky(precision)       # a distance under it is then >= 0, and its inverse exists
        except np.linalg.LinAlgError:
            raise bad("array novelty_precision must be positive definite (a covariance's inverse)") from None
        novelty = cls(arrays["novelty_means"].astype(np.float64), precision, q, gain, offset, touch)
        if touch is not None:
            # made here, not on the node's first window: a file whose numbers make no covariance is refused now
            with np.errstate(all="raise"):
                try:
                    if not np.isfinite(novelty._touch_precisions(1)).all():
                        raise FloatingPointError
                except (np.linalg.LinAlgError, FloatingPointError, OverflowError):
                    raise bad("'novelty.touch' and array novelty_precision make no covariance of a new touch "
                              "(singular or not finite): retrain the model") from None
        return novelty


def novelty_warp(mean, scale) -> tuple[np.ndarray, np.ndarray]:
    """``gain`` and ``offset`` of :class:`Novelty`'s warp for a model whose raw inputs are standardised.

    The raw inputs ``v`` are standardised as ``x = (v - mean) / scale``; then
    ``asinh(v / floor) = asinh(gain * x + offset)`` with ``floor`` :data:`NOVELTY_FLOOR` times
    each input's typical magnitude ``|mean|`` (``scale`` where the mean is 0).
    """
    mean = np.asarray(mean, dtype=np.float64)
    scale = np.asarray(scale, dtype=np.float64)
    floor = NOVELTY_FLOOR * np.where(np.abs(mean) > 0, np.abs(mean), scale)
    return scale / floor, mean / floor


def _gaussian(u, y, n_classes: int) -> tuple[np.ndarray, np.ndarray]:
    means = np.stack([u[y == k].mean(axis=0) if np.any(y == k) else np.zeros(u.shape[1]) for k in range(n_classes)])
    resid = u - means[y]
    cov = resid.T @ resid / max(len(u) - n_classes, 1)
    cov = (1 - NOVELTY_SHRINK) * cov + NOVELTY_SHRINK * np.diag(np.diag(cov)) + 1e-6 * np.eye(u.shape[1])
    precision = np.linalg.inv(cov)
    return means, (precision + precision.T) / 2


def fit_novelty(x, labels, n_classes: int, folds, groups=None, mean=None, scale=None, touch_groups=None,
                touch_floor: float | tuple[float, ...] = NOVELTY_TOUCH_SPREAD, touch_parts=None) -> Novelty:
    """Fit the novelty score on standardised training inputs ``x`` and set its quantiles on held-out windows.

    The held-out windows are of the known textures only: each fold's windows scored by the
    Gaussians of the other folds.

    Parameters
    ----------
    x : ndarray, shape (n, inputs)
    labels : ndarray of int, shape (n,)
    n_classes : int
    folds : ndarray of int, shape (n,)
    groups : sequence, length n, optional
        Each window's recording, windows of one recording consecutive and in time order
        (default: one per label). The held-out contacts of the pooled quantiles are prefixes of
        stretches of 2 .. :data:`NOVELTY_RUN` consecutive windows of one recording and one fold.
    mean, scale : ndarray, shape (inputs,), optional
        How ``x`` was standardised from the raw inputs: the score then warps them back to the
        logarithm of the raw values (:func:`novelty_warp`); without them, ``x`` itself (the score
        of before, windows only).
    touch_groups : sequence of int, length inputs, optional
        With ``mean`` and ``scale``: which inputs share a gain (:attr:`TouchSpread.groups`; e.g. one
        group per vibrissa, or one for a microphone's every channel). The score then allows for a new
        touch (:class:`TouchSpread`, :func:`touch_spread`): its Gaussians are each fold's and the
        final one's class means, the covariance within a recording (``groups``) and the touches'
        spread. Default None: the score of before it.
    touch_floor : float or tuple of float
        The least spread allowed for (default :data:`NOVELTY_TOUCH_SPREAD`); with ``touch_parts``, one per part.
    touch_parts : sequence of int, length inputs, optional
        With ``touch_groups``: per input, the sensor (part, 0 .. k - 1) whose gains it has, each part's spread
        estimated and allowed for on its own (:attr:`TouchSpread.parts`: an early fusion's two senses, whose
        touches vary unalike). Default None: one spread for all the inputs.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(labels)
    folds = np.asarray(folds)
    groups = y if groups is None else np.asarray(groups)
    gain = offset = None
    if mean is not None:
        gain, offset = novelty_warp(mean, scale)
    u = Novelty(np.zeros((1, x.shape[1])), np.eye(x.shape[1]), NOVELTY_QUANTILES, gain, offset).warped(x)
    if touch_groups is not None and gain is None:
        raise InputError("fit_novelty's touch_groups need mean and scale: the allowance for a new touch is in the "
                         "logarithm of the raw inputs")
    if touch_groups is not None and gain is not None:
        tg = tuple(int(v) for v in touch_groups)
        if len(tg) != x.shape[1]:
            raise InputError(f"touch_groups must name a group for each of the {x.shape[1]} inputs, got {len(tg)}")

        tp = None if touch_parts is None else tuple(int(v) for v in touch_parts)
        if tp is not None and (len(tp) != x.shape[1] or min(tp) < 0 or len(set(tp)) != max(tp) + 1 or len(set(tp)) < 2):
            raise InputError(f"touch_parts must give each of the {x.shape[1]} inputs a part 0 .. k - 1, k >= 2, "
                             "each part at least one input")
        if tp is not None and _group_of_two_parts(tg, tp):
            raise InputError("touch_parts: the inputs of one gain group must be of one part (one gain, one sensor)")
        if isinstance(touch_floor, (tuple, list)) and (tp is None or len(touch_floor) != max(tp) + 1):
            raise InputError(f"touch_floor: one least spread per part ({0 if tp is None else max(tp) + 1} with these "
                             f"touch_parts), or one number for all, got {touch_floor!r}")

        def gaussians(rows):
            return _touch_gaussian(u[rows], y[rows], groups[rows], n_classes, tg, touch_floor, tp)
    else:
        def gaussians(rows):
            return (*_gaussian(u[rows], y[rows], n_classes), None)
    held = np.empty(len(x))
    pooled: list[list[float]] = [[] for _ in range(NOVELTY_RUN)]
    for f in np.unique(folds):
        test = folds == f
        means, precision, touch = gaussians(~test)
        fold = Novelty(means, precision, NOVELTY_QUANTILES, touch=touch)
        held[test] = fold.class_scores(u[test]).min(axis=1)
        if gain is not None:
            _pooled_scores(fold, u, groups, test, pooled)
    means, precision, touch = gaussians(np.ones(len(x), dtype=bool))
    if gain is None:
        return Novelty(means, precision, np.quantile(held, NOVELTY_QUANTILES))
    return Novelty(means, precision, _quantile_rows(held, pooled), gain, offset, touch)


def _touch_gaussian(u, y, groups, n_classes: int, touch_groups: tuple, floor, parts: tuple | None = None
                    ) -> tuple[np.ndarray, np.ndarray, TouchSpread]:
    """Class means, the precision of the covariance within a recording, and the :class:`TouchSpread` of ``u``.

    The covariance is of each window about the mean of its texture's part of its recording, shrunk as
    :func:`_gaussian`'s. With ``parts``, each part's spread is estimated on its own inputs' gains and
    floored by its own ``floor`` (a float for all, or one per part).
    """
    p = u.shape[1]
    means = np.stack([u[y == k].mean(axis=0) if np.any(y == k) else np.zeros(p) for k in range(n_classes)])
    _, recording = np.unique(groups, return_inverse=True)
    _, index = np.unique(np.stack([np.asarray(y).ravel(), recording.ravel()], axis=1), axis=0, return_inverse=True)
    index = index.ravel()
    recording_means = np.stack([u[index == r].mean(axis=0) for r in range(index.max() + 1)])
    resid = u - recording_means[index]
    cov = resid.T @ resid / max(len(u) - len(recording_means), 1)
    cov = (1 - NOVELTY_SHRINK) * cov + NOVELTY_SHRINK * np.diag(np.diag(cov)) + 1e-6 * np.eye(p)
    precision = np.linalg.inv(cov)
    windows = tuple(max(int(np.sum(y == k)), 1) for k in range(n_classes))
    touches = tuple(max(len(set(groups[y == k].tolist())), 1) for k in range(n_classes))
    of_part = np.zeros(p, dtype=int) if parts is None else np.asarray(parts)        # one part: every input
    floors = tuple(floor) if isinstance(floor, (tuple, list)) else (floor,) * (int(of_part.max()) + 1)
    structure = gain_structure(touch_groups)
    estimates: list[float | None] = []
    for part in range(len(floors)):
        inside = of_part == part
        e = touch_spread(u, y, groups, cov, structure * np.outer(inside, inside))
        estimates.append(None if e is None else min(e, NOVELTY_MAX_TOUCH_SPREAD))
    spreads = tuple(float(min(max(least, e or 0.0), NOVELTY_MAX_TOUCH_SPREAD)) for least, e in zip(floors, estimates))
    precision = (precision + precision.T) / 2
    if parts is None:
        return means, precision, TouchSpread(spreads[0], touch_groups, windows, touches, estimates[0])
    known = [e for e in estimates if e is not None]
    return means, precision, TouchSpread(max(spreads), touch_groups, windows, touches, max(known) if known else None,
                                         parts, spreads, tuple(estimates))


def touch_spread(u, labels, groups, within, structure) -> float | None:
    """Estimate the spread of the touches' log gains from the recordings' means about their texture's.

    A moment estimate: a recording of ``n`` windows of a texture met in ``m`` recordings lies from
    the mean of that texture's recordings by ``d`` with ``E[d' G d] = (1 - 1 / m) (s**2 tr(G G) +
    tr(G W) / n)`` (``G`` the gains' ``structure``, ``W`` the covariance ``within`` a recording),
    solved for ``s`` (0 where the recordings differ less than their windows' noise explains).
    None where no texture has two recordings.
    """
    u = np.asarray(u, dtype=np.float64)
    y, groups = np.asarray(labels), np.asarray(groups)
    gg = float(np.sum(structure * structure))
    gw = float(np.sum(structure * within))
    if gg == 0:
        return None
    seen = excess = 0.0
    for k in dict.fromkeys(y.tolist()):
        recs = list(dict.fromkeys(groups[y == k].tolist()))
        if len(recs) < 2:
            continue
        rows = [(y == k) & (groups == r) for r in recs]
        rm = np.stack([u[r].mean(axis=0) for r in rows])
        d = rm - rm.mean(axis=0)
        share = 1.0 - 1.0 / len(recs)
        for dr, r in zip(d, rows):
            excess += float(dr @ structure @ dr) - share * gw / int(r.sum())
            seen += share * gg
    if not seen:
        return None
    return math.sqrt(max(excess / seen, 0.0))


def _pooled_scores(novelty: Novelty, u: np.ndarray, groups: np.ndarray, rows: np.ndarray,
                   pooled: list[list[float]]) -> None:
    """Add to ``pooled[n - 1]`` the pooled score of every stretch of ``n`` consecutive windows of one group.

    ``n`` runs over 2 .. :data:`NOVELTY_RUN`; the windows are those among ``rows`` (a boolean mask
    over ``u``'s rows).
    """
    for g in dict.fromkeys(groups[rows].tolist()):
        idx = np.flatnonzero(rows & (groups == g))
        # a contact never crosses a gap in the group's windows (another fold's span between);
        # every start counts (overlapping contacts: more of them than disjoint ones steadies the
        # upper quantiles, which a few dozen contacts leave noisy)
        for block in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            c = np.vstack([np.zeros((1, u.shape[1])), np.cumsum(u[block], axis=0)])
            for n in range(2, min(NOVELTY_RUN, len(block)) + 1):
                means_n = (c[n:] - c[:-n]) / n
                pooled[n - 1].extend(novelty.class_scores(means_n, n).min(axis=1))


def _quantile_rows(windows: np.ndarray, pooled: list[list[float]]) -> np.ndarray:
    """:attr:`Novelty.quantiles` of held-out window scores and pooled scores by contact length.

    A length with fewer than :data:`NOVELTY_MIN_CONTACTS` contacts repeats the row of the one
    before.
    """
    rows = [np.quantile(windows, NOVELTY_QUANTILES)]
    for n in range(1, NOVELTY_RUN):
        rows.append(np.quantile(pooled[n], NOVELTY_QUANTILES) if len(pooled[n]) >= NOVELTY_MIN_CONTACTS else rows[-1])
    return np.stack(rows)


def recalibrate(logits, labels, groups, x=None, novelty: Novelty | None = None, what: str = ""
                ) -> tuple[Calibration, Novelty | None]:
    """Fit a network's calibration and novelty thresholds anew on labelled windows it never trained on.

    The windows are of a new touch, session or sensor; the network is kept (issue 34).

    The windows need no folds: no network trained on them, so its logits on them are held out as they
    stand. The window map, caps and contact pooling are fitted as :func:`fit_calibration` fits them; the
    novelty score keeps its Gaussians and takes its thresholds from these windows (:func:`requantiled`).

    Parameters
    ----------
    logits : ndarray, shape (n, classes)
        The network's logits on the windows.
    labels : ndarray of int, shape (n,)
        Every class at least once (the caps and the map need them all).
    groups : sequence, length n
        Each window's recording, windows of one recording consecutive and in time order.
    x : ndarray, shape (n, inputs), optional
        The windows' standardised input rows, with ``novelty``: the novelty's new thresholds.
    novelty : Novelty, optional
    what : str
        What the windows were, in words (e.g. the recordings' names): kept in ``fitted_on``.

    Returns
    -------
    calibration : Calibration
        ``fitted_on`` says ``recalibrated_on`` (``what``) and the windows' accuracy.
    novelty : Novelty or None
    """
    z = np.asarray(logits, dtype=np.float64)
    y = np.asarray(labels)
    _check_scored(z, y, "logits")
    missing = sorted(set(range(z.shape[1])) - set(y.tolist()))
    if missing:
        raise InputError(f"recalibrating needs labelled windows of every class; none of class(es) {missing}: record "
                         "every texture on the new touch")
    cal = fit_calibration(z, y, groups)
    cal = replace(cal, fitted_on={**cal.fitted_on, "held_out_accuracy": round(float(np.mean(winner(z) == y)), 6),
                                  "recalibrated_on": str(what) or f"{len(y)} windows"})
    if novelty is not None and x is not None:
        novelty = requantiled(novelty, x, groups)
    return cal, novelty


def requantiled(novelty: Novelty, x, groups) -> Novelty:
    """``novelty`` with its quantiles set anew on windows of known textures that its Gaussians never saw.

    The windows are of a new touch, session or sensor (:func:`recalibrate`): the same score, the
    thresholds where the asked share of these windows and of their contacts would be called
    unknown.

    Parameters
    ----------
    x : ndarray, shape (n, inputs)
        Standardised input rows (the model's own standardisation).
    groups : sequence, length n
        Each window's recording, windows of one recording consecutive and in time order.
    """
    u = novelty.warped(x)
    groups = np.asarray(groups)
    windows = novelty.class_scores(u).min(axis=1)
    if novelty.gain is None:
        return replace(novelty, quantiles=np.quantile(windows, NOVELTY_QUANTILES))
    pooled: list[list[float]] = [[] for _ in range(NOVELTY_RUN)]
    _pooled_scores(novelty, u, groups, np.ones(len(u), dtype=bool), pooled)
    return replace(novelty, quantiles=_quantile_rows(windows, pooled))


# -- measures ---------------------------------------------------------------------------------------

def log_loss(log_posteriors, labels) -> float:
    """Mean negative log-posterior of the true class (nats)."""
    lp = np.asarray(log_posteriors, dtype=np.float64)
    y = np.asarray(labels)
    return float(-lp[np.arange(len(y)), y].mean())


def brier_score(posteriors, labels) -> float:
    """Mean over rows of ``sum_k (p_k - [k == y])^2`` (0 = perfect, 2 = sure and wrong)."""
    p = np.asarray(posteriors, dtype=np.float64)
    y = np.asarray(labels)
    t = np.zeros_like(p)
    t[np.arange(len(y)), y] = 1.0
    return float(((p - t) ** 2).sum(axis=1).mean())


def reliability(confidence, correct, bins: int = ECE_BINS) -> dict:
    """Reliability diagram data: per equal-width confidence bin, the count, the mean confidence and the share right.

    The bins are right-closed, the first also holding 0; the mean and the share are None where
    a bin is empty.
    """
    conf = np.asarray(confidence, dtype=np.float64)
    ok = np.asarray(correct, dtype=bool)
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.searchsorted(edges, conf, side="left") - 1, 0, bins - 1)
    count = np.bincount(which, minlength=bins)
    conf_sum = np.bincount(which, weights=conf, minlength=bins)
    ok_sum = np.bincount(which, weights=ok.astype(float), minlength=bins)
    mean_conf = [float(s / c) if c else None for s, c in zip(conf_sum, count)]
    accuracy = [float(s / c) if c else None for s, c in zip(ok_sum, count)]
    return {"edges": edges.tolist(), "count": count.tolist(), "confidence": mean_conf, "accuracy": accuracy}


def expected_calibration_error(confidence, correct, bins: int = ECE_BINS) -> float:
    """ECE: ``sum_b (n_b / n) |accuracy_b - confidence_b|`` over equal-width confidence bins."""
    r = reliability(confidence, correct, bins)
    n = sum(r["count"])
    if n == 0:
        raise InputError("no decisions to measure the calibration of")
    return float(sum(c / n * abs(a - m) for c, a, m in zip(r["count"], r["accuracy"], r["confidence"]) if c))


#: The largest expected calibration error at which decisions on recordings are said to be about as sure
#: as they are right (``evaluate``'s verdict; the target of issues 23 and 34).
HOLDS_ECE = 0.05


def mean_confidence(report: dict) -> float:
    """Return the mean stated confidence (winner's posterior) of a :func:`calibration_report`'s decisions."""
    r = report["reliability"]
    counts = np.asarray(r["count"], dtype=np.float64)
    conf = np.array([0.0 if c is None else c for c in r["confidence"]])
    return float((counts * conf).sum() / counts.sum())


def ece_if_calibrated(report: dict, quantile: float = 0.95, draws: int = 400, seed: int = 0) -> float:
    """Return the ECE a perfectly calibrated model would exceed once in ``1 - quantile`` at a report's confidences.

    Simulated on as many decisions as a :func:`calibration_report`'s, at its confidences: each
    reliability bin's decisions right at random with the bin's mean confidence (binomial),
    ``draws`` times. A few hundred decisions have an ECE of a few hundredths by chance alone,
    which a fixed bound would take for a calibration that does not hold.
    """
    r = report["reliability"]
    counts = np.asarray(r["count"], dtype=np.int64)
    conf = np.array([0.0 if c is None else c for c in r["confidence"]])
    rng = np.random.default_rng(seed)
    right = rng.binomial(counts[None, :], np.clip(conf, 0.0, 1.0)[None, :], size=(draws, len(counts)))
    with np.errstate(invalid="ignore", divide="ignore"):
        gaps = np.where(counts > 0, np.abs(right / np.maximum(counts, 1) - conf), 0.0)
    return float(np.quantile((gaps * counts).sum(axis=1) / counts.sum(), quantile))


def calibration_report(log_posteriors, labels, bins: int = ECE_BINS, sure: float = 0.99) -> dict:
    """Accuracy, log loss, Brier score, ECE and the reliability data of decisions.

    The decisions are given by their log-posteriors (n, classes) and true ``labels`` (n,); also
    how many say at least ``sure`` and what share of those is wrong. A tie (:func:`winner` -1)
    counts as wrong.
    """
    lp = np.asarray(log_posteriors, dtype=np.float64)
    y = np.asarray(labels)
    p = np.exp(lp)
    k = winner(lp)
    conf = p.max(axis=1)
    ok = k == y
    high = conf >= sure
    return {"n": int(len(y)), "accuracy": float(ok.mean()), "log_loss": log_loss(lp, y),
            "brier": brier_score(p, y), "ece": expected_calibration_error(conf, ok, bins),
            "sure": sure, "sure_count": int(high.sum()),
            "sure_wrong": float((high & ~ok).sum() / high.sum()) if high.any() else None,
            "reliability": reliability(conf, ok, bins)}


# -- fitting a network's calibration by grouped folds ----------------------------------------------

def fewest_groups_of_a_label(labels, groups) -> int:
    """Return the fewest groups (recordings, contacts) any one label's windows come from.

    ``labels`` and ``groups``: one per window, of one length (at least one window).
    """
    labels, groups = np.asarray(labels), np.asarray(groups)
    return min(len(set(groups[labels == lab].tolist())) for lab in set(labels.tolist()))


def calibration_folds(labels, groups, k: int = DEFAULT_CALIBRATION_FOLDS, seed: int = 0) -> tuple[np.ndarray, str]:
    """Folds for the held-out windows of a calibration, and how they were made.

    By recording (:func:`supramodal.training.grouped_folds`) when every label has at least two
    recordings and there are at least ``k``; otherwise each recording's windows are cut into
    ``k`` consecutive spans, span ``f`` in fold ``f`` (one long recording per texture, as the
    reference sets: held out in time, not by recording).

    Returns
    -------
    folds : ndarray of int, shape (n,)
    by : {"recording", "span"}
    """
    from supramodal.training import grouped_folds

    labels = np.asarray(labels)
    groups = np.asarray(groups)
    if len(set(groups.tolist())) >= k and fewest_groups_of_a_label(labels, groups) >= 2:
        return grouped_folds(groups.tolist(), labels.tolist(), k, seed), "recording"
    folds = np.empty(len(labels), dtype=int)
    for g in dict.fromkeys(groups.tolist()):
        idx = np.flatnonzero(groups == g)
        folds[idx] = np.arange(len(idx)) * k // len(idx)
    return folds, "span"


def fit_network_calibration(x, labels, n_classes: int, groups=None, k: int = DEFAULT_CALIBRATION_FOLDS,
                            hidden: int | None = None, epochs: int | None = None, seed: int = 0,
                            progress=None, jobs: int = 1, augment=None, touch_groups=None,
                            touch_floor: float = NOVELTY_TOUCH_SPREAD,
                            patience: int | None = EARLY_STOP_PATIENCE) -> tuple[Calibration, Novelty, OutOfFold]:
    """Fit the calibration and novelty of a network as :func:`supramodal.mlp.train_mlp` would train it.

    They are fitted from out-of-fold windows; the network would train on the raw (unstandardised)
    input rows ``x`` (n, inputs), augmented by ``augment`` where given (each fold network alike, the
    held-out rows never).

    Each of ``k`` folds (:func:`calibration_folds`) trains a network with the same hidden units,
    epochs and seed on the other folds (standardised by their own mean and scale) and gives the
    logits of its own windows (:func:`fold_tasks`); the calibration is fitted on those held-out
    logits, never on windows a network trained on (:func:`calibration_of_held_out`).

    Parameters
    ----------
    groups : sequence, length n, optional
        Each window's recording, windows of one recording consecutive and in time order
        (default: one recording per label).
    progress : callable(str), optional
        One line per fold, as each is trained.
    jobs : int
        Worker processes for the fold networks (:func:`supramodal.mlp.train_networks`; the result
        is the same for any).
    augment : callable, optional
        Augmentation of each fold network's training rows, as :func:`fold_tasks` takes it (e.g.
        :meth:`supramodal.model.GainAugment.for_inputs`, whose ``factor`` says how many rows it makes
        of one): the network this calibrates should be trained with it too. The held-out rows, the
        calibration and the novelty see the original rows only. Default None: none.
    touch_groups, touch_floor
        The novelty's allowance for a new touch (:func:`fit_novelty`; default none).
    patience : int or None
        Each fold network stops early on its held-out windows, as a model's own do
        (:func:`fold_tasks`; default :data:`~supramodal.mlp.EARLY_STOP_PATIENCE`); None: every epoch.

    Returns
    -------
    calibration : Calibration
    novelty : Novelty
    out_of_fold : OutOfFold
        The held-out logits and folds themselves, for whatever else needs a network's held-out
        windows (a late fusion's weight: no need to train the same fold networks again).
    """
    from supramodal.mlp import DEFAULT_EPOCHS

    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(labels)
    groups = y if groups is None else np.asarray(groups)
    folds, by = calibration_folds(y, groups, k, seed)
    held_out = HeldOutLogits(y, folds, k, n_classes, progress)
    epochs = DEFAULT_EPOCHS if epochs is None else epochs
    train_fold_networks(x, y, n_classes, folds, k, hidden, epochs, seed, augment, patience, jobs, done=held_out.told,
                        redone=held_out.retold)
    return calibration_of_held_out(x, y, n_classes, groups, folds, by, k, held_out.logits, touch_groups, touch_floor)


def fold_tasks(x, labels, n_classes: int, folds, k: int, hidden: int | None, epochs: int, seed: int,
               augment, patience: int | None, only=None):
    """Yield the calibration's fold networks as :class:`~supramodal.mlp.NetworkTask`, in fold order.

    One per fold with held-out windows: trained on the other folds' rows of ``x`` (n, inputs),
    standardised by their own mean and scale, scoring the fold's own rows. A generator: each
    fold's rows are copied when its task is taken. ``augment``: optional callable
    ``(rows, labels, stream) -> (rows, labels)`` applied to each fold's raw training rows (stream
    ``f + 1``; the held-out rows are never augmented; None: none). ``patience``: each network stops
    early on its fold's held-out rows (:func:`supramodal.mlp.train_mlp`'s ``stop_on``); None: every
    epoch. ``only``: the tasks to yield, by their index among all (default: all).
    """
    from supramodal.mlp import NetworkTask

    y = np.asarray(labels)
    for i, f in enumerate(held_out_folds(folds, k)):
        test = folds == f
        if only is None or i in only:
            mean, scale = fold_scaling(x, folds, f)
            xt, yt = (x[~test], y[~test]) if augment is None else augment(x[~test], y[~test], f + 1)
            stop = {} if patience is None else {"score_labels": y[test], "patience": patience}
            yield NetworkTask((xt - mean) / scale, yt, n_classes, hidden, epochs, seed, (x[test] - mean) / scale,
                              **stop)


def train_fold_networks(x, labels, n_classes: int, folds, k: int, hidden: int | None, epochs: int, seed: int,
                        augment, patience: int | None, jobs: int = 1, done=None, redone=None, watch=None) -> list:
    """Train :func:`fold_tasks`' networks; where they stop early, all at the epochs best for them together.

    Each fold network stops on its own held-out windows (``patience``); then the epochs of the lowest
    held-out error summed over every fold's windows, among the epochs every network looked at
    (:func:`joint_stop_epochs`), and each network that stopped at other epochs is trained again for
    exactly those (the same network as its own training's at those epochs: the training is
    deterministic). The members of an ensemble are so of one age: the calibration is fitted on held-out
    logits of single members, each window one member's, and applied to their mean, which a member much
    sharper than the others would sway. ``patience`` None: every network trains every epoch.

    Parameters
    ----------
    x, labels, n_classes, folds, k, hidden, epochs, seed, augment, patience
        As :func:`fold_tasks`'.
    jobs : int
        Worker processes (:func:`supramodal.mlp.train_networks`; the networks are the same for any).
    done : callable(int, Trained), optional
        Told each fold network's result as it is back from its first training (with ``patience``, the
        network at its own best): progress as it goes.
    redone : callable(int, Trained), optional
        Told each result that the joint stop trained again, once all are in (default: ``done``).
    watch : (int, callable(epoch, mse)), optional
        :func:`~supramodal.mlp.train_networks`' ``watch``, of the first training.

    Returns
    -------
    list of :class:`~supramodal.mlp.Trained`
        The networks deployed, in :func:`fold_tasks`' order (a network trained again keeps the held-out
        errors of its first training).
    """
    from supramodal.mlp import NetworkTask, train_networks

    factor = getattr(augment, "factor", 1)
    work = fold_work(len(x), x.shape[1], n_classes, folds, k, hidden, epochs, patience) * factor
    tasks = fold_tasks(x, labels, n_classes, folds, k, hidden, epochs, seed, augment, patience)
    results = train_networks(tasks, jobs, watch=watch, done=done, work=work)
    if patience is None:
        return results
    sizes = [int(np.sum(folds == f)) for f in held_out_folds(folds, k)]
    best = joint_stop_epochs([r.held_out_errors for r in results], sizes)
    again = [i for i, r in enumerate(results) if len(r.history) != best]
    if again:
        redo = [NetworkTask(t.x, t.labels, n_classes, hidden, best, seed, t.score)
                for t in fold_tasks(x, labels, n_classes, folds, k, hidden, epochs, seed, augment, None, set(again))]
        tell = redone or done
        for i, r in zip(again, train_networks(redo, min(jobs, len(redo)), work=sum(t.work for t in redo))):
            results[i] = r._replace(held_out_errors=results[i].held_out_errors)
            if tell is not None:
                tell(i, results[i])
    return results


def joint_stop_epochs(errors, sizes) -> int:
    """Return the epochs whose held-out error, summed over the fold networks' windows, is lowest.

    ``errors``: per fold network, its looks ``(epochs, mean squared error)``
    (:attr:`~supramodal.mlp.Trained.held_out_errors`); ``sizes``: its held-out windows. Only epochs every
    network looked at count (each trained ``patience`` past its own best); of equal sums, the fewest epochs.
    """
    looks = [dict(e) for e in errors]
    common = set(looks[0]).intersection(*looks[1:])
    if not common:
        raise InputError("the fold networks looked at their held-out errors at no common epochs")
    if not all(np.isfinite(look[e]) for look in looks for e in common):
        raise InputError("a fold network's held-out error is not finite: its inputs or weights overflowed")
    return min(sorted(common), key=lambda e: sum(m * look[e] for m, look in zip(sizes, looks)))


def held_out_folds(folds, k: int) -> list[int]:
    """Return the folds 0 .. ``k`` - 1 that hold windows (of ``folds``, each window's): one network each, in order."""
    folds = np.asarray(folds)
    return [f for f in range(k) if np.any(folds == f)]


def fold_scaling(x, folds, f: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the mean and scale fold ``f``'s network standardises its rows by: those of the other folds' rows."""
    return input_scaling(np.asarray(x)[np.asarray(folds) != f])


def fold_work(n: int, inputs: int, n_classes: int, folds, k: int, hidden: int | None, epochs: int,
              patience: int | None) -> float:
    """Return the summed :attr:`~supramodal.mlp.NetworkTask.work` of :func:`fold_tasks`' networks, not making them."""
    from supramodal.mlp import expected_epochs

    rows = sum(n - int(np.sum(folds == f)) for f in held_out_folds(folds, k))
    return float(rows) * (hidden or inputs) * (inputs + n_classes) * expected_epochs(epochs, patience)


class HeldOutLogits:
    """The fold networks' logits of their held-out windows, gathered as each network is told.

    Each is told by :meth:`told`, in any order (:func:`supramodal.mlp.train_networks` tells them
    as they are back), with a line per fold to ``progress``; :attr:`complete` once every fold is in.
    """

    def __init__(self, labels, folds, k: int, n_classes: int, progress=None, what: str = "calibration fold") -> None:
        self.labels, self.folds, self.progress, self.what = np.asarray(labels), np.asarray(folds), progress, what
        self.logits = np.empty((len(self.labels), n_classes))
        self._order = held_out_folds(self.folds, k)
        self._k = k
        self._in: set[int] = set()

    @property
    def networks(self) -> int:
        """The fold networks (folds with held-out windows: :func:`fold_tasks`' tasks)."""
        return len(self._order)

    @property
    def order(self) -> list[int]:
        """The fold of each fold network, in :func:`fold_tasks`' order."""
        return list(self._order)

    @property
    def complete(self) -> bool:
        """Whether every fold's logits are in."""
        return len(self._in) == len(self._order)

    def retold(self, i: int, result) -> None:
        """Take the ``i``-th fold task's result again, without a line (:func:`train_fold_networks`' ``redone``)."""
        self.logits[self.folds == self._order[i]] = result.logits

    def told(self, i: int, result) -> None:
        """Take the ``i``-th fold task's result (a :class:`supramodal.mlp.Trained`)."""
        f = self._order[i]
        test = self.folds == f
        self.logits[test] = result.logits
        self._in.add(f)
        if self.progress:
            right = float(np.mean(np.argmax(result.logits, axis=1) == self.labels[test]))
            self.progress(f"{self.what} {f + 1}/{self._k}: {int(test.sum())} held-out windows, {right:.3f} right")


def calibration_of_held_out(x, labels, n_classes: int, groups, folds, by: str, k: int,
                            z, touch_groups=None, touch_floor: float | tuple[float, ...] = NOVELTY_TOUCH_SPREAD,
                            touch_parts=None, scaling=None) -> tuple[Calibration, Novelty, OutOfFold]:
    """Fit :func:`fit_network_calibration`'s calibration, novelty and :class:`OutOfFold` from held-out logits.

    The logits ``z`` (n, classes) are the fold networks' of the raw input rows ``x``. ``touch_groups``,
    ``touch_floor`` and ``touch_parts``: the novelty's allowance for a new touch (:func:`fit_novelty`;
    default none). ``scaling``: ``x``'s :func:`input_scaling` where the caller has it (default: computed).
    """
    y = np.asarray(labels)
    cal = fit_calibration(z, y, groups, folds=folds)
    cal = replace(cal, fitted_on={**cal.fitted_on, "folds": int(k), "folds_by": by,
                                  "held_out_accuracy": round(float(np.mean(np.argmax(z, axis=1) == y)), 6)})
    mean, scale = input_scaling(x) if scaling is None else scaling
    novelty = fit_novelty((x - mean) / scale, y, n_classes, folds, groups, mean, scale, touch_groups, touch_floor,
                          touch_parts)
    return cal, novelty, OutOfFold(z, folds, _fingerprint(x, y))


@dataclass(frozen=True)
class OutOfFold:
    """A network's held-out logits from training.

    ``logits`` (n, classes) of each training window from the fold network that did not train on
    it, ``folds`` (n,), and ``fingerprint``, what they were computed on (the input rows and
    labels, hashed: :meth:`matches`). Kept in memory only.
    """

    logits: np.ndarray
    folds: np.ndarray
    fingerprint: str

    def matches(self, x, labels, folds) -> bool:
        """Whether these are the held-out logits of input rows ``x`` with ``labels`` on ``folds``."""
        folds = np.asarray(folds)
        return (folds.shape == self.folds.shape and bool(np.all(folds == self.folds))
                and _fingerprint(np.asarray(x, dtype=np.float64).reshape(len(folds), -1), labels) == self.fingerprint)


def _fingerprint(x, labels) -> str:
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    for a in (np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(labels, dtype=np.int64)):
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def input_scaling(x) -> tuple[np.ndarray, np.ndarray]:
    """Mean and scale of input rows as a model standardises them (a constant input keeps scale 1)."""
    mean = x.mean(axis=0)
    scale = x.std(axis=0)
    scale[scale == 0] = 1.0
    return mean, scale


def calibration_line(fitted_on: dict | None) -> str:
    """Return, in words, what a model's calibration was fitted on (its ``fitted_on``; None: uncalibrated)."""
    if fitted_on is None:
        return "uncalibrated (posteriors: the network's normalised outputs)"
    f = fitted_on
    if "recalibrated_on" in f:
        line = (f"recalibrated on {f.get('windows')} windows its network never trained on ({f['recalibrated_on']})")
        if "log_loss_uncalibrated" in f and "log_loss" in f:
            line += f": log loss {f['log_loss_uncalibrated']:.3f} -> {f['log_loss']:.3f} nats"
        if "held_out_accuracy" in f:
            line += f", {f['held_out_accuracy']:.3f} of them right"
        return line
    by = {"recording": " by recording", "span": " by span of each recording"}.get(f.get("folds_by", ""), "")
    line = f"calibrated on {f.get('windows')} held-out windows ({f.get('folds')} folds{by})"
    if "log_loss_uncalibrated" in f and "log_loss" in f:
        line += f": held-out log loss {f['log_loss_uncalibrated']:.3f} -> {f['log_loss']:.3f} nats"
    if "held_out_accuracy" in f:
        line += f", {f['held_out_accuracy']:.3f} of them right"
    return line
