"""The ``supramodal mock-whisker`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse

from supramodal.node.cli.errors import CliError

#: What ``supramodal mock-whisker`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "a mock whisker-array board streaming frames on a pty, with fault injection"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal mock-whisker SOURCE [--port PATH] [--drop-rate R] ...",
     f"{SUMMARY} ([docs/testing-without-hardware.md](docs/testing-without-hardware.md))"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``mock-whisker`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    from supramodal.drivers.mock_whisker import add_arguments as mock_arguments

    p = subparsers.add_parser("mock-whisker", parents=[common], help=SUMMARY)
    mock_arguments(p)
    return p


def run(args: argparse.Namespace) -> int:
    """Stream the source's samples as the board's frames until stopped.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    from supramodal.drivers.mock_whisker import run as run_board

    samples, rate = _mock_source(args.source)
    return run_board(args, samples, rate)


def _mock_source(source: str):
    """SOURCE of mock-whisker: ``synth:NAME`` (a reference whisker texture), a session or a WAV file."""
    if source.startswith("synth:"):
        from supramodal.textures import reference_texture_set

        ts = reference_texture_set("whisker")
        name = source[len("synth:"):]
        if name not in ts.names:
            raise CliError(f"unknown texture {name!r}; the whisker reference set has {list(ts.names)}")
        return ts.synthesize(ts.names.index(name))[:, None], ts.fs
    from supramodal.replay.driver import ReplayDriver

    drv = ReplayDriver(source, speed="max", on_notice=None)   # a session or a bare WAV file
    return drv.data, drv.rate
