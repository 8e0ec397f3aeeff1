"""The ``supramodal`` command: a thin layer over the model, the drivers and the node.

Each subcommand imports what it needs when it runs, so that, for example, an
experiment never imports sounddevice or pyserial.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from supramodal.errors import SupramodalError


class CliError(SupramodalError):
    """A user error the CLI reports in one line, without a traceback."""


def _cmd_experiment(args) -> int:
    import time

    from supramodal.experiments.common import progress_to_stderr
    from supramodal.experiments.report import figure_table, write_figure
    from supramodal.experiments.runner import run_plans
    from supramodal.experiments.suite import plans
    from supramodal.textures import load_texture_set

    if args.seed < 0:
        raise CliError(f"--seed must be >= 0, got {args.seed}")
    if args.jobs is not None and args.jobs < 1:
        raise CliError(f"--jobs must be >= 1, got {args.jobs}")
    ts = load_texture_set(args.textures) if args.textures else None
    todo = plans(args.figure, quick=args.quick, epochs=args.epochs, seed=args.seed, sets=args.sets,
                 bank=args.bank, texture_set=ts)
    progress = None if args.quiet else progress_to_stderr
    t0 = time.perf_counter()
    results = run_plans(todo, jobs=args.jobs, seed=args.seed, progress=progress)
    written = [p for name, result in results.items() for p in write_figure(name, result, Path(args.out))]
    if progress:
        progress(f"experiment {args.figure}: {time.perf_counter() - t0:.1f} s")
    if args.json:
        print(json.dumps(results[args.figure] if args.figure in results else results))
    else:
        print("\n\n".join(figure_table(name, result) for name, result in results.items()))
        print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _cmd_synth(args) -> int:
    import numpy as np
    from scipy.io import wavfile

    from supramodal.textures import load_texture_set, reference_texture_set

    ts = load_texture_set(args.textures) if args.textures else reference_texture_set(args.bank)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    duration = args.duration if args.duration else ts.duration
    for i, tex in enumerate(ts.textures):
        x = ts.synthesize(i, duration=duration).astype(np.float32)
        path = out / f"{tex.name}.wav"
        wavfile.write(path, int(round(ts.fs)), x)
        print(f"{path}  {len(x) / ts.fs:g} s at {ts.fs:g} Hz, peaks {list(tex.peaks)} Hz")
    return 0


def _speed(text: str):
    if text == "max":
        return "max"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--speed takes a positive factor or 'max', got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"--speed must be > 0, got {text!r}")
    return value


def _cmd_run(args) -> int:
    import signal

    from node.build import build_node
    from node.scene import default_scene, load_scene
    from node.sinks import JsonLinesSink

    scene = load_scene(args.scene) if args.scene else default_scene()
    sinks = [JsonLinesSink("-")] if args.json else None
    progress = None if args.quiet else (lambda m: print(f"supramodal: {m}", file=sys.stderr, flush=True))
    if progress:
        progress(f"scene {scene.source}: {scene.driver['type']} driver, {scene.bank['kind']} bank, "
                 f"features {scene.features['names']}")
    node = build_node(scene, speed=args.speed, sinks_override=sinks, progress=progress)
    # Signals only set a flag: the node finishes what it holds and prints its summary.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: node.stop(signal.Signals(signum).name))
    node.run(max_seconds=args.seconds)
    return 0


def _cmd_record(args) -> int:
    import json as _json
    import signal
    import threading
    import time

    from node.build import build_node
    from node.recorder import SessionRecorder
    from node.scene import load_scene

    scene = load_scene(args.scene)
    name = args.name or time.strftime("session-%Y%m%d-%H%M%S")
    source = _json.dumps({"scene": scene.source, "driver": scene.driver})
    recorder = SessionRecorder(args.out, name, source, label=args.label)
    node = build_node(scene, recorder=recorder, progress=_progress(args))
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: node.stop(signal.Signals(signum).name))
    if args.marks:
        # Each line typed starts a label (its text) at the current stream time; an empty line ends it.
        def read_marks():
            for line in sys.stdin:
                recorder.mark(line.strip() or None)
        threading.Thread(target=read_marks, daemon=True).start()
    summary = node.run(max_seconds=args.seconds)
    if summary.get("recorded"):
        print(f"recorded {summary['stream_seconds']:.2f} s to {summary['recorded'][0]} (+ .json)", file=sys.stderr)
    return 0


def _mock_source(source: str):
    """SOURCE of mock-whisker: ``synth:NAME`` (a reference whisker texture), a session or a WAV file."""
    if source.startswith("synth:"):
        from supramodal.textures import reference_texture_set

        ts = reference_texture_set("whisker")
        name = source[len("synth:"):]
        if name not in ts.names:
            raise CliError(f"unknown texture {name!r}; the whisker reference set has {list(ts.names)}")
        return ts.synthesize(ts.names.index(name))[:, None], ts.fs
    from replay.driver import ReplayDriver

    drv = ReplayDriver(source, speed="max", on_notice=None)   # a session or a bare WAV file
    return drv.data, drv.rate


def _cmd_mock_whisker(args) -> int:
    from drivers.mock_whisker import run

    samples, rate = _mock_source(args.source)
    return run(args, samples, rate)


def _cmd_devices(args) -> int:
    from drivers.devices import format_devices

    print(format_devices())
    return 0


def _mapping(text: str):
    return int(text) if text.isdigit() else text


def _progress(args):
    return None if getattr(args, "quiet", False) else (lambda m: print(f"supramodal: {m}", file=sys.stderr, flush=True))


def _cmd_train(args) -> int:
    from node.training import train_from_manifest
    from supramodal.banks import bank_by_name

    bank = bank_by_name(args.bank)
    model = train_from_manifest(args.manifest, bank, tuple(args.features), args.window, epochs=args.epochs,
                                seed=args.seed, mapping=args.mapping, progress=_progress(args))
    path = model.save(args.out)
    print(f"wrote {path}: {model.bank.kind} bank, features {list(model.features)}, classes {list(model.classes)}, "
          f"{model.training['windows']} training windows, final MSE {model.training['final_mse']:.4g}")
    return 0


def _cmd_evaluate(args) -> int:
    from node.training import evaluate_manifest, format_evaluation
    from supramodal.model import TextureModel

    model = TextureModel.load(args.model)
    result = evaluate_manifest(model, args.manifest, mapping=args.mapping, progress=_progress(args))
    print(json.dumps(result) if args.json else format_evaluation(result))
    return 0


def _cmd_bench(args) -> int:
    import os
    import subprocess

    from benchmarks.filterbank import PINNED_THREADS

    # A child process, so that BLAS and OpenMP read the one-thread settings before numpy loads.
    cmd = [sys.executable, "-m", "benchmarks.filterbank", "--out", args.out] + ["--quick"] * args.quick + ["--json"] * args.json
    return subprocess.run(cmd, env={**os.environ, **PINNED_THREADS}).returncode


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="supramodal", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run the node on a scene (default: the embedded whisker replay scene)")
    p.add_argument("scene", nargs="?", help="scene TOML file (default: the embedded default scene)")
    p.add_argument("--speed", type=_speed, help="replay speed: 1 = real time (default), a factor, or 'max'")
    p.add_argument("--json", action="store_true", help="JSON Lines on stdout instead of the scene's sinks")
    p.add_argument("--seconds", type=float, help="stop after this much stream (default: until it ends or Ctrl-C)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("train", help="train a model from labelled recordings")
    p.add_argument("--bank", choices=["whisker", "cochlea"], required=True)
    p.add_argument("--manifest", required=True, help="CSV with columns path,label[,start,end]; paths relative to it")
    p.add_argument("--out", required=True, help="model file to write (.npz)")
    p.add_argument("--features", nargs="+", default=["Af"], choices=["Af", "A", "f"])
    p.add_argument("--window", type=float, default=0.1, help="window, seconds (default 0.1)")
    p.add_argument("--epochs", type=int, default=500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--mapping", type=_mapping, default="auto",
                   help="recording channels to filters: auto, mono, per-channel, mean, or a channel index")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("evaluate", help="accuracy and confusion of a model on labelled recordings")
    p.add_argument("model", help="model file (.npz)")
    p.add_argument("--manifest", required=True)
    p.add_argument("--mapping", type=_mapping, default="auto")
    p.add_argument("--json", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("record", help="record a scene's raw driver blocks as a session (WAV + JSON)")
    p.add_argument("scene", help="scene TOML file")
    p.add_argument("--out", required=True, help="folder for the session")
    p.add_argument("--name", help="session name (default: session-DATE-TIME)")
    p.add_argument("--label", help="label of the whole recording")
    p.add_argument("--marks", action="store_true",
                   help="read labels from stdin while recording: a line starts that label now, an empty line ends it")
    p.add_argument("--seconds", type=float, help="stop after this much stream (default: until the stream ends or Ctrl-C)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_record)

    from drivers.mock_whisker import add_arguments as mock_arguments

    p = sub.add_parser("mock-whisker", help="a mock whisker-array board streaming frames on a pty, with fault injection")
    mock_arguments(p)
    p.set_defaults(func=_cmd_mock_whisker)

    p = sub.add_parser("devices", help="list audio inputs and serial ports")
    p.set_defaults(func=_cmd_devices)

    p = sub.add_parser("experiment", help="reproduce a figure of the paper (or all of them)")
    p.add_argument("figure", choices=["fig1", "fig3", "fig4", "fig5", "fig6", "all"], help="which figure")
    p.add_argument("--quick", action="store_true", help="short textures and small grids: seconds, not minutes")
    p.add_argument("--jobs", type=int, help="worker processes (default: all cores); results do not depend on it")
    p.add_argument("--seed", type=int, default=0,
                   help="experiment seed: each run's network seed derives from it and the run; also the first "
                        "random texture set's seed")
    p.add_argument("--epochs", type=int, default=500, help="iRPROP- epochs (default 500)")
    p.add_argument("--bank", choices=["whisker", "cochlea"], help="fig3: one bank (default: both)")
    p.add_argument("--textures", metavar="FILE", help="fig3: texture-set JSON file (default: the reference sets)")
    p.add_argument("--sets", type=int, help="fig3: N random texture sets instead of the reference set; "
                                            "all: N random sets per bank besides it (default 5, 0 with --quick)")
    p.add_argument("--out", default="out", help="directory for CSV and PNG (default ./out)")
    p.add_argument("--json", action="store_true", help="print the figure's data as one JSON object instead of a table")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=_cmd_experiment)

    p = sub.add_parser("bench", help="filterbank error against run time, drift, the whole node (report in --out)")
    p.add_argument("--quick", action="store_true", help="short signals and streams (well under a minute; not for quoting)")
    p.add_argument("--out", default="out/bench", help="directory for the report (default ./out/bench)")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser("synth", help="write a texture set as WAV files")
    p.add_argument("--bank", choices=["whisker", "cochlea"], default="whisker")
    p.add_argument("--textures", metavar="FILE", help="texture-set JSON file (default: the bank's reference set)")
    p.add_argument("--duration", type=float, help="seconds per texture (default: the set's)")
    p.add_argument("--out", default="out/textures", help="directory (default ./out/textures)")
    p.set_defaults(func=_cmd_synth)
    return parser


def _is_user_error(exc: BaseException) -> bool:
    """Errors that mean bad input or a missing device: one line, no traceback."""
    from drivers.base import DriverError

    if isinstance(exc, (CliError, ValueError, OSError, DriverError)):
        return True
    graph = sys.modules.get("node.graph")
    return graph is not None and isinstance(exc, graph.NodeError)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except Exception as exc:
        if not _is_user_error(exc):
            raise
        print(f"supramodal: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("supramodal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
