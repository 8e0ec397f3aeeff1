"""The ``supramodal evaluate`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from supramodal.node.cli.arguments import count, mapping, output_folder, progress, say_plots_missing, seed
from supramodal.node.cli.errors import CliError
from supramodal.node.cli.signals import interrupt_until_running

#: What ``supramodal evaluate`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "accuracy and confusion of a model on labelled recordings, or of a fusion"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal evaluate MODEL --manifest FILE.csv [--out DIR] [--cv K]",
     "accuracy per window and per recording against chance, calibration, confusion, how long a touch must last; "
     "CSV and PNG with `--out`"),
    ("supramodal evaluate --scene REC.toml ... [--fused-model FUSED.npz] [--out DIR]",
     "each stream and the fusion of recorded graphs, per window and per contact, and the decision rules (unknown, "
     "changes) against the truth"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``evaluate`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("evaluate", parents=[common], help=SUMMARY)
    p.add_argument("model", nargs="?", help="model file (.npz); not with --scene")
    p.add_argument("--manifest", help="CSV with columns path,label[,start,end]; paths relative to it")
    p.add_argument("--scene", action="append", metavar="NAME.toml",
                   help="instead of a model and a manifest: a recorded graph's replay scene, run at max speed; each "
                        "stream and the fusion scored per window and per contact; give one per recording "
                        "(default: none)")
    p.add_argument("--fused-model", metavar="FILE",
                   help="with --scene: score this early-fusion network instead of the scenes' own fusion "
                        "(default: the scenes' [fusion])")
    p.add_argument("--contact-windows", type=count(1), metavar="N",
                   help="with --scene: a contact is N consecutive windows of one texture, each run of one texture "
                        "cut from its start (a shorter rest left out) (default: each whole run of one texture is "
                        "one contact)")
    p.add_argument("--mapping", type=mapping, default="auto",
                   help="recording channels to filters: auto (one channel to all, or one each), mono, per-channel, "
                        "mean, or a channel index (default auto)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object instead of a table")
    p.add_argument("--out", type=output_folder, metavar="DIR",
                   help="also write the confusion, accuracy against windows pooled, the channels' importance and "
                        "the reliability diagram (reliability.csv/.png) as CSV and PNG into DIR (PNGs need the "
                        "plots extra; with --scene: each stream's and the fusion's accuracy and confusion; default: "
                        "print only)")
    p.add_argument("--cv", type=count(2), metavar="K",
                   help="instead of scoring the model itself, re-train its configuration (bank, features, window, "
                        "peaks, hidden units, epochs) on K-1 folds of the manifest and score it on the K-th, folds "
                        "grouped by manifest line: how well a model like it does on recordings it never saw; with "
                        "--out, writes cv-confusion.csv/.png and cv-reliability.csv/.png (default: no "
                        "cross-validation)")
    p.add_argument("--seed", type=seed, metavar="S",
                   help="with --cv: seed of the folds and of the training (default: the model's own seed)")
    p.add_argument("--force", action="store_true", help="replace earlier evaluation files in --out (default: refuse)")
    return p


def run(args: argparse.Namespace) -> int:
    """Score the model (or hand over to ``--scene`` or ``--cv``).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    # SIGTERM as SIGINT: one line, and the files of --out written whole or not at all (a signal ended it on the spot)
    interrupt_until_running("the evaluation; its files are written all or none")
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
    result = evaluate_manifest(model, args.manifest, mapping=args.mapping, progress=progress(args))
    result["calibration"]["model_version"] = _model_file_version(args.model)
    print(json.dumps(result) if args.json else format_evaluation(result))
    if args.out is not None:
        from supramodal.node.workflows.reports import plots_missing_notice, write_evaluation, write_staged

        files = write_staged(args.out, lambda folder: write_evaluation(result, folder))
        print("wrote " + ", ".join(str(p) for p in files), file=sys.stderr)
        say_plots_missing(plots_missing_notice())
    return 0


def _model_file_version(path) -> int | None:
    """Return the format version a model file says it is (an uncalibrated model of version 1 is said so)."""
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
    result = evaluate_fused(args.scene, fused, progress=progress(args), contact_windows=args.contact_windows)
    print(json.dumps(result) if args.json else format_fused_evaluation(result))
    if args.out is not None:
        from supramodal.node.workflows.reports import write_fused_evaluation, write_staged

        files = write_staged(args.out, lambda folder: write_fused_evaluation(result, folder))
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
                              progress=progress(args))
    print(json.dumps(cv) if args.json else format_cross_validation(cv))
    if bases is not None:
        from supramodal.node.workflows.reports import (
            plots_missing_notice,
            write_confusion,
            write_reliability,
            write_staged,
        )

        what = f"{args.cv}-fold grouped cross-validation of {Path(args.model).name}'s configuration"
        confusion, reliability = (base.name for base in bases)

        def write(folder: Path) -> list[Path]:
            return (write_confusion(cv["labels"], cv["confusion"], folder / confusion,
                                    f"{what}: window accuracy {cv['window_accuracy']['mean']:.3f} +- "
                                    f"{cv['window_accuracy']['sd']:.3f}")
                    + write_reliability(cv["calibration"], folder / reliability, f"{what}: test folds' decisions"))
        files = write_staged(args.out, write)
        print("wrote " + ", ".join(str(p) for p in files), file=sys.stderr)
        say_plots_missing(plots_missing_notice())
    return 0
