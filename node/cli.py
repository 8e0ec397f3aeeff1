"""The ``supramodal`` command: a thin layer over the model, the drivers and the node.

Each subcommand imports what it needs when it runs, so that, for example, an
experiment never imports sounddevice or pyserial.

Errors and exit status (README "Errors and exit status"):

* 0: done; also when the reader of stdout went away (``supramodal run | head``): the
  reader asked for no more, as Ctrl-C does, and a ``set -o pipefail`` script must not fail.
* 2: a :class:`~supramodal.errors.SupramodalError` (bad input, a device or a file the
  user named), or an ``OSError`` naming a file: one line ``supramodal: error: ...``.
* 1: anything else is a bug: its traceback and a line asking to report it.
* 130 / 143: SIGINT / SIGTERM before the stream started (while a scene is built or its
  model trained): one line, nothing processed. Once the node runs, both stop it cleanly:
  what is buffered is processed, the summary printed, and the exit status is 0.

``--debug`` (before or after the command) shows the traceback of every error.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import sys
import threading
import traceback
import warnings
from pathlib import Path

from supramodal import __version__
from supramodal.errors import SupramodalError, SupramodalWarning

#: Exit status of a refused input (argparse uses it for usage errors too).
EXIT_USER_ERROR = 2
#: Exit status of an unexpected exception (what Python itself returns for one).
EXIT_BUG = 1


class CliError(SupramodalError):
    """A user error the CLI reports in one line, without a traceback."""


class StartupInterrupted(BaseException):
    """SIGINT or SIGTERM arrived before the stream started. A BaseException, like
    KeyboardInterrupt, so that no ``except Exception`` on the way swallows it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _interrupt_startup(signum, frame):
    raise StartupInterrupted(signum)


def _interrupt_until_running() -> None:
    """Until :func:`_stop_on_signals`, SIGINT and SIGTERM interrupt the start-up (building the
    scene, training its model) with a one-line message instead of dying silently."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _interrupt_startup)


def _stop_on_signals(node) -> None:
    """From now on SIGINT and SIGTERM only set a flag: the node finishes what it holds and
    prints its summary (before this, :func:`_interrupt_startup` applies). Called by the node once it
    runs (``on_running``): a wait before, for a consumer of an outlet, is still start-up."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: node.stop(signal.Signals(signum).name))


def _check_output(text: str, folder: bool) -> Path:
    """An output path, checked before any long work starts, so that none is lost.

    A file (``folder=False``) must not be a folder, and its folder must exist and be
    writable; the file is written at exactly this path. A folder (``folder=True``) is
    created with its parents when the command writes; it must not be a file, and its
    nearest existing ancestor must be a writable folder.
    """
    path = Path(text).expanduser()
    if folder:
        if path.exists() and not path.is_dir():
            raise argparse.ArgumentTypeError(f"{path} is a file; give a folder")
        parent = next(p for p in (path, *path.parents) if p.exists())
        if not parent.is_dir():
            raise argparse.ArgumentTypeError(f"{path} cannot be created: {parent} is a file")
    else:
        if path.is_dir():
            raise argparse.ArgumentTypeError(f"{path} is a folder; give a file name in it, e.g. {path / 'model.npz'}")
        parent = path.parent
        if not parent.is_dir():
            raise argparse.ArgumentTypeError(f"the folder {parent} does not exist: create it first "
                                             f"(mkdir -p {parent}) or choose another path")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"cannot write in {parent}: permission denied")
    return path


def _output_file(text: str) -> Path:
    return _check_output(text, folder=False)


def _output_folder(text: str) -> Path:
    return _check_output(text, folder=True)


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
    if args.figure == "fusion":
        return _experiment_fusion(args)
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

    from supramodal.errors import InputError
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.textures import load_texture_set, reference_texture_set, texture_samples

    ts = load_texture_set(args.textures) if args.textures else reference_texture_set(args.bank)
    out = Path(args.out)
    paths = [out / f"{tex.name}.wav" for tex in ts.textures]
    if out.is_dir():
        for path in paths:
            check_new_file(path, args.force, "the texture file")
    duration = ts.duration if args.duration is None else args.duration
    try:
        texture_samples(duration, ts.fs)
    except InputError as exc:
        raise InputError(f"--duration: {exc}") from None
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    written = []
    try:
        for i, (tex, path) in enumerate(zip(ts.textures, paths)):
            x = ts.synthesize(i, duration=duration).astype(np.float32)
            written.append(path)             # from here on, this file is ours to remove on failure
            wavfile.write(path, int(round(ts.fs)), x)
            print(f"{path}  {len(x) / ts.fs:g} s at {ts.fs:g} Hz, peaks {list(tex.peaks)} Hz")
    except BaseException:
        # A failed (or interrupted) run leaves nothing: no part of a set, no folder it made.
        for path in written:
            path.unlink(missing_ok=True)
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise
    return 0


def _stream_seconds(text: str) -> float | None:
    """``--seconds``: a positive number of seconds of stream, or ``inf`` (run until the stream ends)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, or inf for no limit; got {text!r}")
    return None if math.isinf(value) else value


def _positive_seconds(text: str) -> float:
    """A finite, positive number of seconds (``--window``, ``--duration``)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite, positive number of seconds; got {text!r}")
    return value


def _count(lo: int):
    """An integer option of at least ``lo`` (``--epochs``, ``--jobs``, ``--sets``, ``--seed``)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {lo}; got {text!r}") from None
        if value < lo:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {lo}; got {text!r}")
        return value
    return parse


def _session_name(text: str) -> str:
    """A session's name: a file name part, never a path (refused at start, not after recording)."""
    from supramodal.checks import NAME_HELP, is_name

    if not is_name(text):
        raise argparse.ArgumentTypeError(f"expected {NAME_HELP} (no folder: give that with --out), got {text!r}")
    return text


def _speed(text: str):
    from supramodal.replay.driver import SPEED_HELP, SPEED_MAX, is_speed

    try:
        value = text if text == SPEED_MAX else float(text)
    except ValueError:
        value = None
    if not is_speed(value):
        raise argparse.ArgumentTypeError(f"expected {SPEED_HELP}, got {text!r}")
    return value


def _default_run_guide(scene, speed) -> list[str]:
    """What the embedded default scene shows, how long it runs, and where to go from it."""
    from supramodal.textures import reference_texture_set
    from supramodal.training import TRAIN_FRACTION

    d = scene.driver
    n = len(reference_texture_set(scene.bank["kind"]).names)
    pace = "at once (--speed max)" if speed == "max" else "in real time (--speed max runs it at once)"
    return [
        f"the default scene: the {scene.bank['kind']} bank replays the last {d['seconds']:g} s of each of the {n} "
        f"reference textures ({n * d['seconds']:g} s of stream) {pace}, with a model trained on the spot on the "
        f"first {TRAIN_FRACTION:.0%} of each texture",
        f"one line per {scene.features['window'] * 1000:g} ms window: the decided texture, its confidence, the "
        "texture really there, ok or -- (wrong); Ctrl-C stops and prints the summary",
        "next: a model of your own recordings (supramodal train --help), the serial whisker array "
        "(examples/whisker_serial.toml with supramodal mock-whisker), your own scene (supramodal run --print-scene)",
    ]


def _scene_line(scene, sinks_replaced: bool = False) -> str:
    """What a scene runs, in one line: driver, bank, features and window (per stream, and the
    fusion, for a scene of several sources); ``sinks_replaced`` (``run --json``): the scene's
    sinks are not made, so no source is said to be sent on."""
    def one(sub) -> str:
        bank = (f"the bank of {sub.bank['file']}" if sub.bank["file"] is not None else f"{sub.bank['kind']} bank")
        return f"{bank}, features {sub.features['names']}, {sub.features['window']:g} s windows"

    sent = [f"source {k['source']} sent on as LSL ({k['chunk'] * 1e3:g} ms chunks)" for k in scene.sinks
            if k["type"] == "lsl-signal"]
    if sinks_replaced and scene.sinks:
        kinds = [k["type"] for k in scene.sinks]
        lsl = "; nothing sent on as LSL" if any(k.startswith("lsl") for k in kinds) else ""
        sent = [f"--json: JSON Lines on stdout instead of the scene's sinks ({', '.join(kinds)}{lsl})"]
    if not scene.is_graph:
        return f"scene {scene.source}: {scene.driver['type']} driver, {one(scene)}" + "".join(f"; {p}" for p in sent)
    parts = [f"stream {s.name}: {s.scene.driver['type']} source {s.source}, {one(s.scene)}" for s in scene.streams]
    parts += sent
    if scene.fusion is not None:
        f = scene.fusion
        how = f"weight {f['weight']}" if f["method"] == "late" else \
            f"model {f['model']}" if f["model"] else "network trained on the spot"
        parts.append(f"fused: {f['streams'][0]} and {f['streams'][1]} ({f['method']}, {how})")
    return f"scene {scene.source}: " + "; ".join(parts)


def _cmd_run(args) -> int:
    from supramodal.node.runtime.sinks import QueuedSink
    from supramodal.node.runtime.sinks.jsonl import JsonLinesSink
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import default_scene, load_scene, scene_to_toml

    scene = load_scene(args.scene) if args.scene else default_scene()
    if args.print_scene:
        print(scene_to_toml(scene), end="")
        return 0
    _interrupt_until_running()
    sinks = [QueuedSink(JsonLinesSink("-"))] if args.json else None
    if args.view is not None:
        from supramodal.node.runtime.sinks.view import add_view
        scene, sinks = add_view(scene, sinks, args.view)
    progress = None if args.quiet else (lambda m: print(f"supramodal: {m}", file=sys.stderr, flush=True))
    if progress and args.scene is None:
        for line in _default_run_guide(scene, args.speed):
            progress(line)
    elif progress:
        progress(_scene_line(scene, sinks_replaced=args.json))
    node = build_node(scene, speed=args.speed, sinks_override=sinks, progress=progress, overwrite=args.force)
    _attach_views(node)
    node.run(max_seconds=args.seconds, on_running=lambda: _stop_on_signals(node))
    return 0


def _attach_views(node, on_mark=None) -> None:
    """A scene's view sinks (if any) get the graph's counters and, while recording, the marks."""
    from supramodal.node.runtime.sinks.view import attach

    attach(node, on_mark)


def _cmd_record(args) -> int:
    import json as _json
    import time

    from supramodal.errors import InputError
    from supramodal.node.runtime.taps.recorder import SessionRecorder
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import load_scene
    from supramodal.node.workflows.graph_recording import GraphMarks, graph_recorders, write_replay_scene

    _interrupt_until_running()
    scene = load_scene(args.scene)
    if args.view is not None:
        from supramodal.node.runtime.sinks.view import add_view
        scene, _ = add_view(scene, None, args.view)
    name = args.name or time.strftime("session-%Y%m%d-%H%M%S")
    labelled = bool(args.label or args.marks)
    if args.replace and not labelled:
        raise CliError("--replace replaces a driver's own labels with --label or --marks: give one of them")
    if scene.is_graph:
        recorders = graph_recorders(scene, args.out, name, overwrite=args.force, label=args.label,
                                    replace=args.replace)
        node = build_node(scene, recorder=recorders, progress=_progress(args))
        own = [s.name for s in node.sources if s.labels is not None and s.labels.ranges]
        if own and labelled and not args.replace:
            raise CliError(f"{scene.source}: source(s) {own} label their streams themselves, and the recording keeps "
                           "those labels; --label and --marks would contradict them (leave them out, or pass "
                           "--replace to label the recording with yours instead)")
        if args.marks:
            _read_marks(GraphMarks(recorders).mark)
        _attach_views(node, GraphMarks(recorders).mark if args.marks else None)    # marks from the page too
        summary = node.run(max_seconds=args.seconds, on_running=lambda: _stop_on_signals(node))
        if summary.get("recorded"):
            try:
                replay = write_replay_scene(scene, node, args.out, name, overwrite=args.force)
            except InputError as exc:
                raise CliError(f"recorded {', '.join(summary['recorded'])}, but {exc}") from None
            wavs = ", ".join(p for p in summary["recorded"] if p.endswith(".wav"))
            print(f"recorded {summary['stream_seconds']:.2f} s to {wavs} (+ .json); replay them in step: "
                  f"supramodal run {replay}", file=sys.stderr)
        return 0
    source = _json.dumps({"scene": scene.source, "driver": scene.driver})
    recorder = SessionRecorder(args.out, name, source, label=args.label, overwrite=args.force, replace=args.replace)
    node = build_node(scene, recorder=recorder, progress=_progress(args))
    if node.streams[0].labels.ranges and labelled and not args.replace:
        raise CliError(f"{scene.source}: the {scene.driver['type']} driver labels its stream itself, and the "
                       "recording keeps those labels with their times; --label and --marks would contradict them "
                       "(leave them out, or pass --replace to label the recording with yours instead)")
    if args.marks:
        _read_marks(recorder.mark)
    _attach_views(node, recorder.mark if args.marks else None)                    # marks from the page too
    summary = node.run(max_seconds=args.seconds, on_running=lambda: _stop_on_signals(node))
    if summary.get("recorded"):
        print(f"recorded {summary['stream_seconds']:.2f} s to {summary['recorded'][0]} (+ .json)", file=sys.stderr)
    return 0


def _read_marks(mark) -> None:
    """``record --marks``: each line typed on stdin starts a label (its text) now, an empty line
    ends it (``mark(label or None)``), on a thread of its own; a line that is no valid label is
    said on stderr and not applied."""
    from supramodal.node.workflows.labels import LabelError, check_label_name

    def read():
        for line in sys.stdin:
            text = line.strip()
            try:
                mark(check_label_name(text, "--marks") if text else None)
            except LabelError as exc:
                print(f"supramodal: {exc}; the line was not applied", file=sys.stderr, flush=True)
    threading.Thread(target=read, name="marks", daemon=True).start()


def _label_name(text: str) -> str:
    """``--label``: a valid label name."""
    from supramodal.node.workflows.labels import LabelError, check_label_name

    try:
        return check_label_name(text, "--label")
    except LabelError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _cmd_view(args) -> int:
    from supramodal.node.workflows.view_replay import ViewReplay

    _interrupt_until_running()
    replay = ViewReplay(args.recording, port=args.port, speed=args.speed, progress=_progress(args))
    replay.serve(on_running=lambda: _stop_on_signals(replay))
    return 0


def _cmd_label(args) -> int:
    from supramodal.node.workflows.labels import label_recording

    written = label_recording(args.recording, args.spans, replace=args.replace)
    for source, labels in written.items():
        names = sorted({n for _, _, n in labels})
        print(f"{source}: {len(labels)} label(s) {names}, in seconds of its own stream")
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
    from supramodal.replay.driver import ReplayDriver

    drv = ReplayDriver(source, speed="max", on_notice=None)   # a session or a bare WAV file
    return drv.data, drv.rate


def _cmd_mock_whisker(args) -> int:
    from supramodal.drivers.mock_whisker import run

    samples, rate = _mock_source(args.source)
    return run(args, samples, rate)


def _experiment_fusion(args) -> int:
    """``experiment fusion``: the two senses fused on the two-sense synthetic world (beyond the paper)."""
    from supramodal.experiments.common import progress_to_stderr
    from supramodal.experiments.fusion import fusion_table, run_fusion
    from supramodal.experiments.report import write_figure

    sets = args.sets if args.sets is not None else (2 if args.quick else 5)
    if sets < 1:
        raise CliError(f"--sets must be >= 1 for experiment fusion, got {sets}")
    result = run_fusion(sets, args.quick, args.epochs, args.seed, None if args.quiet else progress_to_stderr)
    written = write_figure("fusion", result, Path(args.out))
    print(json.dumps(result) if args.json else fusion_table(result) + "\nwrote " + ", ".join(str(p) for p in written))
    return 0


def _source_value(text: str) -> tuple[str, str]:
    """A ``SOURCE=VALUE`` option of ``import-recording``."""
    name, eq, value = text.partition("=")
    if not eq or not name or not value:
        raise argparse.ArgumentTypeError(f"expected SOURCE=VALUE (e.g. whiskers=whiskers.wav); got {text!r}")
    return name, value


def _cmd_import_recording(args) -> int:
    from supramodal.node.workflows.import_recording import import_recording, sources_from_options

    sources = sources_from_options(args.wav, args.times, args.xdf_stream, args.bank, args.model)
    scene = import_recording(args.out, args.name, sources, xdf=args.xdf, markers=args.markers, fusion=args.fusion,
                             overwrite=args.force)
    print(f"wrote {scene} and the sessions of {', '.join(s.name for s in sources)} beside it\n"
          f"next: supramodal run {scene} --speed max")
    return 0


def _cmd_devices(args) -> int:
    from supramodal.drivers.devices import format_devices

    print(format_devices())
    return 0


def _bank(text: str):
    """``--bank``: a paper bank by name, or a bank file, read and checked at parse time."""
    from supramodal.bankfile import load_bank
    from supramodal.banks import bank_by_name

    try:
        return bank_by_name(text) if text in ("whisker", "cochlea") else load_bank(text)
    except SupramodalError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _mapping(text: str):
    return int(text) if text.isdigit() else text


def _progress(args):
    return None if getattr(args, "quiet", False) else (lambda m: print(f"supramodal: {m}", file=sys.stderr, flush=True))


def _cmd_train(args) -> int:
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.node.workflows.training import calibration_line, train_from_manifest
    if args.stream is not None and not args.fusion:
        return _train_stream(args)
    if args.scene or args.fusion:
        return _train_fusion(args)
    if args.manifest is None or args.bank is None or args.out is None:
        raise CliError("train needs --bank, --manifest and --out (or, for a fusion of two senses, --fusion and "
                       "--scene)")
    check_new_file(args.out, args.force, "the model file")      # before the training, not after
    bank = args.bank
    if args.cv:
        from supramodal.node.workflows.reports import plots_missing_notice, write_confusion, write_reliability
        from supramodal.node.workflows.training import cross_validate_manifest, format_cross_validation

        base = args.out.with_name(args.out.stem + "-cv")
        reliability = args.out.with_name(args.out.stem + "-cv-reliability")
        for b in (base, reliability):
            for suffix in (".csv", ".png"):
                check_new_file(b.with_name(b.name + suffix), args.force, "the cross-validation file")
        cv = cross_validate_manifest(args.manifest, bank, tuple(args.features), args.window, args.cv,
                                     epochs=args.epochs, seed=args.seed, mapping=args.mapping, progress=_progress(args))
        print(format_cross_validation(cv))
        files = write_confusion(cv["labels"], cv["confusion"], base,
                                f"{args.cv}-fold grouped cross-validation: window accuracy "
                                f"{cv['window_accuracy']['mean']:.3f} +- {cv['window_accuracy']['sd']:.3f}")
        files += write_reliability(cv["calibration"], reliability,
                                   f"{args.cv}-fold grouped cross-validation: test folds' decisions")
        print("wrote " + ", ".join(str(p) for p in files))
        _say_plots_missing(plots_missing_notice())
    model = train_from_manifest(args.manifest, bank, tuple(args.features), args.window, epochs=args.epochs,
                                seed=args.seed, mapping=args.mapping, progress=_progress(args))
    path = model.save(args.out)
    print(f"wrote {path}: {model.bank.kind} bank, features {list(model.features)}, classes {list(model.classes)}, "
          f"{model.training['windows']} training windows, final MSE {model.training['final_mse']:.4g}")
    print("posteriors: " + calibration_line(None if model.calibration is None else model.calibration.fitted_on))
    return 0


def _train_stream(args) -> int:
    """``train --scene REC.toml ... --stream NAME --out MODEL``: a sense model straight from recorded graphs."""
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.node.workflows.training import calibration_line, train_from_scenes

    if not args.scene or args.out is None:
        raise CliError("--stream trains one stream's model from recorded graphs: give one --scene per recording "
                       "(the DIR/NAME.toml `supramodal record` wrote) and --out MODEL")
    if args.manifest is not None or args.bank is not None or args.cv or args.models or args.live or args.write_scene:
        raise CliError("with --scene and --stream, the recordings' scene says the bank, features and window: leave "
                       "out --manifest, --bank, --cv, --model, --live and --write-scene")
    check_new_file(args.out, args.force, "the model file")
    model = train_from_scenes(args.scene, args.stream, epochs=args.epochs, seed=args.seed, progress=_progress(args))
    path = model.save(args.out)
    print(f"wrote {path}: stream {args.stream}, {model.bank.kind} bank, features {list(model.features)}, classes "
          f"{list(model.classes)}, {model.training['windows']} training windows of {len(args.scene)} recording(s), "
          f"final MSE {model.training['final_mse']:.4g}")
    print("posteriors: " + calibration_line(None if model.calibration is None else model.calibration.fitted_on))
    print("train the fusion on other recordings than these (supramodal train --fusion ... --model "
          f"{args.stream}={path}): its sense posteriors are then those of this model on recordings it never saw")
    return 0


def _stream_models(pairs) -> dict:
    """``--model STREAM=FILE`` options as ``{stream: path}``."""
    out = {}
    for text in pairs or []:
        name, sep, path = text.partition("=")
        if not sep or not name or not path:
            raise CliError(f"--model {text!r}: write STREAM=FILE, e.g. --model whiskers=models/whiskers.npz")
        if name in out:
            raise CliError(f"--model names stream {name!r} twice")
        out[name] = Path(path)
    if out and len(out) != 2:
        raise CliError(f"--model names {len(out)} stream(s); a fusion takes two: give --model for each")
    return out


def _say_plots_missing(notice: str | None) -> None:
    if notice:
        print(f"supramodal: {notice}", file=sys.stderr)


def _train_fusion(args) -> int:
    """``train --fusion early|late --scene S.toml ...``: a fusion learned on recorded two-sense sessions,
    from windows held out of every network that scored them (node/workflows/fused_training.py)."""
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.node.workflows.fused_training import train_fused, write_fused_scene

    if not (args.scene and args.fusion):
        raise CliError("a fusion is trained with --fusion early|late and one --scene per recording (the scene "
                       "`supramodal record` writes for a graph)")
    if args.manifest is not None or args.cv:
        raise CliError("--manifest and --cv train one sense; a fusion is trained on --scene recordings")
    if args.fusion == "early":
        if args.out is None:
            raise CliError("--fusion early needs --out, the model file to write")
        check_new_file(args.out, args.force, "the model file")
    elif args.out is not None:
        raise CliError("--fusion late learns one number, printed for [fusion] weight; it writes no file: "
                       "leave out --out")
    if (args.live is None) != (args.write_scene is None):
        raise CliError("--live SCENE.toml (the scene the recordings were made with) and --write-scene FILE.toml (the "
                       "scene to write, running it with the models and this fusion) go together")
    if args.write_scene is not None:
        check_new_file(args.write_scene, args.force, "the scene file")
    models = _stream_models(args.models)
    result, info = train_fused(args.scene, args.fusion, epochs=args.epochs, seed=args.seed, progress=_progress(args),
                               models=models)
    a, b = info["streams"]
    fused = "late" if args.fusion == "late" else "early"
    print(f"sense posteriors: {info['posteriors']['source']} ({info['posteriors']['why']})")
    print(f"held-out windows ({info['pairs']} pairs of {info['contacts']} contacts, {info['folds']} folds by "
          f"{info['folds_by']}; each scored by networks that never trained on its fold):")
    print(f"  {'':<12}{'accuracy':>10}{'log loss':>10}")
    for name in (a, b, fused):
        h = info["held_out"][name]
        print(f"  {name:<12}{h['accuracy']:>10.3f}{h['log_loss']:>10.3f}")
    if args.fusion == "late":
        weight, sharpness = result
        keys = f"weight = {weight:.2f}, sharpness = {sharpness:.4g}, correlation = {info['correlation']:.3g}"
        print(f"learned late-fusion weight {weight:.2f} of {a} (and {1 - weight:.2f} of {b}) and sharpness "
              f"{sharpness:.4g} on the out-of-fold windows of {info['pairs']} labelled pairs (the late row: each "
              f"fold fused with a weight learned without it): set [fusion] {keys}")
        _write_run_scene(args, write_fused_scene, (a, b), models,
                         {"method": "late", "weight": round(weight, 4), "sharpness": float(f"{sharpness:.4g}"),
                          "correlation": float(f"{info['correlation']:.3g}")})
        return 0
    path = result.save(args.out)
    print(f"wrote {path}: early fusion of {a} and {b}, classes {info['classes']}, {info['pairs']} pairs of windows, "
          f"calibrated on its out-of-fold pairs (the early row); use it with [fusion] method = \"early\", "
          f"model = \"{path.resolve()}\" (a relative path is taken from the scene's folder)")
    _write_run_scene(args, write_fused_scene, (a, b), models, {"method": "early", "model": str(path.resolve())})
    return 0


def _write_run_scene(args, write, streams, models: dict, fusion: dict) -> None:
    """``--write-scene``: the live scene with the sense models and the fusion learned, to run at once."""
    if args.write_scene is None:
        return
    path = write(args.live, streams, fusion, models, args.write_scene)
    print(f"wrote {path}: {args.live} with the sense models and this fusion; run it: supramodal run {path}")


def _cmd_fit(args) -> int:
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.node.workflows.fit_search import fit_search, format_search, write_search

    if args.out.is_dir():
        for name in ("fit.csv", "fit-curve.csv", "fit-curve.png", "bank.json"):
            check_new_file(args.out / name, args.force, "the fit file")
    result = fit_search(args.manifest, k=args.cv, seed=args.seed, quick=args.quick, trials=args.trials,
                        timeout=args.timeout, batch=args.batch, max_window=args.max_window,
                        max_channels=args.max_channels, target=args.target, contact=args.contact,
                        max_epochs=args.epochs, jobs=args.jobs, cluster=args.cluster, mapping=args.mapping,
                        cache_dir=args.out / "cache", cache_memory=args.cache_memory * 2**20, progress=_progress(args))
    print(format_search(result))
    files = write_search(result, args.out)
    b = result["best"]
    print(f"wrote {', '.join(str(p) for p in files)}\nnext: supramodal train --bank {args.out / 'bank.json'} "
          f"--window {b['window']:g} --features {b['features'].replace('+', ' ')} --epochs {b['epochs']} "
          f"--manifest {args.manifest} --out MODEL")
    return 0


def _cmd_evaluate(args) -> int:
    from supramodal.model import TextureModel
    from supramodal.node.workflows.training import evaluate_manifest, format_evaluation

    if args.scene:
        return _evaluate_fusion(args)
    if args.model is None or args.manifest is None:
        raise CliError("evaluate needs a model file and --manifest (or, for two senses fused, --scene)")
    if args.fused_model is not None:
        raise CliError("--fused-model scores a fusion: give --scene recordings")
    if args.contact_windows is not None:
        raise CliError("--contact-windows cuts the contacts of recorded graphs: give --scene recordings (a "
                       "manifest's recordings are pooled in runs of 1, 2, 5 and 10 windows, and whole)")
    model = TextureModel.load(args.model)
    if args.cv:
        return _evaluate_cv(model, args)
    if args.seed is not None:
        raise CliError("--seed applies to --cv only (scoring the model as it is draws nothing at random)")
    if args.out is not None and args.out.is_dir():
        from supramodal.node.runtime.outputs import check_new_file
        from supramodal.node.workflows.reports import EVALUATION_FILES

        for name in EVALUATION_FILES:
            check_new_file(args.out / name, args.force, "the evaluation file")
    result = evaluate_manifest(model, args.manifest, mapping=args.mapping, progress=_progress(args))
    result["calibration"]["model_version"] = _model_file_version(args.model)
    print(json.dumps(result) if args.json else format_evaluation(result))
    if args.out is not None:
        from supramodal.node.workflows.reports import plots_missing_notice, write_evaluation

        files = write_evaluation(result, args.out)
        print("wrote " + ", ".join(str(p) for p in files), file=sys.stderr)
        _say_plots_missing(plots_missing_notice())
    return 0


def _model_file_version(path) -> int | None:
    """The format version a model file says it is (an uncalibrated model of version 1 is said so)."""
    from supramodal.model import read_model_archive

    header, _ = read_model_archive(path)
    return header.get("version") if isinstance(header, dict) else None


def _evaluate_fusion(args) -> int:
    """``evaluate --scene S.toml ...``: each stream and the fusion scored on recorded two-sense sessions."""
    from supramodal.node.workflows.fused_training import evaluate_fused, format_fused_evaluation

    if args.model is not None or args.manifest is not None or args.cv:
        raise CliError("with --scene, the scenes name the models: leave out the model file, --manifest and --cv "
                       "(give --fused-model to score another early-fusion network)")
    fused = None if args.fused_model is None else Path(args.fused_model).resolve()   # from here, not the scenes'
    if args.out is not None and args.out.is_dir():
        from supramodal.node.runtime.events import FUSED_STREAM
        from supramodal.node.runtime.outputs import check_new_file
        from supramodal.node.scene.schema import load_scene
        from supramodal.node.workflows.reports import fused_evaluation_files

        streams = [spec.name for path in args.scene for spec in load_scene(path).streams] + [FUSED_STREAM]
        for name in fused_evaluation_files(dict.fromkeys(streams)):
            check_new_file(args.out / name, args.force, "the evaluation file")
    result = evaluate_fused(args.scene, fused, progress=_progress(args), contact_windows=args.contact_windows)
    print(json.dumps(result) if args.json else format_fused_evaluation(result))
    if args.out is not None:
        from supramodal.node.workflows.reports import write_fused_evaluation

        files = write_fused_evaluation(result, args.out)
        print("wrote " + ", ".join(str(p) for p in files), file=sys.stderr)
    return 0


def _evaluate_cv(model, args) -> int:
    """``evaluate --cv K``: the model's configuration re-trained and scored fold by fold."""
    from supramodal.node.workflows.training import cross_validate_model, format_cross_validation

    if args.seed is not None and args.seed < 0:
        raise CliError(f"--seed must be >= 0, got {args.seed}")
    bases = None if args.out is None else (args.out / "cv-confusion", args.out / "cv-reliability")
    if bases is not None and args.out.is_dir():
        from supramodal.node.runtime.outputs import check_new_file

        for base in bases:
            for suffix in (".csv", ".png"):
                check_new_file(base.with_name(base.name + suffix), args.force, "the cross-validation file")
    cv = cross_validate_model(model, args.manifest, args.cv, seed=args.seed, mapping=args.mapping,
                              progress=_progress(args))
    print(json.dumps(cv) if args.json else format_cross_validation(cv))
    if bases is not None:
        from supramodal.node.workflows.reports import plots_missing_notice, write_confusion, write_reliability

        args.out.mkdir(parents=True, exist_ok=True)
        what = f"{args.cv}-fold grouped cross-validation of {Path(args.model).name}'s configuration"
        files = write_confusion(cv["labels"], cv["confusion"], bases[0],
                                f"{what}: window accuracy {cv['window_accuracy']['mean']:.3f} +- "
                                f"{cv['window_accuracy']['sd']:.3f}")
        files += write_reliability(cv["calibration"], bases[1], f"{what}: test folds' decisions")
        print("wrote " + ", ".join(str(p) for p in files), file=sys.stderr)
        _say_plots_missing(plots_missing_notice())
    return 0


def _cmd_bench(args) -> int:
    import os
    import subprocess

    from supramodal.benchmarks.filterbank import PINNED_THREADS

    # A child process, so that BLAS and OpenMP read the one-thread settings before numpy loads.
    cmd = ([sys.executable, "-m", "supramodal.benchmarks.filterbank", "--out", args.out]
           + ["--quick"] * args.quick + ["--json"] * args.json)
    return subprocess.run(cmd, env={**os.environ, **PINNED_THREADS}).returncode


def build_parser() -> argparse.ArgumentParser:
    from supramodal.features import DEFAULT_WINDOW, FEATURE_TABLE
    from supramodal.mlp import DEFAULT_EPOCHS

    parser = argparse.ArgumentParser(prog="supramodal", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"supramodal {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the traceback of every error, not one line")
    # --debug is also accepted after the command; SUPPRESS keeps the top-level value when it is not.
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    sub = parser.add_subparsers(dest="command", required=True)

    def add_parser(name, **kwargs):
        return sub.add_parser(name, parents=[common], **kwargs)

    p = add_parser("run", help="run the node on a scene (default: the embedded whisker replay scene)")
    p.add_argument("--force", action="store_true", help="replace existing sink files (default: refuse)")
    p.add_argument("scene", nargs="?", help="scene TOML file (default: the embedded default scene)")
    p.add_argument("--speed", type=_speed,
                   help="replay speed: 1 = real time (default: the scene's), a factor, or 'max'")
    p.add_argument("--json", action="store_true", help="JSON Lines on stdout instead of the scene's sinks")
    p.add_argument("--seconds", type=_stream_seconds,
                   help="stop after this much stream; inf: until it ends or Ctrl-C (the default)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--view", nargs="?", const=0, type=int, metavar="PORT",
                   help="also serve a page that shows the run live on 127.0.0.1:PORT (default 0: any free port; the "
                        "URL and the run's token are printed at start; docs/view.md)")
    p.add_argument("--print-scene", action="store_true",
                   help="print the scene (the default one if none is given) as TOML, every key filled in, and exit: "
                        "a starting point to edit, e.g. supramodal run --print-scene > my.toml")
    p.set_defaults(func=_cmd_run)

    p = add_parser("train", help="train a model from labelled recordings, or a fusion of two senses")
    p.add_argument("--force", action="store_true", help="replace an existing model file at --out (default: refuse)")
    p.add_argument("--bank", type=_bank, metavar="whisker|cochlea|FILE",
                   help="the filterbank: whisker (5 kHz), cochlea (44.1 kHz), or a bank file (supramodal-bank JSON: "
                        "any ERB-spaced band at any rate, or explicit channels; docs/node.md); "
                        "required with --manifest")
    p.add_argument("--manifest", help="CSV with columns path,label[,start,end]; paths relative to it")
    p.add_argument("--out", type=_output_file,
                   help="model file to write, at exactly this path (an .npz archive; e.g. model.npz)")
    p.add_argument("--fusion", choices=["early", "late"],
                   help="instead of one sense: learn the fusion of a recorded graph's two streams on its labelled "
                        "pairs of windows (--scene): early, the supramodal network, calibrated (written to --out); "
                        "late, the weight of the first stream, the sharpness and the pooling's correlation "
                        "(printed), learned on out-of-fold "
                        "windows of copies of the streams' models, never on windows a network trained on; both print "
                        "each sense's and the fusion's held-out score (default: one sense, from --manifest)")
    p.add_argument("--scene", action="append", metavar="NAME.toml",
                   help="with --fusion or --stream: a recording's replay scene (supramodal record of a graph writes "
                        "it); give one per recording (default: none)")
    p.add_argument("--stream", metavar="NAME",
                   help="with --scene: train this stream's model from the recordings' labelled sessions, with the "
                        "scene's bank, features and window, calibrated on folds grouped by recording (instead of "
                        "--manifest and --bank)")
    p.add_argument("--model", dest="models", action="append", metavar="STREAM=FILE",
                   help="with --fusion: the sense model a stream decides with, for each of the two fused streams "
                        "(default: the recordings' own); models that `train --stream` made on other recordings give "
                        "the fusion their own posteriors, else it learns from out-of-fold copies (it says which)")
    p.add_argument("--live", metavar="SCENE.toml",
                   help="with --fusion and --write-scene: the scene the recordings were made with")
    p.add_argument("--write-scene", type=_output_file, metavar="FILE.toml",
                   help="with --fusion and --live: write the live scene with the --model files and the fusion "
                        "learned, ready for supramodal run (default: none)")
    p.add_argument("--features", nargs="+", default=["Af"], choices=list(FEATURE_TABLE),
                   help="; ".join(f"{f.name}: {f.description}" for f in FEATURE_TABLE.values()) + " (default Af)")
    p.add_argument("--window", type=_positive_seconds, default=DEFAULT_WINDOW,
                   help=f"window, seconds (default {DEFAULT_WINDOW})")
    p.add_argument("--epochs", type=_count(1), default=DEFAULT_EPOCHS,
                   help=f"iRPROP- epochs (default {DEFAULT_EPOCHS})")
    p.add_argument("--seed", type=_count(0), default=0,
                   help="seed of the network's initial weights and of the cross-validation folds (default 0)")
    p.add_argument("--cv", type=_count(2), metavar="K",
                   help="first report grouped K-fold cross-validation (folds by recording: mean and sd, recall, "
                        "log loss, Brier score and ECE per window and per recording; confusion as MODEL-cv.csv/.png, "
                        "reliability diagram as MODEL-cv-reliability.csv/.png), then train the final model on "
                        "everything (default: no cross-validation)")
    p.add_argument("--mapping", type=_mapping, default="auto",
                   help="recording channels to filters: auto (one channel to all, or one each), mono, per-channel, "
                        "mean, or a channel index (default auto)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr (warnings are still shown)")
    p.set_defaults(func=_cmd_train)

    p = add_parser("fit", help="fit a bank, window, features and network to your recordings under your latency and "
                               "CPU budgets (a joint search by grouped cross-validation; the fit extra)")
    p.add_argument("manifest", help="CSV with columns path,label[,start,end]; paths relative to it")
    p.add_argument("--out", type=_output_folder, default="out/fit",
                   help="folder for fit.csv (every trial), fit-curve.csv/.png (best accuracy per window), bank.json "
                        "(the best bank) and the feature cache (default ./out/fit)")
    p.add_argument("--cv", type=_count(2), default=5, metavar="K", help="folds, grouped by recording (default 5)")
    p.add_argument("--trials", type=_count(1), default=None,
                   help="settings to try (default 60, --quick 16)")
    p.add_argument("--timeout", type=_positive_seconds, default=None, metavar="S",
                   help="time budget: no new round of trials after S seconds (the first always runs; default: none)")
    p.add_argument("--max-window", type=_positive_seconds, default=None, metavar="S",
                   help="latency budget: no window longer than S seconds (default: none)")
    p.add_argument("--max-channels", type=_count(1), default=None, metavar="N",
                   help="CPU budget: no bank with more than N channels (default: none)")
    p.add_argument("--target", choices=("window", "recording", "contact"), default="window",
                   help="the accuracy to maximise: per window, per recording (all its windows pooled) or per "
                        "contact (--contact seconds of windows pooled) (default window)")
    p.add_argument("--contact", type=_positive_seconds, default=0.5, metavar="S",
                   help="seconds of a contact for --target contact (default 0.5)")
    p.add_argument("--epochs", type=_count(1), default=None,
                   help="most iRPROP- epochs a trial may train (default: the search's own list)")
    p.add_argument("--seed", type=_count(0), default=0,
                   help="seed of the sampler, the folds and the networks (default 0)")
    p.add_argument("--batch", type=_count(1), default=4,
                   help="trials asked at once; the result depends on the seed and this, not on --jobs or --cluster "
                        "(default 4)")
    p.add_argument("--quick", action="store_true",
                   help="fewer values per parameter, 16 trials, each fold's network trained on at most 4000 windows")
    p.add_argument("--jobs", type=_count(1), default=1,
                   help="local processes scoring folds (a local Dask cluster when more than 1; default 1)")
    p.add_argument("--cluster", default=None, metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://HOST:PORT) whose workers score the folds instead")
    p.add_argument("--cache-memory", type=_count(16), default=512, metavar="MB",
                   help="feature windows each process keeps in memory; more go to --out/cache (default 512)")
    p.add_argument("--mapping", type=_mapping, default="auto",
                   help="recording channels to filters: auto (one channel to all, or one each), mono, per-channel, "
                        "mean, or a channel index (default auto)")
    p.add_argument("--force", action="store_true", help="replace earlier fit files in --out (default: refuse)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr (warnings are still shown)")
    p.set_defaults(func=_cmd_fit)

    p = add_parser("evaluate", help="accuracy and confusion of a model on labelled recordings, or of a fusion")
    p.add_argument("model", nargs="?", help="model file (.npz); not with --scene")
    p.add_argument("--manifest", help="CSV with columns path,label[,start,end]; paths relative to it")
    p.add_argument("--scene", action="append", metavar="NAME.toml",
                   help="instead of a model and a manifest: a recorded graph's replay scene, run at max speed; each "
                        "stream and the fusion scored per window and per contact; give one per recording "
                        "(default: none)")
    p.add_argument("--fused-model", metavar="FILE",
                   help="with --scene: score this early-fusion network instead of the scenes' own fusion "
                        "(default: the scenes' [fusion])")
    p.add_argument("--contact-windows", type=_count(1), metavar="N",
                   help="with --scene: a contact is N consecutive windows of one texture, each run of one texture "
                        "cut from its start (a shorter rest left out) (default: each whole run of one texture is "
                        "one contact)")
    p.add_argument("--mapping", type=_mapping, default="auto",
                   help="recording channels to filters: auto (one channel to all, or one each), mono, per-channel, "
                        "mean, or a channel index (default auto)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object instead of a table")
    p.add_argument("--out", type=_output_folder, metavar="DIR",
                   help="also write the confusion, accuracy against windows pooled, the channels' importance and "
                        "the reliability diagram (reliability.csv/.png) as CSV and PNG into DIR (PNGs need the "
                        "plots extra; with --scene: each stream's and the fusion's accuracy and confusion; default: "
                        "print only)")
    p.add_argument("--cv", type=_count(2), metavar="K",
                   help="instead of scoring the model itself, re-train its configuration (bank, features, window, "
                        "peaks, hidden units, epochs) on K-1 folds of the manifest and score it on the K-th, folds "
                        "grouped by manifest line: how well a model like it does on recordings it never saw; with "
                        "--out, writes cv-confusion.csv/.png and cv-reliability.csv/.png (default: no "
                        "cross-validation)")
    p.add_argument("--seed", type=int, metavar="S",
                   help="with --cv: seed of the folds and of the training (default: the model's own seed)")
    p.add_argument("--force", action="store_true", help="replace earlier evaluation files in --out (default: refuse)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr (warnings are still shown)")
    p.set_defaults(func=_cmd_evaluate)

    p = add_parser("record", help="record a scene's raw driver blocks as a session (WAV + JSON)")
    p.add_argument("--force", action="store_true", help="replace an existing session of that name (default: refuse)")
    p.add_argument("scene", help="scene TOML file")
    p.add_argument("--out", required=True, type=_output_folder, help="folder for the session (created if missing)")
    p.add_argument("--name", type=_session_name,
                   help="session name: letters, digits, '-' or '_' (default: session-DATE-TIME)")
    p.add_argument("--label", type=_label_name,
                   help="label of the whole recording (of every source of a graph): letters, digits, '-' or '_'")
    p.add_argument("--marks", action="store_true",
                   help="read labels from stdin while recording: a line starts that label now, an empty line ends "
                        "it; in a graph, on the node's common time, mapped to each source through its clock")
    p.add_argument("--replace", action="store_true",
                   help="with --label or --marks: label the recording with them instead of the labels a source's "
                        "driver gives (synth, twosense, a replayed session; default: refused)")
    p.add_argument("--seconds", type=_stream_seconds,
                   help="stop after this much stream; inf: until the stream ends or Ctrl-C (the default)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr (warnings are still shown)")
    p.add_argument("--view", nargs="?", const=0, type=int, metavar="PORT",
                   help="also serve the live page on 127.0.0.1:PORT (default 0: any free port); with --marks its label "
                        "buttons mark too, given the run's token printed at start (docs/view.md)")
    p.set_defaults(func=_cmd_record)

    p = add_parser("view", help="play a recording back into the view's page (pause, speed): docs/view.md")
    p.add_argument("recording", metavar="REC.toml|SESSION",
                   help="the replay scene `supramodal record` wrote for a graph, or a session (NAME.wav + NAME.json)")
    p.add_argument("--port", type=int, default=0, help="the page's port on 127.0.0.1 (default 0: any free one)")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed at the start (default 1: as recorded)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr (the URL is still printed)")
    p.set_defaults(func=_cmd_view)

    p = add_parser("label", help="label a recorded graph after the fact from spans on common time (CSV)")
    p.add_argument("recording", metavar="REC.toml", help="the replay scene `supramodal record` wrote for a graph")
    p.add_argument("spans", metavar="SPANS.csv",
                   help="CSV with the header start,end,label: seconds of the recording's common time (as its replay "
                        "prints window times), in order, not overlapping")
    p.add_argument("--replace", action="store_true",
                   help="replace the labels the sessions hold (default: refuse a session that has any)")
    p.set_defaults(func=_cmd_label)

    from supramodal.drivers.mock_whisker import add_arguments as mock_arguments

    p = add_parser("import-recording", help="a replayable graph recording (sessions and their replay scene) from "
                                            "WAV files and their timestamps (CSV), or from XDF streams")
    p.add_argument("--out", required=True, type=_output_folder, metavar="DIR",
                   help="folder for the recording (created if missing)")
    p.add_argument("--name", type=_session_name, default="imported",
                   help="the recording's name: NAME.SOURCE.wav/.json per source and NAME.toml (default: imported)")
    p.add_argument("--wav", type=_source_value, action="append", default=[], metavar="SOURCE=FILE.wav",
                   help="a source's samples; give one per source (default: none)")
    p.add_argument("--times", type=_source_value, action="append", default=[], metavar="SOURCE=TIMES.csv",
                   help="its timestamps, seconds on the clock every source shares: a CSV with the header "
                        "'end_frame,seconds' (a row per block: frames delivered by its end, when it was complete) "
                        "or 'seconds' (a row per frame); one per --wav (default: none)")
    p.add_argument("--xdf", metavar="FILE.xdf", help="instead of WAV files: an XDF file (the lsl extra)")
    p.add_argument("--xdf-stream", type=_source_value, action="append", default=[], metavar="SOURCE=STREAM",
                   help="with --xdf: a source read from the file's stream of that name; one per source (default: "
                        "none)")
    p.add_argument("--markers", metavar="STREAM",
                   help="with --xdf: a marker stream whose strings label every source (default: no labels)")
    p.add_argument("--bank", type=_source_value, action="append", default=[], metavar="SOURCE=BANK",
                   help="each source's stream bank: whisker, cochlea or a bank file; one per source (default: none, "
                        "so give one for every source)")
    p.add_argument("--model", type=_source_value, action="append", default=[], metavar="SOURCE=MODEL.npz",
                   help="a model for the source's stream, copied beside the sessions (default: none, the stream "
                        "gives feature windows)")
    p.add_argument("--fusion", action="store_true",
                   help="fuse the two streams' decisions (late fusion; learn its weight with train --fusion late); "
                        "needs two sources with models (default: no fusion)")
    p.add_argument("--force", action="store_true", help="replace an earlier import of that name (default: refuse)")
    p.set_defaults(func=_cmd_import_recording)

    p = add_parser("mock-whisker", help="a mock whisker-array board streaming frames on a pty, with fault injection")
    mock_arguments(p)
    p.set_defaults(func=_cmd_mock_whisker)

    p = add_parser("devices", help="list audio inputs and serial ports")
    p.set_defaults(func=_cmd_devices)

    p = add_parser("experiment", help="reproduce a figure of the paper (or all of them)")
    p.add_argument("figure", choices=["fig1", "fig3", "fig4", "fig5", "fig6", "all", "fusion", "calibration"],
                   help="which figure of the paper; fusion: the two senses fused on the two-sense synthetic world "
                        "(beyond the paper; not in all); calibration: whether the confidence means what it says "
                        "(calibration, fusion, unknown textures, anytime decisions; issue 23; not in all)")
    p.add_argument("--quick", action="store_true", help="short textures and small grids: seconds, not minutes")
    p.add_argument("--jobs", type=_count(1), help="worker processes (default: all cores); results do not depend on it")
    p.add_argument("--seed", type=_count(0), default=0,
                   help="experiment seed: each run's network seed derives from it and the run; also the first "
                        "random texture set's seed")
    p.add_argument("--epochs", type=_count(1), default=DEFAULT_EPOCHS,
                   help=f"iRPROP- epochs (default {DEFAULT_EPOCHS})")
    p.add_argument("--bank", choices=["whisker", "cochlea"], help="fig3: one bank (default: both)")
    p.add_argument("--textures", metavar="FILE", help="fig3: texture-set JSON file (default: the reference sets)")
    p.add_argument("--sets", type=_count(0), help="fig3: N random texture sets instead of the reference set; "
                                            "all: N random sets per bank besides it (default 5, 0 with --quick); "
                                            "fusion: N random two-sense sets (default 5, 2 with --quick); "
                                            "calibration: N random sets per bank and N two-sense sets (default 5, "
                                            "1 with --quick)")
    p.add_argument("--out", default="out", type=_output_folder, help="directory for CSV and PNG (default ./out)")
    p.add_argument("--json", action="store_true", help="print the figure's data as one JSON object instead of a table")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=_cmd_experiment)

    p = add_parser("bench", help="filterbank error against run time, drift, the whole node (report in --out)")
    p.add_argument("--quick", action="store_true",
                   help="short signals and streams (well under a minute; not for quoting)")
    p.add_argument("--out", default="out/bench", type=_output_folder,
                   help="directory for the report (default ./out/bench)")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")
    p.set_defaults(func=_cmd_bench)

    p = add_parser("synth", help="write a texture set as WAV files")
    p.add_argument("--force", action="store_true", help="replace existing texture files in --out (default: refuse)")
    p.add_argument("--bank", choices=["whisker", "cochlea"], default="whisker",
                   help="whose reference textures (default whisker)")
    p.add_argument("--textures", metavar="FILE", help="texture-set JSON file (default: the bank's reference set)")
    p.add_argument("--duration", type=_positive_seconds, help="seconds per texture (default: the set's)")
    p.add_argument("--out", default="out/textures", type=_output_folder, help="directory (default ./out/textures)")
    p.set_defaults(func=_cmd_synth)
    return parser


def _is_user_error(exc: BaseException) -> bool:
    """Whether ``exc`` is the user's to fix (one line) rather than a bug (a traceback).

    Every error the project raises on purpose (:class:`SupramodalError`), except a node
    thread's failure whose cause is itself a bug; and an ``OSError`` that names a file
    (a path given on the command line or in a scene: missing, unreadable, not writable).
    """
    graph = sys.modules.get("supramodal.node.runtime.graph")
    if graph is not None and isinstance(exc, graph.NodeError) and exc.__cause__ is not None:
        return _is_user_error(exc.__cause__)
    if isinstance(exc, SupramodalError):
        return True
    return isinstance(exc, OSError) and exc.filename is not None


def _reader_left(exc: BaseException | None) -> bool:
    """Whether ``exc`` means that the reader of stdout went away (``| head``), directly or in a node thread."""
    while exc is not None:
        if isinstance(exc, BrokenPipeError):
            return True
        exc = exc.__cause__
    return False


def _show_warning(message, category, filename, lineno, file=None, line=None, _default=warnings.showwarning):
    """The package's warnings as one line each, like its errors (``--quiet`` hides progress, never these)."""
    if issubclass(category, SupramodalWarning):
        print(f"supramodal: warning: {message}", file=sys.stderr, flush=True)
    else:
        _default(message, category, filename, lineno, file, line)


def main(argv=None) -> int:
    """Run the command line; returns the exit status (see the module docstring).

    The SIGINT and SIGTERM handlers a command installs (to stop a node cleanly) are its own: the
    caller's are put back when it returns, so that a program or a test suite that calls ``main``
    can still be interrupted afterwards.
    """
    args = build_parser().parse_args(argv)
    shown, warnings.showwarning = warnings.showwarning, _show_warning
    handlers = {}
    if threading.current_thread() is threading.main_thread():      # signals are the main thread's
        handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run(args)
    finally:
        warnings.showwarning = shown
        for sig, handler in handlers.items():
            if handler is not None:                                  # None: set outside Python
                signal.signal(sig, handler)


def _run(args) -> int:
    try:
        return args.func(args)
    except StartupInterrupted as exc:
        print(f"supramodal: interrupted by {exc} during start-up (building the scene, training its model); "
              "nothing was processed", file=sys.stderr)
        return 128 + exc.signum
    except KeyboardInterrupt:
        print("supramodal: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT
    except Exception as exc:
        if _reader_left(exc):
            # Python docs' recipe: point stdout at /dev/null so that the interpreter's last
            # flush does not fail again; then stop quietly (exit status: module docstring).
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 0
        if _is_user_error(exc):
            if args.debug:
                traceback.print_exception(exc)
            print(f"supramodal: error: {exc}", file=sys.stderr)
            return EXIT_USER_ERROR
        traceback.print_exception(exc)
        print(f"supramodal: internal error ({type(exc).__name__}): this is a bug in supramodal; please report it "
              "with the traceback above and the command that gave it", file=sys.stderr)
        return EXIT_BUG


if __name__ == "__main__":
    sys.exit(main())
