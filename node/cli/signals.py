"""SIGINT and SIGTERM: during start-up they interrupt it (one line, 130 or 143); once the node runs they stop it
cleanly (what is buffered is processed, the summary printed)."""

from __future__ import annotations

import signal
from types import FrameType
from typing import Any


class StartupInterrupted(BaseException):
    """SIGINT or SIGTERM arrived before the stream started. A BaseException, like
    KeyboardInterrupt, so that no ``except Exception`` on the way swallows it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _interrupt_startup(signum: int, frame: FrameType | None) -> None:
    raise StartupInterrupted(signum)


def interrupt_until_running() -> None:
    """Until :func:`stop_on_signals`, SIGINT and SIGTERM interrupt the start-up (building the
    scene, training its model) with a one-line message instead of dying silently."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _interrupt_startup)


def stop_on_signals(node: Any) -> None:
    """From now on SIGINT and SIGTERM only set a flag: the node finishes what it holds and
    prints its summary (before this, :func:`interrupt_until_running` applies). Called by the node once it
    runs (``on_running``): a wait before, for a consumer of an outlet, is still start-up.

    Parameters
    ----------
    node : Node or ViewReplay
        What to stop: anything with ``stop(reason)``.
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: node.stop(signal.Signals(signum).name))
