"""The robot's touches on the node's common time, from its own contact signal.

With ``[decision] contact_from``, a stream's (or the fusion's) windows are in contact when the robot
says it touches, not when the input's level crosses a threshold: a :class:`ContactTimeline` holds the
signal's edges on common time, written by the node's contact thread from a
:class:`~supramodal.drivers.contact.ContactListener`, and read by the processing threads.

A window is in contact when the signal says so at the window's centre: a window is assigned to the
touch it lies mostly in, so that an edge and the window boundary it is assigned at are at most half a
window apart. A release and a new touch between two windows' centres (shorter than a window) are not
seen: the windows run on as one touch. An edge that reaches the node after the window it falls in was
decided cannot change that decision; on a bus, edges come within milliseconds, a window closes every
100 ms.
"""

from __future__ import annotations

import bisect
import threading
from collections.abc import Iterable

from supramodal.records import JsonValue

__all__ = ["ContactTimeline"]

#: States kept (the oldest go first): 1000 s of a touch sensor that says its state 100 times a second.
MAX_STATES = 100_000


class ContactTimeline:
    """The states of one contact signal on common time (seconds). Thread-safe.

    Parameters
    ----------
    name : str
        The signal's ``contact_from`` value, for the summary.

    Every state said is kept, in time order, not only the edges: a state that comes late (two buses'
    delays differ) may fall between two others, and the repeats around it then say where its contact
    ends. Before the signal's first state, nothing is in contact.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._lock = threading.Lock()
        self._times: list[float] = []       # ascending; equal times in the order they came
        self._states: list[bool] = []
        self._before = False                # the state before the first one kept
        self._touches_gone = 0              # rising edges among the states let go
        self.states = 0                     # states received

    def add(self, states: Iterable[tuple[float, bool]]) -> None:
        """States ``(common time, in contact)``, in any order."""
        with self._lock:
            for t, state in states:
                self.states += 1
                i = bisect.bisect_right(self._times, t)
                self._times.insert(i, t)
                self._states.insert(i, bool(state))
            extra = len(self._times) - MAX_STATES
            if extra > 0:
                gone = self._states[:extra]
                self._touches_gone += _rising(self._before, gone)
                self._before = gone[-1]
                del self._times[:extra], self._states[:extra]

    def at(self, t: float) -> bool:
        """Whether the signal said "in contact" at common time ``t`` (its last state at or before ``t``)."""
        with self._lock:
            i = bisect.bisect_right(self._times, t)
            return self._states[i - 1] if i else self._before

    def in_window(self, start: float, end: float) -> bool:
        """Whether a window from ``start`` to ``end`` (common time) is in contact: the state at its centre."""
        return self.at(0.5 * (start + end))

    def edges(self) -> list[tuple[float, bool]]:
        """Return the signal's changes among the states kept, ``(common time, state from then on)``."""
        with self._lock:
            out, last = [], self._before
            for t, state in zip(self._times, self._states, strict=True):
                if state != last:
                    out.append((t, state))
                    last = state
            return out

    @property
    def touches(self) -> int:
        """Rising edges of the signal so far."""
        with self._lock:
            return self._touches_gone + _rising(self._before, self._states)

    def summary(self) -> dict[str, JsonValue]:
        """``from``, ``states`` received, ``touches`` (rising edges)."""
        return {"from": self.name, "states": self.states, "touches": self.touches}


def _rising(before: bool, states: list[bool]) -> int:
    """Rising edges in ``states``, after the state ``before``."""
    return sum(b and not a for a, b in zip([before, *states], states))
