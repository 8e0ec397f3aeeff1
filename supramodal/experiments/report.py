"""Tables, CSV files and plots of the paper's figures, and the one place that writes any experiment's result.

That place is :func:`write_figure`. matplotlib is optional (extra ``plots``): CSV files are always written,
PNG files when matplotlib can be imported (:mod:`supramodal.experiments.plotting`, which the experiments use
themselves).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from supramodal.experiments.fig3 import PAPER_FIG3
from supramodal.experiments.plotting import have_matplotlib, pyplot, save_figure, write_csv
from supramodal.features import FEATURES

SHADES = {"Af": "0.2", "A": "0.5", "f": "0.75"}
MARKERS = {"Af": "o", "A": "s", "f": "^"}


def fig3_table(result: dict) -> str:
    """Per-texture and mean rates of each feature, beside the paper's means."""
    feats = list(result["features"])
    names = list(result["features"][feats[0]]["per_texture"])
    lines = [f"Fig. 3, {result['bank']} bank, {result['texture_set']}",
             f"{'texture':<10}" + "".join(f"{f:>9}" for f in feats)]
    for n in names:
        lines.append(f"{n:<10}" + "".join(f"{result['features'][f]['per_texture'][n]:>9.3f}" for f in feats))
    lines.append(f"{'mean':<10}" + "".join(f"{result['features'][f]['mean_rate']:>9.3f}" for f in feats))
    if any("sd" in result["features"][f] for f in feats):
        lines.append(f"{'sd':<10}" + "".join(f"{result['features'][f].get('sd', 0.0):>9.3f}" for f in feats))
    paper = PAPER_FIG3.get(result["bank"], {})
    lines.append(f"{'paper':<10}" + "".join(f"{paper.get(f, float('nan')):>9.3f}" for f in feats))
    t = result.get("timing")
    if t and t.get("signal_seconds"):
        lines.append(f"pipeline compute: {t['compute_seconds']:.2f} s for {t['signal_seconds']:.0f} s of signal "
                     f"({t['compute_seconds'] / t['signal_seconds']:.4f} s per s)")
    return "\n".join(lines)


def write_fig3(result: dict, out: Path, suffix: str = "") -> list[Path]:
    """Write ``fig3_<bank><suffix>.csv`` (and ``.png`` where matplotlib is installed) into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    feats = list(result["features"])
    names = list(result["features"][feats[0]]["per_texture"])
    csv_path = out / f"fig3_{result['bank']}{suffix}.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["bank", "feature", "texture", "rate"])
        for f in feats:
            for n in names:
                w.writerow([result["bank"], f, n, f"{result['features'][f]['per_texture'][n]:.4f}"])
            w.writerow([result["bank"], f, "mean", f"{result['features'][f]['mean_rate']:.4f}"])
            if "sd" in result["features"][f]:
                w.writerow([result["bank"], f, "sd", f"{result['features'][f]['sd']:.4f}"])
    written = [csv_path]
    if have_matplotlib():
        written.append(_plot_fig3(result, out / f"fig3_{result['bank']}{suffix}.png"))
    return written


def _plot_fig3(result: dict, path: Path) -> Path:
    import numpy as np

    plt = pyplot()

    feats = list(result["features"])
    names = list(result["features"][feats[0]]["per_texture"])
    fig, ax = plt.subplots(figsize=(8, 5))
    width = 0.8 / len(feats)
    paper = PAPER_FIG3.get(result["bank"], {})
    for k, f in enumerate(feats):
        rates = [result["features"][f]["per_texture"][n] for n in names]
        sd = f" ± {result['features'][f]['sd']:.3f}" if "sd" in result["features"][f] else ""
        ax.bar(np.arange(len(names)) + (k - (len(feats) - 1) / 2) * width, rates, width,
               color=SHADES.get(f, None), edgecolor="k", linewidth=0.5,
               label=f"{f}: mean {result['features'][f]['mean_rate']:.3f}{sd} (paper {paper.get(f, float('nan')):.3f})")
    ax.axhline(1 / len(names), color="r", linestyle=":", linewidth=1, label="chance")
    peaks = result.get("textures", {})
    labels = [f"{n}\n" + "\n".join(f"{p:.0f}" for p in peaks[n]) if n in peaks else n for n in names]
    ax.set_xticks(range(len(names)), labels, fontsize=8)
    if peaks:
        ax.set_xlabel("texture (peak frequencies, Hz)", fontsize=8)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("classification rate")
    note = ("\nbar k: mean over the sets of their k-th texture; ± is the sd of the sets' mean rates"
            if "sets" in result else "")
    ax.set_title(f"Fig. 3, {result['bank']} bank: {result['texture_set']}{note}", fontsize=10)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.25 if peaks else -0.08), ncol=2,
              frameon=False)
    return save_figure(fig, path)


# -- every figure ----------------------------------------------------------------------------------

def _fmt(v, spec=".1f") -> str:
    return "-" if v is None else format(v, spec)


def write_figure(name: str, result: dict, out: Path) -> list[Path]:
    """CSV (and PNG with matplotlib) of one figure's result into ``out``; returns the paths written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if name == "fig3":
        if "figure" not in result:
            return write_fig3(result, out)
        written = []
        for r in result["banks"].values():
            written += write_fig3(r, out)
        for r in result.get("random_sets", {}).values():
            written += write_fig3(r, out, suffix="_random")
        return written
    if name == "calibration":
        from supramodal.experiments.calibration import write_calibration
        from supramodal.experiments.common import progress_to_stderr

        return write_calibration(result, out, notice=progress_to_stderr)
    if name == "change":
        from supramodal.experiments.change import write_change

        return write_change(result, out)
    if name == "newtouch":
        from supramodal.experiments.newtouch import write_newtouch

        return write_newtouch(result, out)
    writer = {"fig1": _write_fig1, "fig4": _write_fig4, "fig5": _write_fig5, "fig6": _write_fig6,
              "fusion": _write_fusion}[name]
    paths = writer(result, out)
    if have_matplotlib():
        plotter = {"fig1": _plot_fig1, "fig4": _plot_fig4, "fig5": _plot_fig5, "fig6": _plot_fig6,
                   "fusion": _plot_fusion}[name]
        paths.append(plotter(result, out / f"{name}.png"))
    return paths


def figure_table(name: str, result: dict) -> str:
    """Return a short text summary of one figure's result, beside the paper's statement."""
    if name == "fig3":
        if "figure" not in result:
            return fig3_table(result)
        parts = [fig3_table(r) for r in result["banks"].values()]
        parts += [fig3_table(r) for r in result.get("random_sets", {}).values()]
        return "\n\n".join(parts)
    if name == "fusion":
        from supramodal.experiments.fusion import fusion_table

        return fusion_table(result)
    if name == "calibration":
        from supramodal.experiments.calibration import calibration_table

        return calibration_table(result)
    return {"fig1": _table_fig1, "fig4": _table_fig4, "fig5": _table_fig5, "fig6": _table_fig6}[name](result)


def _write_fig1(result: dict, out: Path) -> list[Path]:
    paths = []
    for bank, r in result["banks"].items():
        names = [c["name"] for c in r["channels"]]
        rows = ([f] + [r["gain_db"][k][i] for k in range(len(names))] for i, f in enumerate(r["freqs"]))
        paths.append(write_csv(out / f"fig1_{bank}.csv", ["freq_hz"] + [f"{n}_db" for n in names], rows))
    keys = ["name", "cf", "b", "B", "peak_hz", "width_3db", "width_3db_formula", "max_gain_db"]
    rows = ([bank] + [c[k] for k in keys] for bank, r in result["banks"].items() for c in r["channels"])
    paths.append(write_csv(out / "fig1_channels.csv", ["bank"] + keys, rows))
    return paths


def _table_fig1(result: dict) -> str:
    lines = [f"Fig. 1, transfer functions ({result['method']})"]
    for bank, r in result["banks"].items():
        ch = r["channels"]
        B = [c["B"] for c in ch]
        w = [c["width_3db"] for c in ch if c["width_3db"] is not None]
        lines.append(f"{bank}: {len(ch)} channels, "
                     f"cf {min(c['cf'] for c in ch):.0f}..{max(c['cf'] for c in ch):.0f} Hz, "
                     f"B {min(B):.0f}..{max(B):.0f} (mean {sum(B) / len(B):.0f}), "
                     f"-3 dB width {min(w):.1f}..{max(w):.1f} Hz (mean {sum(w) / len(w):.1f})"
                     + (f", {len(ch) - len(w)} channel(s) with no lower -3 dB edge" if len(w) < len(ch) else ""))
    return "\n".join(lines)


def _plot_fig1(result: dict, path: Path) -> Path:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    titles = {"cochlea": "(a) cochlea: 50 channels, 20 Hz..20 kHz, q_ear 9.26, b_min 24.7",
              "whisker": "(b) whiskers: 20 vibrissae, q_ear 35, b_min 15"}
    for ax, (bank, r) in zip(axes, result["banks"].items()):
        for row in r["gain_db"]:
            ax.semilogx(r["freqs"], row, color="k", linewidth=0.6)
        ax.set_ylim(-60, 5)
        ax.set_xlim(r["freqs"][0], r["freqs"][-1])
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel("gain (dB)")
        ax.set_title(titles.get(bank, bank), fontsize=9)
        ax.grid(True, which="both", linewidth=0.3)
    return save_figure(fig, path)


def _write_fig4(result: dict, out: Path) -> list[Path]:
    feats = list(result["features"])
    header = ["freq_hz"] + [f"{f}_{k}" for f in feats for k in ("mean", "sd", "normalised")]
    rows = ([fr] + [result["features"][f][k][i] for f in feats for k in ("mean", "sd", "normalised")]
            for i, fr in enumerate(result["freqs"]))
    keys = ["peak_hz", "low_hz", "high_hz", "width_3db", "q", "closed", "range_db"]
    sharp = ([f] + [result["features"][f]["sharpness"][k] for k in keys] for f in feats)
    return [write_csv(out / "fig4.csv", header, rows), write_csv(out / "fig4_sharpness.csv", ["feature"] + keys, sharp)]


def _table_fig4(result: dict) -> str:
    lines = [f"Fig. 4, vibrissa {result['channel']} (cf {result['cf']:g} Hz, b {result['b']:.1f} Hz): "
             f"{len(result['freqs'])} sines {result['freqs'][0]:g}..{result['freqs'][-1]:g} Hz, "
             f"{result['windows']} steady windows each",
             f"{'feature':<8}{'peak Hz':>9}{'-3dB lo':>9}{'-3dB hi':>9}{'width':>8}{'Q':>7}{'range dB':>10}"]
    for f, r in result["features"].items():
        s = r["sharpness"]
        lines.append(f"{f:<8}{s['peak_hz']:>9.1f}{_fmt(s['low_hz']):>9}{_fmt(s['high_hz']):>9}"
                     f"{_fmt(s['width_3db']):>8}{_fmt(s['q'], '.2f'):>7}{s['range_db']:>10.1f}")
    lines.append("paper: A responds sharply at resonance, f much less (open band: flatter than the sweep shows)")
    return "\n".join(lines)


def _plot_fig4(result: dict, path: Path) -> Path:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    styles = {"A": ("k", "-"), "f": ("0.45", "--"), "Af": ("0.7", ":")}
    for f in ("A", "f", "Af"):
        s = result["features"][f]["sharpness"]
        q = f"Q {s['q']:.1f}" if s["closed"] else "no -3 dB band in sweep"
        colour, ls = styles[f]
        ax.plot(result["freqs"], result["features"][f]["normalised"], color=colour, linestyle=ls,
                label=f"{f} ({q}, range {s['range_db']:.0f} dB)")
    ax.axvline(result["cf"], color="r", linewidth=0.6, linestyle=":")
    ax.axhline(2 ** -0.5, color="0.6", linewidth=0.5)
    ax.set_xlabel("sine frequency (Hz)")
    ax.set_ylabel("feature / its maximum")
    ax.set_ylim(0, 1.05)
    ax.set_title(f"Fig. 4: vibrissa {result['channel']} (cf {result['cf']:g} Hz), pure sines", fontsize=10)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def _write_fig5(result: dict, out: Path) -> list[Path]:
    feats = list(result["features"])
    rows = ([B, result["mean_width_3db"][i], *result["B_range"][i]]
            + [result["features"][f]["mean_rate"][i] for f in feats]
            for i, B in enumerate(result["mean_B"]))
    return [write_csv(out / "fig5.csv", ["mean_B", "mean_width_3db_hz", "B_min", "B_max"] + feats, rows)]


def _table_fig5(result: dict) -> str:
    feats = list(result["features"])
    lines = [f"Fig. 5, whisker bank, {result['texture_set']} ({result['duration']:g} s per texture)",
             f"{'mean B':>8}{'-3dB w':>8}" + "".join(f"{f:>8}" for f in feats)]
    for i, B in enumerate(result["mean_B"]):
        lines.append(f"{B:>8g}{result['mean_width_3db'][i]:>8.1f}"
                     + "".join(f"{result['features'][f]['mean_rate'][i]:>8.3f}" for f in feats))
    mean_b = result["mean_B"]
    best = [f"{f} at B={mean_b[max(range(len(mean_b)), key=result['features'][f]['mean_rate'].__getitem__)]:g}"
            for f in feats]
    lines.append("best: " + ", ".join(best) + f"; paper: {result['paper']}")
    return "\n".join(lines)


def _plot_fig5(result: dict, path: Path) -> Path:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for f in [f for f in FEATURES if f in result["features"]]:
        ax.semilogx(result["mean_B"], result["features"][f]["mean_rate"], color=SHADES[f], marker=MARKERS[f],
                    label=f)
    ax.axhline(1 / 8, color="r", linestyle=":", linewidth=1, label="chance")
    ax.axvline(145, color="0.6", linewidth=0.6, linestyle="--", label="default bank (B 145)")
    ax.set_xlabel("mean bandwidth B = 2 pi b (paper's 'Hz')")
    ax.set_ylabel("mean classification rate")
    ax.set_ylim(0, 1.02)
    ax.set_title(f"Fig. 5: whisker bandwidth, {result['texture_set']}", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", linewidth=0.3)
    return save_figure(fig, path)


def _write_fig6(result: dict, out: Path) -> list[Path]:
    c, w = result["cochlea"], result["whisker"]
    return [write_csv(out / "fig6_cochlea.csv", ["channels", "mean_rate"], zip(c["channels"], c["mean_rate"])),
            write_csv(out / "fig6_whisker.csv", ["groups", "rows", "channels", "mean_rate"],
                 zip(w["groups"], w["rows"], w["channels"], w["mean_rate"]))]


def _table_fig6(result: dict) -> str:
    c, w = result["cochlea"], result["whisker"]
    return "\n".join([
        f"Fig. 6, {result['feature']} feature",
        "cochlea channels: " + " ".join(f"{n}:{r:.2f}" for n, r in zip(c["channels"], c["mean_rate"])),
        "whisker rows:     " + " ".join(f"{g}:{r:.2f}" for g, r in zip(w["rows"], w["mean_rate"])),
        f">= {result['threshold']:.2f} from {_fmt(c['first_at_or_above_threshold'], 'd')} cochlear channels and "
        f"{_fmt(w['first_at_or_above_threshold'], 'd')} whisker rows; paper: {result['paper']}",
    ])


def _plot_fig6(result: dict, path: Path) -> Path:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    c, w = result["cochlea"], result["whisker"]
    axes[0].plot(c["channels"], c["mean_rate"], "k-o", markersize=3)
    axes[0].set_xlabel("cochlear channels (ERB-spaced, 20 Hz..20 kHz)")
    axes[0].set_title("(a) cochlear model", fontsize=10)
    axes[1].plot(w["groups"], w["mean_rate"], "k-o", markersize=4)
    axes[1].set_xticks(w["groups"], [f"{g}\n{r}" for g, r in zip(w["groups"], w["rows"])])
    axes[1].set_xlabel("whisker rows of 4 (added in this order)")
    axes[1].set_title("(b) whisker array model", fontsize=10)
    for ax in axes:
        ax.axhline(result["threshold"], color="0.6", linewidth=0.6, linestyle="--")
        ax.axhline(1 / 8, color="r", linestyle=":", linewidth=1)
        ax.set_ylim(0, 1.02)
        ax.set_ylabel(f"mean classification rate ({result['feature']})")
        ax.grid(True, linewidth=0.3)
    return save_figure(fig, path)


# -- fusion of the two senses (beyond the paper) ---------------------------------------------------

def _write_fusion(result: dict, out: Path) -> list[Path]:
    rows = [(r["set_seed"], m, r["window"][m], r["contact"][m], r["late_weight"], r["late_sharpness"],
             r["calibration"][m]["window"]["ece"], r["calibration"][m]["contact"]["ece"])
            for r in result["sets"] for m in r["window"]]
    return [write_csv(out / "fusion.csv", ["set_seed", "method", "window_accuracy", "contact_accuracy",
                                      "late_weight_of_whiskers", "late_sharpness", "window_ece", "contact_ece"], rows)]


def _plot_fusion(result: dict, path: Path) -> Path:
    plt = pyplot()
    methods = list(result["summary"])
    fig, ax = plt.subplots(figsize=(6, 3))
    x = np.arange(len(methods))
    for k, (kind, label) in enumerate((("window", "100 ms windows"), ("contact", "1 s contacts"))):
        means = [result["summary"][m][kind]["mean"] for m in methods]
        sds = [result["summary"][m][kind]["sd"] for m in methods]
        ax.bar(x + (k - 0.5) * 0.38, means, 0.38, yerr=sds, capsize=3, label=label,
               color=("0.45", "0.75")[k])
    ax.set_xticks(x, methods)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("accuracy")
    ax.set_title(f"two senses, {len(result['sets'])} random sets of 8 textures", fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    return save_figure(fig, path)
