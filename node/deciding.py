"""From a window's log-posteriors to what the node says: the winner, "unknown", the pooled
decision over a contact, and the counts the summary reports. Shared by a stream and the fusion
block, so that both decide by the same rules.

Rules
-----
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

Threading rules: one :class:`Decider` belongs to one processing thread (a stream's or the
fusion's); :meth:`Decider.summary` is read once that thread has ended.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from supramodal.calibration import winner
from supramodal.decisions import DecisionAccumulator

#: What the node says when it will not name a texture.
UNKNOWN = "unknown"


class Decider:
    """Decisions of one stream (or of the fusion) by the rules of the module.

    Parameters
    ----------
    classes : sequence of str
        In the order of the log-posteriors.
    decision : dict
        The scene's ``[decision]``: ``scope``, ``n``, ``method`` and optionally ``confidence``,
        ``unknown``, ``unknown_below`` (0 or absent: off).
    correlation : float
        The pooling's window correlation (a calibrated model's; 0 otherwise).
    novelty_threshold : float or None
        Novelty score above which a stream's window is unknown (None: the novelty rule is off);
        kept for the stream, which compares its windows' scores with it.
    """

    def __init__(self, classes, decision: dict, correlation: float = 0.0,
                 novelty_threshold: float | None = None) -> None:
        self.classes = tuple(classes)
        d = decision
        self.unknown_below = float(d.get("unknown_below") or 0.0)
        self.novelty_threshold = novelty_threshold
        confidence = d.get("confidence") or None
        self.accumulator = None
        self._unknown_flags: deque | None = None
        if d.get("scope", "window") != "window":
            self.accumulator = DecisionAccumulator(len(self.classes), d["scope"], d["n"], d["method"],
                                                   correlation=correlation, confidence=confidence)
            maxlen = d["n"] if d["scope"] == "last" else (d["n"] or None)
            self._unknown_flags = deque(maxlen=maxlen)
        self.unknown = {"novel": 0, "unsure": 0, "tie": 0}
        self.contacts_decided = 0
        self.windows_to_decide: list[int] = []
        self._was_decided = False

    def decide(self, log_posteriors: np.ndarray, in_contact: bool = True, novel: bool = False) -> dict:
        """One window's outcome (``novel``: its inputs are unlike every training texture's): ``decision`` (a class or :data:`UNKNOWN`), ``confidence`` (the
        winner's posterior), ``guess`` (the winner when the decision is unknown, else None),
        ``reason`` (why unknown, else None) and ``pooled`` (dict or None)."""
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
        return {"decision": decision, "confidence": confidence, "guess": guess, "reason": reason,
                "pooled": self._pool(np.full_like(lp, -np.log(lp.size)) if reason == "novel" else lp, in_contact,
                                     reason is not None)}

    def _pool(self, lp: np.ndarray, in_contact: bool, unknown: bool) -> dict | None:
        if self.accumulator is None:
            return None
        d = self.accumulator.update(lp, in_contact)
        if d.windows == 0:                         # out of contact: the accumulation was reset
            self._unknown_flags.clear()
            self._was_decided = False
            return {"label": None, "confidence": 0.0, "windows": 0}
        self._unknown_flags.append(unknown)
        mostly_unknown = 2 * sum(self._unknown_flags) > len(self._unknown_flags)
        label = UNKNOWN if (d.label < 0 or mostly_unknown) else self.classes[d.label]
        out = {"label": label, "confidence": round(d.confidence, 4), "windows": d.windows}
        if self.accumulator.confidence is not None:
            out["decided"] = d.decided
            if d.decided:
                out["decided_after"] = d.windows
                if not self._was_decided:
                    self.contacts_decided += 1
                    self.windows_to_decide.append(d.windows)
                    self._was_decided = True
        return out

    def summary(self) -> dict:
        """``unknown`` windows by reason; with a confidence threshold, ``contacts_decided`` and the
        median ``windows_to_decide``."""
        out = {"unknown_windows": dict(self.unknown)}
        if self.accumulator is not None and self.accumulator.confidence is not None:
            out["contacts_decided"] = self.contacts_decided
            out["windows_to_decide_median"] = (float(np.median(self.windows_to_decide))
                                               if self.windows_to_decide else None)
        return out
