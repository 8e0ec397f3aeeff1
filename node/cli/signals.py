"""SIGINT and SIGTERM: they interrupt the start-up (one line, 130 or 143), and stop a running node cleanly.

Cleanly: what is buffered is processed, the summary printed.
"""

from __future__ import annotations

import signal
from types import FrameType
from typing import Any

#: What a node's start-up is doing, as the message of its interruption says it.
STARTUP = "start-up (building the scene, training its model); nothing was processed"


class StartupInterrupted(BaseException):
    """SIGINT or SIGTERM arrived before the stream started (or during another command's work).

    ``during`` says what was interrupted, and what that left. A BaseException, like KeyboardInterrupt, so that
    no ``except Exception`` on the way swallows it.
    """

    def __init__(self, signum: int, during: str = STARTUP) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.during = during


def interruption_behind(exc: BaseException) -> BaseException | None:
    """Find the interruption (:class:`StartupInterrupted` or KeyboardInterrupt) behind an exception.

    A signal that lands while a C extension module initialises (matplotlib's Agg backend, numpy's parts) has its
    handler's exception turned into that import's ``ImportError: initialization failed``; other libraries wrap
    what interrupted them in their own errors. Such an error is the interruption, not a bug: it is found on the
    chain of causes and contexts Python keeps.

    Returns
    -------
    BaseException or None
        The interruption on ``exc``'s chain (``exc`` itself included), or None if there is none.
    """
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:          # a chain may loop back on itself
        if isinstance(exc, (StartupInterrupted, KeyboardInterrupt)):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__      # type: ignore[assignment]
    return None


def interrupt_until_running(during: str = STARTUP) -> None:
    """Have SIGINT and SIGTERM interrupt the start-up with a one-line message, until :func:`stop_on_signals`.

    The start-up: building the scene, training its model; or ``during``, another command's work. The command
    does not die silently, and the ``with`` blocks on the way close what they opened.
    """
    def interrupt(signum: int, frame: FrameType | None) -> None:
        raise StartupInterrupted(signum, during)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, interrupt)


def stop_on_signals(node: Any) -> None:
    """From now on, have SIGINT and SIGTERM only set a flag: the node finishes what it holds and prints its summary.

    Before this, :func:`interrupt_until_running` applies. Called by the node once it runs (``on_running``): a
    wait before, for a consumer of an outlet, is still start-up.

    Parameters
    ----------
    node : Node or ViewReplay
        What to stop: anything with ``stop(reason)``.
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: node.stop(signal.Signals(signum).name))
