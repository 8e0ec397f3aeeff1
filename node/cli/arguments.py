"""What the commands share: argument types, output paths checked before any work, and progress lines on stderr.

The argument types are checked at parse time.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
from pathlib import Path

from supramodal.errors import SupramodalError


def _check_output(text: str, folder: bool) -> Path:
    """Return an output path, checked before any long work starts, so that none is lost.

    A file (``folder=False``) must not be a folder, and its folder must exist and be
    writable; the file is written at exactly this path. A folder (``folder=True``) is
    created with its parents when the command writes; it must not be a file, and its
    nearest existing ancestor must be a writable folder.
    """
    path = Path(text).expanduser()
    if folder:
        if path.exists() and not path.is_dir():
            raise argparse.ArgumentTypeError(f"{path} is a file; give a folder")
        parent = next(p for p in (path, *path.parents) if p.exists())
        if not parent.is_dir():
            raise argparse.ArgumentTypeError(f"{path} cannot be created: {parent} is a file")
    else:
        if path.is_dir():
            raise argparse.ArgumentTypeError(f"{path} is a folder; give a file name in it, e.g. {path / 'model.npz'}")
        parent = path.parent
        if not parent.is_dir():
            raise argparse.ArgumentTypeError(f"the folder {parent} does not exist: create it first "
                                             f"(mkdir -p {parent}) or choose another path")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"cannot write in {parent}: permission denied")
    return path


def output_file(text: str) -> Path:
    """Parse an output file's path, checked at parse time (see :func:`_check_output`)."""
    return _check_output(text, folder=False)


def output_folder(text: str) -> Path:
    """Parse an output folder's path, checked at parse time (see :func:`_check_output`)."""
    return _check_output(text, folder=True)


def stream_seconds(text: str) -> float | None:
    """``--seconds``: a positive number of seconds of stream, or ``inf`` (run until the stream ends)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, or inf for no limit; got {text!r}")
    return None if math.isinf(value) else value


def positive_seconds(text: str) -> float:
    """Parse a finite, positive number of seconds (``--window``, ``--duration``)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite, positive number of seconds; got {text!r}")
    return value


def count(lo: int):
    """Return the argument type of an integer option of at least ``lo`` (``--epochs``, ``--jobs``, ``--sets``)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {lo}; got {text!r}") from None
        if value < lo:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {lo}; got {text!r}")
        return value
    return parse


#: The largest seed any command takes: numpy's and Optuna's seeds are 32-bit (one range for every command).
MAX_SEED = 2**32 - 1


def seed(text: str) -> int:
    """``--seed``: a whole number 0 .. :data:`MAX_SEED`."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected a whole number from 0 to {MAX_SEED} (2**32 - 1); got {text!r}")
    return value


def cores() -> int:
    """Return the number of cores this process may run on."""
    from supramodal.parallel import default_jobs

    return default_jobs()


def jobs(text: str) -> int:
    """``--jobs``: local worker processes, 1 .. the cores here.

    More only compete for them and hold memory each; a cluster of more machines is ``--cluster``.
    """
    n = cores()
    value = count(1)(text)
    if value > n:
        raise argparse.ArgumentTypeError(f"expected at most the {n} cores here; got {text} (more processes only "
                                         "compete for them; for more machines, run a Dask scheduler and give "
                                         "--cluster)")
    return value


def cluster_address(text: str) -> str:
    """``--cluster``: a Dask scheduler's address, ``tcp://HOST:PORT`` (``HOST:PORT`` taken as tcp)."""
    from urllib.parse import urlsplit

    address = text if "://" in text else f"tcp://{text}"
    try:
        parts = urlsplit(address)
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme not in ("tcp", "tls") or not parts.hostname or port is None or parts.path not in ("", "/"):
        raise argparse.ArgumentTypeError(f"expected a Dask scheduler's address, tcp://HOST:PORT; got {text!r}")
    return address


def session_name(text: str) -> str:
    """Parse a session's name: a file name part, never a path (refused at start, not after recording)."""
    from supramodal.checks import NAME_HELP, is_name

    if not is_name(text):
        raise argparse.ArgumentTypeError(f"expected {NAME_HELP} (no folder: give that with --out), got {text!r}")
    return text


def speed(text: str):
    """``--speed``: a replay's speed, a factor (1.0: real time) or ``max`` (every block at once).

    The replay driver's ``SPEED_HELP`` says which factors it takes.
    """
    from supramodal.replay.driver import SPEED_HELP, SPEED_MAX, is_speed

    try:
        value = text if text == SPEED_MAX else float(text)
    except ValueError:
        value = None
    if not is_speed(value):
        raise argparse.ArgumentTypeError(f"expected {SPEED_HELP}, got {text!r}")
    return value


def label_name(text: str) -> str:
    """``--label``: a valid label name."""
    from supramodal.node.workflows.labels import LabelError, check_label_name

    try:
        return check_label_name(text, "--label")
    except LabelError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def source_value(text: str) -> tuple[str, str]:
    """Parse a ``SOURCE=VALUE`` option of ``import-recording`` into ``(SOURCE, VALUE)``."""
    name, eq, value = text.partition("=")
    if not eq or not name or not value:
        raise argparse.ArgumentTypeError(f"expected SOURCE=VALUE (e.g. whiskers=whiskers.wav); got {text!r}")
    return name, value


def bank(text: str):
    """``--bank``: a paper bank by name, or a bank file, read and checked at parse time."""
    from supramodal.bankfile import load_bank
    from supramodal.banks import bank_by_name

    try:
        return bank_by_name(text) if text in ("whisker", "cochlea") else load_bank(text)
    except SupramodalError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def mapping(text: str):
    """Parse ``--mapping``: a channel index (digits, as an integer), or a mapping's name as it is given."""
    return int(text) if text.isdigit() else text


#: ``--augment-gains``'s form, for its help and its errors.
AUGMENT_GAINS_FORM = "COPIES[,SPREAD[,per-channel|shared]]"


def seeded_augment(args: argparse.Namespace):
    """Return ``--augment-gains`` (:func:`augment_gains`) seeded by ``--seed``, or None where not asked."""
    from dataclasses import replace

    return None if args.augment_gains is None else replace(args.augment_gains, seed=args.seed)


def augment_form(augment) -> str:
    """Return ``--augment-gains``'s text for a :class:`supramodal.model.GainAugment` (a next command's)."""
    gains = "" if augment.per_channel is None else "," + augment.gains
    return f"{augment.copies},{augment.spread:g}{gains}"


def augment_gains(text: str):
    """Parse ``--augment-gains COPIES[,SPREAD[,per-channel|shared]]`` into a :class:`supramodal.model.GainAugment`.

    Seed 0: the command sets its own; its gains by the bank where the third part is left out.
    """
    from supramodal.model import DEFAULT_AUGMENT_SPREAD, GAIN_MODES, MAX_AUGMENT_COPIES, MAX_AUGMENT_SPREAD, GainAugment

    parts = text.split(",")
    problem = None
    if not 1 <= len(parts) <= 3:
        problem = "one to three parts separated by commas"
    else:
        try:
            copies = int(parts[0])
        except ValueError:
            copies = -1
        try:
            spread = float(parts[1]) if len(parts) > 1 else DEFAULT_AUGMENT_SPREAD
        except ValueError:
            spread = math.nan
        gains = parts[2] if len(parts) > 2 else None
        if not 1 <= copies <= MAX_AUGMENT_COPIES:
            problem = f"COPIES a whole number from 1 to {MAX_AUGMENT_COPIES}"
        elif not 0 <= spread <= MAX_AUGMENT_SPREAD:         # nan too
            problem = f"SPREAD (the standard deviation of the gains' natural log) from 0 to {MAX_AUGMENT_SPREAD:g}"
        elif gains is not None and gains not in GAIN_MODES:
            problem = (f"the gains {' or '.join(GAIN_MODES)} (left out: per-channel for a whisker bank, shared for "
                       "a cochlea)")
    if problem is not None:
        raise argparse.ArgumentTypeError(f"expected {AUGMENT_GAINS_FORM} (e.g. 4,0.03), with {problem}; got {text!r}")
    return GainAugment(copies, spread, None if gains is None else gains == GAIN_MODES[0])


class StderrProgress:
    """Progress lines on stderr, ``supramodal: ...``.

    :meth:`transient` lines (a long step's periodic line) rewrite one line in place on a terminal and are
    plain lines elsewhere (a log, a pipe); the next plain line replaces a transient one. Any thread.
    """

    def __init__(self, stream=None) -> None:
        self.stream = sys.stderr if stream is None else stream
        self._open = False                  # a transient line is on the terminal, without its newline
        self._lock = threading.Lock()

    def _tty(self) -> bool:
        isatty = getattr(self.stream, "isatty", None)
        return bool(isatty and isatty())

    def __call__(self, message: str) -> None:
        """Write ``message`` as a plain line, ``supramodal: MESSAGE``, replacing a transient line on the terminal."""
        with self._lock:
            clear = "\r\x1b[K" if self._open else ""
            self._open = False
            self.stream.write(f"{clear}supramodal: {message}\n")
            self.stream.flush()

    def transient(self, message: str) -> None:
        """Write ``message`` as a transient line: in place of the last one on a terminal, a plain line elsewhere."""
        if not self._tty():
            self(message)
            return
        with self._lock:
            self.stream.write(f"\r\x1b[Ksupramodal: {message}")
            self._open = True
            self.stream.flush()


def progress(args):
    """Return the command's progress on stderr (:class:`StderrProgress`), or None with ``--quiet``."""
    return None if getattr(args, "quiet", False) else StderrProgress()


def say_plots_missing(notice: str | None) -> None:
    """Say on stderr why no PNG was written, if ``notice`` says so.

    ``notice``: :func:`~supramodal.node.workflows.reports.plots_missing_notice`'s (None: nothing to say).
    """
    if notice:
        print(f"supramodal: {notice}", file=sys.stderr)
