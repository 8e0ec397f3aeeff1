"""`supramodal fit --quick --max-window 0.1` on 700 recordings of 5 s at 2.2 kHz, timed (issue 38, items 3 and 4).

    python3 -m supramodal.benchmarks.fit_speed [--recordings N] [--seconds S] [--jobs N] [--trials N]
                                               [--patience N] [--quick] [--out DIR] [--json]

Synthesises ``--recordings`` WAVs of ``--seconds`` at :data:`RATE` Hz dealt over :data:`LABELS`
textures (:func:`supramodal.benchmarks.fit_search.speed_manifest`: three wide peaks each texture's 5 %
above the last's, seeded per recording, so the set is the same on every run), then runs the fit as
``supramodal fit MANIFEST --quick --max-window 0.1 --jobs N`` runs it (the same function,
:func:`node.workflows.fit_search.fit_search`, with its feature cache in ``--out``/cache; grouped 5-fold
cross-validation, its default trials and patience) and prints:

* wall seconds and CPU seconds (this process and its worker processes, ``os.times``, counted once the
  workers have ended), the synthesis apart, and where the CPU went: the features (filterbanks, peaks,
  windows), the networks, the rest;
* the trials run (complete, pruned, with an empty band), trials per CPU-minute;
* whether the early stop ended the search (the best not moved by more than its fold spread for
  ``--patience`` trials) and whether the best beat the paper's banks by more than a fold's spread;
* the issue's target: at most :data:`TARGET_SECONDS` of wall on 2 idle cores.

``--quick``: 48 recordings of 2 s, 4 trials of at most 8 epochs (seconds; for ``supramodal bench
--quick``, not for quoting). Writes ``fit_speed.json`` (and the fit's files) to ``--out``; progress on
stderr.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from supramodal.benchmarks import write_result

#: The set: recordings, seconds each, rate (Hz) and textures, as the issue states it.
RECORDINGS, SECONDS, RATE, LABELS = 700, 5.0, 2200, 16
#: The fit's latency budget, seconds, and its folds.
MAX_WINDOW, FOLDS = 0.1, 5
#: The issue's target: wall seconds on 2 idle cores.
TARGET_SECONDS = 600.0
#: ``--quick``: recordings, seconds each, trials and most epochs (a run of seconds, for ``supramodal bench --quick``).
QUICK_RECORDINGS, QUICK_SECONDS, QUICK_TRIALS, QUICK_EPOCHS = 48, 2.0, 4, 8


def _clock() -> tuple[float, float]:
    """Wall seconds and CPU seconds of this process and its ended children."""
    t = os.times()
    return time.perf_counter(), t.user + t.system + t.children_user + t.children_system


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            return next((line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")),
                        platform.processor())
    except OSError:
        return platform.processor()


def run(recordings: int, seconds: float, jobs: int, trials: int | None, patience: int | None,
        max_epochs: int | None, out: Path, say, seed: int = 0) -> dict:
    """Synthesise the set, run the quick fit on it and time it (see the module).

    Parameters
    ----------
    recordings : int
    seconds : float
        Each recording's length, seconds.
    jobs : int
        The fit's local processes (``--jobs``).
    trials, patience, max_epochs : int or None
        The fit's ``--trials``, ``--patience`` and ``--epochs`` (None: its defaults).
    out : Path
        Folder of the fit's files and its feature cache while it runs.
    say : callable(str)
        Progress lines.
    seed : int
        The fit's seed.

    Returns
    -------
    dict
        The figures (see :func:`report`).
    """
    from supramodal.benchmarks.fit_search import speed_manifest
    from supramodal.node.workflows.fit_search import (
        DEFAULT_PATIENCE,
        fit_search,
        format_search,
        paper_verdict,
        write_search,
    )

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        manifest = speed_manifest(Path(tmp), recordings, LABELS, seconds, rate=RATE)
        synth = time.perf_counter() - t0
        say(f"fit_speed: wrote {recordings} recordings of {seconds:g} s at {RATE} Hz in {synth:.0f} s")
        w0, c0 = _clock()
        result = fit_search(manifest, k=FOLDS, seed=seed, quick=True, trials=trials, max_window=MAX_WINDOW,
                            max_epochs=max_epochs, jobs=jobs, cache_dir=out / "cache", progress=say,
                            patience=DEFAULT_PATIENCE if patience is None else patience)
        w1, c1 = _clock()
    load_after = os.getloadavg()
    say(format_search(result))
    write_search(result, out)
    rows = result["rows"]
    states = {s: sum(r["state"] == s for r in rows) for s in ("complete", "pruned", "empty band")}
    wall, cpu = w1 - w0, c1 - c0
    stopped = result.get("stopped")
    return {"recordings": recordings, "seconds_each": seconds, "rate": RATE, "labels": LABELS, "folds": FOLDS,
            "max_window": MAX_WINDOW, "jobs": jobs, "cores": os.cpu_count(), "cpu": _cpu_model(),
            "trials_asked": result["trials"], "patience": result["patience"],
            "trials": len(rows), **states, "stopped_early": stopped is not None,
            "stopped": None if stopped is None else stopped["text"],
            "wall_s": round(wall, 3), "cpu_s": round(cpu, 3), "synth_s": round(synth, 1),
            "features_cpu_s": round(result["features_cpu_seconds"], 1),
            "networks_cpu_s": round(result["networks_cpu_seconds"], 1),
            "trials_per_cpu_minute": round(len(rows) / (cpu / 60), 2) if cpu > 0 else None,
            "filterbank_runs": result["filterbank_runs"],
            "best": round(result["best"]["score"], 3), "best_sd": round(result["best"][f"{result['target']}_sd"], 3),
            "verdict": paper_verdict(result)["text"], "beats_paper": paper_verdict(result)["beats"],
            "target_s": TARGET_SECONDS, "met": wall <= TARGET_SECONDS,
            "load_before": [round(v, 2) for v in load_before], "load_after": [round(v, 2) for v in load_after],
            "date": time.strftime("%Y-%m-%d")}


def report(result: dict) -> str:
    """Return the result as a few lines of Markdown."""
    r = result
    return "\n".join([
        f"`fit --quick --max-window {r['max_window']:g} --jobs {r['jobs']}` on {r['recordings']} recordings of "
        f"{r['seconds_each']:g} s at {r['rate']} Hz, {r['labels']} labels, grouped {r['folds']}-fold "
        f"({r['date']}, {r['cores']} cores, {r['cpu']}; load {', '.join(f'{v:.2f}' for v in r['load_before'])} "
        f"before, {', '.join(f'{v:.2f}' for v in r['load_after'])} after)", "",
        "| wall s | CPU s | trials (complete, pruned, empty band) | trials per CPU-minute | stopped early | "
        "within the target |",
        "|---|---|---|---|---|---|",
        f"| {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['trials']} ({r['complete']}, {r['pruned']}, {r['empty band']}) | "
        f"{r['trials_per_cpu_minute']:.2f} | {'yes' if r['stopped_early'] else 'no'} | "
        f"{'yes' if r['met'] else 'NO'} (<= {r['target_s']:.0f} s) |", "",
        (f"The search {r['stopped']}." if r["stopped"] else f"The search ran all its {r['trials']} trials.")
        + f" Best {r['best']:.3f} +- {r['best_sd']:.3f} of windows. " + r["verdict"], "",
        f"Where the CPU went: {r['features_cpu_s']:.1f} s features ({r['filterbank_runs']} recordings through a "
        f"filterbank, the paper's two banks' included), {r['networks_cpu_s']:.1f} s networks (their windows "
        f"gathered, trained and scored), "
        f"{r['cpu_s'] - r['features_cpu_s'] - r['networks_cpu_s']:.1f} s the rest (Dask, the sampler, reading "
        f"and starting); the synthesis ({r['synth_s']:.1f} s) not counted.",
    ])


def main(argv=None) -> int:
    """Run the benchmark from the command line, write its JSON and print it; return the exit status."""
    from supramodal.memory import keep_freed_memory
    from supramodal.parallel import default_jobs

    parser = argparse.ArgumentParser(prog="python -m supramodal.benchmarks.fit_speed", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recordings", type=int, default=None, help=f"recordings (default {RECORDINGS})")
    parser.add_argument("--seconds", type=float, default=None, help=f"seconds each (default {SECONDS:g})")
    parser.add_argument("--jobs", type=int, default=default_jobs(), help="the fit's processes (default: the cores)")
    parser.add_argument("--trials", type=int, default=None, help="the fit's --trials (default: its own)")
    parser.add_argument("--patience", type=int, default=None, help="the fit's --patience (default: its own)")
    parser.add_argument("--quick", action="store_true",
                        help=f"{QUICK_RECORDINGS} recordings of {QUICK_SECONDS:g} s, {QUICK_TRIALS} trials of at most "
                             f"{QUICK_EPOCHS} epochs (seconds; not for quoting)")
    parser.add_argument("--out", default="out/fit_speed", help="folder of fit_speed.json and the fit's files")
    parser.add_argument("--json", action="store_true", help="print the result as JSON, not a table")
    args = parser.parse_args(argv)
    keep_freed_memory()                                 # as the command line does
    recordings: int = args.recordings or (QUICK_RECORDINGS if args.quick else RECORDINGS)
    seconds: float = args.seconds or (QUICK_SECONDS if args.quick else SECONDS)
    trials: int | None = args.trials or (QUICK_TRIALS if args.quick else None)
    if recordings < FOLDS or not seconds > 0 or args.jobs < 1:
        parser.error(f"--recordings must be at least {FOLDS} (the folds), --seconds > 0 and --jobs >= 1")
    out = Path(args.out)
    result = run(recordings, seconds, args.jobs, trials, args.patience, QUICK_EPOCHS if args.quick else None, out,
                 lambda line: print(line, file=sys.stderr, flush=True))
    return write_result(result, out, "fit_speed", args.json, report)


if __name__ == "__main__":
    sys.exit(main())
