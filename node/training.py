"""Train and evaluate texture models from labelled recordings listed in a manifest.

A manifest is a CSV file with a header and the columns ``path,label`` and,
optionally, ``start,end`` (seconds; a recording's part to use). Paths are relative
to the manifest's folder. Recordings are read and resampled to the bank's rate by
the replay driver, exactly as ``supramodal run`` would replay them, so a model
sees in training what the node feeds it live.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from node.graph import channel_mapper
from replay.driver import ReplayDriver
from supramodal.banks import Bank
from supramodal.decisions import DecisionAccumulator
from supramodal.model import TextureModel
from supramodal.pipeline import FeaturePipeline
from supramodal.training import DEFAULT_EPOCHS


@dataclass(frozen=True)
class Recording:
    """One manifest row: a file, its label and the part of it to use (seconds; None = to the end)."""

    path: Path
    label: str
    start: float = 0.0
    end: float | None = None


def read_manifest(path) -> list[Recording]:
    """Parse and check a manifest; ValueError names the row and the problem."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ValueError(f"no manifest at {path}") from None
    rows = list(csv.DictReader(text.splitlines()))
    if not rows:
        raise ValueError(f"{path}: the manifest lists no recording (expected a header 'path,label' and one row per file)")
    columns = set(rows[0])
    if not {"path", "label"} <= columns or not columns <= {"path", "label", "start", "end"}:
        raise ValueError(f"{path}: columns must be path,label[,start,end]; got {sorted(c for c in columns if c)}")
    out = []
    for i, row in enumerate(rows, start=2):
        where = f"{path}, line {i}"
        if not row.get("path") or not row.get("label"):
            raise ValueError(f"{where}: path and label must not be empty")
        try:
            start = float(row["start"]) if row.get("start") else 0.0
            end = float(row["end"]) if row.get("end") else None
        except ValueError:
            raise ValueError(f"{where}: start and end must be numbers of seconds") from None
        if start < 0 or (end is not None and end <= start):
            raise ValueError(f"{where}: need 0 <= start < end, got start={start}, end={end}")
        p = Path(row["path"])
        out.append(Recording(p if p.is_absolute() else path.parent / p, row["label"].strip(), start, end))
    return out


def recording_windows(rec: Recording, pipeline: FeaturePipeline, mapping="auto", notice=None) -> np.ndarray:
    """Feature windows of one recording (its [start, end) part) through a fresh ``pipeline``,
    shape (n, features, channels)."""
    bank = pipeline.bank
    driver = ReplayDriver(str(rec.path), rate=bank.fs, speed="max", on_notice=notice)
    data = driver.data
    a = int(round(rec.start * driver.rate))
    b = data.shape[0] if rec.end is None else int(round(rec.end * driver.rate))
    if b > data.shape[0] + 1:
        raise ValueError(f"{rec.path}: end {rec.end} s is past the recording's {data.shape[0] / driver.rate:.3f} s")
    x = channel_mapper(mapping, data.shape[1], bank.channels)(data[a:b])
    return pipeline.run(x, block=65536).values


def train_from_manifest(manifest, bank: Bank, features=("Af",), window: float = 0.1, epochs: int = DEFAULT_EPOCHS,
                        seed: int = 0, mapping="auto", progress=None) -> TextureModel:
    """Train a model on every window of every recording in the manifest."""
    recs = read_manifest(manifest)
    classes = tuple(sorted({r.label for r in recs}))
    if len(classes) < 2:
        raise ValueError(f"{manifest}: training needs at least two labels, found {list(classes)}")
    values, labels = [], []
    for k, rec in enumerate(recs):
        v = recording_windows(rec, FeaturePipeline(bank, features, window), mapping, notice=progress)
        if progress:
            progress(f"[{k + 1}/{len(recs)}] {rec.path.name} ({rec.label}): {len(v)} windows")
        values.append(v)
        labels.append(np.full(len(v), classes.index(rec.label)))
    x, y = np.concatenate(values), np.concatenate(labels)
    if len(x) == 0:
        raise ValueError(f"{manifest}: the recordings are shorter than one window")
    return TextureModel.train_for(FeaturePipeline(bank, features, window), x, y, classes, epochs=epochs, seed=seed)


def evaluate_manifest(model: TextureModel, manifest, mapping="auto", progress=None) -> dict:
    """Per-window and per-recording accuracy of ``model`` on the manifest's recordings.

    A recording's decision pools all its windows by summed log-posteriors (as the
    node's ``scope = "contact"`` does over one touch).

    Returns
    -------
    dict
        ``window_accuracy``, ``recording_accuracy``, ``labels`` (row/column order of
        ``confusion``), ``confusion`` (windows; rows = truth, columns = predicted),
        ``recordings`` (per-recording details).
    """
    recs = read_manifest(manifest)
    unknown = sorted({r.label for r in recs} - set(model.classes))
    if unknown:
        raise ValueError(f"{manifest}: label(s) {unknown} are not classes of the model ({list(model.classes)})")
    labels = list(model.classes)
    confusion = np.zeros((len(labels), len(labels)), dtype=int)
    per_rec = []
    for rec in recs:
        v = recording_windows(rec, model.pipeline(), mapping, notice=progress)
        if len(v) == 0:
            raise ValueError(f"{rec.path}: shorter than one window of {model.window_samples / model.bank.fs:g} s")
        out = model.outputs(v)
        pred = np.argmax(out, axis=1)
        truth = labels.index(rec.label)
        np.add.at(confusion, (truth, pred), 1)
        pooled = DecisionAccumulator(len(labels), scope="contact", n=0)
        for o in out:
            decision = pooled.update(o)
        per_rec.append({"path": str(rec.path), "label": rec.label, "windows": int(len(v)),
                        "window_accuracy": float(np.mean(pred == truth)), "predicted": labels[decision.label],
                        "confidence": decision.confidence})
        if progress:
            progress(f"{rec.path.name}: {per_rec[-1]['window_accuracy']:.3f} of windows, recording -> {labels[decision.label]}")
    return {
        "window_accuracy": float(np.trace(confusion) / confusion.sum()),
        "recording_accuracy": float(np.mean([r["predicted"] == r["label"] for r in per_rec])),
        "labels": labels,
        "confusion": confusion.tolist(),
        "recordings": per_rec,
    }


def format_evaluation(result: dict) -> str:
    labels = result["labels"]
    width = max(8, *(len(n) for n in labels)) + 1
    lines = [f"window accuracy     {result['window_accuracy']:.3f}",
             f"recording accuracy  {result['recording_accuracy']:.3f} ({len(result['recordings'])} recordings)",
             "", "confusion (windows; rows = truth, columns = predicted)",
             " " * width + "".join(f"{n:>{width}}" for n in labels)]
    for n, row in zip(labels, result["confusion"]):
        lines.append(f"{n:<{width}}" + "".join(f"{v:>{width}}" for v in row))
    return "\n".join(lines)
