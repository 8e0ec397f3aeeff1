"""The ``supramodal record`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import threading
from pathlib import Path

from supramodal.node.cli.arguments import label_name, output_folder, progress, session_name, stream_seconds
from supramodal.node.cli.errors import CliError
from supramodal.node.cli.run import attach_views
from supramodal.node.cli.signals import interrupt_until_running, stop_on_signals

#: What ``supramodal record`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = ("record the node's input as a session that replays to identical output, with its labels; several sources "
           "in step, with the scene that replays them")
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal record SCENE --out DIR [--label L | --marks] [--seconds S] [--bag FOLDER]",
     f"{SUMMARY} ([docs/node.md](docs/node.md#recording-sessions); as a rosbag2: "
     "[docs/ros2.md](docs/ros2.md#the-nodes-recordings-as-bags))"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``record`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("record", parents=[common], help=SUMMARY)
    p.add_argument("--force", action="store_true", help="replace an existing session of that name (default: refuse)")
    p.add_argument("scene", help="scene TOML file")
    p.add_argument("--out", required=True, type=output_folder, help="folder for the session (created if missing)")
    p.add_argument("--name", type=session_name,
                   help="session name: letters, digits, '-' or '_' (default: session-DATE-TIME)")
    p.add_argument("--label", type=label_name,
                   help="label of the whole recording (of every source of a graph): letters, digits, '-' or '_'")
    p.add_argument("--marks", action="store_true",
                   help="read labels from stdin while recording: a line starts that label now, an empty line ends "
                        "it; in a graph, on the node's common time, mapped to each source through its clock")
    p.add_argument("--replace", action="store_true",
                   help="with --label or --marks: label the recording with them instead of the labels a source's "
                        "driver gives (synth, twosense, a replayed session; default: refused)")
    p.add_argument("--seconds", type=stream_seconds,
                   help="stop after this much stream; inf: until the stream ends or Ctrl-C (the default)")
    p.add_argument("--bag", metavar="FOLDER",
                   help="also write the recording as a rosbag2 (MCAP) folder: each source's samples on "
                        "/supramodal/SOURCE/samples (stamped sensor_msgs/Image), the labels on /supramodal/labels "
                        "(needs the ros2 extra; docs/ros2.md)")
    p.add_argument("--view", nargs="?", const=0, type=int, metavar="PORT",
                   help="also serve the live page on 127.0.0.1:PORT (default 0: any free port); with --marks its label "
                        "buttons mark too, given the run's token printed at start (docs/view.md)")
    return p


def run(args: argparse.Namespace) -> int:
    """Record the scene until it ends, ``--seconds`` or a signal.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    # First: a signal while the scene loads and the modules import is start-up too (it ended the
    # process silently, by the default handler, before the scene was read).
    interrupt_until_running()
    import time

    from supramodal.node.scene.schema import load_scene

    scene = load_scene(args.scene)
    if args.view is not None:
        from supramodal.node.scene.variants import add_view
        scene, _ = add_view(scene, None, args.view)
    name = args.name or time.strftime("session-%Y%m%d-%H%M%S")
    labelled = bool(args.label or args.marks)
    if args.replace and not labelled:
        raise CliError("--replace replaces a driver's own labels with --label or --marks: give one of them")
    sessions = ([(src.name, args.out / f"{name}.{src.name}.wav") for src in scene.sources] if scene.is_graph
                else [(scene.only_source().name, args.out / f"{name}.wav")])
    windows = None
    if args.bag is not None:                # refused before anything is recorded
        from supramodal.node.scene.variants import with_sink
        from supramodal.node.workflows.bag_export import check_bag_target
        check_bag_target(args.bag, [n for n, _ in sessions] + [st.name for st in scene.streams], args.force,
                         made=args.out)
        # the node's windows, for the bag's decision topics: a JSON Lines file of the run's own, gone after
        windows = Path(tempfile.mkdtemp(prefix="supramodal-record-")) / "windows.jsonl"
        scene = with_sink(scene, "jsonl", path=str(windows))
    try:
        return _record(args, scene, name, labelled, sessions, windows)
    finally:
        _keep_or_drop(_staging(args.out, name), args.out / f"{name}.incomplete-{os.getpid()}")
        if windows is not None:
            shutil.rmtree(windows.parent, ignore_errors=True)


def _keep_or_drop(staging: Path, aside: Path) -> None:
    """Keep the sessions of a graph's recording that was not put in place, in ``aside``, or drop an empty one.

    Not put in place: a source never started, the node failed. Its sessions are what the user recorded,
    kept in ``aside`` and said; a staging folder with no session goes.
    """
    if staging.is_dir() and any(staging.glob("*.wav")):
        staging.rename(aside)
        print(f"supramodal: record: the recording was not put in place; the sessions it made are kept in {aside}",
              file=sys.stderr)
    else:
        shutil.rmtree(staging, ignore_errors=True)


def _staging(out: Path, name: str) -> Path:
    """Return the folder a graph's recording is written into, beside it, before its files are put in place at once."""
    return out / f".{name}.record-{os.getpid()}"


def _record(args: argparse.Namespace, scene, name: str, labelled: bool, sessions: list, windows) -> int:
    """Record ``scene`` as ``name`` (see :func:`run`)."""
    import json as _json

    from supramodal.errors import InputError
    from supramodal.node.runtime.taps.recorder import SessionRecorder
    from supramodal.node.scene.build import build_node
    from supramodal.node.workflows.graph_recording import GraphMarks, graph_recorders, write_replay_scene
    from supramodal.node.workflows.labels import replace_all

    if scene.is_graph:
        # The sessions, models and replay scene are written aside and put in place once all are there: a source
        # that had not delivered a block when the recording stopped had no session, and the others' new sessions
        # were replayed with an earlier recording's session of it (or left without a replay scene).
        staging = _staging(args.out, name)
        recorders = graph_recorders(scene, args.out, name, overwrite=args.force, label=args.label,
                                    replace=args.replace, into=staging)
        node = build_node(scene, recorder=recorders, progress=progress(args), overwrite=args.force)
        own = [s.name for s in node.sources if s.labels is not None and s.labels.ranges]
        if own and labelled and not args.replace:
            raise CliError(f"{scene.source}: source(s) {own} label their streams themselves, and the recording keeps "
                           "those labels; --label and --marks would contradict them (leave them out, or pass "
                           "--replace to label the recording with yours instead)")
        if args.marks:
            _read_marks(GraphMarks(recorders).mark)
        attach_views(node, GraphMarks(recorders).mark if args.marks else None)    # marks from the page too
        summary = node.run(max_seconds=args.seconds, on_running=lambda: stop_on_signals(node))
        if summary.recorded:
            try:
                replay = write_replay_scene(scene, node, args.out, name, overwrite=args.force, into=staging)
            except InputError as exc:
                raise CliError(f"{exc}; nothing was put in the recording's place (a recording is kept whole or "
                               "not at all)") from None
            replace_all([(path, args.out / path.name) for path in sorted(staging.iterdir())
                          if not path.name.startswith(".")])
            replay = args.out / replay.name
            wavs = ", ".join(str(args.out / Path(p).name) for p in summary.recorded if p.endswith(".wav"))
            print(f"recorded {summary.stream_seconds:.2f} s to {wavs} (+ .json); replay them in step: "
                  f"supramodal run {replay}", file=sys.stderr)
            _write_bag(args, sessions, windows)
        return 0
    src = scene.only_source()
    source = _json.dumps({"scene": scene.source,
                          "driver": {"type": src.type, **src.options, "mapping": scene.only_stream().mapping}})
    recorder = SessionRecorder(args.out, name, source, label=args.label, overwrite=args.force, replace=args.replace)
    node = build_node(scene, recorder=recorder, progress=progress(args), overwrite=args.force)
    if node.streams[0].labels.ranges and labelled and not args.replace:
        raise CliError(f"{scene.source}: the {src.type} driver labels its stream itself, and the "
                       "recording keeps those labels with their times; --label and --marks would contradict them "
                       "(leave them out, or pass --replace to label the recording with yours instead)")
    if args.marks:
        _read_marks(recorder.mark)
    attach_views(node, recorder.mark if args.marks else None)                    # marks from the page too
    summary = node.run(max_seconds=args.seconds, on_running=lambda: stop_on_signals(node))
    if summary.recorded:
        print(f"recorded {summary.stream_seconds:.2f} s to {summary.recorded[0]} (+ .json)", file=sys.stderr)
        _write_bag(args, sessions, windows)
    return 0


def _write_bag(args: argparse.Namespace, sessions: list, windows) -> None:
    """Write ``record --bag``'s rosbag2: the sessions just recorded, and the windows' decisions.

    ``windows``: the JSON Lines the run wrote.
    """
    if args.bag is None:
        return
    from supramodal.node.workflows.bag_export import export_bag

    done = export_bag(sessions, args.bag, overwrite=args.force, windows=windows)
    topics = ", ".join(f"{t} ({n})" for t, n in done["topics"].items())
    print(f"and as a rosbag2 (MCAP) in {done['bag']}: {topics}", file=sys.stderr)


def _read_marks(mark) -> None:
    """Read ``record --marks``' labels from stdin, on a thread of its own.

    Each line typed on stdin starts a label (its text) now, an empty line ends it (``mark(label or None)``); a
    line that is no valid label is said on stderr and not applied.
    """
    from supramodal.node.workflows.labels import LabelError, check_label_name

    def read():
        for line in sys.stdin:
            text = line.strip()
            try:
                mark(check_label_name(text, "--marks") if text else None)
            except LabelError as exc:
                print(f"supramodal: {exc}; the line was not applied", file=sys.stderr, flush=True)
    threading.Thread(target=read, name="marks", daemon=True).start()
