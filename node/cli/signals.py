"""SIGINT and SIGTERM: they interrupt the start-up (one line, 130 or 143), and stop a running node cleanly.

Cleanly: what is buffered is processed, the summary printed.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable
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


#: The last interruption a handler of :func:`interrupt_until_running` raised in this process, or None: what an
#: error that came of it is (:func:`interruption_behind`). Cleared by :func:`forget_interruption`.
_raised: StartupInterrupted | None = None


def forget_interruption() -> None:
    """Forget the last interruption raised: a command starts (``main`` may be called again in one process)."""
    global _raised
    _raised = None


def interruption_behind(exc: BaseException) -> BaseException | None:
    """Find the interruption (:class:`StartupInterrupted` or KeyboardInterrupt) behind an exception.

    A signal that lands while a C extension module initialises has its handler's exception turned into that
    import's ImportError: pybind11's "initialization failed" (matplotlib's Agg backend) keeps it as the cause;
    numpy's "PyCapsule_Import could not import module" loses it. Libraries wrap what interrupted them in their
    own errors too. Such an error is the interruption, not a bug: it is found on the chain of causes and contexts
    Python keeps, or, where the chain lost it, as the interruption a handler of :func:`interrupt_until_running`
    raised since the command started.

    Returns
    -------
    BaseException or None
        The interruption on ``exc``'s chain (``exc`` itself included), else the one raised since
        :func:`forget_interruption`, else None.
    """
    seen: set[int] = set()
    link: BaseException | None = exc
    while link is not None and id(link) not in seen:          # a chain may loop back on itself
        if isinstance(link, (StartupInterrupted, KeyboardInterrupt)):
            return link
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    return _raised


#: Seconds after an interruption was swallowed until its signal is delivered again (:class:`Redelivery`).
REDELIVER_SECONDS = 0.05


class Redelivery:
    """A ``sys.unraisablehook`` that delivers again the signal of an interruption the interpreter swallowed.

    A handler's exception that lands in code whose exceptions Python cannot raise (a garbage-collector callback,
    such as Dask's ``GCDiagnosis``; a ``__del__``; a weakref callback) is handed to ``sys.unraisablehook``,
    printed as "Exception ignored in ...", and the command goes on: an interrupted ``fit`` kept searching (a CI
    run). Its signal is sent again :data:`REDELIVER_SECONDS` later, from a timer thread, so that it lands outside
    the callback; nothing is printed for it. Any other unraisable exception goes to ``previous``.

    Threading: the hook runs in whichever thread met the exception; the signal is the process's, handled in the
    main thread. :meth:`cancel` (the command's end) stops the deliveries still to come, so that none reaches the
    caller's own handlers.

    Parameters
    ----------
    previous : callable
        The hook before this one, put back by the caller.
    """

    def __init__(self, previous: Callable[[Any], None]) -> None:
        self.previous = previous
        self._timers: list[threading.Timer] = []

    def __call__(self, unraisable: Any) -> None:
        """Take an unraisable exception (``sys.unraisablehook``'s argument): an interruption's signal again."""
        exc = unraisable.exc_value
        if isinstance(exc, StartupInterrupted):
            signum = exc.signum
        elif isinstance(exc, KeyboardInterrupt):
            signum = signal.SIGINT
        else:
            self.previous(unraisable)
            return
        timer = threading.Timer(REDELIVER_SECONDS, os.kill, (os.getpid(), signum))
        timer.daemon = True
        self._timers.append(timer)
        timer.start()

    def cancel(self) -> None:
        """Stop the deliveries still to come."""
        for timer in self._timers:
            timer.cancel()


def interrupt_until_running(during: str = STARTUP) -> None:
    """Have SIGINT and SIGTERM interrupt the start-up with a one-line message, until :func:`stop_on_signals`.

    The start-up: building the scene, training its model; or ``during``, another command's work. The command
    does not die silently, and the ``with`` blocks on the way close what they opened.
    """
    def interrupt(signum: int, frame: FrameType | None) -> None:
        global _raised
        _raised = StartupInterrupted(signum, during)
        raise _raised

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
