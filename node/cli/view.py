"""The ``supramodal view`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse

from supramodal.node.cli.arguments import progress
from supramodal.node.cli.signals import interrupt_until_running, stop_on_signals

#: What ``supramodal view`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "play a recording back into the view's page, with pause and speed"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal view REC.toml|SESSION", f"{SUMMARY} ([docs/view.md](docs/view.md))"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``view`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("view", parents=[common], help=SUMMARY)
    p.add_argument("recording", metavar="REC.toml|SESSION",
                   help="the replay scene `supramodal record` wrote for a graph, or a session (NAME.wav + NAME.json)")
    p.add_argument("--port", type=int, default=0, help="the page's port on 127.0.0.1 (default 0: any free one)")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed at the start (default 1: as recorded)")
    return p


def run(args: argparse.Namespace) -> int:
    """Serve the recording's page until a signal stops it.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    from supramodal.node.workflows.view_replay import ViewReplay

    interrupt_until_running()
    replay = ViewReplay(args.recording, port=args.port, speed=args.speed, progress=progress(args))
    replay.serve(on_running=lambda: stop_on_signals(replay))
    return 0
