"""Saying how a long step goes while it runs: :class:`Ticker`, for the model a node trains on start.

So that a user is never left in silence for a minute.

Threading: the step's own thread calls :meth:`Ticker.stage` and :meth:`Ticker.network_done`; a
thread of the ticker's own says the line every ``period`` seconds. The ``say`` callable is
called from both (it must take a line from any thread, as ``print`` to stderr does). A ``say``
with a ``transient`` attribute (the command line's progress on a terminal) gets the periodic
lines through it, to rewrite one line in place; plain lines otherwise.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from types import TracebackType

__all__ = ["DEFAULT_TICK", "Ticker"]

#: Seconds between two lines of a step still running (the first comes at once).
DEFAULT_TICK = 4.0


class Ticker:
    """Lines that say a training's stage, time so far and time left, at once and every ``period`` s.

    Parameters
    ----------
    say : callable(str)
        Told each line (see the module notes for ``say.transient``).
    what : str
        What is being made, e.g. ``"stream 'main': the model trained on start"``.
    networks : int
        Networks the step trains (its calibration's fold networks, which the model deploys), for the time left.
    period : float
        Seconds between two lines (default :data:`DEFAULT_TICK`).
    clock : callable
        Seconds, monotonic (default :func:`time.monotonic`).

    Use as a context manager: the first line on entry, the thread stopped on exit.
    """

    def __init__(self, say: Callable[[str], None], what: str, networks: int, period: float = DEFAULT_TICK,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.say = say
        self.what = what
        self.networks = max(int(networks), 1)
        self.period = float(period)
        self.clock = clock
        self.started = clock()
        self.done = 0                        # networks trained
        self._training_began: float | None = None     # the first network's start (after the features)
        self._network_started: float | None = None
        self._last_done: float | None = None
        self._epoch_share = 0.0              # of the network in training, the share of its epochs done
        self._stage = "starting"
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="progress", daemon=True)

    def __enter__(self) -> Ticker:
        self.say(f"{self.what}: training ({self.networks} networks: its calibration's fold networks, which it "
                 "deploys); later runs read it from the model cache")
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stop.set()
        self._thread.join()
        if exc is not None:        # a plain line, so that the error that follows starts a line of its own
            self.say(f"{self.what}: stopped after {self.clock() - self.started:.0f} s")

    def stage(self, text: str, epoch_share: float | None = None) -> None:
        """Say what is being done now (a texture's features, a network's epochs).

        ``epoch_share``, in [0, 1]: the share of the network's epochs done, while one is in training.
        """
        with self._lock:
            self._stage = text
            if epoch_share is not None:
                if self._network_started is None:
                    self._network_started = self.clock()
                if self._training_began is None:
                    self._training_began = self._network_started
                self._epoch_share = min(max(float(epoch_share), 0.0), 1.0)

    def network_done(self) -> None:
        """One more network trained (the next one's training begins)."""
        now = self.clock()
        with self._lock:
            if self._training_began is None:
                self._training_began = self.started
            self.done += 1
            self._last_done = self._network_started = now
            self._epoch_share = 0.0

    def line(self) -> str:
        """Return the line for now: the stage, the time so far and, once it can be told, the time left."""
        now = self.clock()
        with self._lock:
            stage, done, share = self._stage, self.done, self._epoch_share
            began, started, last = self._training_began, self._network_started, self._last_done
        out = f"{self.what}: {stage}; {now - self.started:.0f} s so far"
        per = None                                   # seconds per network
        if share > 0 and started is not None:
            per = (now - started) / share            # the network in training, at its pace so far
        elif done and began is not None and last is not None:
            per = (last - began) / done              # the networks trained so far, on average
        if per is not None:
            out += f", about {max(per * (self.networks - done - share), 0.0):.0f} s left"
        return out

    def _run(self) -> None:
        tell = getattr(self.say, "transient", self.say)
        while not self._stop.wait(self.period):
            tell(self.line())
