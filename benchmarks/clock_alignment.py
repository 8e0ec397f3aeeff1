"""Two sources on their own clocks, aligned by their clock models: error against the truth.

Whiskers at 5 kHz in 50-sample blocks, their crystal +100 ppm fast; a microphone at 44.1 kHz in
441-sample blocks, -100 ppm slow, started 37 ms later. Each block arrives after its last sample,
late by an exponential delay (mean = the jitter; 2 ms by default) plus 50 ms for one block in 500,
stamped in order; one 4 s outage of the whisker source halfway (its held-up blocks arrive in a
burst). Both feed a :class:`supramodal.node.runtime.clock.ClockModel`; at true instants every 0.1 s, each
source's sample index at that instant is mapped back to host time through its model:

* **alignment**: |whiskers' time - microphone's time| for the same instant (what pairing windows
  of two streams needs);
* **absolute**: |a model's time - the true time| (what stamping samples for LSL or XDF needs);
* **rate**: |estimated ppm - true ppm|.

Then the error against run time: the same stream with fits over fewer or more segments, with the
per-block cost of ``update`` (µs, this machine) beside the error. Optionally a PNG of the error
over the stream (matplotlib, the `plots` extra).

    python -m supramodal.benchmarks.clock_alignment [--minutes 10] [--seed 0] [--out DIR]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TypedDict

import numpy as np

from supramodal.node.runtime.clock import DEFAULT_WINDOW_SEGMENTS, ClockModel


class Source(TypedDict):
    """A simulated source: its name, nominal rate (Hz), crystal error (ppm), start (host s) and block (samples)."""

    name: str
    nominal: float
    ppm: float
    t0: float
    block: int


WHISKERS = Source(name="whiskers", nominal=5000.0, ppm=+100.0, t0=1000.0, block=50)
MIC = Source(name="microphone", nominal=44100.0, ppm=-100.0, t0=1000.037, block=441)


def simulate(src: Source, seconds: float, jitter: float, rng, outage=None):
    """(index of each block's last sample, arrival time) of a source; see the module docstring."""
    true_rate = src["nominal"] * (1 + src["ppm"] * 1e-6)
    n_blocks = int(seconds * src["nominal"] / src["block"])
    last = (np.arange(n_blocks) + 1) * src["block"] - 1
    truth = src["t0"] + last / true_rate
    arrival = truth + rng.exponential(jitter, n_blocks) + 0.05 * (rng.random(n_blocks) < 0.002)
    if outage is not None:
        held = (truth >= src["t0"] + outage[0]) & (truth < src["t0"] + outage[1])
        arrival[held] = np.maximum(arrival[held], src["t0"] + outage[1])
    return last, np.maximum.accumulate(arrival)


def true_index(src: Source, t):
    """Return the sample index ``src`` truly reaches at host time ``t`` (s; scalar or array), on its true clock."""
    return (np.asarray(t) - src["t0"]) * src["nominal"] * (1 + src["ppm"] * 1e-6)


def run(seconds: float, jitter: float, seed: int, window_segments: int = DEFAULT_WINDOW_SEGMENTS,
        check_every: float = 0.1) -> dict:
    """Feed both sources block by block, in arrival order, measuring the errors every ``check_every`` s.

    ``check_every`` is seconds of host time. Returns the curves and the per-block cost.
    """
    rng = np.random.default_rng(seed)
    streams = []
    for src, outage in ((WHISKERS, (seconds / 2, seconds / 2 + 4.0)), (MIC, None)):
        last, arrival = simulate(src, seconds, jitter, rng, outage)
        streams.append((src, ClockModel(src["nominal"], window_segments=window_segments), last, arrival))
    # one host time line: both sources' blocks in arrival order
    order = np.argsort(np.concatenate([s[3] for s in streams]), kind="stable")
    which = np.concatenate([np.full(len(s[2]), k) for k, s in enumerate(streams)])[order]
    pos = np.concatenate([np.arange(len(s[2])) for s in streams])[order]
    lasts = [s[2].tolist() for s in streams]
    arrivals = [s[3].tolist() for s in streams]
    clocks = [s[1] for s in streams]
    t_start = max(WHISKERS["t0"], MIC["t0"])
    next_check, rows, cost = t_start + 5.0, [], 0.0
    for k, i in zip(which.tolist(), pos.tolist()):
        t0 = time.perf_counter()
        clocks[k].update(lasts[k][i], arrivals[k][i])
        cost += time.perf_counter() - t0
        if arrivals[k][i] >= next_check:
            instant = next_check - 0.5           # a moment whose samples have all arrived
            mapped = [c.time_of(true_index(s[0], instant)) for s, c in zip(streams, clocks)]
            ests = [c.estimate() for c in clocks]
            rows.append((instant - t_start, abs(mapped[0] - mapped[1]), max(abs(m - instant) for m in mapped),
                         max(abs(e.ppm - s[0]["ppm"]) for e, s in zip(ests, streams))))
            next_check += check_every
    curve = np.array(rows)
    return {"curve": curve, "us_per_block": 1e6 * cost / len(which), "blocks": len(which),
            "estimates": [c.estimate() for c in clocks]}


def _summary(r: dict, seconds: float) -> tuple[float, float, float, float, float]:
    c = r["curve"]
    last_minute = c[:, 0] >= seconds - 60.0
    warm = c[:, 0] >= 30.0
    return c[-1, 1], c[last_minute, 1].max(), c[warm, 1].max(), c[last_minute, 2].max(), c[last_minute, 3].max()


def main(argv=None) -> int:
    """Run the benchmark for each jitter and print its table (and, with ``--out``, the plot); return 0."""
    p = argparse.ArgumentParser(prog="python -m supramodal.benchmarks.clock_alignment",
                                description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=10.0, help="stream length, minutes (default 10)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated delays (default 0)")
    p.add_argument("--out", type=Path, default=None, help="folder for clock_alignment.png (default: no plot)")
    args = p.parse_args(argv)
    seconds = 60.0 * args.minutes
    print(f"whiskers 5 kHz/50 +100 ppm, microphone 44.1 kHz/441 -100 ppm, 37 ms apart; {args.minutes:g} min; "
          "exponential delays, 1 block in 500 late by 50 ms, a 4 s whisker outage halfway\n")
    print("| jitter (mean delay) | alignment at the end | max, last minute | max after 30 s | absolute, last minute "
          "| rate error, last minute | µs per block |")
    print("|---|---|---|---|---|---|---|")
    curves = {}
    for jitter in (0.5e-3, 2e-3, 5e-3, 10e-3):
        r = run(seconds, jitter, args.seed)
        end, last_min, warm, absolute, ppm = _summary(r, seconds)
        curves[jitter] = r["curve"]
        print(f"| {jitter * 1e3:g} ms | {end * 1e3:.3f} ms | {last_min * 1e3:.3f} ms | {warm * 1e3:.3f} ms | "
              f"{absolute * 1e3:.3f} ms | {ppm:.2f} ppm | {r['us_per_block']:.1f} |", flush=True)
    print("\nerror against run time (2 ms jitter): segments fitted\n")
    print("| segments (1 s each) | alignment, max last minute | rate error, last minute | µs per block |")
    print("|---|---|---|---|")
    for window in (10, 30, DEFAULT_WINDOW_SEGMENTS, 480):
        r = run(seconds, 2e-3, args.seed, window_segments=window)
        _, last_min, _, _, ppm = _summary(r, seconds)
        print(f"| {window} | {last_min * 1e3:.3f} ms | {ppm:.2f} ppm | {r['us_per_block']:.1f} |", flush=True)
    if args.out is not None:
        try:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            print("matplotlib missing (pip install 'supramodal[plots]'): no plot")
            return 0
        args.out.mkdir(parents=True, exist_ok=True)
        fig, ax = plt.subplots(figsize=(7, 3.2))
        for jitter, c in curves.items():
            ax.semilogy(c[:, 0] / 60.0, np.maximum(c[:, 1], 1e-7) * 1e3, lw=0.8, label=f"{jitter * 1e3:g} ms jitter")
        ax.axhline(0.5, color="k", ls=":", lw=0.8)
        ax.set_xlabel("stream time, minutes")
        ax.set_ylabel("alignment error, ms")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(args.out / "clock_alignment.png", dpi=120)
        print(f"wrote {args.out / 'clock_alignment.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
