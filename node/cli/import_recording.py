"""The ``supramodal import-recording`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse

from supramodal.node.cli.arguments import output_folder, session_name, source_value
from supramodal.node.cli.errors import CliError
from supramodal.node.cli.signals import interrupt_until_running

#: What ``supramodal import-recording`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "a replayable graph recording from a lab's own files: WAV with timestamps, XDF, or a robot's rosbag2"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal import-recording --out DIR (--wav ... | --xdf FILE.xdf ... | --bag BAG ...) --bank SOURCE=BANK",
     f"{SUMMARY} ([docs/node.md](docs/node.md#importing-a-recording-made-elsewhere), [docs/ros2.md](docs/ros2.md))"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``import-recording`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("import-recording", parents=[common], help=SUMMARY)
    p.add_argument("--out", required=True, type=output_folder, metavar="DIR",
                   help="folder for the recording (created if missing)")
    p.add_argument("--name", type=session_name, default="imported",
                   help="the recording's name: NAME.SOURCE.wav/.json per source and NAME.toml (default: imported)")
    p.add_argument("--wav", type=source_value, action="append", default=[], metavar="SOURCE=FILE.wav",
                   help="a source's samples; give one per source (default: none)")
    p.add_argument("--times", type=source_value, action="append", default=[], metavar="SOURCE=TIMES.csv",
                   help="its timestamps, seconds on the clock every source shares: a CSV with the header "
                        "'end_frame,seconds' (a row per block: frames delivered by its end, when it was complete) "
                        "or 'seconds' (a row per frame); one per --wav (default: none)")
    p.add_argument("--xdf", metavar="FILE.xdf", help="instead of WAV files: an XDF file (the lsl extra)")
    p.add_argument("--xdf-stream", type=source_value, action="append", default=[], metavar="SOURCE=STREAM",
                   help="with --xdf: a source read from the file's stream of that name; one per source (default: "
                        "none)")
    p.add_argument("--markers", metavar="STREAM",
                   help="with --xdf: a marker stream whose strings label every source (default: no labels)")
    p.add_argument("--bag", metavar="BAG",
                   help="instead of WAV files: a rosbag2 (its folder, or its .mcap or .db3 file; the ros2 extra)")
    p.add_argument("--topic", type=source_value, action="append", default=[], metavar="SOURCE=TOPIC",
                   help="with --bag: a source read from the bag's sensor topic (std_msgs *MultiArray or a stamped "
                        "sensor_msgs/Image, samples x channels, at its bank's rate); one per source (default: none)")
    p.add_argument("--label-topic", metavar="TOPIC",
                   help="with --bag: a std_msgs/String topic whose messages label every source (default: no labels)")
    p.add_argument("--bank", type=source_value, action="append", default=[], metavar="SOURCE=BANK",
                   help="each source's stream bank: whisker, cochlea or a bank file; one per source (default: none, "
                        "so give one for every source)")
    p.add_argument("--model", type=source_value, action="append", default=[], metavar="SOURCE=MODEL.npz",
                   help="a model for the source's stream, copied beside the sessions (default: none, the stream "
                        "gives feature windows)")
    p.add_argument("--mapping", type=source_value, action="append", default=[], metavar="SOURCE=MAPPING",
                   help="how a source of several channels feeds its bank: mean, a channel index (e.g. 0), "
                        "per-channel (as many channels as filters) or mono; written as its [[stream]] mapping "
                        "(default: auto, which takes one channel, or as many as the bank has filters)")
    p.add_argument("--fusion", action="store_true",
                   help="fuse the two streams' decisions (late fusion; learn its weight with train --fusion late); "
                        "needs two sources with models (default: no fusion)")
    p.add_argument("--force", action="store_true", help="replace an earlier import of that name (default: refuse)")
    return p


def run(args: argparse.Namespace) -> int:
    """Write the sessions and their replay scene.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    from supramodal.node.workflows.import_recording import import_recording, sources_from_options

    # SIGTERM as SIGINT: one line, and the import's staging folder removed (a signal ended it on the spot, leaving it)
    interrupt_until_running("the import; a recording is imported whole or not at all")
    if args.label_topic is not None and args.markers is not None:
        raise CliError("--markers labels from an XDF file, --label-topic from a bag: give one")
    sources = sources_from_options(args.wav, args.times, args.xdf_stream, args.bank, args.model, args.topic,
                                   args.mapping)
    scene = import_recording(args.out, args.name, sources, xdf=args.xdf, markers=args.markers or args.label_topic,
                             fusion=args.fusion, overwrite=args.force, bag=args.bag)
    print(f"wrote {scene} and the sessions of {', '.join(s.name for s in sources)} beside it\n"
          f"next: supramodal run {scene} --speed max")
    return 0
