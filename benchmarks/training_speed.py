"""Training against one network, and the default scene's first decision (issue 38, item 1).

    python3 -m supramodal.benchmarks.training_speed [--rounds R] [--jobs N] [--out DIR] [--json]

On the whisker reference set's training part (Fig. 3's first 75 % of each texture, Af; the
model the default scene trains on start), each round measures, one after the other:

* **one network**: a network of all the training windows alone (:func:`supramodal.mlp.train_task`), as a
  yardstick (what an uncalibrated model trains; before 2026-11-30, the deployed network beside ten fold networks);
* **train, 1 job**: :meth:`supramodal.model.TextureModel.train`: its calibration's fold networks (three,
  which the model deploys) and the calibration's fitting, in this process;
* **train, N jobs**: the same over ``--jobs`` worker processes (default: the cores); the model is
  checked to be the one of 1 job, weights and calibration alike;
* **calibration fit**: :func:`supramodal.calibration.fit_calibration` alone on the 1-job model's
  held-out logits (the window map, its caps and the contact pooling; part of each train above);
* **first decision**: ``supramodal run --speed max`` on the embedded default scene with the model
  cache off (``SUPRAMODAL_CACHE=off``), a user's first run: seconds from the command's start to
  its first decision line, with the user's own BLAS threads.

CPU is the process's own and its workers' (``os.times``; BLAS and OpenMP held to one thread here,
re-executed so before numpy loads, so that CPU is arithmetic, not threads spinning). The
report gives each measurement's median over the rounds and the ratios to one network; the issue's
targets are train CPU <= 3 x and wall <= 1.5 x one network's, and the first decision within 10 s
on 2 idle cores. Writes ``training_speed.json`` to ``--out``; prints progress on stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import time

from supramodal.benchmarks import run_pinned, write_result
from supramodal.memory import keep_freed_memory
from supramodal.parallel import THREAD_VARS, default_jobs

#: The first decision line of ``supramodal run`` (a window's end time in seconds, then its decision).
FIRST_DECISION = re.compile(r"^\s*\d+\.\d+ s\s+\S")


def _clock() -> tuple[float, float]:
    t = os.times()
    return time.perf_counter(), t.user + t.system + t.children_user + t.children_system


def _timed(fn) -> tuple[object, float, float]:
    w0, c0 = _clock()
    out = fn()
    w1, c1 = _clock()
    return out, w1 - w0, c1 - c0


def first_decision_seconds(timeout: float = 300.0) -> float:
    """Seconds from ``supramodal run --speed max`` (default scene, cache off) to its first decision."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
    env["SUPRAMODAL_CACHE"] = "off"
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "supramodal", "run", "--speed", "max"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if FIRST_DECISION.match(line):
                return time.perf_counter() - t0
            if time.perf_counter() - t0 > timeout:
                break
        raise RuntimeError("supramodal run printed no decision")
    finally:
        proc.kill()
        proc.wait()


def _same_model(a, b) -> bool:
    import numpy as np

    return (all(np.array_equal(p, q) for p, q in zip(a.mlp.params(), b.mlp.params(), strict=True))
            and json.dumps(a.calibration.to_dict(), sort_keys=True)
            == json.dumps(b.calibration.to_dict(), sort_keys=True))


def run(rounds: int, jobs: int, say) -> dict:
    """Return the measurements (see the module); ``say`` is told progress lines."""
    import numpy as np

    from supramodal.calibration import fit_calibration, input_scaling
    from supramodal.experiments.common import default_bank
    from supramodal.features import DEFAULT_WINDOW
    from supramodal.mlp import NetworkTask, train_task
    from supramodal.model import TextureModel
    from supramodal.pipeline import FeaturePipeline
    from supramodal.textures import reference_texture_set
    from supramodal.training import split, texture_features

    ts = reference_texture_set("whisker")
    pipeline = FeaturePipeline(default_bank(ts), ("Af",), DEFAULT_WINDOW)
    say("features of the whisker reference set")
    values, _ = texture_features(ts, pipeline.bank, pipeline.features, pipeline.window)
    x_train, y_train, _, _ = split(values)
    x = x_train.reshape(len(x_train), -1)
    mean, scale = input_scaling(x)
    y = np.asarray(y_train)
    task = NetworkTask((x - mean) / scale, y, len(ts.names), seed=0)
    rows: dict[str, list[tuple[float, float]]] = {"one network": [], "train, 1 job": [], f"train, {jobs} jobs": [],
                                                  "calibration fit": []}
    first: list[float] = []
    for r in range(rounds):
        _, wall, cpu = _timed(lambda: train_task(task))
        rows["one network"].append((wall, cpu))
        say(f"round {r + 1}/{rounds}: one network {wall:.1f} s")
        one, wall, cpu = _timed(lambda: TextureModel.train_for(pipeline, x_train, y_train, ts.names, seed=0, jobs=1))
        rows["train, 1 job"].append((wall, cpu))
        say(f"round {r + 1}/{rounds}: train, 1 job {wall:.1f} s")
        many, wall, cpu = _timed(lambda: TextureModel.train_for(pipeline, x_train, y_train, ts.names, seed=0,
                                                                jobs=jobs))
        rows[f"train, {jobs} jobs"].append((wall, cpu))
        if not _same_model(one, many):
            raise RuntimeError(f"the model of {jobs} jobs differs from the model of 1 job")
        say(f"round {r + 1}/{rounds}: train, {jobs} jobs {wall:.1f} s (the same model)")
        assert isinstance(one, TextureModel) and one.out_of_fold is not None     # trained with calibration folds
        _, wall, cpu = _timed(lambda held=one.out_of_fold: fit_calibration(held.logits, y, y, folds=held.folds))
        rows["calibration fit"].append((wall, cpu))
        say(f"round {r + 1}/{rounds}: calibration fit {cpu:.2f} s CPU")
        first.append(first_decision_seconds())
        say(f"round {r + 1}/{rounds}: the default scene's first decision after {first[-1]:.1f} s")
    base_wall = statistics.median(w for w, _ in rows["one network"])
    base_cpu = statistics.median(c for _, c in rows["one network"])
    table = {}
    for name, got in rows.items():
        wall, cpu = statistics.median(w for w, _ in got), statistics.median(c for _, c in got)
        table[name] = {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "wall_ratio": round(wall / base_wall, 2),
                       "cpu_ratio": round(cpu / base_cpu, 2)}
    return {"windows": int(len(x)), "inputs": int(x.shape[1]), "classes": len(ts.names), "rounds": rounds,
            "jobs": jobs, "cores": default_jobs(), "load_before": os.getloadavg()[0], "rows": table,
            "first_decision_s": round(statistics.median(first), 2),
            "first_decision_each_s": [round(v, 2) for v in first],
            "date": time.strftime("%Y-%m-%d")}


def report(result: dict) -> str:
    """Return the result as a Markdown table."""
    lines = [f"Training on {result['windows']} windows x {result['inputs']} inputs, {result['classes']} classes; "
             f"median of {result['rounds']} round(s) on {result['cores']} cores ({result['date']}, load "
             f"{result['load_before']:.1f} at the start)", "",
             "| | wall s | CPU s | wall / one network | CPU / one network |", "|---|---|---|---|---|"]
    for name, row in result["rows"].items():
        lines.append(f"| {name} | {row['wall_s']:.2f} | {row['cpu_s']:.2f} | {row['wall_ratio']:.2f} | "
                     f"{row['cpu_ratio']:.2f} |")
    lines += ["", f"The default scene's first decision (empty cache): {result['first_decision_s']:.1f} s "
              f"(each round: {', '.join(f'{v:.1f}' for v in result['first_decision_each_s'])})"]
    return "\n".join(lines)


def main(argv=None) -> int:
    """Run the benchmark from the command line, write its JSON and print it; return the exit status."""
    parser = argparse.ArgumentParser(prog="python -m supramodal.benchmarks.training_speed", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3, help="rounds, interleaved (default 3)")
    parser.add_argument("--jobs", type=int, default=default_jobs(), help="worker processes (default: the cores)")
    parser.add_argument("--out", default="out/training_speed", help="folder of training_speed.json")
    parser.add_argument("--json", action="store_true", help="print the result as JSON, not a table")
    args = parser.parse_args(argv)
    keep_freed_memory()                                 # as the command line does
    if args.rounds < 1 or args.jobs < 1:
        parser.error("--rounds and --jobs must be >= 1")
    result = run(args.rounds, args.jobs, lambda line: print(line, file=sys.stderr, flush=True))
    return write_result(result, args.out, "training_speed", args.json, report)


if __name__ == "__main__":
    run_pinned("supramodal.benchmarks.training_speed")      # one BLAS thread, set before numpy loads
    sys.exit(main())
