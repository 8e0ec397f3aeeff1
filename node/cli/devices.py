"""``supramodal devices``: list audio inputs and serial ports."""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``devices`` command's parser and its arguments to ``subparsers``;
    ``common`` is the parent parser of every command (``--debug``)."""
    p = subparsers.add_parser("devices", parents=[common],
                              help="list audio inputs and serial ports")
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
