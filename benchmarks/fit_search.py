"""`supramodal fit`'s joint search measured: under a latency budget against the paper's banks, and its speed.

    python3 -m supramodal.benchmarks.fit_search budget [--max-window S] [--jobs N] [--trials N] [--out DIR]
    python3 -m supramodal.benchmarks.fit_search speed [--recordings N] [--jobs N] [--out DIR]

``budget``: on the synthetic sensors of :mod:`supramodal.benchmarks.fit_sensors` (and the LMT surface
recordings where the project's shared data holds them), ``fit --max-window S`` (default 0.1 s; the
full fit, 60 trials, unless ``--quick``);
prints, per sensor, the fit's best and, at the window S, the best trial there beside the paper's
whisker and cochlea banks with the same features and network, per window in grouped 4-fold
cross-validation (mean +- sd over folds), and whether the fit is at least the better paper bank.

``speed``: a synthetic set of 600 recordings of 5 s at 2 kHz and 16 labels (each texture's three
peaks 5 % above the last's), the quick fit on it (grouped 5-fold), timed, beside today's coordinate
search (:mod:`node.workflows.fit`) on the same recordings. Today's fit takes hours there, so it is estimated
from measured parts: one of its folds (the first candidate's: the model ``train`` would make, with
its calibration's networks (ten when this was measured), on four fifths of the recordings) and one
filterbank pass over the recordings, times its 15 cross-validations (13 candidates and the paper's two
banks) of 5 folds.
The machine's load average is printed before and after.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from supramodal.benchmarks.fit_sensors import WIDTH, sensor_manifests
from supramodal.node.workflows.fit_search import fit_search, format_search, write_search
from supramodal.replay.wavio import write_wav
from supramodal.textures import synthesize

#: The speed benchmark's set: 16 textures, three peaks each 5 % above the last texture's.
SPEED_RATE = 2000
SPEED_BASE = (60.0, 160.0, 380.0)


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f}, {five:.2f}, {fifteen:.2f} on {os.cpu_count()} cores"


def speed_manifest(folder: Path, recordings: int = 600, labels: int = 16, seconds: float = 5.0,
                   rate: int = SPEED_RATE) -> Path:
    """Write ``recordings`` WAVs of ``seconds`` at ``rate`` Hz (default :data:`SPEED_RATE`), dealt over ``labels``.

    ``labels`` is a number of textures; each recording's noise is seeded by its index, so the
    set is the same on every run.
    """
    rows = ["path,label"]
    for i in range(recordings):
        t = i % labels
        peaks = tuple(f * (1 + 0.05 * t) for f in SPEED_BASE)
        x = 0.2 * synthesize(peaks, rate, seconds, width=WIDTH, seed=10_000 + i)
        write_wav(folder / f"t{t:02d}_{i:04d}.wav", x[:, None], rate)
        rows.append(f"t{t:02d}_{i:04d}.wav,t{t:02d}")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")
    return folder / "manifest.csv"


def today_estimate(manifest: Path, k: int = 5, epochs: int = 300) -> dict:
    """Today's coordinate search (:func:`node.workflows.fit.fit_manifest`, quick) on ``manifest``, estimated.

    Estimated from one fold of its first candidate and one filterbank pass, both measured.
    """
    from supramodal.model import TextureModel
    from supramodal.node.workflows.fit import STEPS, Candidate
    from supramodal.node.workflows.manifest import read_manifest
    from supramodal.node.workflows.training import recording_group, recording_windows
    from supramodal.pipeline import FeaturePipeline
    from supramodal.replay.wavio import wav_info
    from supramodal.training import grouped_folds

    recs = read_manifest(manifest)
    c = Candidate(fs=float(wav_info(recs[0].path).rate))
    bank = c.bank()
    t0 = time.perf_counter()
    windows = [recording_windows(r, FeaturePipeline(bank, c.features, c.window)) for r in recs]
    filterbank = time.perf_counter() - t0
    classes = sorted({r.label for r in recs})
    fold = grouped_folds([r.where for r in recs], [r.label for r in recs], k, 0)
    train = [i for i in range(len(recs)) if fold[i] != 0]
    # One fold as node.workflows.training's cross-validation trains it: the model `train` makes, calibrated.
    x = np.concatenate([windows[i] for i in train])
    y = np.concatenate([np.full(len(windows[i]), classes.index(recs[i].label)) for i in train])
    groups = np.repeat([recording_group(recs[i]) for i in train], [len(windows[i]) for i in train])
    t0 = time.perf_counter()
    TextureModel.train_for(FeaturePipeline(bank, c.features, c.window), x, y, classes, epochs=epochs, seed=0,
                           groups=groups)
    one_fold = time.perf_counter() - t0
    candidates = sum(len(quick) for _, _, quick in STEPS) + 2
    return {"filterbank_s": filterbank, "fold_s": one_fold, "candidates": candidates, "k": k,
            "seconds": candidates * (filterbank + k * one_fold)}


def _budget(args) -> int:
    out = Path(args.out)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        sensors = sensor_manifests(Path(tmp), _say)
        print(f"before: {_load()}", flush=True)
        for name, manifest in sensors.items():
            result = fit_search(manifest, k=4, quick=args.quick, trials=args.trials, max_window=args.max_window,
                                jobs=args.jobs, seed=args.seed, cache_dir=out / "cache", progress=_say)
            print(f"\n## {name}\n{format_search(result)}", flush=True)
            write_search(result, out / name.split()[0].lower())
            b = result["best"]
            at = next(p for p in result["curve"] if p["window"] == max(p["window"] for p in result["curve"]))
            f, w, c = at["fitted"], at["whisker"], at["cochlea"]
            paper = max(w["window_mean"], c["window_mean"])
            rows.append(f"| {name} | {b['window_mean']:.3f} +- {b['window_sd']:.3f} ({b['window']:g} s, "
                        f"{b['features']}) | {at['window']:g} s, {f['features']}: {f['window_mean']:.3f} +- "
                        f"{f['window_sd']:.3f} | {w['window_mean']:.3f} +- {w['window_sd']:.3f} | "
                        f"{c['window_mean']:.3f} +- {c['window_sd']:.3f} | "
                        f"{'yes' if b['window_mean'] >= paper else 'NO'} | {result['seconds']:.0f} s |")
        print(f"after: {_load()}")
    mode = " --quick" if args.quick else ""
    print(f"\nfit{mode} --max-window {args.max_window:g}, grouped 4-fold CV, window accuracy (mean +- sd over folds)\n"
          "| sensor | fit's best | fit's best at the budget's window | whisker (same window, features, network) | "
          "cochlea (same) | best >= better paper bank | time |\n|---|---|---|---|---|---|---|\n" + "\n".join(rows))
    return 0


def _speed(args) -> int:
    out = Path(args.out)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        manifest = speed_manifest(Path(tmp), args.recordings)
        _say(f"wrote {args.recordings} recordings in {time.perf_counter() - t0:.0f} s")
        before = _load()
        result = fit_search(manifest, k=5, quick=True, jobs=args.jobs, seed=args.seed, trials=args.trials,
                            cache_dir=out / "cache", progress=_say)
        after = _load()
        print(format_search(result), flush=True)
        write_search(result, out)
        today = None if args.no_baseline else today_estimate(manifest)
    new = result["seconds"]
    print(f"\nquick fit of {args.recordings} recordings of 5 s at {SPEED_RATE} Hz, 16 labels, grouped 5-fold, "
          f"--jobs {args.jobs}: {new:.0f} s ({new / 60:.1f} min); {before} before, {after} after")
    if today is not None:
        print(f"today's fit (node/workflows/fit.py, --quick, estimated): {today['candidates']} cross-validations x "
              f"({today['filterbank_s']:.1f} s filterbank pass + {today['k']} folds x {today['fold_s']:.1f} s "
              f"measured for one fold) = {today['seconds']:.0f} s ({today['seconds'] / 3600:.1f} h), in one process")
        print(f"| | today's fit (estimated) | joint search (measured) | speed-up |\n|---|---|---|---|\n"
              f"| time | {today['seconds']:.0f} s | {new:.0f} s | {today['seconds'] / new:.1f}x |")
    return 0


def main(argv=None) -> int:
    """Run the ``budget`` or the ``speed`` measurement named on the command line; return its exit status."""
    p = argparse.ArgumentParser(prog="python3 -m supramodal.benchmarks.fit_search", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="what", required=True)
    b = sub.add_parser("budget", help="the fit under a latency budget against the paper's banks")
    b.add_argument("--max-window", type=float, default=0.1, help="latency budget, seconds (default 0.1)")
    b.add_argument("--trials", type=int, default=None, help="trials per sensor (default: the fit's)")
    b.add_argument("--quick", action="store_true", help="the quick fit (default: the full one)")
    b.add_argument("--out", default="out/fit_search", help="folder for each sensor's fit files")
    s = sub.add_parser("speed", help="the quick fit on 600 recordings, beside today's fit")
    s.add_argument("--recordings", type=int, default=600, help="recordings (default 600)")
    s.add_argument("--trials", type=int, default=None, help="trials (default: the quick fit's)")
    s.add_argument("--no-baseline", action="store_true", help="do not measure today's fit's parts")
    s.add_argument("--out", default="out/fit_speed", help="folder for the fit files")
    for q in (b, s):
        q.add_argument("--jobs", type=int, default=2, help="local processes (default 2)")
        q.add_argument("--seed", type=int, default=0, help="the fit's seed (default 0)")
    args = p.parse_args(argv)
    np.seterr(all="ignore")
    return _budget(args) if args.what == "budget" else _speed(args)


if __name__ == "__main__":
    sys.exit(main())
