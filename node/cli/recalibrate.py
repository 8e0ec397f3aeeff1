"""The ``supramodal recalibrate`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse
from pathlib import Path

from supramodal.node.cli.arguments import mapping, output_file, progress
from supramodal.node.cli.errors import CliError

#: What ``supramodal recalibrate`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = ('refit a model\'s calibration and "unknown" thresholds on a new touch, session or sensor, keeping its '
           "network")
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal recalibrate MODEL (--manifest FILE.csv | --scene REC.toml ... --stream NAME) --out NEW",
     f"{SUMMARY} ([docs/own-robot.md]"
     "(docs/own-robot.md#7-a-new-touch-session-or-sensor-recalibrate-keep-the-network))"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``recalibrate`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("recalibrate", parents=[common], help=SUMMARY)
    p.add_argument("model", metavar="MODEL.npz", help="the model to recalibrate (a sense model of `supramodal train`)")
    p.add_argument("--manifest", help="CSV with columns path,label[,start,end] of the new recordings; paths relative "
                                      "to it")
    p.add_argument("--scene", action="append", metavar="REC.toml",
                   help="instead of --manifest: a recorded graph's replay scene (supramodal record writes it); one "
                        "per recording, with --stream")
    p.add_argument("--stream", metavar="NAME", help="with --scene: the stream whose model this is")
    p.add_argument("--mapping", type=mapping, default="auto",
                   help="with --manifest: how a recording's channels feed the bank's (as for train; default auto)")
    p.add_argument("--out", type=output_file, required=True,
                   help="the recalibrated model file to write (the model given is left as it is)")
    p.add_argument("--force", action="store_true", help="replace an existing file at --out (default: refuse)")
    return p


def run(args: argparse.Namespace) -> int:
    """Recalibrate the model, write it to ``--out`` and say what changed.

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
    from supramodal.node.cli.signals import interrupt_until_running
    from supramodal.node.cli.train import save_model
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.node.workflows.training import recalibrate_model

    interrupt_until_running("the recalibration; a model file is written whole or not at all")
    if Path(args.out).resolve() == Path(args.model).resolve():
        raise CliError(f"--out {args.out} is the model being recalibrated: write the recalibrated model to a file of "
                       "its own, so that the model and its calibration stay as they were")
    check_new_file(args.out, args.force, "the model file")
    model = _sense_model(args.model)
    if model.calibration is None:
        print("supramodal: the model was not calibrated (a version 1 file): it is calibrated now, on these recordings")
    before = calibration_line(None if model.calibration is None else model.calibration.fitted_on)
    new = recalibrate_model(model, args.manifest, args.scene or (), args.stream, args.mapping, progress(args))
    path = save_model(new, args.out)[-1]
    assert new.calibration is not None, "recalibrate_model fits a calibration"
    print(f"wrote {path}: {args.model}'s network, classes {list(new.classes)}")
    print(f"posteriors were {before}")
    print(f"posteriors now {calibration_line(new.calibration.fitted_on)}")
    if new.novelty is not None:
        print("unknown: the thresholds of [decision] unknown are set on these recordings' windows")
    return 0


def _sense_model(path):
    """Return the sense model at ``path``; an early-fusion file is refused with what to do instead."""
    from supramodal.fused_model import EARLY_FORMAT
    from supramodal.model import ModelError, TextureModel

    try:
        return TextureModel.load(path)
    except ModelError as exc:
        if EARLY_FORMAT in str(exc):
            raise CliError(f"{path} is an early-fusion model: recalibrate takes a sense model; recalibrate each "
                           "sense, then learn the early fusion again (train --fusion early)") from None
        raise
