"""Train and evaluate texture models from labelled recordings listed in a manifest.

A manifest is a CSV file with a header and the columns ``path,label`` and,
optionally, ``start,end`` (seconds; a recording's part to use). Paths are relative
to the manifest's folder. :mod:`node.workflows.manifest` reads and checks it (format, rules
and errors there) before any training starts. Recordings are read and resampled to the bank's rate by
the replay driver, exactly as ``supramodal run`` would replay them, so a model
sees in training what the node feeds it live.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from supramodal.banks import Bank
from supramodal.calibration import (
    DEFAULT_CALIBRATION_FOLDS,
    calibration_line,
    calibration_report,
    pool_log_posteriors,
    winner,
)
from supramodal.errors import InputError, SupramodalError
from supramodal.evaluation import POOLED_WINDOWS, anytime_sweep, permutation_importance, pooled_accuracy
from supramodal.mlp import DEFAULT_EPOCHS, EARLY_STOP_PATIENCE, Ensemble
from supramodal.model import GainAugment, TextureModel
from supramodal.node.runtime.streams import channel_mapper
from supramodal.node.scene.band import warn_if_beyond_band
from supramodal.node.workflows.manifest import ManifestError, Recording, manifest_classes, read_manifest
from supramodal.pipeline import FeaturePipeline
from supramodal.replay.driver import ReplayDriver
from supramodal.replay.session import session_paths
from supramodal.training import grouped_folds


def recording_windows(rec: Recording, pipeline: FeaturePipeline, mapping="auto", notice=None) -> np.ndarray:
    """Return the feature windows of one recording (its [start, end) part) through a fresh ``pipeline``.

    Shape (n, features, channels).

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
                        seed: int = 0, mapping="auto", progress=None, jobs: int = 1,
                        augment: GainAugment | None = None, hidden: int | None = None) -> TextureModel:
    """Train a model on every window of every recording in the manifest, calibrated on held-out windows.

    The held-out windows are out-of-fold windows of folds grouped by recording (manifest line) where every
    label has two recordings and there are enough of them, else of spans of each recording
    (:meth:`supramodal.model.TextureModel.train`). ``augment``: gain augmentation of every network's
    training windows, the calibration's fold networks (which the model deploys) alike (default none).
    ``hidden``: the networks' hidden units (default None: as many as their inputs, the paper's rule).

    The manifest is read and checked whole (:func:`node.workflows.manifest.read_manifest`) before
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
    say = None if progress is None else (lambda m: progress(f"calibration: {m}"))
    return _train(recs, classes, windows, make_pipeline(), epochs, seed, hidden, calibration_progress=say, jobs=jobs,
                  augment=augment)


def _manifest_windows(manifest, make_pipeline, mapping, progress):
    """Return the manifest's recordings, its classes (sorted) and every recording's feature windows.

    ``make_pipeline()``: a fresh FeaturePipeline per recording.
    """
    recs = read_manifest(manifest)
    classes = manifest_classes(recs, manifest)
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


def _train(recs, classes, windows, pipeline: FeaturePipeline, epochs: int, seed: int, hidden=None,
           calibration_progress=None, groups=None, jobs: int = 1, augment: GainAugment | None = None,
           calibration_folds: int = DEFAULT_CALIBRATION_FOLDS, patience: int | None = EARLY_STOP_PATIENCE
           ) -> TextureModel:
    """Train a model on the recordings' windows, calibrated on out-of-fold windows of folds grouped by recording.

    The groups are ``groups``, one per entry of ``recs`` (default :func:`recording_group`), where there are
    enough recordings; its networks over ``jobs`` worker processes (the same model for any), each trained on
    its windows gain-augmented by ``augment`` (None: not); ``calibration_folds`` its calibration's fold
    networks, which it deploys (0: one network, uncalibrated), each stopped early after ``patience`` epochs
    without a lower held-out error (None: every epoch).
    """
    x = np.concatenate(windows)
    y = np.concatenate([np.full(len(v), classes.index(r.label)) for r, v in zip(recs, windows)])
    names = [recording_group(r) for r in recs] if groups is None else list(groups)
    groups = np.repeat(np.array(names), [len(v) for v in windows])
    model = TextureModel.train_for(pipeline, x, y, classes, epochs=epochs, seed=seed, hidden=hidden, groups=groups,
                                   calibration_progress=calibration_progress, jobs=jobs, augment=augment,
                                   calibration_folds=calibration_folds, patience=patience)
    _warn_if_calibrated_on_spans(model)
    return model


def _warn_if_calibrated_on_spans(model: TextureModel) -> None:
    """Warn in one line when the calibration's folds had to be spans of recordings.

    Its held-out windows then share a touch with windows that trained their fold's network, and its confidence
    may not hold on a new touch (issue 34: 0.966 right by spans, 0.798 on a new touch, log loss 0.082 against
    0.973).
    """
    import warnings

    from supramodal.errors import SupramodalWarning

    fitted = {} if model.calibration is None else model.calibration.fitted_on
    if fitted.get("folds_by") != "span":
        return
    warnings.warn(f"calibrated on spans of each recording, not whole recordings (a texture in fewer than two "
                  f"recordings, or fewer than {fitted.get('folds', DEFAULT_CALIBRATION_FOLDS)} recordings in all): "
                  "its confidence may not hold on a new touch; record each texture on two or more separate touches, "
                  f"one recording each ({fitted.get('folds', DEFAULT_CALIBRATION_FOLDS)} recordings or more in all), "
                  "so that the calibration holds whole touches out", SupramodalWarning,
                  stacklevel=3)


def session_fingerprint(path) -> str:
    """``sha256:HEX`` of a session's WAV bytes: which recording a model saw, wherever it was moved."""
    import hashlib

    digest = hashlib.sha256()
    with open(session_paths(path)[0], "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return "sha256:" + digest.hexdigest()


def scene_stream(path, stream: str):
    """Return the recorded graph's replay scene at ``path``, stream ``stream`` of it and the session its source plays.

    As ``(scene, stream spec, session path, source spec)``.

    Raises
    ------
    InputError
        Naming the scene: no stream of that name (its streams listed), or a source that is not a
        recorded session.
    """
    from supramodal.node.scene.registry import driver_spec
    from supramodal.node.scene.schema import load_scene

    scene = load_scene(path)
    spec = next((s for s in scene.streams if s.name == stream), None)
    if spec is None:
        raise InputError(f"{scene.source}: no stream {stream!r}; its streams are {[s.name for s in scene.streams]} "
                         "(--stream names one)")
    src = scene.source_named(spec.source)
    session = driver_spec(src.type).replays(src.options)
    if session is None:
        raise InputError(f"{scene.source}: stream {stream!r} reads source {src.name!r} of type {src.type!r}, "
                         "not a recording; give the scene `supramodal record` wrote (DIR/NAME.toml)")
    return scene, spec, scene.resolve(session.path), src


def train_from_scenes(paths, stream: str, epochs: int = DEFAULT_EPOCHS, seed: int = 0, progress=None,
                      hidden=None, jobs: int = 1, augment: GainAugment | None = None) -> TextureModel:
    """Train a stream's model straight from recorded graphs (``train --scene REC.toml ... --stream NAME``).

    Each scene is a replay scene ``supramodal record`` wrote; the stream's bank, features and window
    are the scene's (the same in every scene, else refused), its samples the session its source
    plays, read at the bank's rate as the node reads them, and its labels the session's (seconds of
    the device's own stream: ``record --marks``, ``--label`` or ``supramodal label``). Each labelled
    span is a trial, as a manifest line is; the calibration's folds are grouped by **recording**
    (every span of one recording in one fold) where every label lies in two recordings or more and
    there are enough of them (:meth:`supramodal.model.TextureModel.train`). The model keeps, under
    ``training["sessions"]``, the fingerprint of every session it saw (:func:`session_fingerprint`),
    so that ``train --fusion`` can tell recordings it never saw. ``augment``: gain augmentation of every
    network's training windows (gains by bank resolved with the stream's bank; default none).

    Raises
    ------
    InputError
        Naming the scene: a missing stream, streams configured differently, a recording without
        labels, a span holding no window, fewer than two labels.
    """
    recs, windows, groups, seen, make = scene_windows(paths, stream, progress)
    classes = tuple(sorted({r.label for r in recs}))
    if len(classes) < 2:
        raise InputError(f"training needs windows of at least two labels, the recordings have {list(classes)}; "
                         "record (or label) another texture")
    say = None if progress is None else (lambda m: progress(f"calibration: {m}"))
    model = _train(recs, classes, windows, make(), epochs, seed, hidden, calibration_progress=say, groups=groups,
                   jobs=jobs, augment=augment)
    model.training.update({"sessions": seen, "stream": stream})
    return model


def scene_windows(paths, stream: str, progress=None
                  ) -> tuple[list[Recording], list[np.ndarray], list[str], list[str], Callable[[], FeaturePipeline]]:
    """Return the labelled windows of one stream of recorded graphs (``--scene REC.toml ... --stream NAME``).

    As :func:`train_from_scenes` and :func:`recalibrate_model` read them.

    Returns
    -------
    recs : list of Recording
        One per labelled span that holds a window.
    windows : list of ndarray (n, features, channels)
        Each span's windows.
    groups : list of str
        Each span's recording (its scene's path): the calibration's group.
    sessions : list of str
        Every session's fingerprint (:func:`session_fingerprint`).
    make : callable
        Makes the stream's pipeline (the same in every scene, else refused).
    """
    from supramodal.fused_model import Sense
    from supramodal.node.scene.build import bank_for, pipeline_for
    from supramodal.replay.session import load_session

    recs: list[Recording] = []
    windows: list[np.ndarray] = []
    groups: list[str] = []
    seen: list[str] = []
    owners: dict[str, object] = {}                      # fingerprint -> the scene it came in
    make: Callable[[], FeaturePipeline] | None = None     # the first scene's pipeline, and its sense
    sense: Sense | None = None
    for path in paths:
        scene, spec, session, _ = scene_stream(path, stream)
        make_here = lambda sc=scene, sp=spec: pipeline_for(sc, bank_for(sc, sp), sp)     # noqa: E731
        if make is None:
            make, first, sense = make_here, path, Sense.of(stream, make_here())
        else:
            assert sense is not None, "set with make, by the first scene"
            try:
                sense.check_pipeline(make_here(), in_fusion=False)
            except SupramodalError as exc:
                raise InputError(f"{path}: stream {stream!r} differs from {first}'s ({exc}); train on recordings "
                                 "of one graph") from None
        fingerprint = session_fingerprint(session)
        if fingerprint in owners:
            # the same recording twice (or a copy of it): its windows would be counted twice, and folds by
            # recording would hold it on both sides (the calibration fitted on leaked copies)
            raise InputError(f"{path}: its recording is {owners[fingerprint]}'s again (the same samples); give each "
                             "recording once")
        owners[fingerprint] = path
        labels = load_session(session).labels
        if not labels:
            raise InputError(f"{session}: the recording has no labels; label it (supramodal label {path} SPANS.csv, "
                             "or record with --marks or --label)")
        for lab in labels:
            rec = Recording(session, lab.label, lab.start, lab.end)
            pipeline = make()
            v = recording_windows(rec, pipeline, spec.mapping, notice=progress)
            if len(v):
                recs.append(rec)
                windows.append(v)
                groups.append(str(path))
        seen.append(fingerprint)
        if progress:
            progress(f"{path}: {len(labels)} labelled span(s) of {sorted({lab.label for lab in labels})}")
    if make is None:
        raise InputError("no recording given: name one or more with --scene")
    return recs, windows, groups, seen, make


def recalibrate_model(model: TextureModel, manifest=None, scenes=(), stream: str | None = None, mapping="auto",
                      progress=None) -> TextureModel:
    """Return ``model`` recalibrated on labelled recordings of a new touch, session or sensor, its network kept.

    See :meth:`supramodal.model.TextureModel.recalibrated`. From a ``manifest`` (CSV of recordings and labels)
    or from recorded graphs (``scenes``, the ``stream`` of each), read through the model's own pipeline.

    Raises
    ------
    InputError
        Naming the cause: neither or both sources, a label the model does not know, a stream configured
        unlike the model, a texture without windows.
    """
    if (manifest is None) == (not scenes):
        raise InputError("recalibrate on one kind of recordings: --manifest CSV, or --scene REC.toml ... --stream NAME")
    if manifest is not None:
        recs, _, windows = _manifest_windows(manifest, model.pipeline, mapping, progress)
        groups = [recording_group(r) for r in recs]
        what = f"{len(recs)} recording(s) of manifest {Path(manifest).name}"
    else:
        if stream is None:
            raise InputError("--scene recordings need --stream NAME: the stream whose model this is")
        recs, windows, scene_of, seen, make = scene_windows(scenes, stream, progress)
        model.check_pipeline(make())
        what = f"stream {stream} of {len(set(scene_of))} recording(s): " + ", ".join(Path(g).name for g in
                                                                                    dict.fromkeys(scene_of))
        # each labelled span its own group: a pooling run or a novelty contact never crosses from one texture to
        # the next within a recording (no folds here to keep a recording whole)
        groups = [f"{g}@{recording_group(r)}" for g, r in zip(scene_of, recs)]
    unknown = sorted({r.label for r in recs} - set(model.classes))
    if unknown:
        raise InputError(f"label(s) {unknown} are not among the model's classes {list(model.classes)}: recalibration "
                         "keeps the network, which knows only those; train a new model to add a texture")
    x = np.concatenate(windows)
    y = np.concatenate([np.full(len(v), model.classes.index(r.label)) for r, v in zip(recs, windows)])
    missing = sorted(set(model.classes) - {r.label for r, v in zip(recs, windows) if len(v)})
    if missing:
        raise InputError(f"the recordings have no window of {missing}: recalibration needs every texture the model "
                         "knows; record each on the new touch")
    group_of = np.repeat(np.array(groups), [len(v) for v in windows])
    new = model.recalibrated(x, y, group_of, what=what[:300])
    if scenes and "sessions" in model.training:
        # its calibration has now seen these recordings: a fusion must not take them for unseen ones
        new.training["sessions"] = list(dict.fromkeys([*model.training["sessions"], *seen]))
    return new


def recording_group(rec: Recording) -> str:
    """Return the calibration group of a manifest line's windows: its file and span.

    The same whatever manifest lists it, so that a fold's model is calibrated as a re-run on its recordings is.
    """
    return f"{rec.path}@{rec.start:g}-{'end' if rec.end is None else f'{rec.end:g}'}"


def cross_validate_manifest(manifest, bank: Bank, features=("Af",), window: float = 0.1, k: int = 5,
                            epochs: int = DEFAULT_EPOCHS, seed: int = 0, mapping="auto", progress=None,
                            augment: GainAugment | None = None, hidden: int | None = None) -> dict:
    """Cross-validate, grouped ``k``-fold, the training :func:`train_from_manifest` would do.

    Folds are grouped by manifest line, one trial (:func:`supramodal.training.grouped_folds`):
    the windows of one trial are never on both sides. A long recording may be split into
    several lines (``start``, ``end``) to make several trials; their spans must not overlap. Each
    fold's model is trained as the final one would be (same features, window, epochs, seed, hidden units, gain
    augmentation) on the other folds' recordings and scored on its own.

    Returns
    -------
    dict
        ``k``, ``seed``, ``folds`` (per fold: ``window_accuracy``, ``recording_accuracy``,
        ``recordings``), ``window_accuracy`` and ``recording_accuracy`` (``{"mean", "sd"}``
        over folds; sd with ``ddof=1``), ``labels``, ``confusion`` (windows of every test fold;
        rows = truth), ``recall`` (per label, from ``confusion``), ``chance`` (the largest
        label's share of windows: what always answering it would score), ``calibration``
        (per ``window`` and per ``recording``, a :func:`~supramodal.calibration.calibration_report`
        of every test fold's decisions scored together, each by its fold's calibrated model).
    """
    make_pipeline = lambda: FeaturePipeline(bank, features, window)       # noqa: E731
    return _cross_validate(manifest, make_pipeline, k, epochs, seed, hidden, mapping, progress, augment)


def cross_validate_model(model: TextureModel, manifest, k: int = 5, seed: int | None = None, mapping="auto",
                         progress=None) -> dict:
    """Cross-validate, grouped ``k``-fold, ``model``'s configuration on the manifest.

    Each fold trains a fresh model exactly as ``model`` was made (bank, features, window, peak
    settings, hidden units, epochs, gain augmentation, early stopping: a file from before it has none, and
    its copies train every epoch) on the other folds' recordings and scores it on its own: how
    well a model like this one generalises to recordings it has not seen, which scoring ``model``
    itself on its own training recordings cannot say. ``seed`` defaults to the model's.

    Returns
    -------
    dict
        As :func:`cross_validate_manifest`.
    """
    seed = model.training.get("seed", 0) if seed is None else seed
    folds = _deployed_folds(model)
    # a version 3 file from before early stopping has no patience: its fold networks trained every epoch
    patience = EARLY_STOP_PATIENCE if folds is None else model.training.get("patience")
    return _cross_validate(manifest, model.pipeline, k, int(model.training["epochs"]), seed,
                           model.mlp.shape[1], mapping, progress, model.augment, folds, patience)


def _deployed_folds(model: TextureModel) -> int | None:
    """Return the calibration folds a copy of ``model`` trains with, so that it deploys as ``model`` does.

    As many as its networks (an ensemble of its calibration's fold networks), 0 for an uncalibrated model;
    None (the default) for a calibrated model of one network (a file of before version 3, which trained
    one network beside ten fold networks: its copies are made as this version makes them).
    """
    if not model.calibrated:
        return 0
    return len(model.mlp.members) if isinstance(model.mlp, Ensemble) else None


def _cross_validate(manifest, make_pipeline, k, epochs, seed, hidden, mapping, progress, augment=None,
                    calibration_folds: int | None = None, patience: int | None = EARLY_STOP_PATIENCE) -> dict:
    recs, classes, windows = _manifest_windows(manifest, make_pipeline, mapping, progress)
    _refuse_overlapping_trials(recs)
    fold = grouped_folds([r.where for r in recs], [r.label for r in recs], k, seed)
    confusion = np.zeros((len(classes), len(classes)), dtype=int)
    folds = []
    # Each fold's _score arrays as lists: log-posteriors and pooled rows (arrays), truths (numpy integers).
    scored: dict[str, list[Any]] = {"log_posteriors": [], "pooled": [], "recording_truth": [], "window_truth": []}
    calibrated = True
    for f in range(k):
        train = [i for i in range(len(recs)) if fold[i] != f]
        test = [i for i in range(len(recs)) if fold[i] == f]
        seen = sorted({recs[i].label for i in train})
        if seen != list(classes):
            missing = sorted(set(classes) - set(seen))
            raise ManifestError(f"{manifest}: fold {f + 1} of {k} would train without {missing}: record them more "
                                "often or lower --cv")
        model = _train([recs[i] for i in train], classes, [windows[i] for i in train],
                       make_pipeline(), epochs, seed, hidden, augment=augment,
                       calibration_folds=DEFAULT_CALIBRATION_FOLDS if calibration_folds is None else calibration_folds,
                       patience=patience)
        result, part = _score_recordings(model, [recs[i] for i in test], [windows[i] for i in test])
        for key, value in part.items():
            scored[key] += list(value)
        calibrated &= model.calibrated
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
            "chance": float(totals.max() / totals.sum()),
            "calibration": {"calibrated": calibrated,
                            **_calibration_reports({k: np.array(v) if k != "log_posteriors" else v
                                                    for k, v in scored.items()})}}


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
    """Return a cross-validation's result as text.

    Window and recording accuracy (mean +- sd over the folds, chance beside), recall per label, the
    calibration of every test fold's decisions where it was measured, and the confusion table.
    ``result``: what :func:`cross_validate_manifest` or :func:`cross_validate_model` returns.
    """
    w, r = result["window_accuracy"], result["recording_accuracy"]
    lines = [f"grouped {result['k']}-fold cross-validation (folds by manifest line: a trial's windows on one side; "
             f"seed {result['seed']})",
             f"window accuracy     {w['mean']:.3f} +- {w['sd']:.3f} (chance {result['chance']:.3f})",
             f"recording accuracy  {r['mean']:.3f} +- {r['sd']:.3f}",
             "recall per label    " + ", ".join(f"{c} {v:.3f}" for c, v in result["recall"].items() if v is not None)]
    if "calibration" in result:
        lines += ["", "every test fold's decisions scored together, each by its fold's model:",
                  format_calibration(result["calibration"])]
    return "\n".join(lines) + "\n\n" + _confusion_table(result["labels"], result["confusion"])


def _confusion_table(labels, confusion) -> str:
    width = max(8, *(len(n) for n in labels)) + 1
    lines = ["confusion (windows; rows = truth, columns = predicted)",
             " " * width + "".join(f"{n:>{width}}" for n in labels)]
    for n, row in zip(labels, confusion):
        lines.append(f"{n:<{width}}" + "".join(f"{v:>{width}}" for v in row))
    return "\n".join(lines)


def evaluate_manifest(model: TextureModel, manifest, mapping="auto", progress=None) -> dict:
    """Per-window and per-recording accuracy and calibration of ``model`` on the manifest's recordings.

    A recording's decision pools all its windows as the node's ``scope = "contact"`` pools one
    touch (the model's calibrated pooling; summed log-posteriors for an uncalibrated model).

    Returns
    -------
    dict
        ``window_accuracy``, ``recording_accuracy``, ``labels`` (row/column order of
        ``confusion``), ``confusion`` (windows; rows = truth, columns = predicted; a tie is in no
        column), ``recordings`` (per-recording details), ``calibration`` (``calibrated``,
        ``fitted_on`` and, per ``window`` and per ``recording``, a
        :func:`~supramodal.calibration.calibration_report`: accuracy, log loss, Brier score, ECE,
        reliability bins, how many decisions say >= 0.99 and the share of them wrong).
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
    importance = permutation_importance(model.log_posteriors, np.concatenate(windows), truth)
    result["channel_importance"] = dict(zip(model.bank.names, importance.round(6).tolist()))
    return result


def score_recordings(model: TextureModel, recs: list[Recording], windows: list[np.ndarray], progress=None) -> dict:
    """Return the result of :func:`evaluate_manifest` for recordings whose feature windows are known.

    Decisions come from the model's log-posteriors (calibrated when the model is): a window's is
    their winner, a recording's the winner of its windows pooled
    (:meth:`~supramodal.calibration.Calibration.pool` when calibrated, summed log-posteriors
    otherwise). A tie is no decision and counts as wrong (``predicted`` None), never the class
    whose name sorts first.
    """
    return _score_recordings(model, recs, windows, progress)[0]


def _score_recordings(model: TextureModel, recs, windows, progress=None) -> tuple[dict, dict]:
    """:func:`score_recordings`' result, and the arrays it was computed from (:func:`_score`)."""
    labels = list(model.classes)
    confusion = np.zeros((len(labels), len(labels)), dtype=int)
    per_rec = []
    scored = _score(model, recs, windows)
    for rec, v, lp, pooled in zip(recs, windows, scored["log_posteriors"], scored["pooled"]):
        pred = winner(lp)
        truth = labels.index(rec.label)
        decided = pred >= 0
        np.add.at(confusion[truth], pred[decided], 1)     # truth's row: a view of confusion, counted in place
        k = int(winner(pooled))
        per_rec.append({"path": str(rec.path), "label": rec.label, "windows": int(len(v)),
                        "window_accuracy": float(np.mean(pred == truth)), "predicted": labels[k] if k >= 0 else None,
                        "confidence": float(np.exp(pooled.max()))})
        if progress:
            progress(f"{rec.path.name}: {per_rec[-1]['window_accuracy']:.3f} of windows, recording -> "
                     f"{per_rec[-1]['predicted'] or 'no decision (tie)'}")
    truths = [labels.index(r.label) for r in recs]
    totals = np.bincount(scored["window_truth"], minlength=len(labels))
    return {
        "window_accuracy": float(np.mean(np.concatenate([winner(lp) for lp in scored["log_posteriors"]])
                                         == scored["window_truth"])),
        "recording_accuracy": float(np.mean([r["predicted"] == r["label"] for r in per_rec])),
        "chance": float(totals.max() / totals.sum()),
        "pooled": {str(n): dict(zip(("accuracy", "runs"), pooled_accuracy(scored["log_posteriors"], truths, n)))
                   for n in POOLED_WINDOWS},
        "labels": labels,
        "confusion": confusion.tolist(),
        "recordings": per_rec,
        "calibration": {"calibrated": model.calibrated,
                        "fitted_on": None if model.calibration is None else model.calibration.fitted_on,
                        **_calibration_reports(scored)},
        "anytime": _anytime(model, scored),
    }, scored


def _anytime(model: TextureModel, scored: dict) -> list[dict] | None:
    """Return the anytime sweep: each recording as one touch, decided once its pooled confidence reaches a threshold.

    The thresholds are each of :data:`~supramodal.evaluation.ANYTIME_THRESHOLDS`
    (:func:`~supramodal.evaluation.anytime_sweep`, as the node's ``[decision] confidence`` decides a contact);
    None for an uncalibrated model, whose confidence is no probability to set a threshold on.
    """
    if model.calibration is None:          # not model.calibrated
        return None
    lps = scored["log_posteriors"]
    starts = np.cumsum([0] + [len(lp) for lp in lps])
    runs = [np.arange(a, b) for a, b in zip(starts[:-1], starts[1:])]
    rho, caps = model.calibration.contact_pooling
    rows = anytime_sweep(np.concatenate(lps), scored["window_truth"], runs, rho, caps=caps)
    return [{k: v for k, v in r.items() if k != "windows"} for r in rows]


def _score(model: TextureModel, recs: list[Recording], windows: list[np.ndarray]) -> dict:
    """Each recording's window log-posteriors and its pooled log-posteriors, with the truths."""
    labels = list(model.classes)
    lps = [model.log_posteriors(v) for v in windows]
    pool = model.calibration.pool if model.calibration is not None else (lambda lp: pool_log_posteriors(lp, 0.0))
    truths = np.array([labels.index(r.label) for r in recs])
    return {"log_posteriors": lps, "pooled": np.array([pool(lp) for lp in lps]), "recording_truth": truths,
            "window_truth": np.repeat(truths, [len(lp) for lp in lps])}


def _calibration_reports(scored: dict) -> dict:
    """Calibration (:func:`supramodal.calibration.calibration_report`) per window and per recording."""
    return {"window": calibration_report(np.concatenate(scored["log_posteriors"]), scored["window_truth"]),
            "recording": calibration_report(scored["pooled"], scored["recording_truth"])}


def format_evaluation(result: dict) -> str:
    """Return an evaluation's result (:func:`evaluate_manifest`'s) as text.

    Window and recording accuracy (chance beside), accuracy against windows pooled, the calibration, the
    anytime decisions where there are any, the channels carrying the decision where measured, and the
    confusion table.
    """
    lines = [f"window accuracy     {result['window_accuracy']:.3f} (chance {result['chance']:.3f}: always the "
             "commonest label)",
             f"recording accuracy  {result['recording_accuracy']:.3f} ({len(result['recordings'])} recordings, "
             "all windows of each pooled)", "",
             "windows pooled      accuracy (runs of that many consecutive windows)"]
    for n, p in result["pooled"].items():
        shown = "-" if p["accuracy"] is None else f"{p['accuracy']:.3f}"
        lines.append(f"  {n:>3}               {shown} ({p['runs']} runs)")
    lines.append(f"  whole recording   {result['recording_accuracy']:.3f}")
    if "calibration" in result:
        lines += ["", format_calibration(result["calibration"])]
    if result.get("anytime"):
        lines += ["", format_anytime(result["anytime"])]
    if "channel_importance" in result:
        top = sorted(result["channel_importance"].items(), key=lambda kv: -kv[1])
        lines += ["", "channels carrying the decision (window accuracy lost when the channel is shuffled)",
                  "  " + ", ".join(f"{name} {v:+.3f}" for name, v in top[:8])]
    return "\n".join(lines) + "\n\n" + _confusion_table(result["labels"], result["confusion"])


def format_anytime(rows: list[dict]) -> str:
    """Return the anytime decisions of :func:`evaluate_manifest` (its ``anytime``) as a table."""
    lines = ["decided as soon as sure (each recording one touch, as [decision] confidence = c decides a contact)",
             f"  {'c':>6}  {'decided':>9}  {'right of decided':>16}  {'median windows':>14}  {'right at the end':>16}"]
    for r in rows:
        right = "-" if not r["decided"] else f"{r['right'] / r['decided']:.3f}"
        median = "-" if r["median_windows"] is None else f"{r['median_windows']:g}"
        lines.append(f"  {r['confidence']:>6g}  {r['decided']:>4} of {r['contacts']:<2}  {right:>16}  {median:>14}  "
                     f"{r['end_right']:>9} of {r['contacts']:<3}")
    return "\n".join(lines)


def format_calibration(calibration: dict) -> str:
    """Return, as text, how far the confidence can be trusted.

    A model's calibration, and per window and per recording its decisions' accuracy, log loss, Brier score,
    ECE and the share wrong of those that say >= 0.99 (``calibration`` as in :func:`evaluate_manifest`'s
    result).
    """
    lines = [f"posteriors          {describe_calibration(calibration)}"]
    w, r = calibration["window"], calibration["recording"]
    sure = w["sure"]

    def said(report) -> str:
        if not report["sure_count"]:
            return "none"
        return f"{report['sure_count']}, {report['sure_wrong']:.3f} wrong"

    rows = [("decisions", str(w["n"]), str(r["n"])), ("accuracy", f"{w['accuracy']:.3f}", f"{r['accuracy']:.3f}"),
            ("log loss (nats)", f"{w['log_loss']:.3f}", f"{r['log_loss']:.3f}"),
            ("Brier score", f"{w['brier']:.3f}", f"{r['brier']:.3f}"),
            (f"ECE ({len(w['reliability']['count'])} bins)", f"{w['ece']:.3f}", f"{r['ece']:.3f}"),
            (f"say >= {sure:g}", said(w), said(r))]
    lines.append(f"{'':<20}{'per window':>18}{'per recording':>20}")
    lines += [f"{name:<20}{a:>18}{b:>20}" for name, a, b in rows]
    lines.append("(a recording: all its windows pooled as the node pools a contact; ECE: expected calibration "
                 "error, the confidence's mean distance from the accuracy)")
    if calibration.get("calibrated"):
        from supramodal.node.workflows.reports import confidence_verdict

        lines.append("windows: " + confidence_verdict(w))
    return "\n".join(lines)


def describe_calibration(calibration: dict) -> str:
    """``calibrated on ...`` or ``uncalibrated (model file version 1)``, in words."""
    if not calibration.get("calibrated"):
        version = calibration.get("model_version")
        why = "model file version 1" if version == 1 else "trained without calibration folds"
        return (f"uncalibrated ({why}): the network's normalised outputs, whose confidence is not a probability; "
                "retrain with `supramodal train` to calibrate them")
    if not calibration.get("fitted_on"):
        return "calibrated (each fold's model on out-of-fold windows of its own training recordings)"
    return calibration_line(calibration["fitted_on"])
