"""The measurements of ``supramodal bench`` (see :mod:`supramodal.benchmarks.filterbank`).

Definitions used throughout:

* real-time factor (RTF): compute seconds per second of signal, wall clock
  (``time.perf_counter``) on one core, median of repeated runs, each run on a
  fresh filterbank or pipeline whose matrices were built beforehand;
* relative error: per channel ``max |y - y_ref| / max |y_ref|`` over the compared
  span, the bank's figure being the worst channel; ``inf`` where a channel
  returns NaN or Inf. A channel is *bad* when its error is not finite or above 1.
  ``y_ref`` is the float64 reference backend (:class:`supramodal.backends.ReferenceFilterbank`).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from supramodal.backends import make_filterbank
from supramodal.banks import Bank, bank_by_name
from supramodal.benchmarks.filterbank import PINNED_THREADS
from supramodal.benchmarks.filterbank.peers import make_peer
from supramodal.benchmarks.filterbank.report import clean, write_report
from supramodal.decisions import DecisionRules, window_decision
from supramodal.gammatone import reference_impulse_response, relative_error
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.model import TextureModel
from supramodal.node.runtime.graph import Labels, Node
from supramodal.node.runtime.sinks import ListSink
from supramodal.pipeline import FeaturePipeline
from supramodal.replay.driver import ReplayDriver
from supramodal.textures import reference_texture_set
from supramodal.training import TRAIN_FRACTION

#: (backend, dtype) pairs measured; "fast" and "reference" are the product's backends, the rest peers.
VARIANTS = (("fast", "float64"), ("fast", "float32"), ("reference", "float64"),
            ("scipy-iir", "float64"), ("scipy-iir", "float32"), ("slaney", "float64"), ("slaney", "float32"))
PRODUCT = ("fast", "reference")
BANKS = ("cochlea", "whisker")
FEATURES = ("Af",)


@dataclass(frozen=True)
class Config:
    """What one bench run measures; :data:`FULL` and :data:`QUICK`."""

    quick: bool
    speed_seconds: dict                   # bank -> seconds of white noise for part a
    blocks: dict                          # bank -> block sizes of part a
    repeats: int                          # runs per measurement (fewer when a run exceeds the budget)
    budget: float                         # seconds of measuring per configuration before stopping repeats
    ir_samples: dict                      # bank -> impulse-response length for the design error
    drift_checkpoints: tuple              # seconds of stream at which part b reports
    drift_channels: dict                  # bank -> channel indices streamed in part b
    texture_seconds: float                # synthesised seconds per texture in part c
    session_seconds: float                # held-out seconds per texture replayed in part c
    node_blocks: dict                     # bank -> block sizes of part c (the first for every backend)
    node_speed: float                     # replay speed of the threaded node (1 = real time)
    epochs: int
    seed: int = 2010


FULL = Config(
    quick=False,
    speed_seconds={"cochlea": 1.0, "whisker": 10.0},
    blocks={"cochlea": (64, 441, 4410), "whisker": (50, 64, 441, 4410)},
    repeats=5, budget=6.0,
    ir_samples={"cochlea": 8192, "whisker": 5000},
    drift_checkpoints=(1, 60, 600, 3600),
    drift_channels={"cochlea": (0, 12, 24, 37, 49), "whisker": tuple(range(20))},
    texture_seconds=40.0, session_seconds=5.0,
    node_blocks={"cochlea": (441, 64), "whisker": (50,)},
    node_speed=1.0,
    epochs=DEFAULT_EPOCHS,
)

QUICK = replace(
    FULL, quick=True,
    speed_seconds={"cochlea": 0.1, "whisker": 1.0},
    repeats=1, budget=0.5,
    ir_samples={"cochlea": 4096, "whisker": 2500},
    drift_checkpoints=(1, 10),
    drift_channels={"cochlea": (0, 49), "whisker": tuple(range(20))},
    texture_seconds=4.0, session_seconds=0.5,
    node_blocks={"cochlea": (441,), "whisker": (50,)},
    node_speed=float("inf"),
    epochs=30,
)


def make_backend(bank: Bank, backend: str, dtype: str):
    """Return a fresh filterbank of the product (``fast``, ``reference``) or a peer."""
    if backend in PRODUCT:
        return make_filterbank(bank, backend, dtype=np.dtype(dtype))
    return make_peer(bank, backend, np.dtype(dtype))


def warm(fb, L: int):
    """Build what a backend builds on first use, then return it to rest."""
    fb.process(np.zeros(L))
    fb.reset()
    return fb


def channel_errors(y: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per channel :func:`~supramodal.gammatone.relative_error`; inf where y is not finite."""
    err = relative_error(y, ref, axis=-1)
    err[~np.isfinite(err)] = np.inf
    return err


def summarise_errors(err: np.ndarray) -> tuple[float, int]:
    """(worst channel's error, number of bad channels)."""
    return float(np.max(err)), int(np.sum(~np.isfinite(err) | (err > 1.0)))


def interleaved(jobs: dict, repeats: int, budget: float) -> dict:
    """Run each job ``repeats`` times, one run of every job per round.

    Interleaved so that a change of load on a shared machine affects every job alike.
    ``jobs[key](first)`` sets a run up, untimed (``first``:
    the job's first run), and returns the callable that is timed. A job whose runs exceed ``budget``
    seconds stops repeating. Returns ``{key: (wall seconds per run, CPU seconds per run)}``.
    """
    times: dict[Any, tuple[list[float], list[float]]] = {k: ([], []) for k in jobs}
    for r in range(repeats):
        for key, setup in jobs.items():
            wall, cpu = times[key]
            if r and sum(wall) > budget:
                continue
            run = setup(r == 0)
            t0, c0 = time.perf_counter(), time.process_time()
            run()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    return times


def stream_job(bank: Bank, variant, x: np.ndarray, L: int, keep: dict):
    """Return a job (for :func:`interleaved`) running a fresh, warmed filterbank over ``x`` in blocks of ``L``.

    The first run's output goes to ``keep[variant]``.
    """
    def setup(first: bool):
        fb = warm(make_backend(bank, *variant), L)

        def run() -> None:
            if first:
                keep[variant] = np.concatenate([fb.process(x[i : i + L]) for i in range(0, x.size, L)], axis=1)
            else:
                for i in range(0, x.size, L):
                    fb.process(x[i : i + L])
        return run
    return setup


def pareto(points: list[tuple[float, float]]) -> list[bool]:
    """Non-dominated points of (cost, error) pairs, lower is better in both; non-finite never on it."""
    front = []
    for i, (c, e) in enumerate(points):
        ok = np.isfinite(e) and not any(
            (c2 <= c and e2 <= e and (c2 < c or e2 < e)) for j, (c2, e2) in enumerate(points)
            if j != i and np.isfinite(e2))
        front.append(bool(ok))
    return front


# -- part a: error against run time -----------------------------------------------------------

def speed_error(cfg: Config, progress) -> list[dict]:
    """Measure part a: each variant's speed and error against the reference, per bank and block length.

    Returns one row per bank, block length and variant: real-time factors (wall and CPU), the
    streamed output's and the impulse response's error against the reference, the bad
    channels, and whether the row is on the speed/error Pareto front of its bank and block.
    ``progress`` is told a line per row.
    """
    rows = []
    for kind in BANKS:
        bank = bank_by_name(kind)
        rng = np.random.default_rng(cfg.seed)
        x = rng.standard_normal(int(cfg.speed_seconds[kind] * bank.fs))
        ref = make_filterbank(bank, "reference").process(x)
        n_ir = cfg.ir_samples[kind]
        ir_ref = reference_impulse_response(bank, n_ir)
        ir = {}
        with np.errstate(all="ignore"):
            for v in VARIANTS:
                ir[v] = summarise_errors(channel_errors(make_backend(bank, *v).impulse_response(n_ir), ir_ref))
        for L in cfg.blocks[kind]:
            n = x.size // L * L
            outputs: dict[tuple[str, str], np.ndarray] = {}
            with np.errstate(all="ignore"):
                times = interleaved({v: stream_job(bank, v, x[:n], L, outputs) for v in VARIANTS}, cfg.repeats,
                                    cfg.budget)
            for v in VARIANTS:
                err, bad = summarise_errors(channel_errors(outputs.pop(v), ref[:, :n]))
                wall, cpu = times[v]
                rtf = float(np.median(wall)) / (n / bank.fs)
                rows.append({"bank": kind, "channels": bank.channels, "fs": bank.fs, "backend": v[0], "dtype": v[1],
                             "block": L, "rtf": rtf, "rtf_runs": [r / (n / bank.fs) for r in wall],
                             "cpu_rtf": float(np.median(cpu)) / (n / bank.fs),
                             "signal_seconds": n / bank.fs, "error": err, "bad_channels": bad,
                             "ir_error": ir[v][0], "ir_bad_channels": ir[v][1]})
                progress(f"a. {kind:7} {v[0]:9} {v[1]:7} block {L:5}: RTF {rtf:.5f}  error {err:.2e}"
                         + (f"  ({bad} bad channels)" if bad else ""))
    for kind in BANKS:
        for L in {r["block"] for r in rows if r["bank"] == kind}:
            group = [r for r in rows if r["bank"] == kind and r["block"] == L]
            for r, on in zip(group, pareto([(r["rtf"], r["error"]) for r in group])):
                r["pareto"] = on
    return rows


# -- part b: error against stream duration ----------------------------------------------------

def sub_bank(bank: Bank, channels) -> Bank:
    """Return the bank of ``bank``'s ``channels`` (indices) alone."""
    idx = list(channels)
    return Bank(bank.kind, bank.fs, bank.cf[idx], bank.b[idx], tuple(bank.names[i] for i in idx))


def envelope(per_second: np.ndarray, bins: int = 120) -> list:
    """[[end second, max error over the interval], ...] on log-spaced intervals: the drift plot's data."""
    ends = np.unique(np.geomspace(1, per_second.size, bins).round().astype(int))
    starts = np.concatenate([[0], ends[:-1]])
    return [[int(b), float(np.max(per_second[a:b]))] for a, b in zip(starts, ends)]


def drift(cfg: Config, progress) -> dict:
    """Every backend and peer against the reference over one long stream of white noise, 1 s blocks."""
    out: dict[str, Any] = {"checkpoints": list(cfg.drift_checkpoints), "channels": {}, "rows": [], "series": {}}
    total = max(cfg.drift_checkpoints)
    for kind in BANKS:
        bank = sub_bank(bank_by_name(kind), cfg.drift_channels[kind])
        out["channels"][kind] = list(bank.names)
        L = int(round(bank.fs))
        ref = make_filterbank(bank, "reference")
        others = [(b, d) for b, d in VARIANTS if b != "reference"]
        fbs = {v: make_backend(bank, *v) for v in others}
        # relative_error's numerator and divisor, kept apart second by second, so that the error over
        # the last second and over the whole stream up to each mark follow without keeping the stream.
        diff = {v: np.zeros((total, bank.channels)) for v in others}
        scale = np.zeros((total, bank.channels))
        rng = np.random.default_rng(cfg.seed + 1)
        t0 = time.perf_counter()
        for s in range(total):
            x = rng.standard_normal(L)
            yr = ref.process(x)
            scale[s] = np.max(np.abs(yr), axis=1)
            with np.errstate(all="ignore"):
                for v, fb in fbs.items():
                    d = np.max(np.abs(fb.process(x).astype(np.float64) - yr), axis=1)
                    d[~np.isfinite(d)] = np.inf
                    diff[v][s] = d
            if (s + 1) % 600 == 0 or s + 1 == total:
                progress(f"b. {kind}: {s + 1} s of stream ({time.perf_counter() - t0:.0f} s)")
        for v in others:
            with np.errstate(all="ignore"):
                per_second = np.max(diff[v] / scale, axis=1)
            out["series"][f"{kind}/{v[0]}/{v[1]}"] = envelope(per_second)
            for t in cfg.drift_checkpoints:
                with np.errstate(all="ignore"):
                    upto = np.max(np.max(diff[v][:t], axis=0) / np.max(scale[:t], axis=0))
                out["rows"].append({"bank": kind, "backend": v[0], "dtype": v[1], "seconds": t,
                                    "error_last_second": float(per_second[t - 1]), "error_up_to": float(upto)})
    return out


# -- part c: the whole node -------------------------------------------------------------------

def texture_session(kind: str, cfg: Config):
    """Training windows from the first :data:`~supramodal.training.TRAIN_FRACTION` of each texture.

    The session is the last seconds of each.
    """
    ts = reference_texture_set(kind)
    bank = bank_by_name(kind)
    pipe_W = FeaturePipeline(bank, FEATURES).window_samples
    values, labels, session, ranges = [], [], [], []
    n_session = int(round(cfg.session_seconds * bank.fs))
    t = 0.0
    for i, name in enumerate(ts.names):
        x = ts.synthesize(i, duration=cfg.texture_seconds)
        w = FeaturePipeline(bank, FEATURES).run(x[: int(TRAIN_FRACTION * x.size)], block=65536)
        values.append(w.values)
        labels += [i] * len(w)
        session.append(x[-n_session:])
        ranges.append((t, t + n_session / bank.fs, name))
        t += n_session / bank.fs
    model = TextureModel.train(np.concatenate(values), np.array(labels), ts.names, bank, FEATURES, pipe_W,
                               epochs=cfg.epochs, seed=0, calibration_folds=0)   # labels only
    return bank, model, np.concatenate(session), ranges


def make_pipeline(bank: Bank, backend: str, dtype: str) -> FeaturePipeline:
    """Return a warmed feature pipeline of ``bank`` on the product's ``backend`` or a peer's filterbank."""
    if backend in PRODUCT:
        pipe = FeaturePipeline(bank, FEATURES, backend=backend, dtype=np.dtype(dtype))
    else:
        pipe = FeaturePipeline(bank, FEATURES, dtype=np.dtype(dtype))
        pipe.filterbank = make_peer(bank, backend, np.dtype(dtype))
    warm(pipe.filterbank, pipe.window_samples)
    return pipe


def chain_job(bank, model, session, L, variant, keep: dict):
    """Return a job (for :func:`interleaved`) running the pipeline to decisions, block by block.

    It runs as the node's processing thread runs it (fresh, warmed pipeline each run); the
    first run's decided labels go to ``keep[(variant, L)]``.
    """
    def setup(first: bool):
        pipe = make_pipeline(bank, *variant)

        def run() -> None:
            labels = []
            with np.errstate(all="ignore"):
                for i in range(0, session.size, L):
                    w = pipe.process(session[i : i + L])
                    if len(w):
                        for o in model.log_posteriors(w.values):
                            labels.append(window_decision(o).label)
                w = pipe.finish()
                if len(w):
                    labels += [window_decision(o).label for o in model.log_posteriors(w.values)]
            if first:
                keep[(variant, L)] = labels
        return run
    return setup


def threaded_node(bank, model, session, ranges, L, speed):
    """Run the node itself (driver thread, ring buffer, processing thread, sink) on the replayed session."""
    sink = ListSink()
    driver = ReplayDriver((session[:, None], bank.fs), block_size=L, speed=speed, on_notice=None)
    node = Node(driver, make_pipeline(bank, "fast", "float64"), [sink], model=model,
                decision=DecisionRules(scope="window"), mapping="mono", labels=Labels(list(ranges)), overrun="block")
    summary = node.run()
    return summary, [e["predicted"] for e in sink.events]


def node_part(cfg: Config, progress) -> dict:
    """Measure part c: the chain to decisions per variant and block length, and the threaded node.

    Returns ``{"chain": rows, "threaded": rows}``: real-time factors, windows, and agreement
    with the reference's decisions (and accuracy) per bank. ``progress`` is told a line per row.
    """
    rows, threaded = [], []
    for kind in BANKS:
        bank, model, session, ranges = texture_session(kind, cfg)
        seconds = session.size / bank.fs
        W = int(round(0.1 * bank.fs))
        truth = [next(k for k, (a, b, _) in enumerate(ranges) if a <= (w + 0.5) * W / bank.fs < b)
                 for w in range(session.size // W)]
        progress(f"c. {kind}: model trained, session of {seconds:g} s")
        labels: dict[tuple[tuple[str, str], int], list[int]] = {}
        first = cfg.node_blocks[kind][0]
        jobs = {(v, L): chain_job(bank, model, session, L, v, labels)
                for v in VARIANTS for L in (cfg.node_blocks[kind] if v[0] == "fast" else (first,))}
        times = interleaved(jobs, cfg.repeats, cfg.budget)
        ref = labels[(("reference", "float64"), first)]
        for (v, L), (wall, cpu) in times.items():
            got = np.array(labels[(v, L)])
            agree = float(np.mean(got == np.array(ref))) if got.size else float("nan")
            acc = float(np.mean(got == np.array(truth[: got.size]))) if got.size else float("nan")
            rtf = float(np.median(wall)) / seconds
            rows.append({"bank": kind, "backend": v[0], "dtype": v[1], "block": L, "rtf": rtf,
                         "rtf_runs": [r / seconds for r in wall], "cpu_rtf": float(np.median(cpu)) / seconds,
                         "windows": int(got.size), "agreement": agree, "accuracy": acc, "session_seconds": seconds})
            progress(f"c. {kind:7} {v[0]:9} {v[1]:7} block {L:4}: RTF {rtf:.5f}  agreement {agree:.3f}")
        summary, predicted = threaded_node(bank, model, session, ranges, first, cfg.node_speed)
        ref_names = [model.classes[k] for k in ref]
        agree = float(np.mean([p == q for p, q in zip(predicted, ref_names)])) if predicted else float("nan")
        threaded.append({"bank": kind, "backend": "fast", "dtype": "float64", "block": first,
                         "speed": cfg.node_speed, "rtf": summary["real_time_factor"],
                         "latency_ms": summary["latency_ms"], "windows": summary["windows"],
                         "window_accuracy": summary["window_accuracy"], "agreement": agree,
                         "frames_dropped": summary["frames"]["dropped"]})
        progress(f"c. {kind}: threaded node RTF {summary['real_time_factor']:.5f}, agreement {agree:.3f}")
    return {"chain": rows, "threaded": threaded}


# -- targets ----------------------------------------------------------------------------------

def targets(results: dict) -> list[dict]:
    """Return the issue's Done-when figures, each with its measured value and whether it is met."""
    a, c = results["speed_error"], results["node"]["chain"]

    def row(rows, **kw):
        hits = [r for r in rows if all(r.get(k) == v for k, v in kw.items())]
        return hits[0] if hits else None

    out = []

    def add(name, value, limit, met, note=""):
        out.append({"target": name, "value": value, "limit": limit, "met": bool(met), "note": note})

    for kind, L, limit in (("cochlea", 441, 0.03), ("cochlea", 64, 0.1), ("whisker", 50, 0.002)):
        r = row(c, bank=kind, backend="fast", dtype="float64", block=L)
        if r:
            add(f"{kind} pipeline to decisions, float64, {L}-sample blocks: RTF", r["rtf"], limit, r["rtf"] <= limit)
    for kind in BANKS:
        errs = [r["error"] for r in a if r["bank"] == kind and r["backend"] == "fast" and r["dtype"] == "float64"]
        if errs:
            add(f"{kind} fast float64 filterbank: max relative error (stream, every block size)", max(errs), 1e-12,
                max(errs) <= 1e-12)
        for dtype in ("float64", "float32"):
            fast = row(a, bank=kind, backend="fast", dtype=dtype, block=441)
            peers = [r for r in a if r["bank"] == kind and r["block"] == 441 and r["backend"] not in PRODUCT
                     and r["dtype"] == dtype]
            if fast and peers:
                best = min(peers, key=lambda r: r["rtf"])
                speedup = best["rtf"] / fast["rtf"]
                add(f"{kind} 441-sample blocks: speed-up of fast {dtype} over the faster {dtype} peer "
                    f"({best['backend']})", speedup, 5.0, speedup >= 5.0,
                    f"peer error {best['error']:.2g} ({best['bad_channels']} bad channels) vs {fast['error']:.2g}")
    return out


# -- main -------------------------------------------------------------------------------------

def machine() -> dict:
    """Return this machine for the report: CPU, logical CPUs, Python, numpy, scipy, platform, pinned threads."""
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next((line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")), cpu)
    except OSError:
        pass
    import scipy

    return {"cpu": cpu, "logical_cpus": os.cpu_count(), "python": platform.python_version(),
            "numpy": np.__version__, "scipy": scipy.__version__, "platform": platform.platform(),
            "threads": {k: os.environ.get(k) for k in PINNED_THREADS}}


def run(cfg: Config, progress=lambda m: None) -> dict:
    """All three parts; the results as one JSON-ready dict."""
    t0 = time.perf_counter()
    load0 = os.getloadavg() if hasattr(os, "getloadavg") else None
    results: dict[str, Any] = {"meta": {"quick": cfg.quick, "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
                                         "machine": machine(), "config": asdict(cfg), "load_average_start": load0}}
    results["speed_error"] = speed_error(cfg, progress)
    results["drift"] = drift(cfg, progress)
    results["node"] = node_part(cfg, progress)
    results["targets"] = targets(results)
    results["meta"]["load_average_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None
    results["meta"]["seconds"] = time.perf_counter() - t0
    return results


def main(argv=None) -> int:
    """Run the benchmark and write its report (``supramodal bench``); return 0."""
    parser = argparse.ArgumentParser(prog="supramodal bench", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short signals and streams (well under a minute)")
    parser.add_argument("--out", default="out/bench", help="directory for the report (default ./out/bench)")
    parser.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")
    args = parser.parse_args(argv)
    progress = (lambda m: print(f"supramodal bench: {m}", file=sys.stderr, flush=True))
    results = run(QUICK if args.quick else FULL, progress)
    written = write_report(results, args.out)
    if args.json:
        print(json.dumps(clean(results)))
    else:
        for t in results["targets"]:
            print(f"{'met    ' if t['met'] else 'NOT MET'}  {t['target']}: {t['value']:.4g} (limit {t['limit']:g})")
        print("wrote " + ", ".join(str(p) for p in written))
    return 0
