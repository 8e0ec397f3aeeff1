"""Exit statuses and the one split of every error: the user's to fix (one line) or a bug (a traceback)."""

from __future__ import annotations

import sys

from supramodal.errors import SupramodalError

#: Exit status of a refused input (argparse uses it for usage errors too).
EXIT_USER_ERROR = 2
#: Exit status of an unexpected exception (what Python itself returns for one).
EXIT_BUG = 1


class CliError(SupramodalError):
    """A user error the CLI reports in one line, without a traceback."""


def is_user_error(exc: BaseException) -> bool:
    """Whether ``exc`` is the user's to fix (one line) rather than a bug (a traceback).

    Every error the project raises on purpose (:class:`SupramodalError`), except a node
    thread's failure whose cause is itself a bug; and an ``OSError`` that names a file
    (a path given on the command line or in a scene: missing, unreadable, not writable).

    Parameters
    ----------
    exc : BaseException
        The exception a command raised.

    Returns
    -------
    bool
        True for one line ``supramodal: error: ...``, False for a traceback.
    """
    graph = sys.modules.get("supramodal.node.runtime.graph")
    if graph is not None and isinstance(exc, graph.NodeError) and exc.__cause__ is not None:
        return is_user_error(exc.__cause__)
    if isinstance(exc, SupramodalError):
        return True
    return isinstance(exc, OSError) and exc.filename is not None


def reader_left(exc: BaseException | None) -> bool:
    """Whether ``exc`` means that the reader of stdout went away (``| head``), directly or in a node thread.

    Parameters
    ----------
    exc : BaseException or None
        The exception a command raised; its chain of causes is followed.

    Returns
    -------
    bool
        True if a ``BrokenPipeError`` is in the chain.
    """
    while exc is not None:
        if isinstance(exc, BrokenPipeError):
            return True
        exc = exc.__cause__
    return False
