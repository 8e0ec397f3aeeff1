"""The bench's report: Markdown, CSV, PNG (matplotlib, optional) and JSON."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from supramodal.experiments.plotting import have_matplotlib
from supramodal.training import TRAIN_FRACTION

LABELS = {("fast", "float64"): "fast float64", ("fast", "float32"): "fast float32",
          ("reference", "float64"): "reference float64",
          ("scipy-iir", "float64"): "scipy iir float64", ("scipy-iir", "float32"): "scipy iir float32",
          ("slaney", "float64"): "Slaney float64", ("slaney", "float32"): "Slaney float32"}
MARKERS = {"fast": "o", "reference": "s", "scipy-iir": "^", "slaney": "v"}


def clean(obj):
    """JSON-safe copy: non-finite floats become None (strict JSON has no Infinity or NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean(v) for v in obj]
    return obj


def _e(v) -> str:
    return "bad" if v is None or not math.isfinite(v) else f"{v:.1e}"


def _rtf(v) -> str:
    return f"{v:.4f}" if v >= 1e-3 else f"{v:.5f}"


def write_report(results: dict, out) -> list[Path]:
    """Write the report's files into ``out``; return the paths written.

    The files are ``report.md``, ``speed_error.csv``, ``drift.csv``, ``node.csv``,
    ``bench.json`` and, with matplotlib, ``pareto.png`` and ``drift.png``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []

    path = out / "bench.json"
    path.write_text(json.dumps(clean(results), indent=1))
    written.append(path)

    a, d, c = results["speed_error"], results["drift"]["rows"], results["node"]
    written.append(_csv(out / "speed_error.csv",
                        ["bank", "backend", "dtype", "block", "rtf", "cpu_rtf", "error", "bad_channels", "ir_error",
                         "pareto"],
                        [[r["bank"], r["backend"], r["dtype"], r["block"], f"{r['rtf']:.6g}", f"{r['cpu_rtf']:.6g}",
                          f"{r['error']:.3g}", r["bad_channels"], f"{r['ir_error']:.3g}", int(r["pareto"])]
                         for r in a]))
    written.append(_csv(out / "drift.csv", ["bank", "backend", "dtype", "seconds", "error_last_second", "error_up_to"],
                        [[r["bank"], r["backend"], r["dtype"], r["seconds"], f"{r['error_last_second']:.3g}",
                          f"{r['error_up_to']:.3g}"] for r in d]))
    node_rows = [[r["bank"], r["backend"], r["dtype"], r["block"], f"{r['rtf']:.6g}", f"{r['cpu_rtf']:.6g}",
                  f"{r['agreement']:.4f}", f"{r['accuracy']:.4f}", r["windows"], 0] for r in c["chain"]]
    node_rows += [[r["bank"], r["backend"], r["dtype"], r["block"], f"{r['rtf']:.6g}", f"{r['rtf']:.6g}",
                   f"{r['agreement']:.4f}", f"{r['window_accuracy'] or float('nan'):.4f}", r["windows"], 1]
                  for r in c["threaded"]]
    written.append(_csv(out / "node.csv", ["bank", "backend", "dtype", "block", "rtf", "cpu_rtf", "agreement",
                                           "accuracy", "windows", "threaded"], node_rows))

    plots = have_matplotlib()
    if plots:
        written.append(_plot_pareto(results, out / "pareto.png"))
        written.append(_plot_drift(results, out / "drift.png"))
    path = out / "report.md"
    path.write_text(markdown(results, plots))
    written.insert(0, path)
    return written


def _by_variant(rows: list) -> dict:
    """Rows grouped by (backend, dtype), in order of first appearance."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["backend"], r["dtype"]), []).append(r)
    return groups


def _csv(path: Path, header: list, rows: list) -> Path:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return path


def markdown(results: dict, plots: bool = True) -> str:
    """Return the text of ``report.md`` for ``results`` (with ``plots``, it shows the PNGs)."""
    meta = results["meta"]
    m = meta["machine"]
    load = lambda la: "n/a" if not la else ", ".join(f"{v:.2f}" for v in la)  # noqa: E731
    lines = [
        "# supramodal bench" + (" (quick run: short signals, not for quoting)" if meta["quick"] else ""),
        "",
        f"Run {meta['started']}, {meta['seconds']:.0f} s. {m['cpu']}, {m['logical_cpus']} logical CPUs, "
        f"Python {m['python']}, numpy {m['numpy']}, scipy {m['scipy']}; BLAS/OpenMP threads pinned to 1 "
        f"({', '.join(f'{k}={v}' for k, v in m['threads'].items())}). Load average (1, 5, 15 min) at start "
        f"{load(meta['load_average_start'])}, at end {load(meta['load_average_end'])}: other processes share the "
        "machine, so every real-time factor is an upper bound for a quiet core.",
        "",
        "Real-time factor (RTF): compute seconds per second of signal, wall clock, median of repeated runs "
        "(CSV and JSON also give the CPU-time figure, `cpu_rtf`, less sensitive to other processes). "
        "Error: per channel max |y - y_ref| / max |y_ref| against the float64 reference backend (four first-order "
        "complex sections per channel with scipy.signal.lfilter), the worst channel; \"bad\": a channel returns "
        "NaN or Inf or an error above 1.",
        "",
        "## Targets",
        "",
        "Pipeline figures: part c, back-to-back blocks on one core; filterbank figures: part a.",
        "",
        "| target | measured | limit | met | note |",
        "|---|---|---|---|---|",
    ]
    for t in results["targets"]:
        lines.append(f"| {t['target']} | {t['value']:.4g} | {t['limit']:g} | {'yes' if t['met'] else '**no**'} | "
                     f"{t.get('note', '')} |")
    lines += ["", "## a. Error against run time", "",
              "Filterbank only, mono white noise (std 1) in blocks, one scipy call per channel per block for the "
              "peers (state carried). `ir error`: the design's impulse response against the sampled analytic "
              "gammatone. Pareto-optimal points are marked *. The reference recurses on its pole once per sample, "
              "the fast form once per pass (a block of up to 24 sub-blocks): against the analytic gammatone "
              "(`ir error`) the fast "
              "form is the more accurate of the two, and its error against the reference on a stream is mostly "
              "the reference's own."]
    a = results["speed_error"]
    for kind in dict.fromkeys(r["bank"] for r in a):
        rows = [r for r in a if r["bank"] == kind]
        blocks = sorted({r["block"] for r in rows})
        r0 = rows[0]
        lines += ["",
                  f"### {kind} ({r0['channels']} channels, {r0['fs']:g} Hz, {r0['signal_seconds']:.3g} s of noise)",
                  "",
                  "| backend | " + " | ".join(f"RTF @{L}" for L in blocks)
                  + " | error (worst block) | bad channels | ir error |",
                  "|---|" + "---|" * (len(blocks) + 3)]
        for key, rr in _by_variant(rows).items():
            by = {r["block"]: r for r in rr}
            cells = [(_rtf(by[L]["rtf"]) + ("*" if by[L]["pareto"] else "")) if L in by else "" for L in blocks]
            worst = max(r["error"] for r in rr)
            lines.append(f"| {LABELS.get(key, key)} | " + " | ".join(cells) +
                         f" | {_e(worst)} | {max(r['bad_channels'] for r in rr)} | {_e(rr[0]['ir_error'])} |")
    if plots:
        lines += ["", "![error against RTF](pareto.png)"]

    d = results["drift"]
    lines += ["", "## b. Error against stream duration", "",
              "One stream of white noise (std 1) in 1 s blocks through every backend and the reference at once; "
              "error over the last second before each mark, and (in brackets) over the whole stream up to it. "
              "Channels streamed: " + "; ".join(f"{k}: {', '.join(v)}" for k, v in d["channels"].items()) + "."]
    marks = d["checkpoints"]
    for kind in d["channels"]:
        lines += ["", f"### {kind}", "", "| backend | " + " | ".join(_dur(t) for t in marks) + " |",
                  "|---|" + "---|" * len(marks)]
        for key, rr in _by_variant([r for r in d["rows"] if r["bank"] == kind]).items():
            at = {r["seconds"]: r for r in rr}
            cells = [f"{_e(at[t]['error_last_second'])} ({_e(at[t]['error_up_to'])})" for t in marks]
            lines.append(f"| {LABELS.get(key, key)} | " + " | ".join(cells) + " |")
    f32 = [r["error_up_to"] for r in d["rows"] if r["backend"] == "fast" and r["dtype"] == "float32"]
    f64 = [r["error_up_to"] for r in d["rows"] if r["backend"] == "fast" and r["dtype"] == "float64"]
    if f32 and f64:
        lines += ["", f"Fast float64 stays at {_e(max(f64))} or below over the whole stream (no drift); fast float32 "
                  f"at {_e(max(f32))} or below, against the bound of 1e-6 stated in docs/stability.md."]
    if plots:
        lines += ["", "![error against stream time](drift.png)"]

    c = results["node"]
    lines += ["", "## c. The whole node", "",
              "Pipeline to decisions (gammatone, peaks, Af per 100 ms window, MLP, winner-take-all) on a replayed "
              "session of the eight reference textures (held-out seconds of each, model trained on the spot on the "
              f"first {100 * TRAIN_FRACTION:g} % of each texture), block by block as the node's processing thread "
              "runs it. "
              "Agreement: share "
              "of windows whose decision equals the float64 reference backend's; accuracy: against the truth.", "",
              "| bank | backend | block | RTF | CPU RTF | agreement | accuracy | windows |",
              "|---|---|---|---|---|---|---|---|"]
    for r in c["chain"]:
        lines.append(f"| {r['bank']} | {LABELS.get((r['backend'], r['dtype']))} | {r['block']} | {_rtf(r['rtf'])} | "
                     f"{_rtf(r['cpu_rtf'])} | {r['agreement']:.3f} | {r['accuracy']:.3f} | {r['windows']} |")
    lines += ["", "The threaded node itself (replay driver, ring buffer, processing thread, list sink, as "
              "`supramodal run` builds it; RTF = processing-thread CPU time per second of stream; latency = "
              "decision time minus the arrival of the block that completed the window):", "",
              "| bank | block | replay speed | RTF | latency p50 / p99 (ms) | agreement | windows |",
              "|---|---|---|---|---|---|---|"]
    for r in c["threaded"]:
        lat = r["latency_ms"] or {}
        speed = ("real time" if r["speed"] == 1 else "as fast as possible" if not math.isfinite(r["speed"])
                 else r["speed"])
        lines.append(f"| {r['bank']} | {r['block']} | {speed} | {_rtf(r['rtf'])} | "
                     f"{lat.get('p50', float('nan')):.2f} / {lat.get('p99', float('nan')):.2f} | "
                     f"{r['agreement']:.3f} | "
                     f"{r['windows']} |")
    if any(r["speed"] == 1 for r in c["threaded"]):
        lines += ["", "Paced in real time, the processing thread handles each block after ~10 ms spent waiting (the "
                  "core meanwhile runs the driver thread and other processes), so the same code runs with cold "
                  "caches: its CPU time per second of stream is higher than the back-to-back figures of the table "
                  "above, which are the throughput of the pipeline to decisions on one core."]
    return "\n".join(lines) + "\n"


def _dur(t: int) -> str:
    return f"{t} s" if t < 60 else f"{t // 60} min"


def _plot_pareto(results: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    a = results["speed_error"]
    banks = list(dict.fromkeys(r["bank"] for r in a))
    ncol = max(len({r["block"] for r in a if r["bank"] == k}) for k in banks)
    fig, axes = plt.subplots(len(banks), ncol, figsize=(3.6 * ncol, 3.3 * len(banks)), squeeze=False)
    floor, ceiling = 1e-17, 30.0          # exact (the reference against itself) / NaN, Inf or above 1
    for i, kind in enumerate(banks):
        blocks = sorted({r["block"] for r in a if r["bank"] == kind})
        for j in range(ncol):
            ax = axes[i][j]
            if j >= len(blocks):
                ax.axis("off")
                continue
            rows = [r for r in a if r["bank"] == kind and r["block"] == blocks[j]]
            for r in rows:
                bad = not math.isfinite(r["error"]) or r["error"] > 1
                ax.scatter(r["rtf"], ceiling if bad else max(r["error"], floor),
                           marker="x" if bad else MARKERS[r["backend"]],
                           facecolors="none" if r["dtype"] == "float32" and not bad else None,
                           color=f"C{list(LABELS).index((r['backend'], r['dtype']))}",
                           label=LABELS[(r["backend"], r["dtype"])] + (" (bad)" if bad else ""))
            front = sorted((r["rtf"], r["error"]) for r in rows if r["pareto"])
            if front:
                ax.step([p[0] for p in front], [max(p[1], floor) for p in front], where="post", color="k",
                        linewidth=0.8, linestyle="--")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_ylim(floor / 10, ceiling * 10)
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set_title(f"{kind}, {blocks[j]}-sample blocks", fontsize=9)
            ax.set_xlabel("real-time factor (one core)", fontsize=8)
            ax.set_ylabel("max relative error", fontsize=8)
            ax.tick_params(labelsize=7)
    handles, names = [], []
    for ax in axes.flat:
        for h, n in zip(*ax.get_legend_handles_labels()):
            if n not in names:
                handles.append(h)
                names.append(n)
    fig.legend(handles, names, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle("Error against run time (dashed: Pareto front; x at the top: NaN, Inf or error > 1; "
                 "bottom row: 0, the reference against itself)", fontsize=10)
    fig.tight_layout(rect=(0, 0.08, 1, 0.96))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _plot_drift(results: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    series = results["drift"]["series"]
    banks = list(results["drift"]["channels"])
    fig, axes = plt.subplots(1, len(banks), figsize=(6 * len(banks), 3.6), squeeze=False)
    for ax, kind in zip(axes[0], banks):
        for key, values in series.items():
            k, backend, dtype = key.split("/")
            if k != kind:
                continue
            t = np.array([p[0] for p in values], dtype=float)
            v = np.array([p[1] if p[1] is not None else np.inf for p in values], dtype=float)
            v = np.where(np.isfinite(v) & (v <= 1), np.maximum(v, 1e-17), 30.0)     # NaN, Inf, > 1: at the top
            ax.plot(t, v, label=LABELS[(backend, dtype)], color=f"C{list(LABELS).index((backend, dtype))}",
                    linewidth=0.8, linestyle="-" if dtype == "float64" else ":")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(1e-17, 300.0)
        ax.set_xlabel("stream time (s)")
        ax.set_ylabel("max relative error (log-spaced intervals)")
        ax.set_title(f"{kind}: error against the reference over the stream (NaN, Inf or > 1 drawn at the top)",
                     fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
