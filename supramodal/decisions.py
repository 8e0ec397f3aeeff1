"""Decisions over time: per window, over the last N windows, or over the current contact.

A robot decides per touch, not per 100 ms. Every function here takes a window's
*log-posteriors* (a model's :meth:`~supramodal.model.TextureModel.log_posteriors`: calibrated
when the model is, finite, never clipped). The accumulated decision is the winner of

* ``"log"``: the pooled log-posteriors ``log_softmax(g(n) sum_t log p_k(t))`` with
  ``g(n) = n_eff(n) / n``, the effective number of independent windows per window
  (:func:`supramodal.calibration.pool_log_posteriors`; ``rho``, the model's fitted correlation of
  neighbouring windows, 0 = naive Bayes), or
* ``"vote"``: the count of windows each class won (ties go to the larger summed posterior),

over the last ``n`` windows (``scope="last"``) or over the windows since the
current contact began, at most the last ``n`` (``scope="contact"``; ``n = 0``: every one). A
contact is a run of consecutive windows whose input RMS is at least ``threshold``; a window below
it ends the contact and resets the accumulation.

Decide as soon as it is sure: with a ``confidence`` threshold and ``scope="contact"``, the first
pooled decision of a contact whose confidence reaches it is the contact's *final* decision
(:attr:`Decision.decided`); it stands, with the number of windows it took, until the contact
ends, while the per-window output goes on as before.

A tie (several classes share the top pooled score) is no decision: label -1, never a class
picked by its place in the class list.

:class:`Decider` says what a stream (or a fusion) of windows says: the winner, "unknown", and the
pooled decision, by these rules:

* The window's decision is the winner of its log-posteriors (:func:`supramodal.calibration.winner`).
  A tie is no decision: :data:`UNKNOWN`, reason ``"tie"`` (never the class that sorts first).
* ``[decision] unknown = r`` (a false-unknown rate in (0, 1); needs a model with a novelty score):
  a window whose novelty score is above the model's threshold for ``r`` is :data:`UNKNOWN`,
  reason ``"novel"``. ``[decision] unknown_below = c``: a window whose calibrated confidence is
  below ``c`` is :data:`UNKNOWN`, reason ``"unsure"``. The winner is kept as the event's ``guess``.
* The pooled decision (``scope = "last"`` or ``"contact"``) pools every window's log-posteriors
  (:class:`supramodal.decisions.DecisionAccumulator`, with the model's fitted correlation), except
  that a novel window adds no evidence (its inputs are unlike anything the network was trained
  on, so its posteriors say nothing of the known textures: it is pooled as uniform); it is
  :data:`UNKNOWN` while more than half of its windows are. With ``confidence = c`` and
  ``scope = "contact"``, the contact's decision is final as soon as its pooled confidence reaches
  ``c``: the pooled dict then says ``"decided": true`` and ``"decided_after"`` windows.
* ``[decision] change = f`` (false changes per minute allowed, > 0; needs ``scope = "contact"``): the
  texture may change within a contact (a whisker sliding from one surface onto the next without
  lifting off). A :class:`ChangeDetector` watches the windows' evidence against the current pooled
  decision; when it finds another texture, the pooled decision starts again from the windows since
  the change began (a final decision too), and that window's pooled dict says ``"change": {"from",
  "to", "after"}`` (``after``: the windows since the change began).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from supramodal.calibration import (
    POOLING_RUN,
    Calibration,
    HeldOutChanges,
    cap_gaps,
    effective_windows,
    pool_log_posteriors,
    winner,
)
from supramodal.errors import InputError
from supramodal.features import DEFAULT_WINDOW
from supramodal.records import JsonRecord, JsonValue

SCOPES = ("window", "last", "contact")
METHODS = ("log", "vote")
#: Defaults of a decision (the scene's [decision] section takes them from here).
DEFAULT_SCOPE = "window"
DEFAULT_POOLED = 10
DEFAULT_METHOD = "log"
DEFAULT_CONTACT_THRESHOLD = 0.01
@dataclass(frozen=True)
class DecisionRules:
    """How a stream (or a fusion) of windows decides: a scene's ``[decision]``.

    Every rule's meaning is :class:`Decider`'s. The defaults are those a scene gets when it gives
    none, with the rules of issue 23 off (0: no final contact decision, no "unknown").

    Attributes
    ----------
    scope : {"window", "last", "contact"}
        Decide each window alone, pool the last ``n`` windows, or pool the current contact's.
    n : int
        Windows pooled (``scope = "contact"``: at most the last ``n``; 0 = every one).
    method : {"log", "vote"}
        Pool log-posteriors, or count each window's winner.
    contact_threshold : float
        Input RMS at and above which a window is in contact.
    confidence : float
        Calibrated pooled confidence at which a contact's decision is final, in [0, 1) (0: never).
    unknown : float
        Share of windows of known textures the novelty score may call unknown, in [0, 1) (0: off).
    unknown_below : float
        Calibrated confidence below which a window is unknown, in [0, 1) (0: off).
    change : float
        False changes of texture per minute allowed within a contact, >= 0 (0: off, a contact keeps
        one texture; needs ``scope = "contact"``): :class:`ChangeDetector`.
    """

    scope: str = DEFAULT_SCOPE
    n: int = DEFAULT_POOLED
    method: str = DEFAULT_METHOD
    contact_threshold: float = DEFAULT_CONTACT_THRESHOLD
    confidence: float = 0.0
    unknown: float = 0.0
    unknown_below: float = 0.0
    change: float = 0.0

    @property
    def calibrated_rules(self) -> list[str]:
        """The rules set here that need calibrated posteriors, by name.

        Those are ``confidence``, ``unknown``, ``unknown_below`` and ``change``.
        """
        return [k for k in ("confidence", "unknown", "unknown_below", "change") if getattr(self, k)]


#: The rules when a scene gives no ``[decision]``.
DEFAULT_DECISION = DecisionRules()


@dataclass(frozen=True)
class Decision:
    """One decision.

    Attributes
    ----------
    label : int
        Winning class index, or -1: out of contact, or a tie.
    confidence : float
        The winner's share: ``p_label`` for one window; for an accumulated decision, the
        pooled posterior of the winner (``"log"``) or its fraction of the votes (``"vote"``).
    windows : int
        How many windows the decision is based on (0 when out of contact).
    decided : bool
        The contact's final decision has been taken (its confidence reached the threshold);
        ``label``, ``confidence`` and ``windows`` are then those of the moment it was taken.
    """

    label: int
    confidence: float
    windows: int
    decided: bool = False


def window_decision(log_posteriors: np.ndarray) -> Decision:
    """Winner-take-all on one window's log-posteriors, shape (classes,) (-1 on a tie)."""
    lp = np.asarray(log_posteriors, dtype=np.float64)
    k = int(winner(lp))
    return Decision(k, float(np.exp(lp.max())), 1)


class DecisionAccumulator:
    """Pools per-window log-posteriors into a decision over several windows.

    Parameters
    ----------
    n_classes : int
    scope : {"window", "last", "contact"}
        ``"window"`` decides each window alone (the paper's setting).
    n : int
        Windows pooled for ``scope="last"`` (default :data:`DEFAULT_POOLED`, 1 s of 100 ms windows);
        for ``"contact"``, the most windows kept (0 = unlimited).
    method : {"log", "vote"}
    correlation : float
        ``rho`` in [0, 1] of the ``"log"`` pooling (default 0: summed log-posteriors, naive
        Bayes).
    confidence : float or None
        With ``scope="contact"``: the pooled confidence at which a contact's decision is final
        (see the module); None: never final.
    caps : sequence of sequences of float, or None
        The ``"log"`` pooling's caps per pair of classes (:func:`~supramodal.calibration.cap_gaps`),
        shape (classes, classes); None: uncapped. A calibrated model's pooling is
        ``correlation, caps = model.calibration.contact_pooling``: the accumulator then pools
        exactly as :meth:`~supramodal.calibration.Calibration.pool` does.
    """

    def __init__(self, n_classes: int, scope: str = DEFAULT_SCOPE, n: int = DEFAULT_POOLED,
                 method: str = DEFAULT_METHOD, correlation: float = 0.0, confidence: float | None = None,
                 caps=None) -> None:
        if scope not in SCOPES:
            raise InputError(f"decision scope must be one of {SCOPES}, got {scope!r}")
        if method not in METHODS:
            raise InputError(f"decision method must be one of {METHODS}, got {method!r}")
        if scope == "last" and n < 1:
            raise InputError(f"scope 'last' needs n >= 1 windows, got {n}")
        if n < 0:
            raise InputError(f"n must be >= 0, got {n}")
        if not (0.0 <= correlation <= 1.0):
            raise InputError(f"the pooling's correlation must lie in [0, 1], got {correlation!r}")
        if confidence is not None:
            if scope != "contact":
                raise InputError(f"a decision confidence threshold needs scope 'contact', got {scope!r}")
            if not (0.0 < confidence < 1.0):
                raise InputError(f"the decision confidence must lie in (0, 1), got {confidence!r}")
            if method != "log":
                raise InputError("a decision confidence threshold needs method 'log' (a vote's share is no "
                                 "probability: one window is a unanimous vote)")
        self.n_classes = int(n_classes)
        self.scope, self.method = scope, method
        self.correlation = float(correlation)
        self.caps = None if caps is None else np.asarray(caps, dtype=np.float64)
        if self.caps is not None and self.caps.shape != (self.n_classes, self.n_classes):
            raise InputError(f"the pooling's caps must have shape ({self.n_classes}, {self.n_classes}), "
                             f"got {self.caps.shape}")
        self.confidence = confidence
        maxlen = n if scope == "last" else (n or None)
        self._history: deque[np.ndarray] = deque(maxlen=maxlen)
        self._final: Decision | None = None

    def reset(self) -> None:
        """Forget every pooled window and the final decision (a contact ended)."""
        self._history.clear()
        self._final = None

    def restart(self, keep: int, may_decide: bool = True) -> Decision:
        """Forget the final decision and every pooled window but the last ``keep``, and return their decision.

        ``keep`` >= 1: the texture changed ``keep`` windows ago. The decision of those is final at
        once where it is sure enough (as :meth:`update` decides).
        """
        kept = list(self._history)[-keep:]
        self.reset()
        self._history.extend(kept)
        return self._final_if_sure(self._pooled(), may_decide)

    def update(self, log_posteriors: np.ndarray, in_contact: bool = True, may_decide: bool = True) -> Decision:
        """Add one window's log-posteriors (classes,) and return the current decision.

        ``may_decide`` False: the contact's decision may not become final at this window (its
        caller has a reason of its own not to be sure, e.g. most windows are unknown).
        """
        lp = np.asarray(log_posteriors, dtype=np.float64)
        if lp.shape != (self.n_classes,):
            raise InputError(f"expected {self.n_classes} log-posteriors, got shape {lp.shape}")
        if self.scope == "window":
            return window_decision(lp)
        if self.scope == "contact" and not in_contact:
            self.reset()
            return Decision(-1, 0.0, 0)
        self._history.append(lp)
        if self._final is not None:
            return self._final
        return self._final_if_sure(self._pooled(), may_decide)

    def _final_if_sure(self, d: Decision, may_decide: bool) -> Decision:
        """``d``, made the contact's final decision where its confidence reaches the threshold."""
        if self.confidence is not None and may_decide and d.label >= 0 and d.confidence >= self.confidence:
            d = Decision(d.label, d.confidence, d.windows, decided=True)
            self._final = d
        return d

    def _pooled(self) -> Decision:
        lp = np.array(self._history)
        if self.method == "log":
            pooled = pool_log_posteriors(lp, self.correlation, self.caps)
            return Decision(int(winner(pooled)), float(np.exp(pooled.max())), len(lp))
        p = np.exp(lp)
        won = winner(lp)                                # a tied window votes for no class
        votes = np.bincount(won[won >= 0], minlength=self.n_classes).astype(float)
        if not votes.any():
            return Decision(-1, 0.0, len(lp))
        tie = votes == votes.max()
        score = np.where(tie, p.sum(axis=0), -np.inf)
        return Decision(int(winner(score)), float(votes.max() / len(lp)), len(lp))


#: Seconds per minute, for a change rate given per minute.
_MINUTE = 60.0


def windows_per_change(rate: float, window_seconds: float = DEFAULT_WINDOW) -> float:
    """Windows of ``window_seconds`` per false change at ``rate`` false changes per minute (``[decision] change``).

    That is ``N`` of :class:`ChangeDetector`.
    """
    return _MINUTE / (window_seconds * rate)


#: Most recent windows a change detector looks back over (the contact pooling's fitted run length).
CHANGE_LOOKBACK = POOLING_RUN
#: Fewest windows of a stretch that :class:`Decider`'s change detector tests: one window alone never
#: signals a change (a single window's posterior is the least reliable evidence on a new touch).
CHANGE_MIN_WINDOWS = 2
#: Held-out windows whose statistic :func:`fit_change_threshold` measures directly before it extrapolates.
CHANGE_TAIL = 20
#: Windows of a touch whose stretches :meth:`ChangeDetector.still_statistics` weighs at once (memory: ``20 x
#: classes`` floats each).
_CHANGE_CHUNK = 4096


class ChangeDetector:
    """Whether a contact's last few windows, pooled as a contact is, name another texture than the current decision.

    At every window it pools each recent stretch (the last ``n`` windows, ``n`` = ``min_windows`` ..
    :data:`CHANGE_LOOKBACK`) as the calibration pools a contact
    (:func:`~supramodal.calibration.pool_log_posteriors`: the windows' correlation ``rho``, the contact
    caps), and signals a change to ``j`` when one stretch's pooled log-odds of ``j`` against the current
    decision ``k`` pass the threshold ``h``; the change began ``n`` windows ago.

    * It is Page's CUSUM of the windows' log-likelihood ratios ``log p_j - log p_k`` (calibrated
      posteriors, equal priors), whose statistic is the largest sum over the recent stretches, with each
      stretch's sum weighted as the pooling weighs ``n`` correlated windows (``n_eff(n) / n``): a
      network's preference that persists through a touch is not taken for new evidence window after
      window.
    * The contact caps bound what a stretch may claim for ``j`` against ``k``: a pair the network cannot
      tell apart never signals a change; the other sense (or the fusion) has to.
    * The threshold, by default ``h = log((K - 1) N)``, ``N`` windows per false change allowed, ``K``
      classes: under the current texture, calibrated and independent evidence for one alternative passes
      ``h`` from a restart once in ``e^h`` windows at most (Lorden 1971), ``N`` for the ``K - 1``
      together. A bound, and a loose one where the classes are far apart; :func:`fit_change_threshold`
      fits ``h`` to the rate asked on held-out windows of the training touches instead (``threshold``).

    Not thread-safe: one per processing thread, like :class:`Decider`.

    Parameters
    ----------
    n_classes : int
    windows_per_false_change : float
        ``N`` above, > 1.
    correlation : float
        ``rho`` in [0, 1] (default 0).
    caps : array-like (classes, classes) or None
        The contact caps; None: uncapped.
    threshold : float or None
        ``h``, fitted (:func:`fit_change_threshold`); None (default): the bound above.
    min_windows : int
        Fewest windows of a stretch tested, 1 .. :data:`CHANGE_LOOKBACK` (default 1: every stretch;
        :class:`Decider` tests :data:`CHANGE_MIN_WINDOWS`).
    """

    def __init__(self, n_classes: int, windows_per_false_change: float, correlation: float = 0.0,
                 caps=None, threshold: float | None = None, min_windows: int = 1) -> None:
        if not windows_per_false_change > 1:
            raise InputError(f"a change detector needs more than one window per false change, got "
                             f"{windows_per_false_change!r}")
        if not 0.0 <= correlation <= 1.0:
            raise InputError(f"a change detector's correlation must lie in [0, 1], got {correlation!r}")
        if threshold is not None and not threshold >= 0:       # also refuses NaN; +inf: never signals
            raise InputError(f"a change detector's threshold must be a log-odds >= 0, got {threshold!r}")
        if not (isinstance(min_windows, (int, np.integer)) and 1 <= min_windows <= CHANGE_LOOKBACK):
            raise InputError(f"a change detector's stretches must hold 1 .. {CHANGE_LOOKBACK} windows at least, "
                             f"got {min_windows!r}")
        self.n_classes = int(n_classes)
        self.windows_per_false_change = float(windows_per_false_change)
        self.bound = float(np.log(max(self.n_classes - 1, 1) * windows_per_false_change))
        self.threshold = self.bound if threshold is None else float(threshold)
        self.correlation = float(correlation)
        self.caps = None if caps is None else np.asarray(caps, dtype=np.float64)
        self.min_windows = int(min_windows)
        lengths = np.arange(1, CHANGE_LOOKBACK + 1)
        self._weights = effective_windows(lengths, self.correlation) / lengths      # g(n), n = 1 .. lookback
        self._recent: deque[np.ndarray] = deque(maxlen=CHANGE_LOOKBACK)
        #: The last window's statistic: the largest pooled log-odds of a recent stretch for another class
        #: against the current one (-inf: none tested).
        self.statistic = -np.inf
        #: Windows since the last change signalled began (its onset, :meth:`update`); 0 before any.
        self.onset = 0

    def reset(self) -> None:
        """Forget the recent windows (a contact ended)."""
        self._recent.clear()
        self.statistic = -np.inf

    def update(self, log_posteriors: np.ndarray, current: int) -> tuple[int, int] | None:
        """Add one window's log-posteriors (classes,) and test the recent stretches against the ``current`` decision.

        ``current`` is a class index (-1: none, nothing is tested). Returns ``(new class, windows of the
        stretch that passed)`` when a stretch names another texture past the threshold (the windows before
        it are then forgotten), else None.

        The change's onset (:attr:`onset`, windows since it began) is then Page's estimate: of the stretch that
        passed and the longer recent ones, the one whose summed log-likelihood ratio of the new class against
        the current one is largest, the change point most likely for windows independent given the texture.
        The stretch that passed is often shorter: the pooling weighs a longer stretch's evidence less
        (``n_eff(n) / n``), which measures how sure the change is, not where it began.
        """
        self._recent.append(np.asarray(log_posteriors, dtype=np.float64))
        self.statistic = -np.inf
        if current < 0 or len(self._recent) < self.min_windows:
            return None
        recent = np.array(self._recent)[::-1]                       # newest first: row n-1 ends the stretch of n
        sums = np.cumsum(recent, axis=0) * self._weights[:len(recent), None]
        sums = sums[self.min_windows - 1:]                          # row i: the stretch of min_windows + i
        pooled = sums if self.caps is None else cap_gaps(sums, self.caps)     # a log-odds needs no normalising
        lead = pooled - pooled[:, [current]]
        lead[:, current] = -np.inf
        n, j = np.unravel_index(int(np.argmax(lead)), lead.shape)
        self.statistic = float(lead[n, j])
        if self.statistic <= self.threshold:
            return None
        since = int(n) + self.min_windows
        # the onset: where the summed log-likelihood ratio of j against the current class is largest, the
        # stretch that passed or a longer one (the weights g(n) measure the evidence, they do not place it)
        llr = np.cumsum(recent[:, j] - recent[:, current])
        self.onset = since + int(np.argmax(llr[since - 1:]))
        kept = list(self._recent)[-since:]
        self._recent.clear()
        self._recent.extend(kept)
        return int(j), since

    def still_statistics(self, log_posteriors: np.ndarray, current: int) -> np.ndarray:
        """Return :attr:`statistic` after each window of a touch (windows, classes), tested against ``current``.

        As :meth:`update` window by window from an empty detector, never restarted (so its threshold
        does not matter), for every window at once: the last :data:`CHANGE_LOOKBACK` windows ending at
        each, newest first (zeros before the touch, whose stretches are then left out), summed in
        :meth:`update`'s order. This detector's recent windows are neither read nor changed.
        """
        lp = log_posteriors
        if current < 0 or not len(lp):              # no decision to test against, or no window
            return np.full(len(lp), -np.inf)
        L, m = CHANGE_LOOKBACK, self.min_windows
        windows = np.lib.stride_tricks.sliding_window_view(np.concatenate([np.zeros((L - 1, lp.shape[1])), lp]),
                                                           L, axis=0)                 # (windows, classes, L)
        out = np.empty(len(lp))
        for start in range(0, len(lp), _CHANGE_CHUNK):
            recent = windows[start:start + _CHANGE_CHUNK].transpose(0, 2, 1)[:, ::-1]   # (chunk, L, classes)
            sums = (np.cumsum(recent, axis=1) * self._weights[:, None])[:, m - 1:]     # stretch of m + i windows
            pooled = sums if self.caps is None else cap_gaps(sums, self.caps)
            lead = pooled - pooled[..., [current]]
            lead[..., current] = -np.inf
            t = np.arange(start, start + len(recent))
            lead[np.arange(m, L + 1)[None, :] > t[:, None] + 1] = -np.inf              # longer than the touch so far
            out[start:start + len(recent)] = lead.max(axis=(1, 2))
        return out


def change_statistics(log_posteriors, label: int, correlation: float = 0.0, caps=None,
                      min_windows: int = CHANGE_MIN_WINDOWS) -> np.ndarray:
    """Each window's :attr:`ChangeDetector.statistic` on one still touch of texture ``label``, shape (windows,).

    Tested against ``label`` throughout (never restarted): what a false change would have to
    pass there (:meth:`ChangeDetector.still_statistics`).
    """
    lp = np.asarray(log_posteriors, dtype=np.float64)
    if lp.ndim != 2:
        raise InputError(f"a touch's log-posteriors must have shape (windows, classes), got {lp.shape}")
    detector = ChangeDetector(lp.shape[1], 2.0, correlation, caps, threshold=np.inf, min_windows=min_windows)
    return detector.still_statistics(lp, int(label))


def fit_change_threshold(touches, labels, windows_per_false_change: float, correlation: float = 0.0, caps=None,
                         min_windows: int = CHANGE_MIN_WINDOWS, tail: int = CHANGE_TAIL) -> float:
    """Fit the threshold ``h`` of a :class:`ChangeDetector` on held-out windows of the training touches.

    At ``h`` its statistic passes ``h`` on at most one window in ``N = windows_per_false_change``
    of still touches; never fitted on the touches it will be scored on.

    ``touches``: each one touch's held-out (out-of-fold) calibrated log-posteriors (windows, classes), in
    time order; ``labels``: each one's texture. Their windows' statistics (:func:`change_statistics`,
    ``T`` of them) give the share ``e(h0)`` of windows at or above a level ``h0``:

    * where ``T / N >= tail``, ``h`` is measured: the level that at most ``T / N`` windows pass;
    * else ``h = h0 + log(N e(h0))`` from ``h0`` the ``tail``-th largest statistic (at least 0), where
      ``e(h0) = tail / T`` is measured. Each stretch's pooled log-odds ``L`` of ``j`` against the texture
      ``k`` it comes from is calibrated, so that ``P_k(L >= h) = E_j[exp(-L); L >= h]``, and
      ``exp(h) P_k(L >= h)`` falls as ``h`` grows: the share passing ``h`` is at most ``e(h0) exp(h0 - h)``,
      and at most ``1 / N`` at this ``h``.

    A window past ``h`` counts though it continues an excursion that already passed it: a false change is
    one excursion, so the rate fitted errs low. Returns ``h >= 0``.
    """
    _check_change_fit(windows_per_false_change, tail)
    stats = held_out_change_statistics(touches, labels, correlation, caps, min_windows)
    h = _change_threshold(stats, len(stats), windows_per_false_change, tail)
    assert h is not None                        # every statistic is at hand
    return h


def held_out_change_statistics(touches, labels, correlation: float = 0.0, caps=None,
                               min_windows: int = CHANGE_MIN_WINDOWS) -> np.ndarray:
    """Every window's :func:`change_statistics` on held-out ``touches`` of textures ``labels``, largest first.

    Each touch is one touch's calibrated log-posteriors, (windows, classes), in time order.
    """
    touches = list(touches)
    labels = list(labels)
    if len(touches) != len(labels) or not touches:
        raise InputError(f"fitting a change threshold needs touches and one label each, got {len(touches)} touches "
                         f"and {len(labels)} labels")
    stats = np.concatenate([change_statistics(lp, k, correlation, caps, min_windows)
                            for lp, k in zip(touches, labels)])
    return np.sort(stats)[::-1]


def change_threshold(largest, windows: int, windows_per_false_change: float, tail: int = CHANGE_TAIL) -> float | None:
    """:func:`fit_change_threshold`'s ``h`` from statistics already measured.

    ``largest`` are the largest of the held-out windows' statistics, in decreasing order, of ``windows`` in
    all (a model's :class:`~supramodal.calibration.HeldOutChanges`). None when the level asked lies among
    the statistics not kept (a rate so high that more than ``len(largest)`` windows may pass it).
    """
    return _change_threshold(np.asarray(largest, dtype=np.float64), int(windows), windows_per_false_change, tail)


def fitted_change_threshold(calibration: Calibration | None, rules: DecisionRules,
                            window_seconds: float) -> float | None:
    """Return the change detector's threshold for ``rules.change`` false changes a minute.

    The threshold is fitted on the held-out windows of a model's ``calibration`` (its
    :class:`~supramodal.calibration.HeldOutChanges`: a stream's model's, or an early fusion's), with windows
    of ``window_seconds``; None (the detector's bound) without a change rule, for an uncalibrated model or
    one trained before they were kept, or at a rate beyond the statistics kept.
    """
    changes = None if calibration is None else calibration.changes
    per_change = windows_per_change(rules.change, window_seconds) if rules.change else 0.0
    if changes is None or per_change <= 1 or changes.windows < CHANGE_TAIL:
        return None                             # (a rate of one change a window or more: the Decider refuses it)
    return change_threshold(changes.largest, changes.windows, per_change)


def _check_change_fit(windows_per_false_change: float, tail: int) -> None:
    if not windows_per_false_change > 1:
        raise InputError(f"fitting a change threshold needs more than one window per false change, got "
                         f"{windows_per_false_change!r}")
    if not (isinstance(tail, (int, np.integer)) and tail >= 1):
        raise InputError(f"the tail measured must be >= 1 windows, got {tail!r}")


def _change_threshold(stats: np.ndarray, n: int, windows_per_false_change: float, tail: int) -> float | None:
    _check_change_fit(windows_per_false_change, tail)
    if n < tail or len(stats) < tail:
        raise InputError(f"fitting a change threshold needs at least {tail} held-out windows, got {n}")
    allowed = n / float(windows_per_false_change)
    if allowed >= tail:
        at = int(allowed)
        if at >= n:
            return 0.0
        return None if at >= len(stats) else float(max(stats[at], 0.0))
    h0 = float(max(stats[tail - 1], 0.0))
    return h0 + float(np.log(tail / allowed))


def change_touches(groups, folds, labels) -> list[np.ndarray]:
    """Return the held-out touches of a calibration, as index arrays in time order.

    A touch is a run of consecutive windows of one recording (``groups``) and one texture
    (``labels``) scored by one fold network (``folds``).
    """
    g, f, y = np.asarray(groups), np.asarray(folds), np.asarray(labels)
    if len(g) == 0:
        return []
    cut = np.flatnonzero((g[1:] != g[:-1]) | (f[1:] != f[:-1]) | (y[1:] != y[:-1])) + 1
    return np.split(np.arange(len(g)), cut)


def held_out_changes(log_posteriors, labels, groups, folds, correlation: float = 0.0, caps=None) -> HeldOutChanges:
    """Return a calibration's :class:`~supramodal.calibration.HeldOutChanges`.

    That is the change statistic of every held-out window (``log_posteriors``, calibrated,
    (n, classes)) on its touch (:func:`change_touches`), tested against its own texture, pooled
    as a contact is (``correlation``, ``caps``).
    """
    lp = np.asarray(log_posteriors, dtype=np.float64)
    y = np.asarray(labels)
    touches = change_touches(groups, folds, y)
    return HeldOutChanges.of(held_out_change_statistics([lp[i] for i in touches], [int(y[i[0]]) for i in touches],
                                                        correlation, caps))


#: What the node says when it will not name a texture.
UNKNOWN = "unknown"


@dataclass(frozen=True)
class TextureChange:
    """A change of texture found within a contact (``[decision] change``).

    Attributes
    ----------
    from_ : str
        The decision before the change (JSON ``"from"``: ``from`` is a Python keyword).
    to : str
        The texture it changed to.
    after : int
        Windows since the change began, the signalling window included: the new pooled decision
        starts there.
    """

    from_: str
    to: str
    after: int

    def to_dict(self) -> dict[str, Any]:
        """``{"from", "to", "after"}``, as sinks write it."""
        return {"from": self.from_, "to": self.to, "after": self.after}


@dataclass(frozen=True)
class PooledDecision:
    """The decision pooled over windows (``[decision] scope`` other than ``"window"``).

    Attributes
    ----------
    label : str or None
        The pooled winner, :data:`UNKNOWN`, or None out of contact.
    confidence : float
        Its pooled posterior (4 decimals; 0 out of contact).
    windows : int
        Windows pooled (0 out of contact).
    decided : bool or None
        Whether the contact's final decision is taken; None without a ``confidence`` rule.
    decided_after : int or None
        Windows the final decision took, once taken.
    change : TextureChange or None
        The change of texture said at this window (said once), which started this pooled decision.
    """

    label: str | None
    confidence: float
    windows: int
    decided: bool | None = None
    decided_after: int | None = None
    change: TextureChange | None = None

    def to_dict(self) -> dict[str, Any]:
        """As sinks write it (JSON ``"accumulated"``).

        ``label``, ``confidence``, ``windows``, and ``change``, ``decided``, ``decided_after``
        where they apply.
        """
        out: dict[str, Any] = {"label": self.label, "confidence": self.confidence, "windows": self.windows}
        if self.change is not None:
            out["change"] = self.change.to_dict()
        if self.decided is not None:
            out["decided"] = self.decided
        if self.decided_after is not None:
            out["decided_after"] = self.decided_after
        return out


#: The pooled decision out of contact: nothing pooled.
OUT_OF_CONTACT = PooledDecision(None, 0.0, 0)


@dataclass(frozen=True)
class WindowDecision:
    """One window's outcome as a :class:`Decider` says it.

    Attributes
    ----------
    decision : str
        A class name, or :data:`UNKNOWN`.
    confidence : float
        The winner's posterior.
    guess : str or None
        The winner when the decision is unknown (None on a tie, or when known).
    reason : str or None
        Why unknown: ``"novel"``, ``"unsure"`` or ``"tie"``; None when known.
    pooled : PooledDecision or None
        The decision pooled over windows; None with ``scope = "window"``.
    """

    decision: str
    confidence: float
    guess: str | None
    reason: str | None
    pooled: PooledDecision | None


@dataclass(frozen=True, eq=False)
class DecisionCounts(JsonRecord):
    """What a :class:`Decider` decided over a run (:meth:`Decider.summary`), as the node's summary says it.

    Attributes
    ----------
    unknown_windows : mapping of str to int
        Windows said :data:`UNKNOWN`, by reason (``"novel"``, ``"unsure"``, ``"tie"``).
    changes : int or None
        Texture changes found within a contact; None without a change detector (``[decision] change``).
    contacts_decided : int or None
        Pooled decisions that reached the confidence threshold; None without one (and then
        ``windows_to_decide_median`` is None too).
    windows_to_decide_median : float or None
        The median windows a pooled decision took to be decided; None when none was.
    """

    unknown_windows: Mapping[str, int]
    changes: int | None = None
    contacts_decided: int | None = None
    windows_to_decide_median: float | None = None

    def to_dict(self) -> dict[str, JsonValue]:
        """Return the counts as the summary's JSON has them (``changes``, the decided counts: where they apply)."""
        out: dict[str, JsonValue] = {"unknown_windows": dict(self.unknown_windows)}
        if self.changes is not None:
            out["changes"] = self.changes
        if self.contacts_decided is not None:
            out["contacts_decided"] = self.contacts_decided
            out["windows_to_decide_median"] = self.windows_to_decide_median
        return out


class Decider:
    """Decisions of one stream (or of the fusion) by the rules of the module.

    One per processing thread (not thread-safe); :meth:`summary` is read once that thread has
    ended.

    Parameters
    ----------
    classes : sequence of str
        In the order of the log-posteriors.
    rules : DecisionRules
        The scene's ``[decision]`` (default: :data:`DEFAULT_DECISION`).
    correlation : float
        The pooling's window correlation (a calibrated model's; 0 otherwise).
    novelty_threshold : float or None
        Novelty score above which a stream's window is unknown (None: the novelty rule is off);
        kept for the stream, which compares its windows' scores with it.
    caps : array-like (classes, classes) or None
        The pooling's caps per pair of classes (a calibrated model's contact caps; None: uncapped).
    window_seconds : float
        Seconds between windows (default :data:`~supramodal.features.DEFAULT_WINDOW`): what a change
        rate per minute (``rules.change``) is per window.
    change_threshold : float or None
        With ``rules.change``: the change detector's threshold fitted for that rate on held-out windows
        (:func:`fit_change_threshold`); None (default): the bound of :class:`ChangeDetector`.
    """

    def __init__(self, classes, rules: DecisionRules = DEFAULT_DECISION, correlation: float = 0.0,
                 novelty_threshold: float | None = None, caps=None, window_seconds: float = DEFAULT_WINDOW,
                 change_threshold: float | None = None) -> None:
        self.classes = tuple(classes)
        self.rules = rules
        self.unknown_below = float(rules.unknown_below)
        self.novelty_threshold = novelty_threshold
        confidence = rules.confidence or None
        self.accumulator: DecisionAccumulator | None = None
        # which of the pooled windows were unknown (the accumulator's windows, the same maxlen)
        self._unknown_flags: deque[bool] = deque()
        if rules.scope != "window":
            self.accumulator = DecisionAccumulator(len(self.classes), rules.scope, rules.n, rules.method,
                                                   correlation=correlation, confidence=confidence, caps=caps)
            maxlen = rules.n if rules.scope == "last" else (rules.n or None)
            self._unknown_flags = deque(maxlen=maxlen)
        self.detector: ChangeDetector | None = None
        if rules.change:
            if rules.scope != "contact" or rules.method != "log" or rules.n != 0:
                raise InputError("[decision] change re-decides within a contact: it needs scope = \"contact\", "
                                 f"method = \"log\" and n = 0 (scope is {rules.scope!r}, method {rules.method!r}, n "
                                 f"{rules.n}; with n > 0 the pooled decision forgets older windows by itself)")
            per_change = windows_per_change(rules.change, window_seconds)
            if per_change <= 1:
                raise InputError(f"[decision] change = {rules.change:g} per minute allows a false change every "
                                 f"{per_change:g} windows of {window_seconds:g} s: ask for fewer than "
                                 f"{_MINUTE / window_seconds:g} per minute")
            self.detector = ChangeDetector(len(self.classes), per_change, correlation, caps, threshold=change_threshold,
                                           min_windows=CHANGE_MIN_WINDOWS)
        self._label = -1                              # the pooled decision before this window, as a class index
        self.changes = 0
        self.unknown = {"novel": 0, "unsure": 0, "tie": 0}
        self.contacts_decided = 0
        self.windows_to_decide: list[int] = []
        self._final: PooledDecision | None = None

    def decide(self, log_posteriors: np.ndarray, in_contact: bool = True, novel: bool = False) -> WindowDecision:
        """One window's outcome (``novel``: its inputs are unlike every training texture's)."""
        lp = np.asarray(log_posteriors, dtype=np.float64)
        k = int(winner(lp))
        confidence = float(np.exp(lp.max()))
        reason = None
        if k < 0:
            reason = "tie"
        elif novel:
            reason = "novel"
        elif confidence < self.unknown_below:
            reason = "unsure"
        if reason is not None:
            self.unknown[reason] += 1
        decision = UNKNOWN if reason else self.classes[k]
        guess = self.classes[k] if reason and k >= 0 else None
        return WindowDecision(decision, confidence, guess, reason,
                              self._pool(np.full_like(lp, -np.log(lp.size)) if reason == "novel" else lp, in_contact,
                                         reason is not None))

    def _pool(self, lp: np.ndarray, in_contact: bool, unknown: bool) -> PooledDecision | None:
        if self.accumulator is None:
            return None
        if self.accumulator.scope == "contact" and not in_contact:
            self.accumulator.update(lp, in_contact)   # the contact ended: the accumulation resets
            self._unknown_flags.clear()
            self._final = None
            self._label = -1
            if self.detector is not None:
                self.detector.reset()
            return OUT_OF_CONTACT
        self._unknown_flags.append(unknown)
        change = None
        if self.detector is not None:
            found = self.detector.update(lp, self._label)
            if found is not None:                     # to which class, and the windows since its onset
                change = (found[0], self.detector.onset)
        mostly_unknown = 2 * sum(self._unknown_flags) > len(self._unknown_flags)
        d = self.accumulator.update(lp, in_contact, may_decide=not mostly_unknown)
        changed = None
        if change is not None:
            # the texture changed `since` windows ago (the change's onset): the decision starts again from those
            to, since = change
            kept = list(self._unknown_flags)[-since:]
            self._unknown_flags.clear()
            self._unknown_flags.extend(kept)
            self._final = None
            mostly_unknown = 2 * sum(self._unknown_flags) > len(self._unknown_flags)
            d = self.accumulator.restart(since, may_decide=not mostly_unknown)
            changed = TextureChange(self.classes[self._label], self.classes[to], since)
            self.changes += 1
        self._label = -1 if (d.label < 0 or mostly_unknown) else d.label
        if self._final is not None:                   # the contact's final decision stands as it was said
            return self._final
        label = UNKNOWN if (d.label < 0 or mostly_unknown) else self.classes[d.label]
        decided = None if self.accumulator.confidence is None else d.decided
        out = PooledDecision(label, round(d.confidence, 4), d.windows, decided, d.windows if decided else None,
                             changed)
        if decided:
            self.contacts_decided += 1
            self.windows_to_decide.append(d.windows)
            self._final = replace(out, change=None)             # the change is said once
        return out

    def summary(self) -> DecisionCounts:
        """Return what was decided over the run.

        ``unknown`` windows by reason; with a confidence threshold, ``contacts_decided`` and the median
        ``windows_to_decide`` (with ``change``, a change starts a decision of its own, counted too); with
        ``change``, ``changes``.
        """
        pooling = self.accumulator is not None and self.accumulator.confidence is not None
        return DecisionCounts(
            dict(self.unknown),
            changes=self.changes if self.detector is not None else None,
            contacts_decided=self.contacts_decided if pooling else None,
            windows_to_decide_median=(float(np.median(self.windows_to_decide))
                                      if pooling and self.windows_to_decide else None))


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
