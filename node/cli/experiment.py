"""The ``supramodal experiment`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from supramodal.node.cli.arguments import count, jobs, output_folder, positive_seconds, seed
from supramodal.node.cli.errors import CliError

#: What ``supramodal experiment`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "the paper's figures and this project's experiments, as CSV and PNG, beside the paper's results"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal experiment fig1|...|all|fusion|calibration|newtouch|change [--quick]",
     f"{SUMMARY} ([docs/results.md](docs/results.md))"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``experiment`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    from supramodal.mlp import DEFAULT_EPOCHS

    p = subparsers.add_parser("experiment", parents=[common], help=SUMMARY)
    p.add_argument("figure", choices=["fig1", "fig3", "fig4", "fig5", "fig6", "all", "fusion", "calibration",
                                          "newtouch", "change"],
                   help="which figure of the paper; fusion: the two senses fused on the two-sense synthetic world "
                        "(beyond the paper; not in all); calibration: whether the confidence means what it says "
                        "(calibration, fusion, unknown textures, anytime decisions; not in all); "
                        "newtouch: the same on a touch the models never met, and after recalibrating on half of it "
                        "(not in all); change: re-deciding when the texture changes within a contact (not in all)")
    p.add_argument("--quick", action="store_true", help="short textures and small grids: seconds, not minutes")
    p.add_argument("--jobs", type=jobs, help="worker processes (default: all cores); results do not depend on it")
    p.add_argument("--seed", type=seed, default=0,
                   help="experiment seed: each run's network seed derives from it and the run; also the first "
                        "random texture set's seed")
    p.add_argument("--epochs", type=count(1), default=DEFAULT_EPOCHS,
                   help=f"iRPROP- epochs (default {DEFAULT_EPOCHS})")
    p.add_argument("--bank", choices=["whisker", "cochlea"], help="fig3: one bank (default: both)")
    p.add_argument("--textures", metavar="FILE", help="fig3: texture-set JSON file (default: the reference sets)")
    p.add_argument("--sets", type=count(0), help="fig3: N random texture sets instead of the reference set; "
                                            "all: N random sets per bank besides it (default 5, 0 with --quick); "
                                            "fusion: N random two-sense sets (default 5, 2 with --quick); "
                                            "calibration: N random sets per bank and N two-sense sets (default 5, "
                                            "1 with --quick); newtouch, change: N two-sense sets (default 5, 2 "
                                            "with --quick)")
    p.add_argument("--augment", action="store_true",
                   help="newtouch, change: gain augmentation of every network's training windows (4 more copies of "
                        "each, gains exp(N(0, 0.03)): per vibrissa for the whiskers, one level for the microphone; "
                        "seeded by --seed; the networks take 5 times the CPU)")
    p.add_argument("--touch-seconds", type=positive_seconds, metavar="S",
                   help="newtouch: seconds of each touch (default 10, 6 with --quick); longer touches give every "
                        "figure more windows and contacts to count, and the models more to learn from")
    p.add_argument("--more-touches", type=count(0), metavar="K",
                   help="newtouch: K further new touches of every known texture, on which the per-contact "
                        "false-unknown rate is also measured, with how often one touch a texture (as touch 3) lands "
                        "within 0.03..0.08 (default 0; each further touch is synthesised and its features "
                        "extracted, both senses)")
    p.add_argument("--out", default="out", type=output_folder, help="directory for CSV and PNG (default ./out)")
    p.add_argument("--json", action="store_true", help="print the figure's data as one JSON object instead of a table")
    return p


def run(args: argparse.Namespace) -> int:
    """Run the figure's plans, print its table (or JSON) and write its files.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
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
    if args.augment and args.figure not in AUGMENTED:
        raise CliError(f"--augment is experiment newtouch's (the models on a touch they never met) and change's "
                       f"(re-deciding when the texture changes), not {args.figure}'s: leave it out, or run "
                       "experiment newtouch --augment")
    for option, value, what in (("--touch-seconds", args.touch_seconds, "the length of each touch"),
                                ("--more-touches", args.more_touches, "further new touches")):
        if value is not None and args.figure != "newtouch":
            raise CliError(f"{option} is experiment newtouch's ({what}), not {args.figure}'s: leave it out")
    if args.figure in TWO_SENSE_EXPERIMENTS:
        return _two_sense_experiment(args)
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


#: The experiments over random two-sense sets: name -> (their module, its run and table functions).
TWO_SENSE_EXPERIMENTS = {"fusion": ("fusion", "run_fusion", "fusion_table"),
                         "newtouch": ("newtouch", "run_newtouch", "newtouch_table"),
                         "change": ("change", "run_change", "change_table")}
#: The experiments whose networks may train on gain-augmented windows (``--augment``: their run takes ``augment``).
AUGMENTED = ("newtouch", "change")


def _two_sense_experiment(args) -> int:
    """Run ``experiment fusion|newtouch|change``: an experiment over random two-sense sets (beyond the paper).

    It writes its table (or JSON) and its files.
    """
    import importlib

    from supramodal.experiments.common import progress_to_stderr
    from supramodal.experiments.report import write_figure

    module, run, table = TWO_SENSE_EXPERIMENTS[args.figure]
    m = importlib.import_module(f"supramodal.experiments.{module}")
    sets = args.sets if args.sets is not None else (2 if args.quick else 5)
    if sets < 1:
        raise CliError(f"--sets must be >= 1 for experiment {args.figure}, got {sets}")
    more = {}
    if args.augment:                    # newtouch's and change's: as their modules' --augment, seeded by --seed
        from supramodal.model import GainAugment

        more["augment"] = GainAugment(seed=args.seed)
    if args.touch_seconds is not None:
        more["touch_seconds"] = args.touch_seconds
    if args.more_touches is not None:
        more["more_touches"] = args.more_touches
    result = getattr(m, run)(sets, args.quick, args.epochs, args.seed, None if args.quiet else progress_to_stderr,
                             args.jobs, **more)
    written = write_figure(args.figure, result, Path(args.out))
    print(json.dumps(result) if args.json else getattr(m, table)(result) + "\nwrote "
          + ", ".join(str(p) for p in written))
    return 0
