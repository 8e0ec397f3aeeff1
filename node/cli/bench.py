"""The ``supramodal bench`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse
import sys

from supramodal.node.cli.arguments import output_folder

#: What ``supramodal bench`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "filterbank error against run time, drift over 60 min of stream, the whole node"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal bench [--quick] [--out DIR]", f"{SUMMARY} ([last report](docs/bench/report.md))"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``bench`` command's parser and its arguments to ``subparsers``;
    ``common`` is the parent parser of every command (``--debug``)."""
    p = subparsers.add_parser("bench", parents=[common], help=SUMMARY)
    p.add_argument("--quick", action="store_true",
                   help="short signals and streams (well under a minute; not for quoting)")
    p.add_argument("--out", default="out/bench", type=output_folder,
                   help="directory for the report (default ./out/bench)")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")
    return p


def run(args: argparse.Namespace) -> int:
    """Run the benchmark in a child process; its exit status is the command's.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    import os
    import subprocess

    from supramodal.benchmarks.filterbank import PINNED_THREADS

    # A child process, so that BLAS and OpenMP read the one-thread settings before numpy loads.
    cmd = ([sys.executable, "-m", "supramodal.benchmarks.filterbank", "--out", args.out]
           + ["--quick"] * args.quick + ["--json"] * args.json)
    return subprocess.run(cmd, env={**os.environ, **PINNED_THREADS}).returncode
