"""`supramodal fit` on three sensors: the fitted bank's accuracy beside the paper's whisker and cochlea banks.

The sensors are the LMT surface recordings (44.1 kHz, where present) and two synthetic sensors
with bands unlike the paper's (2.2 kHz with content below 1 kHz; 6 kHz with content below
2.5 kHz). Prints, per sensor, the fitted bank's grouped cross-validation accuracy beside the
paper's whisker and cochlea banks (same window and features), mean and sd over folds.

    python3 -m supramodal.benchmarks.fit_sensors [--quick] [--jobs N] [--out DIR]

Each synthetic sensor: 5 textures of three wide spectral peaks, each texture's 5 % above the
last's, low in the sensor's band; 4 recordings of 3 s each (different noise seeds), so grouped
4-fold cross-validation has a recording of every texture in each fold. The LMT recordings (one
4.8 s recording per texture) are split into 4 lines of 1.2 s each, the trials of the folds.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from supramodal.node.workflows.fit import fit_manifest, format_fit, write_fit
from supramodal.replay.wavio import write_wav
from supramodal.textures import synthesize

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmt-surface-sounds"
LMT = ["carpet", "fiber", "rough_paper", "sheep_skin", "textile", "wallpaper"]

#: name -> (rate, {texture: three peaks, Hz})
def _family(base, names, step=0.05):
    """Textures whose three peaks are the base's scaled by 1, 1 + step, and so on.

    They are close together, so that a bank's channel spacing in the band decides how well they
    separate.
    """
    return {n: tuple(round(f * (1 + step * i), 1) for f in base) for i, n in enumerate(names)}


SYNTHETIC = {
    "fingertip-2.2kHz": (2200, _family((70, 190, 450), ("silk", "denim", "cork", "felt", "mesh"))),
    "accelerometer-6kHz": (6000, _family((180, 650, 1600), ("tile", "wood", "foam", "grit", "vinyl"))),
}
#: Relative peak width of the synthetic textures (wider than the paper's 0.2: harder to tell apart).
WIDTH = 0.4


def synthetic_manifest(folder: Path, rate: int, textures: dict, recordings: int = 4, seconds: float = 3.0) -> Path:
    """Write a synthetic sensor's recordings and ``manifest.csv`` into ``folder``; return the manifest's path.

    Each texture of ``textures`` (name -> peaks) gets ``recordings`` WAVs of ``seconds`` at
    ``rate`` Hz, each with its own noise seed.
    """
    rows = ["path,label"]
    for t, (name, peaks) in enumerate(textures.items()):
        for r in range(recordings):
            x = 0.2 * synthesize(peaks, rate, seconds, width=WIDTH, seed=1000 * t + r)
            write_wav(folder / f"{name}{r}.wav", x[:, None], rate)
            rows.append(f"{name}{r}.wav,{name}")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")
    return folder / "manifest.csv"


def lmt_manifest(folder: Path, lines: int = 4, seconds: float = 211611 / 44100) -> Path:
    """Write ``manifest.csv`` for the LMT recordings into ``folder``; return its path.

    Each texture's recording of ``seconds`` is split into ``lines`` equal spans (the folds' trials).
    """
    step = seconds / lines
    rows = ["path,label,start,end"] + [f"{SHARED / n}.wav,{n},{i * step:.4f},{(i + 1) * step:.4f}"
                                       for n in LMT for i in range(lines)]
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")
    return folder / "manifest.csv"


def sensor_manifests(folder: Path, say) -> dict[str, Path]:
    """Write each sensor's manifest under ``folder``; return them by sensor name.

    The sensors are the LMT recordings where they are (``say`` says their row is left out where
    not), and every :data:`SYNTHETIC` sensor.
    """
    sensors = {}
    if SHARED.is_dir():
        (folder / "lmt").mkdir()
        sensors["LMT surfaces 44.1 kHz"] = lmt_manifest(folder / "lmt")
    else:
        say(f"the LMT recordings are not at {SHARED}: their row is left out")
    for name, (rate, textures) in SYNTHETIC.items():
        (folder / name).mkdir()
        sensors[name] = synthetic_manifest(folder / name, rate, textures)
    return sensors


def main(argv=None) -> int:
    """Fit each sensor's bank and print its accuracy beside the paper's banks; return 0."""
    p = argparse.ArgumentParser(prog="python3 -m supramodal.benchmarks.fit_sensors",
                                description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="fewer values per parameter")
    p.add_argument("--jobs", type=int, default=1, help="processes (default 1)")
    p.add_argument("--out", default="out/fit_sensors", help="folder for each sensor's fit files")
    args = p.parse_args(argv)
    progress = lambda m: print(m, file=sys.stderr, flush=True)   # noqa: E731
    out = Path(args.out)
    with tempfile.TemporaryDirectory() as tmp:
        sensors = sensor_manifests(Path(tmp), progress)
        summary = []
        for name, manifest in sensors.items():
            t0 = time.perf_counter()
            result = fit_manifest(manifest, k=4, quick=args.quick, jobs=args.jobs, progress=progress)
            print(f"\n## {name} ({time.perf_counter() - t0:.0f} s)\n{format_fit(result)}", flush=True)
            write_fit(result, out / name.split()[0].lower())
            b, w, c = result["best"], result["paper"]["whisker"], result["paper"]["cochlea"]
            summary.append(f"| {name} | {b['window_mean']:.3f} +- {b['window_sd']:.3f} | "
                           f"{w['window_mean']:.3f} +- {w['window_sd']:.3f} | {c['window_mean']:.3f} +- "
                           f"{c['window_sd']:.3f} | {b['recording_mean']:.3f} | {w['recording_mean']:.3f} | "
                           f"{c['recording_mean']:.3f} |")
    print("\n| sensor | fitted (windows) | whisker | cochlea | fitted (trials) | whisker | cochlea |\n"
          "|---|---|---|---|---|---|---|\n" + "\n".join(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
