"""Train and evaluate texture models from labelled recordings listed in a manifest.

A manifest is a CSV file with a header and the columns ``path,label`` and,
optionally, ``start,end`` (seconds; a recording's part to use). Paths are relative
to the manifest's folder. :mod:`node.manifest` reads and checks it (format, rules
and errors there) before any training starts. Recordings are read and resampled to the bank's rate by
the replay driver, exactly as ``supramodal run`` would replay them, so a model
sees in training what the node feeds it live.
"""

from __future__ import annotations

import numpy as np

from supramodal.node.band import warn_if_beyond_band
from supramodal.node.streams import channel_mapper
from supramodal.node.manifest import ManifestError, Recording, read_manifest
from supramodal.replay.driver import ReplayDriver
from supramodal.banks import Bank
from supramodal.decisions import DecisionAccumulator
from supramodal.errors import SupramodalError
from supramodal.evaluation import POOLED_WINDOWS, permutation_importance, pooled_accuracy
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.model import TextureModel
from supramodal.pipeline import FeaturePipeline
from supramodal.training import grouped_folds


def recording_windows(rec: Recording, pipeline: FeaturePipeline, mapping="auto", notice=None) -> np.ndarray:
    """Feature windows of one recording (its [start, end) part) through a fresh ``pipeline``,
    shape (n, features, channels).

    Raises
    ------
    ManifestError
        Naming the manifest's line, if the file cannot be replayed into the pipeline's
        bank, or if the part asked for lies past its end.
    """
    bank = pipeline.bank
    try:
        driver = ReplayDriver(str(rec.path), rate=bank.fs, speed="max", on_notice=notice)
        data = driver.data
        x = channel_mapper(mapping, data.shape[1], bank.channels, setting="--mapping")
    except (SupramodalError, ValueError) as e:          # a file or mapping that does not fit
        raise ManifestError(f"{rec.where}: {e}") from e
    warn_if_beyond_band(bank, driver.source_rate, f"{rec.where}: {rec.path.name}")
    a = int(round(rec.start * driver.rate))
    b = data.shape[0] if rec.end is None else int(round(rec.end * driver.rate))
    duration = data.shape[0] / driver.rate
    if a >= data.shape[0] or b > data.shape[0] + 1:
        raise ManifestError(f"{rec.where}: [{rec.start:g}, {rec.end if rec.end is not None else duration:g}) s "
                            f"is not inside {rec.path.name}, which is {duration:g} s long")
    return pipeline.run(x(data[a:b]), block=65536).values


def _no_window(rec: Recording, window_seconds: float) -> ManifestError:
    return ManifestError(f"{rec.where}: {rec.path.name} [{rec.start:g}, {'end' if rec.end is None else f'{rec.end:g}'}"
                         f") s holds no complete window of {window_seconds:g} s; widen the span or drop the line")


def train_from_manifest(manifest, bank: Bank, features=("Af",), window: float = 0.1, epochs: int = DEFAULT_EPOCHS,
                        seed: int = 0, mapping="auto", progress=None) -> TextureModel:
    """Train a model on every window of every recording in the manifest.

    The manifest is read and checked whole (:func:`node.manifest.read_manifest`) before
    any feature is computed; a line whose part of its file holds no complete window is
    refused (its label would be a class the model never saw).

    Raises
    ------
    ManifestError
        Naming the manifest's line, the cause and the fix; or the manifest if it has fewer
        than two labels.
    """
    make_pipeline = lambda: FeaturePipeline(bank, features, window)       # noqa: E731
    recs, classes, windows = _manifest_windows(manifest, make_pipeline, mapping, progress)
    return _train(recs, classes, windows, make_pipeline(), epochs, seed)


def _manifest_windows(manifest, make_pipeline, mapping, progress):
    """The manifest's recordings, its classes (sorted) and every recording's feature windows
    (``make_pipeline()``: a fresh FeaturePipeline per recording)."""
    recs = read_manifest(manifest)
    classes = tuple(sorted({r.label for r in recs}))
    if len(classes) < 2:
        raise ManifestError(f"{manifest}: training needs at least two labels, found {list(classes)}; "
                            "add recordings of another texture")
    windows = []
    for k, rec in enumerate(recs):
        pipeline = make_pipeline()
        v = recording_windows(rec, pipeline, mapping, notice=progress)
        if len(v) == 0:
            raise _no_window(rec, pipeline.window_samples / pipeline.bank.fs)
        if progress:
            progress(f"[{k + 1}/{len(recs)}] {rec.path.name} ({rec.label}): {len(v)} windows")
        windows.append(v)
    return recs, classes, windows


def _train(recs, classes, windows, pipeline: FeaturePipeline, epochs: int, seed: int, hidden=None) -> TextureModel:
    x = np.concatenate(windows)
    y = np.concatenate([np.full(len(v), classes.index(r.label)) for r, v in zip(recs, windows)])
    return TextureModel.train_for(pipeline, x, y, classes, epochs=epochs, seed=seed, hidden=hidden)


def cross_validate_manifest(manifest, bank: Bank, features=("Af",), window: float = 0.1, k: int = 5,
                            epochs: int = DEFAULT_EPOCHS, seed: int = 0, mapping="auto", progress=None) -> dict:
    """Grouped ``k``-fold cross-validation of the training :func:`train_from_manifest` would do.

    Folds are grouped by manifest line, one trial (:func:`supramodal.training.grouped_folds`):
    the windows of one trial are never on both sides. A long recording may be split into
    several lines (``start``, ``end``) to make several trials; their spans must not overlap. Each fold's model is trained as the final one
    would be (same features, window, epochs, seed) on the other folds' recordings and scored on
    its own.

    Returns
    -------
    dict
        ``k``, ``seed``, ``folds`` (per fold: ``window_accuracy``, ``recording_accuracy``,
        ``recordings``), ``window_accuracy`` and ``recording_accuracy`` (``{"mean", "sd"}``
        over folds; sd with ``ddof=1``), ``labels``, ``confusion`` (windows of every test fold;
        rows = truth), ``recall`` (per label, from ``confusion``), ``chance`` (the largest
        label's share of windows: what always answering it would score).
    """
    make_pipeline = lambda: FeaturePipeline(bank, features, window)       # noqa: E731
    return _cross_validate(manifest, make_pipeline, k, epochs, seed, None, mapping, progress)


def cross_validate_model(model: TextureModel, manifest, k: int = 5, seed: int | None = None, mapping="auto",
                         progress=None) -> dict:
    """Grouped ``k``-fold cross-validation of ``model``'s configuration on the manifest.

    Each fold trains a fresh model exactly as ``model`` was made (bank, features, window, peak
    settings, hidden units, epochs) on the other folds' recordings and scores it on its own: how
    well a model like this one generalises to recordings it has not seen, which scoring ``model``
    itself on its own training recordings cannot say. ``seed`` defaults to the model's.

    Returns
    -------
    dict
        As :func:`cross_validate_manifest`.
    """
    seed = model.training.get("seed", 0) if seed is None else seed
    return _cross_validate(manifest, model.pipeline, k, int(model.training["epochs"]), seed,
                           model.mlp.shape[1], mapping, progress)


def _cross_validate(manifest, make_pipeline, k, epochs, seed, hidden, mapping, progress) -> dict:
    recs, classes, windows = _manifest_windows(manifest, make_pipeline, mapping, progress)
    _refuse_overlapping_trials(recs)
    fold = grouped_folds([r.where for r in recs], [r.label for r in recs], k, seed)
    confusion = np.zeros((len(classes), len(classes)), dtype=int)
    folds = []
    for f in range(k):
        train = [i for i in range(len(recs)) if fold[i] != f]
        test = [i for i in range(len(recs)) if fold[i] == f]
        seen = sorted({recs[i].label for i in train})
        if seen != list(classes):
            missing = sorted(set(classes) - set(seen))
            raise ManifestError(f"{manifest}: fold {f + 1} of {k} would train without {missing}: record them more "
                                "often or lower --cv")
        model = _train([recs[i] for i in train], classes, [windows[i] for i in train],
                       make_pipeline(), epochs, seed, hidden)
        result = score_recordings(model, [recs[i] for i in test], [windows[i] for i in test])
        confusion += np.array(result["confusion"])
        folds.append({"window_accuracy": result["window_accuracy"], "recording_accuracy": result["recording_accuracy"],
                      "recordings": [r["path"] for r in result["recordings"]]})
        if progress:
            progress(f"fold {f + 1}/{k}: {len(test)} recordings, {result['window_accuracy']:.3f} of windows, "
                     f"{result['recording_accuracy']:.3f} of recordings")

    def spread(key):
        v = np.array([fo[key] for fo in folds])
        return {"mean": float(v.mean()), "sd": float(v.std(ddof=1))}

    totals = confusion.sum(axis=1)
    return {"k": k, "seed": seed, "folds": folds, "window_accuracy": spread("window_accuracy"),
            "recording_accuracy": spread("recording_accuracy"), "labels": list(classes),
            "confusion": confusion.tolist(),
            "recall": {c: float(confusion[i, i] / totals[i]) if totals[i] else None for i, c in enumerate(classes)},
            "chance": float(totals.max() / totals.sum())}


def _refuse_overlapping_trials(recs: list[Recording]) -> None:
    """Two lines of one file whose spans overlap share windows: a fold could test on what it trained on."""
    by_file: dict = {}
    for r in recs:
        by_file.setdefault(r.path, []).append(r)
    for lines in by_file.values():
        lines.sort(key=lambda r: r.start)
        for a, b in zip(lines, lines[1:]):
            if a.end is None or a.end > b.start:
                raise ManifestError(f"{b.where}: its span of {b.path.name} overlaps {a.where}'s; cross-validation "
                                    "takes each line as one trial, so the spans of one file must not overlap")


def format_cross_validation(result: dict) -> str:
    w, r = result["window_accuracy"], result["recording_accuracy"]
    lines = [f"grouped {result['k']}-fold cross-validation (folds by manifest line: a trial's windows on one side; "
             f"seed {result['seed']})",
             f"window accuracy     {w['mean']:.3f} +- {w['sd']:.3f} (chance {result['chance']:.3f})",
             f"recording accuracy  {r['mean']:.3f} +- {r['sd']:.3f}",
             "recall per label    " + ", ".join(f"{c} {v:.3f}" for c, v in result["recall"].items() if v is not None)]
    return "\n".join(lines) + "\n\n" + _confusion_table(result["labels"], result["confusion"])


def _confusion_table(labels, confusion) -> str:
    width = max(8, *(len(n) for n in labels)) + 1
    lines = ["confusion (windows; rows = truth, columns = predicted)",
             " " * width + "".join(f"{n:>{width}}" for n in labels)]
    for n, row in zip(labels, confusion):
        lines.append(f"{n:<{width}}" + "".join(f"{v:>{width}}" for v in row))
    return "\n".join(lines)


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
    unknown = [r for r in recs if r.label not in model.classes]
    if unknown:
        raise ManifestError(f"{unknown[0].where}: label {unknown[0].label!r} is not a class of the model "
                            f"({list(model.classes)}); {len(unknown)} line(s) have such labels: fix the labels "
                            "or evaluate a model trained on them")
    windows = []
    for rec in recs:
        v = recording_windows(rec, model.pipeline(), mapping, notice=progress)
        if len(v) == 0:
            raise _no_window(rec, model.window_samples / model.bank.fs)
        windows.append(v)
    result = score_recordings(model, recs, windows, progress)
    truth = np.concatenate([np.full(len(v), model.classes.index(r.label)) for r, v in zip(recs, windows)])
    importance = permutation_importance(model.outputs, np.concatenate(windows), truth)
    result["channel_importance"] = dict(zip(model.bank.names, importance.round(6).tolist()))
    return result


def score_recordings(model: TextureModel, recs: list[Recording], windows: list[np.ndarray], progress=None) -> dict:
    """The result of :func:`evaluate_manifest` for recordings whose feature windows are known."""
    labels = list(model.classes)
    confusion = np.zeros((len(labels), len(labels)), dtype=int)
    per_rec = []
    outputs = [model.outputs(v) for v in windows]
    for rec, v, out in zip(recs, windows, outputs):
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
    truths = [labels.index(r.label) for r in recs]
    totals = confusion.sum(axis=1)
    return {
        "window_accuracy": float(np.trace(confusion) / confusion.sum()),
        "recording_accuracy": float(np.mean([r["predicted"] == r["label"] for r in per_rec])),
        "chance": float(totals.max() / totals.sum()),
        "pooled": {str(n): dict(zip(("accuracy", "runs"), pooled_accuracy(outputs, truths, n)))
                   for n in POOLED_WINDOWS},
        "labels": labels,
        "confusion": confusion.tolist(),
        "recordings": per_rec,
    }


def format_evaluation(result: dict) -> str:
    lines = [f"window accuracy     {result['window_accuracy']:.3f} (chance {result['chance']:.3f}: always the "
             "commonest label)",
             f"recording accuracy  {result['recording_accuracy']:.3f} ({len(result['recordings'])} recordings, "
             "all windows of each pooled)", "",
             "windows pooled      accuracy (runs of that many consecutive windows)"]
    for n, p in result["pooled"].items():
        shown = "-" if p["accuracy"] is None else f"{p['accuracy']:.3f}"
        lines.append(f"  {n:>3}               {shown} ({p['runs']} runs)")
    lines.append(f"  whole recording   {result['recording_accuracy']:.3f}")
    if "channel_importance" in result:
        top = sorted(result["channel_importance"].items(), key=lambda kv: -kv[1])
        lines += ["", "channels carrying the decision (window accuracy lost when the channel is shuffled)",
                  "  " + ", ".join(f"{name} {v:+.3f}" for name, v in top[:8])]
    return "\n".join(lines) + "\n\n" + _confusion_table(result["labels"], result["confusion"])
