"""The ``supramodal fit`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse

from supramodal.node.cli.arguments import (
    AUGMENT_GAINS_FORM,
    augment_form,
    augment_gains,
    cluster_address,
    count,
    jobs,
    mapping,
    output_folder,
    positive_seconds,
    progress,
    seed,
    seeded_augment,
)
from supramodal.node.cli.signals import interrupt_until_running

#: ``--patience``'s default, trials: the search's own (``fit_search.DEFAULT_PATIENCE``), written here so that the
#: parser does not import the search and numpy with it (tests/test_fit_search.py holds the two equal).
DEFAULT_PATIENCE = 0

#: What ``supramodal fit`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = ("fit a bank, window, features and network to your sensor by grouped cross-validation under your latency "
           "and CPU budgets (the `fit` extra)")
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal fit MANIFEST [--out DIR] [--max-window S] [--trials N] [--jobs N]",
     f"{SUMMARY}; writes `bank.json` for `train --bank` ([docs/own-sensor.md](docs/own-sensor.md))"),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``fit`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("fit", parents=[common], help=SUMMARY)
    p.add_argument("manifest", help="CSV with columns path,label[,start,end]; paths relative to it")
    p.add_argument("--out", type=output_folder, default="out/fit",
                   help="folder for fit.csv (every trial), fit-curve.csv/.png (best accuracy per window), bank.json "
                        "(the best bank) and the feature cache (default ./out/fit)")
    p.add_argument("--cv", type=count(2), default=5, metavar="K", help="folds, grouped by recording (default 5)")
    p.add_argument("--trials", type=count(1), default=None,
                   help="settings to try (default 60, --quick 16)")
    p.add_argument("--timeout", type=positive_seconds, default=None, metavar="S",
                   help="time budget: no new round of trials after S seconds (the first always runs; default: none)")
    p.add_argument("--patience", type=count(0), default=DEFAULT_PATIENCE, metavar="N",
                   help="stop early once the best has not moved by more than its fold spread (sd over folds) for N "
                        f"trials, checked after each round; 0: run every trial (default {DEFAULT_PATIENCE})")
    p.add_argument("--max-window", type=positive_seconds, default=None, metavar="S",
                   help="latency budget: no window longer than S seconds (default: none)")
    p.add_argument("--max-channels", type=count(1), default=None, metavar="N",
                   help="CPU budget: no bank with more than N channels (default: none)")
    p.add_argument("--target", choices=("window", "recording", "contact"), default="window",
                   help="the accuracy to maximise: per window, per recording (all its windows pooled) or per "
                        "contact (--contact seconds of windows pooled) (default window)")
    p.add_argument("--contact", type=positive_seconds, default=0.5, metavar="S",
                   help="seconds of a contact for --target contact (default 0.5)")
    p.add_argument("--epochs", type=count(1), default=None,
                   help="most iRPROP- epochs a trial may train (default: the search's own list)")
    p.add_argument("--seed", type=seed, default=0,
                   help="seed of the sampler, the folds and the networks (default 0)")
    p.add_argument("--batch", type=count(1), default=4,
                   help="trials asked at once; the result depends on the seed and this, not on --jobs or --cluster "
                        "(default 4)")
    p.add_argument("--quick", action="store_true",
                   help="fewer values per parameter, 16 trials, each fold's model trained on at most 4000 windows")
    p.add_argument("--jobs", type=jobs, default=1,
                   help="local processes scoring folds (a local Dask cluster when more than 1; default 1)")
    p.add_argument("--cluster", type=cluster_address, default=None, metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://HOST:PORT) whose workers score the folds instead")
    p.add_argument("--cache-memory", type=count(16), default=512, metavar="MB",
                   help="feature windows each process keeps in memory; more go to --out/cache (default 512)")
    p.add_argument("--mapping", type=mapping, default="auto",
                   help="recording channels to filters: auto (one channel to all, or one each), mono, per-channel, "
                        "mean, or a channel index (default auto)")
    p.add_argument("--augment-gains", type=augment_gains, metavar=AUGMENT_GAINS_FORM,
                   help="score every setting as `train --augment-gains` will train the model: each fold's model's "
                        "networks (the paper's banks' too) also train on COPIES copies of each training window with "
                        "random gains exp(N(0, SPREAD)); the networks cost 1 + COPIES times the CPU (default: none)")
    p.add_argument("--force", action="store_true", help="replace earlier fit files in --out (default: refuse)")
    return p


def run(args: argparse.Namespace) -> int:
    """Run the joint search and write its files into ``--out``.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.node.workflows.fit_search import fit_search, format_search, write_search
    from supramodal.node.workflows.reports import write_staged

    if args.out.is_dir():
        for name in ("fit.csv", "fit-curve.csv", "fit-curve.png", "bank.json"):
            check_new_file(args.out / name, args.force, "the fit file")
    # SIGTERM as SIGINT: the search's workers and their cluster are closed on the way out (a SIGTERM
    # ended the fit on the spot, leaking their semaphores), and one line says what was left
    interrupt_until_running("the fit's search; no fit file was written")
    cache = args.out / "cache"
    made_cache = not cache.exists()          # a folder the user (or an earlier fit) had stays, empty or not
    try:
        result = fit_search(args.manifest, k=args.cv, seed=args.seed, quick=args.quick, trials=args.trials,
                            timeout=args.timeout, batch=args.batch, max_window=args.max_window,
                            max_channels=args.max_channels, target=args.target, contact=args.contact,
                            max_epochs=args.epochs, jobs=args.jobs, cluster=args.cluster, mapping=args.mapping,
                            cache_dir=cache, cache_memory=args.cache_memory * 2**20, patience=args.patience,
                            augment=seeded_augment(args), progress=progress(args))
    except BaseException:
        # The cache's files are this search's (a completed one removes them): an interrupted one left them behind.
        for path in cache.glob("*.npy"):
            path.unlink(missing_ok=True)
        raise
    finally:
        # The folder too, once empty, when this fit made it: it is the search's scratch, not one of the
        # fit's files (an empty fit/cache was left after every fit). Anything else in it is not the fit's
        # to remove.
        if made_cache:
            try:
                cache.rmdir()
            except OSError:
                pass
    print(format_search(result))
    # Written aside and put in place all at once (written in place, an interrupted fit left some files new, the
    # rest an earlier fit's, or one cut short).
    interrupt_until_running("writing the fit's files; they are put in place all or none")
    files = write_staged(args.out, lambda folder: write_search(result, folder))
    b = result["best"]
    # The model the folds scored: the same seed (its networks' start, and the gains drawn where augmented) and
    # the same channels of the recordings.
    augment = "" if args.augment_gains is None else f" --augment-gains {augment_form(args.augment_gains)}"
    seeded = "" if args.seed == 0 else f" --seed {args.seed}"
    mapped = "" if args.mapping == "auto" else f" --mapping {args.mapping}"
    print(f"wrote {', '.join(str(p) for p in files)}\nnext: supramodal train --bank {args.out / 'bank.json'} "
          f"--window {b['window']:g} --features {b['features'].replace('+', ' ')} --hidden {b['hidden']} "
          f"--epochs {b['epochs']} --manifest {args.manifest}{mapped}{augment}{seeded} --out MODEL")
    return 0
