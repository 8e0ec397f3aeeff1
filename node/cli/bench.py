"""The ``supramodal bench`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse
import sys

from supramodal.node.cli.arguments import output_folder

#: What ``supramodal bench`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = ("filterbank error against run time, drift over 60 min of stream, the whole node; training against one "
           "network, the pipeline against its filterbank, the fit's trials per CPU-minute")
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal bench [--quick] [--out DIR]", f"{SUMMARY} ([last report](docs/bench/report.md))"),
)
#: The speed benchmarks run after the filterbank's, each ``python -m supramodal.benchmarks.NAME`` in a child
#: process of its own: (NAME, what the report calls it, its arguments with ``--quick``). Each writes
#: ``NAME.json`` into ``--out``; the report lists what its ``report()`` makes of it.
SPEED = (
    ("training_speed", "Training against one network", ("--rounds", "1")),
    ("pipeline_speed", "The pipeline against its filterbank", ("--seconds", "2", "--rounds", "1")),
    ("fit_speed", "The fit's search on 700 recordings", ("--quick",)),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``bench`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("bench", parents=[common], help=SUMMARY)
    p.add_argument("--quick", action="store_true",
                   help="short signals and streams, one round, a fit of 48 short recordings (a minute or two; not "
                        "for quoting)")
    p.add_argument("--out", default="out/bench", type=output_folder,
                   help="directory for the report (default ./out/bench)")
    p.add_argument("--json", action="store_true",
                   help="print the results as one JSON object on stdout: the filterbank's under 'filterbank', each "
                        "speed benchmark's under its name")
    return p


def speed_section(results: dict) -> str:
    """Return the report's part on the speed benchmarks: each one's command and its ``report()`` of ``results[NAME]``.

    Those absent are left out.
    """
    import importlib

    lines = ["## d. Training, the pipeline and the fit's search", "",
             "Each benchmark in a child process of its own, BLAS and OpenMP held to one thread; its JSON beside "
             "this report."]
    for name, title, _ in SPEED:
        if name in results:
            report = importlib.import_module(f"supramodal.benchmarks.{name}").report
            lines += ["", f"### {title} (`python -m supramodal.benchmarks.{name}`)", "", report(results[name])]
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    """Run the filterbank benchmark, then the speed benchmarks (:data:`SPEED`), each in a child process.

    Add the speed benchmarks' figures to the report; the first child's failure is the command's.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    import json
    import os
    import subprocess
    from pathlib import Path

    from supramodal.benchmarks import PINNED_THREADS

    # Child processes, so that BLAS and OpenMP read the one-thread settings before numpy loads.
    env = {**os.environ, **PINNED_THREADS}
    out = Path(args.out)
    cmd = ([sys.executable, "-m", "supramodal.benchmarks.filterbank", "--out", str(out)]
           + ["--quick"] * args.quick + ["--json"] * args.json)
    filterbank = subprocess.run(cmd, env=env, stdout=subprocess.PIPE if args.json else None, text=True)
    if filterbank.returncode:
        return filterbank.returncode
    results: dict = {"filterbank": json.loads(filterbank.stdout)} if args.json else {}
    for name, _, quick in SPEED:
        # Their JSON on stdout is kept from the user's (the file holds it); their progress goes to stderr.
        child = subprocess.run([sys.executable, "-m", f"supramodal.benchmarks.{name}", "--out", str(out), "--json",
                                *(quick if args.quick else ())], env=env, stdout=subprocess.DEVNULL)
        if child.returncode:
            print(f"supramodal bench: python -m supramodal.benchmarks.{name} failed (exit status {child.returncode})",
                  file=sys.stderr)
            return child.returncode
        results[name] = json.loads((out / f"{name}.json").read_text())
    with open(out / "report.md", "a") as fh:
        fh.write("\n" + speed_section(results))
    if args.json:
        print(json.dumps(results))
    else:
        print(speed_section(results), end="")
        print(f"wrote {out / 'report.md'} (part d) and " + ", ".join(str(out / f"{n}.json") for n, _, _ in SPEED))
    return 0
