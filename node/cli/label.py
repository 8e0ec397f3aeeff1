"""The ``supramodal label`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse

#: What ``supramodal label`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "label a recorded graph after the fact (spans `start,end,label` on common time)"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal label REC.toml SPANS.csv", SUMMARY),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``label`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("label", parents=[common], help=SUMMARY)
    p.add_argument("recording", metavar="REC.toml", help="the replay scene `supramodal record` wrote for a graph")
    p.add_argument("spans", metavar="SPANS.csv",
                   help="CSV with the header start,end,label: seconds of the recording's common time (as its replay "
                        "prints window times), in order, not overlapping")
    p.add_argument("--replace", action="store_true",
                   help="replace the labels the sessions hold (default: refuse a session that has any)")
    return p


def run(args: argparse.Namespace) -> int:
    """Label the recording's sessions and print what each got.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    from supramodal.node.cli.signals import interrupt_until_running
    from supramodal.node.workflows.labels import label_recording

    # SIGTERM as SIGINT: one line, and the sidecars staged are removed (a signal ended it on the spot, leaving them)
    interrupt_until_running("labelling; the sessions are labelled all or none")
    written = label_recording(args.recording, args.spans, replace=args.replace)
    for source, labels in written.items():
        names = sorted({n for _, _, n in labels})
        print(f"{source}: {len(labels)} label(s) {names}, in seconds of its own stream")
    return 0
