"""The ``supramodal devices`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse

#: What ``supramodal devices`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "list audio inputs and serial ports"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal devices", SUMMARY),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``devices`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("devices", parents=[common], help=SUMMARY)
    return p


def run(args: argparse.Namespace) -> int:
    """Print the audio inputs and serial ports.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    from supramodal.drivers.devices import format_devices

    print(format_devices())
    return 0
