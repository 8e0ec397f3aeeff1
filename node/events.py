"""Driver events on their way to the sinks: rate-limited per kind, counted exactly.

Threading rules
---------------
An :class:`EventLimiter` is used by one thread (the node's event thread); it
holds no lock and calls nothing.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from dataclasses import replace

from supramodal.drivers.base import DriverEvent


class EventLimiter:
    """At most ``burst`` events per kind per ``interval`` seconds; repeats folded into counts.

    Events of a kind pass at once while fewer than ``burst`` of that kind passed
    in the last ``interval`` (so rare events, such as two unplugs a second
    apart, are each shown as they happen). Beyond that they are held back and
    counted; the next one passed (an event once there is room again, :meth:`due`
    once there is, or :meth:`flush` at the end) carries them: its ``count`` is 1
    + those held back, its message the latest. A board spewing errors gives at
    most ``burst`` lines per kind per interval, and nothing is lost:
    :attr:`counts` holds every occurrence per kind.

    Parameters
    ----------
    interval : float, default 1.0
        Seconds.
    burst : int, default 3
    clock : callable, default time.monotonic
    """

    def __init__(self, interval: float = 1.0, burst: int = 3, clock=time.monotonic) -> None:
        self.interval = float(interval)
        self.burst = int(burst)
        self._clock = clock
        self._passed: dict[str, deque] = {}  # kind -> when its last (up to burst) events passed
        self._held: dict[str, DriverEvent] = {}  # kind -> latest held event, count = occurrences held
        self.counts: Counter = Counter()  # kind -> occurrences seen (dropped ones included)
        self.dropped: Counter = Counter()  # kind -> occurrences a driver dropped before we saw them

    def add(self, ev: DriverEvent) -> DriverEvent | None:
        """Take one event; return what to show now (it, carrying any held back), or None."""
        self.counts[ev.kind] += ev.count
        now = self._clock()
        held = self._held.pop(ev.kind, None)
        if held is not None:
            ev = replace(ev, count=ev.count + held.count)
        if self._room(ev.kind, now):
            return ev
        self._held[ev.kind] = ev
        return None

    def _room(self, kind: str, now: float) -> bool:
        """May an event of ``kind`` pass now? If so, note that it does."""
        passed = self._passed.setdefault(kind, deque())
        while passed and now - passed[0] >= self.interval:
            passed.popleft()
        if len(passed) >= self.burst:
            return False
        passed.append(now)
        return True

    def add_dropped(self, dropped: dict[str, int]) -> None:
        """Count events a driver's bounded log dropped (per kind) before they were taken."""
        for kind, n in dropped.items():
            self.counts[kind] += n
            self.dropped[kind] += n

    def due(self) -> list[DriverEvent]:
        """Held events whose kind's interval is over: show them now."""
        now = self._clock()
        out = [ev for kind, ev in self._held.items() if self._room(kind, now)]
        for ev in out:
            del self._held[ev.kind]
        return out

    def flush(self) -> list[DriverEvent]:
        """Every held event, whatever the time (the stream has ended)."""
        out = list(self._held.values())
        self._held.clear()
        return out

    def summary(self) -> dict:
        """``{"counts": {kind: occurrences}, "dropped": {kind: n}}`` for the node's summary."""
        return {"counts": dict(sorted(self.counts.items())), "dropped": dict(sorted(self.dropped.items()))}
