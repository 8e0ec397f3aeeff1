"""The whole feature pipeline against its filterbank alone, block by block (issue 38, items 2 and 4).

    python3 -m supramodal.benchmarks.pipeline_speed [--seconds S] [--rounds R] [--out DIR] [--json]

For each bank at a live device's block (the cochlea bank at 441 samples, 10 ms at 44.1 kHz; the
whisker bank at 50 samples, 10 ms at 5 kHz), white noise of ``--seconds`` is fed block by block to

* **filterbank**: the filterbank alone (:func:`supramodal.backends.make_filterbank`, the fast form),
  each block as it comes;
* **pipeline**: the node's :class:`~supramodal.pipeline.FeaturePipeline` as a scene's defaults make
  it (Af, 100 ms windows, ``chunk`` 10 ms: the filterbank run on each 10 ms as it comes and the
  peaks and windows on each stage of chunks, so that only the last is left when a window closes;
  non-finite samples replaced);
* **pipeline, whole windows**: the same with ``chunk`` 0 (each window run once it is complete).

CPU seconds (``time.process_time``, BLAS and OpenMP held to one thread, re-executed so before
numpy loads); the median over ``--rounds`` interleaved rounds; the ratio to the filterbank (the
issue's target: the pipeline at most 2 x) and the real-time factor (CPU over the signal's seconds).
Writes ``pipeline_speed.json`` to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

from supramodal.benchmarks import run_pinned, write_result
from supramodal.memory import keep_freed_memory

#: (bank, samples per block): a live device's 10 ms.
CASES = (("cochlea", 441), ("whisker", 50))


def _cpu(feed, blocks) -> float:
    t0 = time.process_time()
    for b in blocks:
        feed(b)
    return time.process_time() - t0


def run(seconds: float, rounds: int, say) -> dict:
    """Return the measurements (see the module); ``say`` is told progress lines."""
    import numpy as np

    from supramodal.backends import make_filterbank
    from supramodal.banks import bank_by_name
    from supramodal.pipeline import FeaturePipeline

    rows = []
    for kind, block in CASES:
        bank = bank_by_name(kind)
        n = int(seconds * bank.fs) // block * block
        x = np.random.default_rng(0).normal(size=n)
        blocks = [x[i:i + block] for i in range(0, n, block)]
        times: dict[str, list[float]] = {"filterbank": [], "pipeline": [], "pipeline, whole windows": []}
        for r in range(rounds):
            fb = make_filterbank(bank)
            times["filterbank"].append(_cpu(fb.process, blocks))
            live = FeaturePipeline(bank, ("Af",), chunk=0.01, nonfinite="zero")
            times["pipeline"].append(_cpu(live.process, blocks))
            whole = FeaturePipeline(bank, ("Af",), nonfinite="zero")
            times["pipeline, whole windows"].append(_cpu(whole.process, blocks))
            say(f"{kind}, {block}-sample blocks, round {r + 1}/{rounds}: "
                + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in times.items()))
        base = statistics.median(times["filterbank"])
        for name, got in times.items():
            cpu = statistics.median(got)
            rows.append({"bank": kind, "block": block, "channels": bank.channels, "what": name, "cpu_s": round(cpu, 6),
                         "ratio": round(cpu / base, 2), "real_time_factor": round(cpu / (n / bank.fs), 4)})
    return {"seconds": seconds, "rounds": rounds, "rows": rows, "load_before": os.getloadavg()[0],
            "date": time.strftime("%Y-%m-%d")}


def report(result: dict) -> str:
    """Return the result as a Markdown table."""
    lines = [f"{result['seconds']:g} s of noise per bank, median of {result['rounds']} round(s), one core "
             f"({result['date']}, load {result['load_before']:.1f} at the start)", "",
             "| bank | block | | CPU s | / filterbank | real-time factor |", "|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['bank']} ({r['channels']} ch) | {r['block']} | {r['what']} | {r['cpu_s']:.3f} | "
                     f"{r['ratio']:.2f} | {r['real_time_factor']:.4f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Run the benchmark from the command line, write its JSON and print it; return the exit status."""
    parser = argparse.ArgumentParser(prog="python -m supramodal.benchmarks.pipeline_speed", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0, help="seconds of noise per bank (default 20)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, interleaved (default 3)")
    parser.add_argument("--out", default="out/pipeline_speed", help="folder of pipeline_speed.json")
    parser.add_argument("--json", action="store_true", help="print the result as JSON, not a table")
    args = parser.parse_args(argv)
    keep_freed_memory()                                 # as the command line does
    if args.rounds < 1 or not args.seconds > 0:
        parser.error("--rounds must be >= 1 and --seconds > 0")
    result = run(args.seconds, args.rounds, lambda line: print(line, file=sys.stderr, flush=True))
    return write_result(result, args.out, "pipeline_speed", args.json, report)


if __name__ == "__main__":
    run_pinned("supramodal.benchmarks.pipeline_speed")      # one BLAS thread, set before numpy loads
    sys.exit(main())
