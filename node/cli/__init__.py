"""The ``supramodal`` command: a thin layer over the model, the drivers and the node.

One module per command (``run``, ``train``, ...), each with ``add_parser(subparsers, common)``
(its arguments) and ``run(args)`` (the command), listed once in :data:`COMMANDS`: a new command
is one module and one line there. What the commands share: the argument types (``arguments``),
the signal handling (``signals``) and the exit statuses (``errors``). Each command imports what
it needs when it runs, so that, for example, an experiment never imports sounddevice or pyserial.

Errors and exit status (README "Errors and exit status"):

* 0: done; also when the reader of stdout went away (``supramodal run | head``): the
  reader asked for no more, as Ctrl-C does, and a ``set -o pipefail`` script must not fail.
* 2: a :class:`~supramodal.errors.SupramodalError` (bad input, a device or a file the
  user named), or an ``OSError`` naming a file: one line ``supramodal: error: ...``.
* 1: anything else is a bug: its traceback and a line asking to report it.
* 130 / 143: SIGINT / SIGTERM before the stream started (while a scene is built or its
  model trained): one line, nothing processed. Once the node runs, both stop it cleanly:
  what is buffered is processed, the summary printed, and the exit status is 0.

``--debug`` (before or after the command) shows the traceback of every error.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
import threading
import traceback
import warnings
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Any, TextIO

from supramodal import __version__
from supramodal.drivers.ros2 import split_ros_arguments, use_ros_arguments
from supramodal.errors import SupramodalWarning
from supramodal.logs import logger, set_log_level
from supramodal.memory import keep_freed_memory
from supramodal.node.cli.errors import EXIT_BUG, EXIT_USER_ERROR, CliError, is_user_error, reader_left
from supramodal.node.cli.signals import (
    Redelivery,
    StartupInterrupted,
    forget_interruption,
    interruption_behind,
)

__all__ = ["COMMANDS", "command_module", "EXIT_BUG", "EXIT_USER_ERROR", "CliError", "build_parser", "main"]

#: The commands, in the order ``supramodal --help`` lists them: name -> the dotted name of its module, which
#: has ``add_parser(subparsers, common)`` and ``run(args) -> int`` (:func:`command_module` imports it).
COMMANDS: dict[str, str] = {
    "run": "supramodal.node.cli.run",
    "train": "supramodal.node.cli.train",
    "fit": "supramodal.node.cli.fit",
    "evaluate": "supramodal.node.cli.evaluate",
    "recalibrate": "supramodal.node.cli.recalibrate",
    "record": "supramodal.node.cli.record",
    "view": "supramodal.node.cli.view",
    "label": "supramodal.node.cli.label",
    "import-recording": "supramodal.node.cli.import_recording",
    "mock-whisker": "supramodal.node.cli.mock_whisker",
    "devices": "supramodal.node.cli.devices",
    "experiment": "supramodal.node.cli.experiment",
    "bench": "supramodal.node.cli.bench",
    "synth": "supramodal.node.cli.synth",
}


def command_module(name: str) -> ModuleType:
    """Import and return the module of the command ``name`` (a key of :data:`COMMANDS`)."""
    return importlib.import_module(COMMANDS[name])


def build_parser() -> argparse.ArgumentParser:
    """Build the parser of the whole command line: the global options and one subparser per command.

    Returns
    -------
    argparse.ArgumentParser
        Its ``parse_args`` gives a namespace whose ``func`` runs the command.
    """
    assert __doc__ is not None
    parser = argparse.ArgumentParser(prog="supramodal", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"supramodal {__version__}")
    # --debug, -q and -v are also accepted after the command; SUPPRESS keeps the top-level value when not.
    common = argparse.ArgumentParser(add_help=False)
    for p, default in ((parser, False), (common, argparse.SUPPRESS)):
        p.add_argument("--debug", action="store_true", default=default,
                       help="show the traceback of every error, not one line")
        p.add_argument("-q", "--quiet", action="store_true", default=default,
                       help="no progress and no notices on stderr: the results, the warnings and a view's address only")
        p.add_argument("-v", "--verbose", action="store_true", default=default,
                       help="every notice, the package's debugging lines and the libraries' own (liblsl's log, Dask's)")
    sub = parser.add_subparsers(dest="command", required=True)
    add = sub.add_parser

    def add_described(name: str, **kwargs: Any) -> argparse.ArgumentParser:
        # a command's --help opens with what it does: its line in the command list
        kwargs.setdefault("description", kwargs.get("help"))
        return add(name, **kwargs)

    sub.add_parser = add_described      # type: ignore[method-assign]
    for name in COMMANDS:
        module = command_module(name)
        module.add_parser(sub, common).set_defaults(func=module.run)
    return parser


def _show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  file: TextIO | None = None, line: str | None = None,
                  _default: Callable[..., Any] = warnings.showwarning) -> None:
    """Show the package's warnings as one line each, like its errors (``--quiet`` hides progress, never these).

    Other warnings are shown as Python shows them.
    """
    if issubclass(category, SupramodalWarning):
        print(f"supramodal: warning: {message}", file=sys.stderr, flush=True)
    else:
        _default(message, category, filename, lineno, file, line)


#: The environment variable of Dask's configuration that sets its ``distributed`` logger's level, read by each
#: process as it imports Dask: the fit's local worker processes inherit it.
DASK_LOGGING_ENV = "DASK_LOGGING__DISTRIBUTED"


def quiet_libraries() -> Callable[[], None]:
    """Keep the libraries' own log lines out (Dask's: its nannies, scheduler and workers), and return the undo.

    Without ``-v`` a command says what it does itself; Dask's lines (a nanny that kills a worker slow to
    end, a heartbeat that finds the scheduler gone as a fit closes) are for whoever runs a Dask cluster,
    and show with ``-v``. They are raised to ERROR: in this process, and, through :data:`DASK_LOGGING_ENV`,
    in the processes it starts; a user who set that variable keeps what they set. liblsl's own log is kept
    out by the LSL driver and sinks unless ``-v``.
    """
    if os.environ.get(DASK_LOGGING_ENV):
        return lambda: None             # the user's own choice of Dask's level, louder or quieter: kept
    os.environ[DASK_LOGGING_ENV] = "error"
    dask = logging.getLogger("distributed")
    saved_level = dask.level
    if dask.getEffectiveLevel() < logging.ERROR:
        dask.setLevel(logging.ERROR)    # where Dask is already imported (it sets the level as it is)

    def undo() -> None:
        dask.setLevel(saved_level)
        os.environ.pop(DASK_LOGGING_ENV, None)
    return undo


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (see the module docstring).

    The SIGINT and SIGTERM handlers a command installs (to stop a node cleanly) are its own: the
    caller's are put back when it returns, so that a program or a test suite that calls ``main``
    can still be interrupted afterwards.

    Parameters
    ----------
    argv : sequence of str, optional
        The arguments after the program's name (default: ``sys.argv[1:]``). ``--ros-args`` sections
        (up to ``--`` or the end) are ROS 2's: taken off, and given to the node's ROS 2 parts
        (:func:`supramodal.drivers.ros2.use_ros_arguments`).

    Returns
    -------
    int
        The exit status: 0, 1 (a bug), 2 (the user's error), 128 + a signal's number.
    """
    # ROS 2's own arguments (``--ros-args -r __ns:=/robot ...``, as a launch file passes them) are
    # not the command's: kept for the node's ROS 2 parts, then the rest parsed as usual.
    own, ros = split_ros_arguments(sys.argv[1:] if argv is None else argv)
    use_ros_arguments(ros)
    parser = build_parser()
    args = parser.parse_args(own)
    if args.quiet and args.verbose:
        parser.error("-q/--quiet and -v/--verbose: choose one")
    keep_freed_memory()              # numpy's temporaries reuse heap pages (supramodal/memory.py: 2x faster training)
    level = logger.level
    set_log_level(logging.WARNING if args.quiet else logging.DEBUG if args.verbose else logging.INFO)
    libraries = None if args.verbose else quiet_libraries()
    shown, warnings.showwarning = warnings.showwarning, _show_warning
    handlers = {}
    if threading.current_thread() is threading.main_thread():      # signals are the main thread's
        handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    redelivery = Redelivery(sys.unraisablehook)     # an interruption a gc callback swallowed, delivered again
    sys.unraisablehook = redelivery
    try:
        return _run(args)
    finally:
        redelivery.cancel()
        sys.unraisablehook = redelivery.previous
        set_log_level(level)         # main() may be called again in this process (a test, a notebook)
        if libraries is not None:
            libraries()
        warnings.showwarning = shown
        for sig, handler in handlers.items():
            if handler is not None:                                  # None: set outside Python
                signal.signal(sig, handler)


def _interrupted(exc: BaseException) -> int:
    """Say that a signal interrupted the command, and return its exit status (128 + the signal's number)."""
    if isinstance(exc, StartupInterrupted):
        print(f"supramodal: interrupted by {exc} during {exc.during}", file=sys.stderr)
        return 128 + exc.signum
    print("supramodal: interrupted", file=sys.stderr)
    return 128 + signal.SIGINT


def _run(args: argparse.Namespace) -> int:
    """Run the parsed command and turn what it raised into its message and exit status."""
    forget_interruption()
    try:
        return args.func(args)
    except (StartupInterrupted, KeyboardInterrupt) as exc:
        return _interrupted(exc)
    except Exception as exc:
        interruption = interruption_behind(exc)
        if interruption is not None:        # a library's error in place of the signal's (signals.py)
            return _interrupted(interruption)
        if reader_left(exc):
            # Python docs' recipe: point stdout at /dev/null so that the interpreter's last
            # flush does not fail again; then stop quietly (exit status: module docstring).
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 0
        if is_user_error(exc):
            if args.debug:
                traceback.print_exception(exc)
            print(f"supramodal: error: {exc}", file=sys.stderr)
            return EXIT_USER_ERROR
        traceback.print_exception(exc)
        print(f"supramodal: internal error ({type(exc).__name__}): this is a bug in supramodal; please report it "
              "with the traceback above and the command that gave it", file=sys.stderr)
        return EXIT_BUG
