"""Evaluation results as files a user opens: CSV always, PNG where matplotlib is installed (extra ``plots``)."""

from __future__ import annotations

import contextlib
import csv
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = ["EVALUATION_FILES", "plots_missing_notice", "pyplot_or_none", "write_confusion", "write_evaluation",
           "write_fused_evaluation", "fused_evaluation_files", "write_reliability", "write_anytime", "scored_text",
           "contact_text", "FUSION_COLUMNS", "write_staged"]

#: Files ``evaluate --out`` writes (the PNGs where matplotlib is installed).
EVALUATION_FILES = ("confusion.csv", "confusion.png", "pooling.csv", "channels.csv", "evaluation.png",
                    "reliability.csv", "reliability.png", "anytime.csv", "anytime.png")


def write_staged(folder: Path, write: Callable[[Path], list[Path]]) -> list[Path]:
    """Write a command's files into ``folder`` whole or not at all.

    ``write(staging)`` writes them into a folder of their own inside it (``folder`` made if missing), then
    each is put in place, Ctrl-C and SIGTERM held until the last is
    (:func:`supramodal.node.workflows.labels.replace_all`). An interruption or a failure before that leaves
    every earlier file of ``folder`` as it was and nothing beside them (written in place, an interrupted
    report had some files new and the rest an earlier run's, or one cut short). Returns the paths written in
    ``folder``.
    """
    from supramodal.node.workflows.labels import replace_all

    folder = Path(folder)
    made = not folder.exists()
    staging = folder / f".staging-{os.getpid()}"      # named before it is made: an interruption knows what to remove
    try:
        staging.mkdir(parents=True, exist_ok=True)
        names = [Path(p).name for p in write(staging)]
        replace_all([(staging / name, folder / name) for name in names])
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if made:
            with contextlib.suppress(OSError):
                folder.rmdir()                          # a folder made for nothing is not left behind
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return [folder / name for name in names]


def confidence_verdict(calibration: dict, fused: bool = False) -> str:
    """Say in one line whether decisions on labelled recordings were about as sure as they were right.

    Their mean stated confidence beside their accuracy, and the ECE against
    :data:`supramodal.calibration.HOLDS_ECE` and against what a calibrated model's would reach by chance on as
    many windows (``calibration``: a :func:`~supramodal.calibration.calibration_report`, or its ``accuracy``,
    ``ece`` and ``n`` with ``confidence`` and ``ece_if_calibrated``), and what to do where they were not
    (``fused``: the decisions of a fusion, which is not recalibrated itself).
    """
    from supramodal.calibration import HOLDS_ECE, ece_if_calibrated, mean_confidence

    c = calibration
    if "reliability" in c:          # a whole calibration_report: what the verdict reads, derived from it
        c = {**c, "confidence": mean_confidence(c), "ece_if_calibrated": ece_if_calibrated(c)}
    said = f"says {c['confidence']:.2f} on average and is right on {c['accuracy']:.2f} of {c['n']} windows"
    if c["ece"] <= HOLDS_ECE:
        return f"{said}: its confidence holds on these recordings (ECE {c['ece']:.3f})"
    if c["ece"] <= c.get("ece_if_calibrated", 0.0):
        return (f"{said}: too few windows to tell whether its confidence holds (ECE {c['ece']:.3f}; a calibrated "
                f"model's reaches {c['ece_if_calibrated']:.3f} on as many one time in 20); score more recordings")
    way = "surer than it is right" if c["confidence"] > c["accuracy"] else "less sure than it is right"
    fix = ("recalibrate each sense on labelled recordings like these (supramodal recalibrate), then learn the fusion "
           "again" if fused else "recalibrate it on labelled recordings like these (supramodal recalibrate), keeping "
           "its network")
    return f"{said}: its confidence does not hold on these recordings (ECE {c['ece']:.3f} > {HOLDS_ECE}, {way}); {fix}"


def write_confusion(labels, confusion, base: Path, title: str) -> list[Path]:
    """Write ``base.csv`` (counts; rows = truth, columns = predicted) and ``base.png`` (each row as shares).

    ``base.png`` shows each row as shares of its windows, so a rare label reads as clearly as a common one.

    Returns the paths written (the PNG only where matplotlib can be imported).
    """
    counts = np.asarray(confusion, dtype=int)
    csv_path = base.with_name(base.name + ".csv")
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["truth \\ predicted", *labels])
        for name, row in zip(labels, counts):
            w.writerow([name, *row.tolist()])
    written = [csv_path]
    plt = pyplot_or_none()
    if plt is None:
        return written
    shares = counts / np.maximum(counts.sum(axis=1, keepdims=True), 1)
    n = len(labels)
    fig, ax = plt.subplots(figsize=(1.2 + 0.55 * n, 1.0 + 0.5 * n))
    ax.imshow(shares, cmap="Greys", vmin=0, vmax=1)
    for i in range(n):
        for j in range(n):
            ax.text(j, i, f"{shares[i, j]:.2f}", ha="center", va="center", fontsize=8,
                    color="white" if shares[i, j] > 0.5 else "black")
    ax.set_xticks(range(n), labels, rotation=45, ha="right")
    ax.set_yticks(range(n), labels)
    ax.set_xlabel("predicted")
    ax.set_ylabel("truth")
    ax.set_title(title, fontsize=9)
    return written + [_save_png(plt, fig, base.with_name(base.name + ".png"))]


def _save_png(plt, fig, path: Path, description: str | None = None) -> Path:
    """Lay ``fig`` out, write it to ``path`` (120 dpi) and free it; return ``path``.

    ``description``: kept in the PNG's ``Description`` text chunk (what the figure shows).
    """
    fig.tight_layout()
    fig.savefig(path, dpi=120, metadata=None if description is None else {"Description": description})
    plt.close(fig)
    return path


def pyplot_or_none():
    """Return matplotlib.pyplot on a file backend, or None where matplotlib is not installed.

    Imported with Ctrl-C held: :func:`supramodal.interrupts.import_optional`.
    """
    from supramodal.interrupts import import_optional

    matplotlib = import_optional("matplotlib")
    if matplotlib is None:
        return None
    matplotlib.use("Agg")
    return import_optional("matplotlib.pyplot")


def plots_missing_notice() -> str | None:
    """Return what a user without matplotlib is told instead of the PNGs (None where it is installed)."""
    if pyplot_or_none() is not None:
        return None
    return ("no PNG written (confusion, reliability diagram, plots): matplotlib is not installed; "
            "pip install \"supramodal[plots]\" to draw them (the CSV files hold the same numbers)")


def write_reliability(calibration: dict, base: Path, title: str) -> list[Path]:
    """Write ``base.csv``, the reliability bins of the decisions, and ``base.png``, the reliability diagram.

    The bins per window and per recording (``calibration["window"]`` and ``["recording"]``, each a
    :func:`supramodal.calibration.calibration_report`); the diagram: per confidence bin, the share of
    decisions right against their mean confidence (a calibrated model's bars reach the diagonal). Returns the
    paths written (the PNG only where matplotlib can be imported).
    """
    scopes = [(name, calibration[name]) for name in ("window", "recording") if calibration.get(name)]
    csv_path = base.with_name(base.name + ".csv")
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["scope", "confidence from", "confidence to", "decisions", "mean confidence", "accuracy"])
        for name, report in scopes:
            r = report["reliability"]
            for lo, hi, n, conf, acc in zip(r["edges"][:-1], r["edges"][1:], r["count"], r["confidence"],
                                            r["accuracy"]):
                w.writerow([name, f"{lo:.6g}", f"{hi:.6g}", n, "" if conf is None else f"{conf:.6f}",
                            "" if acc is None else f"{acc:.6f}"])
    written = [csv_path]
    plt = pyplot_or_none()
    if plt is None:
        return written
    fig, axes = plt.subplots(1, len(scopes), figsize=(4.2 * len(scopes), 4.0), squeeze=False)
    for ax, (name, report) in zip(axes[0], scopes):
        r = report["reliability"]
        edges = np.array(r["edges"])
        width = np.diff(edges)
        shown = [i for i, n in enumerate(r["count"]) if n]
        ax.bar(edges[:-1][shown], [r["accuracy"][i] for i in shown], width[shown], align="edge", color="0.55",
               edgecolor="0.2", label="share right")
        ax.plot([r["confidence"][i] for i in shown], [r["accuracy"][i] for i in shown], "o", color="0.1",
                markersize=3, label="mean confidence")
        ax.plot([0, 1], [0, 1], ":", color="0.4", label="calibrated")
        for i in shown:
            ax.text(edges[i] + width[i] / 2, 0.02, str(r["count"][i]), rotation=90, ha="center", va="bottom",
                    fontsize=6, color="white" if (r["accuracy"][i] or 0) > 0.15 else "black")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("confidence (winner's posterior)")
        ax.set_ylabel("share of decisions right")
        ax.set_title(f"per {name}: ECE {report['ece']:.3f}, {report['n']} decisions", fontsize=9)
        ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(title, fontsize=9)
    return written + [_save_png(plt, fig, base.with_name(base.name + ".png"))]


def write_evaluation(result: dict, folder: Path) -> list[Path]:
    """Write the files of ``evaluate --out`` into ``folder``.

    The confusion (``confusion.csv/.png``), accuracy against windows pooled (``pooling.csv``) and the
    channels' importance (``channels.csv``), with one PNG of the last two (``evaluation.png``), and the
    reliability diagram (``reliability.csv/.png``). Returns the paths written.
    """
    folder.mkdir(parents=True, exist_ok=True)
    written = write_confusion(result["labels"], result["confusion"], folder / "confusion",
                              f"window accuracy {result['window_accuracy']:.3f} (chance {result['chance']:.3f})")
    written += write_reliability(result["calibration"], folder / "reliability", _reliability_title(result))
    pooled = [(int(n), p["accuracy"], p["runs"]) for n, p in result["pooled"].items()]
    with open(folder / "pooling.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["windows pooled", "accuracy", "runs"])
        w.writerows(pooled + [("recording", result["recording_accuracy"], len(result["recordings"]))])
    channels = list(result["channel_importance"].items())
    with open(folder / "channels.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["channel", "window accuracy lost when shuffled"])
        w.writerows(channels)
    written += [folder / "pooling.csv", folder / "channels.csv"]
    if result.get("anytime"):
        written += write_anytime(result["anytime"], folder / "anytime")
    plt = pyplot_or_none()
    if plt is None:
        return written
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.6))
    shown = [(n, a) for n, a, _ in pooled if a is not None]
    left.plot([n for n, _ in shown], [a for _, a in shown], "o-", color="0.2")
    left.axhline(result["chance"], color="0.6", linestyle=":", label="chance")
    left.axhline(result["recording_accuracy"], color="0.4", linestyle="--", label="whole recording")
    left.set_xscale("log")
    left.set_xticks([n for n, _ in shown], [str(n) for n, _ in shown])
    left.set_xlabel("windows pooled")
    left.set_ylabel("accuracy")
    left.set_ylim(0, 1.02)
    left.legend(fontsize=8, loc="lower right")
    right.bar(range(len(channels)), [v for _, v in channels], color="0.4")
    right.set_xticks(range(len(channels)), [n for n, _ in channels], rotation=90, fontsize=7)
    right.set_ylabel("accuracy lost when shuffled")
    right.set_title("channels carrying the decision", fontsize=9)
    return written + [_save_png(plt, fig, folder / "evaluation.png")]


def write_anytime(rows: list[dict], base: Path) -> list[Path]:
    """Write ``base.csv`` and ``base.png``: per confidence threshold, the touches decided and how.

    The touches decided, the share of those right, and the median windows it took (``rows``:
    :func:`supramodal.evaluation.anytime_sweep`'s, without the per-touch windows). Returns the paths written
    (the PNG where matplotlib is).
    """
    csv_path = base.with_name(base.name + ".csv")
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["confidence", "touches", "decided", "right", "right of decided", "median windows to decide",
                    "right at the end"])
        for r in rows:
            w.writerow([r["confidence"], r["contacts"], r["decided"], r["right"],
                        "" if not r["decided"] else f"{r['right'] / r['decided']:.6f}",
                        "" if r["median_windows"] is None else r["median_windows"], r["end_right"]])
    plt = pyplot_or_none()
    if plt is None:
        return [csv_path]
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.4))
    c = [r["confidence"] for r in rows]
    left.plot(c, [r["right"] / r["decided"] if r["decided"] else np.nan for r in rows], "o-", color="0.2",
              label="right of decided")
    left.plot(c, [r["decided"] / r["contacts"] for r in rows], "s--", color="0.55", label="decided")
    left.plot(c, c, ":", color="0.4", label="the threshold")
    left.set_xlabel("confidence threshold")
    left.set_ylabel("share of touches")
    left.set_ylim(0, 1.02)
    left.legend(fontsize=8, loc="lower right")
    right.plot(c, [np.nan if r["median_windows"] is None else r["median_windows"] for r in rows], "o-", color="0.2")
    right.set_xlabel("confidence threshold")
    right.set_ylabel("median windows to decide")
    right.set_ylim(bottom=0)
    fig.suptitle("decided as soon as sure (each recording one touch)", fontsize=9)
    return [csv_path, _save_png(plt, fig, base.with_name(base.name + ".png"))]


def _reliability_title(result: dict) -> str:
    c = result["calibration"]
    return "calibrated posteriors" if c.get("calibrated") else "uncalibrated posteriors (normalised outputs)"


def fused_evaluation_files(streams) -> list[str]:
    """Return the file names :func:`write_fused_evaluation` writes for ``streams``.

    The CSVs; each also gets a PNG where matplotlib is installed.
    """
    names = ["fusion.csv", "fusion.png"]
    for name in streams:
        names += [f"confusion-{name}.csv", f"confusion-{name}.png"]
    return names


#: The columns of ``fusion.csv`` (:func:`write_fused_evaluation`).
FUSION_COLUMNS = ("stream", "window accuracy", "windows", "contact accuracy", "contacts", "windows per contact",
                  "method", "weight", "sharpness", "correlation", "model files")


def _distinct(values) -> list:
    return list(dict.fromkeys(values))


def _name(path) -> str:
    return "trained on the spot" if path is None else Path(path).name


def scored_text(scored: list[dict]) -> str:
    """Return what a stream's score is of, in words.

    ``scored``: :func:`~supramodal.node.workflows.fused_training.evaluate_fused`'s ``scored``, one entry per
    scene; entries that differ are joined by ``"; "``.
    """
    said = []
    for e in scored:
        if "method" not in e:
            said.append(f"model {_name(e['model'])}")
        elif e["method"] == "early":
            said.append(f"early fusion, network {_name(e['model'])}")
        else:
            senses = " and ".join(f"{name} {_name(path)}" for name, path in e["senses"].items())
            said.append(f"late fusion, weight {e['weight']:.4g}, sharpness {e['sharpness']:.4g}, "
                        f"correlation {e['correlation']:.4g}, of {senses}")
    return "; ".join(_distinct(said)) or "-"


def contact_text(contact_windows: int | None) -> str:
    """Return what a contact is, in words (``None``: each run of windows of one texture)."""
    if contact_windows is None:
        return "each run of windows of one texture, pooled"
    return (f"{contact_windows} windows each, pooled (each run of one texture cut from its start; a shorter rest "
            "left out)")


def _columns(r: dict) -> list:
    """Return a row's columns after ``contacts``.

    Windows per contact, method, weight, sharpness, correlation and model files (values that differ between
    scenes joined by ``" | "``).
    """
    def join(values) -> str:
        return " | ".join("" if v is None else (f"{v:.6g}" if isinstance(v, float) else str(v))
                          for v in _distinct(values))

    scored = r["scored"]
    per = "run" if r["contact_windows"] is None else r["contact_windows"]
    if not scored or "method" not in scored[0]:
        return [per, "", "", "", "", join(_name(e["model"]) for e in scored)]
    files = [_name(e["model"]) if e["method"] == "early" else " + ".join(_name(p) for p in e["senses"].values())
             for e in scored]
    return [per, join(e["method"] for e in scored), join(e["weight"] for e in scored),
            join(e["sharpness"] for e in scored), join(e["correlation"] for e in scored), join(files)]


def write_fused_evaluation(result: dict, folder: Path) -> list[Path]:
    """Write the files of ``evaluate --scene --out`` into ``folder``.

    Per stream (each sense and ``fused``) its accuracy per window and per contact, what a contact is and what
    was scored (``fusion.csv``, columns :data:`FUSION_COLUMNS`; and side by side in ``fusion.png``, whose
    title and ``Description`` name them too) and its confusion (``confusion-STREAM.csv/.png``). Returns the
    paths written.
    """
    folder.mkdir(parents=True, exist_ok=True)
    rows = [(name, r["window_accuracy"], r["windows"], r["contact_accuracy"], r["contacts"])
            for name, r in result.items()]
    with open(folder / "fusion.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(FUSION_COLUMNS)
        w.writerows([*row[:3], "" if row[3] is None else row[3], row[4], *_columns(result[row[0]])] for row in rows)
    written = [folder / "fusion.csv"]
    what = {name: scored_text(r["scored"]) for name, r in result.items()}
    for name, r in result.items():
        written += write_confusion(r["labels"], r["confusion"], folder / f"confusion-{name}",
                                   f"{name}: window accuracy {r['window_accuracy']:.3f} of {r['windows']}\n"
                                   f"{what[name]}")
    plt = pyplot_or_none()
    if plt is None:
        return written
    contacts = contact_text(next(iter(result.values()))["contact_windows"])
    fig, ax = plt.subplots(figsize=(1.5 + 1.3 * len(rows), 3.4))
    x = np.arange(len(rows))
    ax.bar(x - 0.18, [r[1] for r in rows], 0.36, color="0.55", label="per window")
    ax.bar(x + 0.18, [np.nan if r[3] is None else r[3] for r in rows], 0.36, color="0.2", label="per contact")
    ax.set_xticks(x, [r[0] for r in rows])
    ax.set_ylim(0, 1.02)
    ax.set_ylabel("accuracy")
    ax.legend(fontsize=8, loc="lower right")
    fused = what.get("fused", "")
    ax.set_title(f"each sense alone and fused\nfused: {fused}\ncontacts: {contacts}", fontsize=7, wrap=True)
    description = "; ".join(f"{name}: {text}" for name, text in what.items()) + f"; contacts: {contacts}"
    return written + [_save_png(plt, fig, folder / "fusion.png", description)]
