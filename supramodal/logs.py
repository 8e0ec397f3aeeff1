"""One package logger: ``logging.getLogger("supramodal")`` and its children.

What the package says on its own, beside what a command prints as its results (stdout) and its
progress lines: a driver's notices (a serial line that resynchronised, a file resampled), a sink's
trouble (the view's failed request, the ROS 2 publisher that stopped answering). Each module logs to
a child (:func:`get_logger`: ``supramodal.drivers.serial``, ``supramodal.sinks.view``, ...), so a library
user quiets one part or all of it, or sends it to a file, with the standard :mod:`logging` calls::

    import logging
    logging.getLogger("supramodal").setLevel(logging.WARNING)        # notices off, warnings on
    logging.getLogger("supramodal.drivers").addHandler(logging.FileHandler("drivers.log"))

By default the package logger writes its records of level INFO and above to the process's *current*
``sys.stderr`` (looked up at each record, so a test's or a notebook's capture of stderr sees them) as
``supramodal: message``, and does not pass them on to the root logger (an application that configures
logging of its own would otherwise print each twice). :func:`set_log_level` is what the command line's
``-q`` (WARNING) and ``-v`` (DEBUG) call. Python's :mod:`warnings` stay what they are (the command line
shows each as one line).
"""

from __future__ import annotations

import logging
import sys

__all__ = ["LOGGER_NAME", "get_logger", "logger", "set_log_level"]

#: The package logger's name; every child's begins with it.
LOGGER_NAME = "supramodal"


class _CurrentStderr(logging.StreamHandler):
    """A stream handler that writes to whatever ``sys.stderr`` is at the time of each record."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:     # StreamHandler.__init__ sets it; the property ignores it
        pass


def _package_logger() -> logging.Logger:
    log = logging.getLogger(LOGGER_NAME)
    if not any(isinstance(h, _CurrentStderr) for h in log.handlers):
        handler = _CurrentStderr()
        handler.setFormatter(logging.Formatter(f"{LOGGER_NAME}: %(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)
        log.propagate = False
    return log


#: The package logger (``"supramodal"``).
logger = _package_logger()


def get_logger(part: str) -> logging.Logger:
    """Return the child logger of one part of the package, ``supramodal.<part>`` (e.g. ``"drivers.serial"``)."""
    return logger.getChild(part)


def set_log_level(level: int | str) -> None:
    """Set the package logger's level (a :mod:`logging` level or its name: ``"WARNING"``, ``"DEBUG"``)."""
    logger.setLevel(level.upper() if isinstance(level, str) else level)
