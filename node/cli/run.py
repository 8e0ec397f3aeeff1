"""The ``supramodal run`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse

from supramodal.node.cli.arguments import progress as progress_of
from supramodal.node.cli.arguments import speed, stream_seconds
from supramodal.node.cli.signals import interrupt_until_running, stop_on_signals

#: What ``supramodal run`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "run the node on a scene (TOML; default: the embedded whisker replay)"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal run [SCENE] [--speed S|max] [--seconds S] [--view [PORT]] [--print-scene]",
     f"{SUMMARY}; `--view` shows it live in the browser ([docs/view.md](docs/view.md)), `--print-scene` prints the "
     "scene with every key, to start your own"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``run`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("run", parents=[common], help=SUMMARY)
    p.add_argument("--force", action="store_true", help="replace existing sink files (default: refuse)")
    p.add_argument("scene", nargs="?", help="scene TOML file (default: the embedded default scene)")
    p.add_argument("--speed", type=speed,
                   help="replay speed: 1 = real time (default: the scene's), a factor, or 'max'")
    p.add_argument("--json", action="store_true", help="JSON Lines on stdout instead of the scene's sinks")
    p.add_argument("--seconds", type=stream_seconds,
                   help="stop after this much stream; inf: until it ends or Ctrl-C (the default)")
    p.add_argument("--view", nargs="?", const=0, type=int, metavar="PORT",
                   help="also serve a page that shows the run live on 127.0.0.1:PORT (default 0: any free port; the "
                        "URL and the run's token are printed at start; docs/view.md)")
    p.add_argument("--print-scene", action="store_true",
                   help="print the scene (the default one if none is given) as TOML, every key filled in, and exit: "
                        "a starting point to edit, e.g. supramodal run --print-scene > my.toml")
    return p


def run(args: argparse.Namespace) -> int:
    """Run the node on the scene until it ends, ``--seconds`` or a signal.

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
    from supramodal.node.runtime.sinks import QueuedSink
    from supramodal.node.runtime.sinks.jsonl import JsonLinesSink
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import default_scene, load_scene, scene_to_toml

    scene = load_scene(args.scene) if args.scene else default_scene()
    if args.print_scene:
        print(scene_to_toml(scene), end="")
        return 0
    sinks = [QueuedSink(JsonLinesSink("-"))] if args.json else None
    if args.view is not None:
        from supramodal.node.scene.variants import add_view
        scene, sinks = add_view(scene, sinks, args.view)
    progress = progress_of(args)
    if progress and args.scene is None:
        for line in _default_run_guide(scene, args.speed):
            progress(line)
    elif progress:
        progress(_scene_line(scene, sinks_replaced=args.json))
    notice = speed_notice(scene, args.speed)
    if notice and progress:
        progress(notice)
    node = build_node(scene, speed=args.speed, sinks_override=sinks, progress=progress, overwrite=args.force)
    attach_views(node)
    node.run(max_seconds=args.seconds, on_running=lambda: stop_on_signals(node))
    return 0


def _default_run_guide(scene, speed) -> list[str]:
    """Return what the embedded default scene shows, how long it runs, and where to go from it."""
    from supramodal.textures import reference_texture_set
    from supramodal.training import TRAIN_FRACTION

    stream = scene.only_stream()
    seconds = float(scene.only_source().options["seconds"])
    n = len(reference_texture_set(stream.bank.kind).names)
    pace = "at once (--speed max)" if speed == "max" else "in real time (--speed max runs it at once)"
    return [
        f"the default scene: the {stream.bank.kind} bank replays the last {seconds:g} s of each of the {n} "
        f"reference textures ({n * seconds:g} s of stream) {pace}, with a model trained on the spot on the "
        f"first {TRAIN_FRACTION:.0%} of each texture",
        f"one line per {stream.features.window * 1000:g} ms window: the decided texture, its confidence, the "
        "texture really there, ok or -- (wrong); Ctrl-C stops and prints the summary",
        "next: a model of your own recordings (supramodal train --help), the serial whisker array "
        "(examples/whisker_serial.toml with supramodal mock-whisker), your own scene (supramodal run --print-scene)",
    ]


def speed_notice(scene, speed) -> str | None:
    """Return what ``--speed`` does not do on this scene, said once: it paces replayed sources only.

    None: it paces some, or was not given.
    """
    from supramodal.node.scene.registry import driver_spec

    if speed is None:
        return None
    live = [s for s in scene.sources if driver_spec(s.type).live]
    if len(live) < len(scene.sources):
        return None
    kinds = ", ".join(dict.fromkeys(s.type for s in live))
    return (f"--speed {speed} is ignored: it paces replayed sources, and this scene's are live ({kinds}): they "
            "deliver at their own pace")


def _scene_line(scene, sinks_replaced: bool = False) -> str:
    """Return what a scene runs, in one line: driver, bank, features and window.

    Per stream, and the fusion, for a scene of several sources. ``sinks_replaced`` (``run --json``): the
    scene's sinks are not made, so no source is said to be sent on.
    """
    def one(stream) -> str:
        bank = f"the bank of {stream.bank.file}" if stream.bank.file is not None else f"{stream.bank.kind} bank"
        return f"{bank}, features {list(stream.features.names)}, {stream.features.window:g} s windows"

    sent = [f"source {k.source} sent on as LSL ({float(k.options['chunk']) * 1e3:g} ms chunks)" for k in scene.sinks
            if k.type == "lsl-signal"]
    if sinks_replaced and scene.sinks:
        kinds = [k.type for k in scene.sinks]
        lsl = "; nothing sent on as LSL" if any(k.startswith("lsl") for k in kinds) else ""
        sent = [f"--json: JSON Lines on stdout instead of the scene's sinks ({', '.join(kinds)}{lsl})"]
    if not scene.is_graph:
        return (f"scene {scene.source}: {scene.only_source().type} driver, {one(scene.only_stream())}"
                + "".join(f"; {p}" for p in sent))
    parts = [f"stream {s.name}: {scene.source_named(s.source).type} source {s.source}, {one(s)}"
             for s in scene.streams]
    parts += sent
    if scene.fusion is not None:
        f = scene.fusion
        how = f"weight {f.weight}" if f.method == "late" else \
            f"model {f.model}" if f.model else "network trained on the spot"
        parts.append(f"fused: {f.streams[0]} and {f.streams[1]} ({f.method}, {how})")
    return f"scene {scene.source}: " + "; ".join(parts)


def attach_views(node, on_mark=None) -> None:
    """Give a scene's view sinks (if any) the marks' handler ``on_mark`` while recording.

    Their counters the graph gives every sink itself (:meth:`Sink.watch <supramodal.node.runtime.sinks.Sink.watch>`).
    """
    from supramodal.node.runtime.sinks.view import attach

    attach(node, on_mark)
