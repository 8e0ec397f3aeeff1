"""The ``supramodal train`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse
from pathlib import Path

from supramodal.node.cli.arguments import (
    AUGMENT_GAINS_FORM,
    augment_gains,
    bank,
    cores,
    count,
    jobs,
    mapping,
    output_file,
    positive_seconds,
    progress,
    say_plots_missing,
    seed,
    seeded_augment,
)
from supramodal.node.cli.errors import CliError
from supramodal.node.cli.signals import interrupt_until_running

#: What ``supramodal train`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "train a model from labelled recordings, or a fusion of two senses"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal train --bank B --manifest FILE.csv --out MODEL [--cv K]",
     "train a calibrated model from labelled recordings (`path,label[,start,end]`); `--cv K` reports grouped "
     "cross-validation first ([docs/own-sensor.md](docs/own-sensor.md), calibration: [docs/model.md](docs/model.md))"),
    ("supramodal train --scene REC.toml ... --stream NAME --out MODEL",
     "train one stream's model from recorded graphs (`supramodal record`), calibrated on folds grouped by recording "
     "([docs/own-robot.md](docs/own-robot.md))"),
    ("supramodal train --fusion early|late --scene REC.toml ... [--model STREAM=FILE]",
     "learn the fusion of two senses on recorded graphs, on windows the senses never trained on; prints each "
     "sense's and the fusion's held-out score and refuses a fusion worse than a sense"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``train`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    from supramodal.features import DEFAULT_WINDOW, FEATURE_TABLE
    from supramodal.mlp import DEFAULT_EPOCHS

    p = subparsers.add_parser("train", parents=[common], help=SUMMARY)
    p.add_argument("--force", action="store_true", help="replace an existing model file at --out (default: refuse)")
    p.add_argument("--bank", type=bank, metavar="whisker|cochlea|FILE",
                   help="the filterbank: whisker (5 kHz), cochlea (44.1 kHz), or a bank file (supramodal-bank JSON: "
                        "any ERB-spaced band at any rate, or explicit channels; docs/node.md); "
                        "required with --manifest")
    p.add_argument("--manifest", help="CSV with columns path,label[,start,end]; paths relative to it")
    p.add_argument("--out", type=output_file,
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
    p.add_argument("--write-scene", type=output_file, metavar="FILE.toml",
                   help="with --fusion and --live: write the live scene with the --model files and the fusion "
                        "learned, ready for supramodal run (default: none)")
    p.add_argument("--features", nargs="+", default=["Af"], choices=list(FEATURE_TABLE),
                   help="; ".join(f"{f.name}: {f.description}" for f in FEATURE_TABLE.values()) + " (default Af)")
    p.add_argument("--window", type=positive_seconds, default=DEFAULT_WINDOW,
                   help=f"window, seconds (default {DEFAULT_WINDOW})")
    p.add_argument("--epochs", type=count(1), default=DEFAULT_EPOCHS,
                   help=f"iRPROP- epochs (default {DEFAULT_EPOCHS})")
    p.add_argument("--hidden", type=count(1), metavar="N",
                   help="hidden units of the networks (default: as many as their inputs, features x channels, the "
                        "paper's rule; `supramodal fit` says the ones it scored)")
    p.add_argument("--seed", type=seed, default=0,
                   help="seed of the network's initial weights and of the cross-validation folds (default 0)")
    p.add_argument("--cv", type=count(2), metavar="K",
                   help="first report grouped K-fold cross-validation (folds by recording: mean and sd, recall, "
                        "log loss, Brier score and ECE per window and per recording; confusion as MODEL-cv.csv/.png, "
                        "reliability diagram as MODEL-cv-reliability.csv/.png), then train the final model on "
                        "everything (default: no cross-validation)")
    p.add_argument("--mapping", type=mapping, default="auto",
                   help="recording channels to filters: auto (one channel to all, or one each), mono, per-channel, "
                        "mean, or a channel index (default auto)")
    p.add_argument("--jobs", type=jobs, default=cores(),
                   help="worker processes for the model's networks, its calibration's fold networks (default: the "
                        "cores here); the model is the same for any")
    p.add_argument("--augment-gains", type=augment_gains, metavar=AUGMENT_GAINS_FORM,
                   help="gain augmentation, for models that must hold on a new touch or session (each has its own "
                        "sensor gains): every network (the calibration's fold networks, which the model deploys; "
                        "with --fusion early, the early network's, each sense's columns by its own bank) also trains "
                        "on "
                        "COPIES copies of each training window with random gains exp(N(0, SPREAD)) (default 0.03) on "
                        "Af and A, one per channel (per-channel: a whisker array's vibrissae) or one for all (shared: "
                        "a microphone's level; left out: per-channel for a whisker bank, shared for a cochlea or a "
                        "custom bank); the held-out windows, scaling and calibration see the originals; the networks "
                        "cost 1 + COPIES times the CPU; the model file keeps it (default: none; e.g. 4,0.03)")
    return p


def run(args: argparse.Namespace) -> int:
    """Train a sense model from a manifest (or hand over to ``--stream`` or ``--fusion``).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    from supramodal.calibration import calibration_line
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.node.workflows.training import train_from_manifest

    # SIGTERM as SIGINT: one line, and a model file written whole or not at all (a signal ended it on the spot)
    interrupt_until_running("the training; a model file is written whole or not at all")
    if args.stream is not None and not args.fusion:
        return _train_stream(args)
    if args.scene or args.fusion:
        return _train_fusion(args)
    if args.manifest is None or args.bank is None or args.out is None:
        raise CliError("train needs --bank, --manifest and --out (or, for a fusion of two senses, --fusion and "
                       "--scene)")
    check_new_file(args.out, args.force, "the model file")      # before the training, not after
    bank = args.bank
    cv = None
    if args.cv:
        from supramodal.node.workflows.training import cross_validate_manifest, format_cross_validation

        base = args.out.with_name(args.out.stem + "-cv")
        reliability = args.out.with_name(args.out.stem + "-cv-reliability")
        for b in (base, reliability):
            for suffix in (".csv", ".png"):
                check_new_file(b.with_name(b.name + suffix), args.force, "the cross-validation file")
        cv = cross_validate_manifest(args.manifest, bank, tuple(args.features), args.window, args.cv,
                                     epochs=args.epochs, seed=args.seed, mapping=args.mapping, progress=progress(args),
                                     augment=seeded_augment(args), hidden=args.hidden)
        print(format_cross_validation(cv))
    model = train_from_manifest(args.manifest, bank, tuple(args.features), args.window, epochs=args.epochs,
                                seed=args.seed, mapping=args.mapping, progress=progress(args), jobs=args.jobs,
                                augment=seeded_augment(args), hidden=args.hidden)
    # The model and its cross-validation's files are put in place together (the files written first, an
    # interrupted training left a new report beside the earlier model)
    written = save_model(model, args.out, cv=None if cv is None else (args.cv, cv))
    path = written[-1]
    if cv is not None:
        from supramodal.node.workflows.reports import plots_missing_notice

        print("wrote " + ", ".join(str(p) for p in written[:-1]))
        say_plots_missing(plots_missing_notice())
    print(f"wrote {path}: {model.bank.kind} bank, features {list(model.features)}, classes {list(model.classes)}, "
          f"{model.training['windows']} training windows, final MSE {model.training['final_mse']:.4g}")
    print("posteriors: " + calibration_line(None if model.calibration is None else model.calibration.fitted_on))
    _say_augment(model)
    return 0


def _say_augment(model) -> None:
    """Print the report's line of the gain augmentation its networks trained with (none: no line)."""
    if model.augment is not None:
        print(model.augment.describe())


def save_model(model, out, cv: tuple[int, dict] | None = None) -> list[Path]:
    """Save ``model`` (a sense or a fused model) to ``out`` whole or not at all, with its cross-validation's files.

    The cross-validation's files go beside it (``cv``: its folds and result): written aside, then put in place
    together (written in place, an interrupted save left a model file cut short where the earlier one was).
    Returns the files written, the model last.
    """
    from supramodal.node.workflows.reports import write_confusion, write_reliability, write_staged

    out = Path(out)

    def write(folder: Path) -> list[Path]:
        files: list[Path] = []
        if cv is not None:
            k, result = cv
            accuracy = result["window_accuracy"]
            files += write_confusion(result["labels"], result["confusion"], folder / f"{out.stem}-cv",
                                     f"{k}-fold grouped cross-validation: window accuracy "
                                     f"{accuracy['mean']:.3f} +- {accuracy['sd']:.3f}")
            files += write_reliability(result["calibration"], folder / f"{out.stem}-cv-reliability",
                                       f"{k}-fold grouped cross-validation: test folds' decisions")
        return [*files, model.save(folder / out.name)]

    return write_staged(out.parent, write)


def _train_stream(args) -> int:
    """``train --scene REC.toml ... --stream NAME --out MODEL``: a sense model straight from recorded graphs."""
    from supramodal.calibration import calibration_line
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.node.workflows.training import train_from_scenes

    if not args.scene or args.out is None:
        raise CliError("--stream trains one stream's model from recorded graphs: give one --scene per recording "
                       "(the DIR/NAME.toml `supramodal record` wrote) and --out MODEL")
    if args.manifest is not None or args.bank is not None or args.cv or args.models or args.live or args.write_scene:
        raise CliError("with --scene and --stream, the recordings' scene says the bank, features and window: leave "
                       "out --manifest, --bank, --cv, --model, --live and --write-scene")
    check_new_file(args.out, args.force, "the model file")
    model = train_from_scenes(args.scene, args.stream, epochs=args.epochs, seed=args.seed, progress=progress(args),
                              hidden=args.hidden, jobs=args.jobs, augment=seeded_augment(args))
    path = save_model(model, args.out)[-1]
    print(f"wrote {path}: stream {args.stream}, {model.bank.kind} bank, features {list(model.features)}, classes "
          f"{list(model.classes)}, {model.training['windows']} training windows of {len(args.scene)} recording(s), "
          f"final MSE {model.training['final_mse']:.4g}")
    print("posteriors: " + calibration_line(None if model.calibration is None else model.calibration.fitted_on))
    _say_augment(model)
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


def _train_fusion(args) -> int:
    """Run ``train --fusion early|late --scene S.toml ...``: learn a fusion on recorded two-sense sessions.

    From windows held out of every network that scored them (node/workflows/fused_training.py).
    """
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.node.workflows.fused_training import train_fused, write_fused_scene

    if not (args.scene and args.fusion):
        raise CliError("a fusion is trained with --fusion early|late and one --scene per recording (the scene "
                       "`supramodal record` writes for a graph)")
    if args.manifest is not None or args.cv:
        raise CliError("--manifest and --cv train one sense; a fusion is trained on --scene recordings")
    if args.hidden is not None:
        raise CliError("--hidden sets one sense's networks (--manifest or --stream); an early fusion's network "
                       "takes the paper's rule, a late fusion's copies of the sense models each model's own: leave it "
                       "out")
    if args.augment_gains is not None and args.fusion != "early":
        raise CliError("--augment-gains trains one sense (--stream) or the early fusion's network; a late "
                       "fusion's copies of the sense models train as each model did (its file keeps its gain "
                       "augmentation): train the senses with it (--stream), then give them with --model")
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
    result, info = train_fused(args.scene, args.fusion, epochs=args.epochs, seed=args.seed, progress=progress(args),
                               models=models, augment=seeded_augment(args), jobs=args.jobs)
    a, b = info["streams"]
    fused = "late" if args.fusion == "late" else "early"
    print(f"sense posteriors: {info['posteriors']['source']} ({info['posteriors']['why']})")
    # A contact is what the folds keep whole; said here, since a recording of one texture can hold several (a
    # window missing from its pairs, unlabelled or decided alone, ends one).
    print(f"held-out windows ({info['pairs']} pairs in {info['contacts']} contacts, a contact a run of consecutive "
          f"windows of one texture; {info['folds']} folds by {info['folds_by']}; each scored by networks that never "
          f"trained on its fold):")
    print(f"  {'':<12}{'accuracy':>10}{'log loss':>10}{'ECE':>8}  saying >= 0.99, wrong")
    for name in (a, b, fused):
        h = info["held_out"][name]
        sure = "none say it" if not h["sure_count"] else f"{h['sure_wrong']:.1%} of {h['sure_count']}"
        print(f"  {name:<12}{h['accuracy']:>10.3f}{h['log_loss']:>10.3f}{h['ece']:>8.3f}  {sure}")
    if args.fusion == "late":
        weight, sharpness = result
        keys = f"weight = {weight:.2f}, sharpness = {sharpness:.4g}, correlation = {info['correlation']:.3g}"
        print(f"learned late-fusion weight {weight:.2f} of {a} (and {1 - weight:.2f} of {b}) and sharpness "
              f"{sharpness:.4g} on the out-of-fold windows of {info['pairs']} labelled pairs (the late row: each "
              f"fold fused with a weight learned without it): set [fusion] {keys}")
        _write_run_scene(args, write_fused_scene, (a, b), models, method="late", weight=round(weight, 4),
                         sharpness=float(f"{sharpness:.4g}"), correlation=float(f"{info['correlation']:.3g}"))
        return 0
    path = save_model(result, args.out)[-1]
    print(f"wrote {path}: early fusion of {a} and {b}, classes {info['classes']}, {info['pairs']} pairs of windows, "
          f"calibrated on its out-of-fold pairs (the early row); use it with [fusion] method = \"early\", "
          f"model = \"{path.resolve()}\" (a relative path is taken from the scene's folder)")
    if result.augment is not None:
        for name, augment in zip((a, b), result.augment):
            print(f"{name}: {augment.describe()}")
    _write_run_scene(args, write_fused_scene, (a, b), models, method="early", model=str(path.resolve()))
    return 0


def _write_run_scene(args, write, streams, models: dict[str, str], **fusion: str | float) -> None:
    """``--write-scene``: the live scene with the sense models and the fusion learned, to run at once."""
    if args.write_scene is None:
        return
    path = write(args.live, streams, models, args.write_scene, **fusion)
    print(f"wrote {path}: {args.live} with the sense models and this fusion; run it: supramodal run {path}")
