"""Ctrl-C and SIGTERM held over a step that must not be cut, and optional modules imported that way.

Two steps of a command must not be cut by a signal half-way:

* putting several files in place (a report, a label's sidecars): each ``os.replace`` is atomic, the set is
  not; :func:`held_interrupts` around the loop makes it all or none;
* importing an optional module built as a C extension (matplotlib, pylsl, rclpy): an interruption inside the
  extension's initialisation comes out as an ``ImportError`` ("Importing the numpy C-extensions failed ...
  PyCapsule_Import could not import module"), which reads as "not installed" (a report without its plots, a
  wrong hint), loses the Ctrl-C, and leaves a half-initialised extension that can abort the interpreter as it
  exits ("Fatal Python error: PyThreadState_Get", exit -6). :func:`import_optional` holds the signal over the
  import instead.

A held signal is delivered, to the handler it was meant for, as soon as the step ends (a user's Ctrl-C
waits at most as long as the step: milliseconds for the replaces, a fraction of a second for an import).
Signals are held on the main thread only, the one Python's handlers run on; elsewhere the step runs as it is.

Pure Python; the node's workflows, drivers and replay use it.
"""

from __future__ import annotations

import contextlib
import importlib
import signal
import threading
from collections.abc import Iterator
from types import ModuleType
from typing import Any

__all__ = ["HELD_SIGNALS", "held_interrupts", "import_optional"]

#: The signals :func:`held_interrupts` holds: what a user (Ctrl-C) or a supervisor (SIGTERM) sends to stop.
HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def held_interrupts() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM for the duration of the ``with`` block, then deliver the first that came.

    The handlers in place before are restored at the block's end, whether it ended normally or by an
    exception; a signal that came meanwhile is then raised again (``signal.raise_signal``), so it reaches
    the handler it was meant for (``KeyboardInterrupt`` for a default SIGINT; where the block raised, its
    error is the interruption's context). On a thread other than the main thread nothing is held.
    """
    caught: list[int] = []
    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for held in HELD_SIGNALS:
            previous[held] = signal.signal(held, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if caught:                      # also after an error of the block: the user's stop comes first
            signal.raise_signal(caught[0])


def import_optional(name: str) -> ModuleType | None:
    """Import the module ``name`` (dotted) with Ctrl-C and SIGTERM held; None where it cannot be imported.

    Parameters
    ----------
    name : str
        The module's dotted name, e.g. ``"matplotlib.pyplot"``.

    Returns
    -------
    module or None
        None where the import raised ``ImportError`` (not installed, or installed without what it needs);
        any other error of the import propagates, and a signal that came during it is delivered after it.
    """
    with held_interrupts():
        try:
            return importlib.import_module(name)
        except ImportError:
            return None
