"""Training and scoring a fusion of two senses on recorded two-sense sessions.

The sessions are those `supramodal record` writes for a graph (each source's session with its
blocks' times, and ``NAME.toml``, the scene that replays them in step). Each scene is run at
``max`` speed, so the two streams' windows are paired on common time exactly as the node pairs
them live; the pairs whose truth is known are the data:

* :func:`train_fused` fits the supramodal network (early fusion) on the pairs' feature windows,
  or learns the late-fusion weight and sharpness on out-of-fold log-posteriors of copies of the
  streams' models (never on windows a network trained on), and scores each sense and the fusion
  on held-out windows;
* :func:`evaluate_fused` scores each stream and the fusion, per window (accuracy and calibration)
  and per contact (a run of windows of one texture, its decisions pooled by summed
  log-posteriors, as the node pools a contact).
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np

from supramodal.calibration import (
    DEFAULT_CALIBRATION_FOLDS,
    calibration_folds,
    calibration_report,
    ece_if_calibrated,
    fewest_groups_of_a_label,
    mean_confidence,
    winner,
)
from supramodal.checks import integer
from supramodal.errors import InputError, SupramodalWarning
from supramodal.fused_model import (
    EarlyFusionModel,
    Sense,
    fused_pooling,
    held_out_scores,
    learn_late_fusion_out_of_fold,
    senses_out_of_fold,
    worse_than_a_sense,
)
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.model import GainAugment, ModelError
from supramodal.node.runtime.events import FUSED_STREAM, WindowEvent, log_posteriors_of
from supramodal.node.runtime.sinks import ListSink
from supramodal.node.scene.build import build_node
from supramodal.node.scene.schema import SceneError, load_scene, scene_to_toml
from supramodal.node.scene.variants import relocated, with_absolute_paths, with_fusion, with_models

#: How a fusion is learned from sessions.
FUSION_METHODS = ("early", "late")


def _graph_for(path, fused_model=None, models=None):
    scene = load_scene(path)
    if models:
        scene = with_models(scene, models)
    if not scene.is_graph or scene.fusion is None:
        raise SceneError(f"{scene.source}: a scene with a [fusion] block of two streams is needed (the scene "
                         "`supramodal record` writes for a graph replays a two-sense recording)")
    if fused_model is not None:
        scene = dataclasses.replace(scene, fusion=dataclasses.replace(scene.fusion, method="early",
                                                                      model=str(fused_model)))
    return scene


def scene_pairs(path, progress=None, models=None):
    """Run the scene at ``max`` speed; return ``(graph, pairs)``.

    ``pairs``: the fused pairs of window events ``(event_a, event_b)`` whose truth is known, in order. Pairing
    does not depend on the fusion method, so the scene's fusion is run as late fusion here (its own model is
    not needed). ``models``: ``{stream: model file}`` to decide with instead of the scene's
    (:func:`with_models`).
    """
    scene = _graph_for(path, models=models)
    assert scene.fusion is not None, "_graph_for refuses a scene without a [fusion]"
    scene = dataclasses.replace(scene, fusion=dataclasses.replace(scene.fusion, method="late", model=None, weight=0.5))
    graph = build_node(scene, speed="max", sinks_override=[])
    graph.fusion.kept_pairs = []
    graph.run()
    pairs = [(a, b) for a, b in graph.fusion.kept_pairs if a.truth is not None and a.truth == b.truth]
    if progress:
        progress(f"{scene.source}: {len(pairs)} labelled pairs of {graph.fusion.paired} paired windows")
    return graph, pairs


def train_fused(paths, method: str = "early", epochs: int = DEFAULT_EPOCHS, seed: int = 0, progress=None,
                k: int = DEFAULT_CALIBRATION_FOLDS, models=None, augment: GainAugment | None = None, jobs: int = 1):
    """Learn a fusion on the labelled pairs of the scenes at ``paths``.

    Every number learned comes from windows held out of the network that made them: the pairs are
    dealt to ``k`` folds by contact (a run of consecutive windows of one texture in one recording;
    :func:`supramodal.calibration.calibration_folds`, shuffled by ``seed``), and each sense's
    log-posteriors are either

    * ``"unseen"``: the streams' own models' log-posteriors, when both models say which sessions they
      were trained on (``training["sessions"]``, written by ``train --scene --stream``) and none of
      these recordings is among them: the models the fusion will run with, on recordings they never
      saw; or
    * ``"out-of-fold"``: otherwise (a model saw some of these recordings, or does not say what it saw),
      those of a copy of the stream's model (same configuration) trained on the other folds
      (:func:`supramodal.fused_model.senses_out_of_fold`), never those of a model on its own
      training windows.

    ``models``: ``{stream: model file}`` deciding instead of the scenes' own (:func:`with_models`).

    * ``"late"``: the first stream's weight and the sharpness
      (:func:`supramodal.fused_model.learn_late_fusion_out_of_fold`) learned on those
      out-of-fold log-posteriors; the fused held-out score is cross-fitted (each fold fused with a
      weight learned without it).
    * ``"early"``: the supramodal network trained on every pair, calibrated on out-of-fold pairs of
      the same folds (:meth:`~supramodal.fused_model.EarlyFusionModel.train`); its held-out score
      is that of its calibration folds. ``augment``: gain augmentation of its networks' training pairs
      (each sense's gains by its bank; a late fusion trains no network, and takes none).

    Returns
    -------
    (EarlyFusionModel, dict) or ((float, float), dict)
        The network (``method="early"``) or the first stream's late-fusion ``(weight, sharpness)``,
        and what it was learned on: ``pairs``, ``classes``, ``streams``, ``contacts``, ``folds``,
        ``folds_by``, (late) ``fold_weights`` and ``correlation`` (the fused decisions' contact
        pooling, :func:`supramodal.fused_model.fused_pooling`), and ``held_out``: per stream and
        for the fusion (``"late"`` or ``"early"``) its held-out window ``accuracy`` and
        ``log_loss``, ``brier``, ``ece``, ``sure_count`` and ``sure_wrong``;
        ``posteriors``: ``{"source": "unseen" | "out-of-fold", "why": text}``, which of the two above.
    """
    from supramodal.node.scene.schema import load_scene
    from supramodal.node.workflows.training import scene_stream, session_fingerprint

    if method not in FUSION_METHODS:
        raise InputError(f"the fusion method is one of {FUSION_METHODS}, got {method!r}")
    if augment is not None and method != "early":
        raise InputError("gain augmentation is of a network's training windows; a late fusion trains none (its "
                         "senses' models train as each did: train them with it)")
    senses: tuple[Sense, Sense] | None = None        # the first scene's, and its classes
    classes: tuple[str, ...] | None = None
    stream_models: tuple = ()
    rows_a: list[np.ndarray] = []       # each pair's feature window of either sense
    rows_b: list[np.ndarray] = []
    truth: list[int] = []
    groups: list[str] = []
    own: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])    # each sense model's own log-posteriors per pair
    seen = 0
    # The same recording twice (or a copy of it), checked before any work: its pairs would be counted twice,
    # on both sides of the folds.
    fingerprints: dict[str, object] = {}
    for path in paths:
        try:
            fingerprint = session_fingerprint(scene_stream(path, load_scene(path).streams[0].name)[2])
        except (InputError, OSError):
            continue                    # no recorded session here: scene_pairs says what the scene is not
        if fingerprint in fingerprints:
            raise InputError(f"{path}: its recording is {fingerprints[fingerprint]}'s again (the same samples); give "
                             "each recording once")
        fingerprints[fingerprint] = path
    for k_scene, path in enumerate(paths):
        graph, pairs = scene_pairs(path, progress, models) if models else scene_pairs(path, progress)
        a, b = (next(s for s in graph.streams if s.name == n) for n in graph.fusion.inputs)
        if senses is None:
            senses, classes = (Sense.of(a.name, a.pipeline), Sense.of(b.name, b.pipeline)), graph.fusion.classes
            stream_models = (a.model, b.model)
        else:
            assert classes is not None, "set with senses, by the first scene"
            try:
                for sense, stream in zip(senses, (a, b)):
                    sense.check_pipeline(stream.pipeline)
            except ModelError as exc:
                raise InputError(f"{path}: its streams differ from the first scene's ({exc}); train on recordings "
                                 "of one graph") from None
            if sorted(graph.fusion.classes) != sorted(classes):
                raise InputError(f"{path}: its textures {list(graph.fusion.classes)} differ from the first scene's "
                                 f"{list(classes)}; train on recordings of one graph")
        for model, stream in zip(stream_models, (a, b)):
            if "sessions" in model.training:        # a model that says what it saw (train --stream)
                seen += session_fingerprint(scene_stream(path, stream.name)[2]) in model.training["sessions"]
        groups += contact_groups(pairs, f"{k_scene}:")
        for ea, eb in pairs:
            rows_a.append(np.stack([ea.features[f] for f in senses[0].features]))
            rows_b.append(np.stack([eb.features[f] for f in senses[1].features]))
            truth.append(classes.index(ea.truth))
            if all("sessions" in m.training for m in stream_models):     # their own posteriors may serve
                for lps_own, e in zip(own, (ea, eb)):
                    lps_own.append(log_posteriors_of(e)[[list(e.classes).index(c) for c in classes]])
    if not truth:
        raise InputError("no labelled pair of windows in these recordings: record with a source that labels its "
                         "stream, or label the sessions")
    assert senses is not None and classes is not None, "a labelled pair came from a scene, which set them"
    missing = sorted(set(classes) - {classes[k] for k in truth})
    if missing:
        raise InputError(f"the recordings have no labelled pair of {missing}: record every texture")
    y = np.array(truth)
    va, vb = np.array(rows_a), np.array(rows_b)
    names = [s.name for s in senses]
    said = [m.training.get("sessions") for m in stream_models]
    if all(s is not None for s in said) and not seen:
        lps = [np.array(v) for v in own]
        folds, by = calibration_folds(y, np.asarray(groups), k, seed)
        posteriors = {"source": "unseen", "why": f"the sense models were trained on {len(said[0])} and "
                      f"{len(said[1])} other recording(s), none of these {len(paths)}: their own posteriors"}
    else:
        say = None if progress is None else (lambda m: progress(f"held-out windows: {m}"))
        lps, folds, by = senses_out_of_fold(stream_models, (va, vb), y, classes, groups, k, seed, say, names)
        why = (f"the sense models saw {seen} of these recordings' sessions" if seen else
               "the sense models do not say which recordings they were trained on")
        posteriors = {"source": "out-of-fold", "why": f"{why}: out-of-fold posteriors of copies of them trained "
                      "without each fold"}
    held = held_out_scores(dict(zip(names, lps)), y)
    info = {"pairs": len(y), "classes": list(classes), "streams": names, "contacts": len(set(groups)),
            "folds": int(len(np.unique(folds))), "folds_by": "contact" if by == "recording" else by,
            "posteriors": posteriors}
    if by == "span":
        # Held-out spans then lie between training windows of the same touch: their score flatters.
        warnings.warn(f"{len(set(groups))} contacts are too few for {k} folds of whole contacts (every texture in "
                      f"two or more, {k} or more in all): the held-out windows are time spans of contacts whose "
                      "other windows trained the fold's networks, so the weight and the held-out scores are "
                      "optimistic; record more contacts", SupramodalWarning, stacklevel=2)
    if method == "early":
        _warn_if_early_without_augmentation(y, groups, augment)
        say = None if progress is None else (lambda m: progress(f"early network's calibration: {m}"))
        model = EarlyFusionModel.train(senses, va, vb, y, classes, epochs=epochs, seed=seed, groups=groups,
                                       calibration_folds=k, calibration_progress=say, augment=augment, jobs=jobs)
        assert model.calibration is not None, "EarlyFusionModel.train calibrates on calibration_folds=k > 0 folds"
        assert model.out_of_fold is not None, "kept by EarlyFusionModel.train with its calibration"
        fused = model.calibration.log_posteriors(model.out_of_fold.logits)
        held.update(held_out_scores({"early": fused}, y))
        info["held_out"] = held
        _refuse_worse_than_a_sense("early", fused, dict(zip(names, lps)), y)
        return model, info
    late = learn_late_fusion_out_of_fold(lps[0], lps[1], y, folds)
    held.update(held_out_scores({"late": late["fused"]}, y))
    info["held_out"] = held
    _refuse_worse_than_a_sense("late", late["fused"], dict(zip(names, lps)), y)
    info["fold_weights"] = late["fold_weights"]
    info["correlation"] = fused_pooling(late["fused"], y, folds, groups)
    return (late["weight"], late["sharpness"]), info


#: Contacts (touches) of a texture below which an early network trained without gain augmentation is warned of.
FEW_TOUCHES = 3


def _warn_if_early_without_augmentation(labels, groups, augment: GainAugment | None) -> None:
    """Warn in one line when an early network is to learn from few touches of some texture, without augmentation.

    It then learns the touches' own gains: on the two-sense world (two touches of each texture, scored on a
    third; `supramodal experiment newtouch`, 2026-11-30), its ECE on the new touch was 0.04 to 0.24 without gain
    augmentation, and 56 of its 708 windows saying >= 0.99 were wrong on one set of 40 s touches; with
    ``--augment-gains 4,0.03``, 0.013 to 0.036 (docs/results.md, "Trust on a new touch").
    """
    if augment is not None:
        return
    fewest = fewest_groups_of_a_label(labels, groups)
    if fewest >= FEW_TOUCHES:
        return
    warnings.warn(f"an early network learns from {fewest} contact(s) of some texture, without gain augmentation: "
                  "it may learn those touches' own gains and overclaim on a touch it never met; add "
                  "--augment-gains 4,0.03 (the network then takes 5 times the CPU), or record each texture on "
                  f"{FEW_TOUCHES} or more separate touches", SupramodalWarning, stacklevel=3)


def _refuse_worse_than_a_sense(method: str, fused, senses: dict, labels) -> None:
    """Raise an :class:`InputError` when the fusion does worse on its held-out windows than a sense alone.

    As :func:`supramodal.fused_model.worse_than_a_sense` tells: a robot would act on its answers.
    """
    worse = worse_than_a_sense(fused, senses, labels)
    if worse is None:
        return
    name, own, fused_loss = worse
    raise InputError(f"the {method} fusion learned here does worse on its held-out windows than {name} alone (log "
                     f"loss {fused_loss:.3f} against {own:.3f}): it would be surer than it is right; run {name} "
                     f"alone, or record more contacts of each texture so that the fusion has more to learn from")


def write_fused_scene(live, streams, models: dict[str, str], out, *, method: str, model: str | None = None,
                      weight: float | None = None, sharpness: float | None = None,
                      correlation: float | None = None) -> Path:
    """Write the scene that runs the fusion live.

    It is the scene ``live`` (the one the recordings were made with) with the streams in ``models``
    (``{stream: model file}``) deciding with those files and a ``[fusion]`` of ``method`` over ``streams``:
    ``model`` (early), or ``weight``, ``sharpness`` and ``correlation`` (late; the [fusion] keys). Paths the
    scene names relative to its own folder (a replay's file, a bank file, a sink's file) are written absolute,
    so the new scene runs from its own folder. Where ``live`` fused the same two streams, its
    ``[fusion.decision]`` and ``max_wait`` are kept. Returns ``out``; refuses an existing file (the caller
    checks ``--force``).
    """
    scene = load_scene(live)
    learned = {"model": model, "weight": weight, "sharpness": sharpness, "correlation": correlation}
    checked = with_fusion(with_models(with_absolute_paths(scene), models), streams=list(streams), method=method,
                          **{k: v for k, v in learned.items() if v is not None})
    before = scene.fusion
    if before is not None and set(before.streams) == set(streams):
        # the live scene's own way of deciding on the fused windows, and its wait, as it had them
        assert checked.fusion is not None, "with_fusion gives a fusion"
        checked = dataclasses.replace(checked, fusion=dataclasses.replace(
            checked.fusion, decision=before.decision, contact_from=before.contact_from, max_wait=before.max_wait))
    out = Path(out)
    out.write_text(f"# {scene.source} with its sense models and the fusion learned by supramodal train --fusion.\n"
                   + scene_to_toml(relocated(checked, out)))
    return out


def contact_groups(pairs, prefix: str = "") -> list[str]:
    """Return each pair's contact, the groups whole folds are made of.

    Contacts are runs of pairs of one truth whose first stream's windows follow one
    another (``prefix`` + the run's number).
    """
    out, run, last = [], -1, None
    for ea, _ in pairs:
        if last is None or ea.truth != last.truth or ea.window != last.window + 1:
            run += 1
        out.append(f"{prefix}{run}")
        last = ea
    return out


def evaluate_fused(paths, fused_model=None, progress=None, contact_windows: int | None = None) -> dict:
    """Each stream's and the fusion's accuracy over the scenes at ``paths`` (run at ``max``).

    Parameters
    ----------
    paths : sequence of path
        Replay scenes of recorded graphs with a ``[fusion]`` block (``supramodal record`` writes them).
    fused_model : path, optional
        An early-fusion model file to score instead of the scenes' own fusion.
    progress : callable, optional
        Told one line per scene.
    contact_windows : int, optional
        Windows per contact, >= 1: each run of windows of one texture is cut into contacts of this
        many consecutive windows from its start (a shorter rest is left out), as
        :func:`supramodal.evaluation.pooled_accuracy` cuts a recording. Default None: a contact is
        the whole run.

    Returns
    -------
    dict
        Per stream (each sense and ``"fused"``): ``window_accuracy`` and ``windows``, with the
        calibration of its log-posteriors (log loss, Brier score, ECE, the share wrong of the
        windows that say >= 0.99); ``contact_accuracy`` and ``contacts`` (each contact's windows
        pooled by summed log-posteriors), ``contact_windows``; ``labels``, ``confusion``,
        ``unknown``; and ``scored``, per scene what was scored: a sense's ``model`` file (None: a
        model trained on the spot), the fusion's ``method``, ``weight`` and ``sharpness`` (late
        fusion; None with early), ``correlation`` (its contact pooling), ``model`` (the early
        network's file; None: trained on the spot, or late fusion) and ``senses``, each fused
        stream's model file.

    Raises
    ------
    InputError
        ``contact_windows`` not an integer >= 1, no labelled window, or no run of one texture as
        long as ``contact_windows``.
    """
    if contact_windows is not None and not integer(1)(contact_windows):
        raise InputError(f"the windows per contact must be an integer >= 1, got {contact_windows!r}")
    windows: dict[str, list] = {}
    contacts: dict[str, list] = {}
    decided: dict[str, list] = {}           # stream -> [(truth, decision)] of its labelled windows
    classes: dict[str, tuple] = {}
    scored: dict[str, tuple[list, list]] = {}   # stream -> (log-posteriors, truth index) of its labelled windows
    what: dict[str, list] = {}              # stream -> per scene, what was scored
    decided_runs: dict[str, list] = {}      # stream -> its contacts' labelled windows, in order (see _contact_runs)
    for path in paths:
        scene = _graph_for(path, fused_model)
        sink = ListSink()
        graph = build_node(scene, speed="max", sinks_override=[sink])
        graph.run()
        for name, entry in _scored(scene, graph).items():
            what.setdefault(name, []).append(entry)
        if progress:
            progress(f"{scene.source}: {len(sink.windows)} window events")
        by_stream: dict[str, list] = {}
        decided_by_stream: dict[str, list] = {}     # every decided window: an unlabelled one splits no contact
        for e in sink.windows:
            if e.posteriors is not None:
                decided_by_stream.setdefault(e.stream, []).append(e)
                if e.truth is not None:
                    by_stream.setdefault(e.stream, []).append(e)
        for name, events in decided_by_stream.items():
            decided_runs.setdefault(name, []).extend(_contact_runs(events))
        for name, events in by_stream.items():
            windows.setdefault(name, []).extend(e.decision == e.truth for e in events)
            contacts.setdefault(name, []).extend(_contacts(events, contact_windows))
            decided.setdefault(name, []).extend((e.truth, e.decision) for e in events)
            classes.setdefault(name, tuple(events[0].classes))
            lps, ys = scored.setdefault(name, ([], []))
            for e in events:
                if e.truth in e.classes:
                    order = [list(e.classes).index(c) for c in classes[name]]
                    lps.append(log_posteriors_of(e)[order])
                    ys.append(classes[name].index(e.truth))
    if FUSED_STREAM not in windows:
        raise InputError("no labelled window in these recordings: record with a source that labels its stream")
    if not contacts[FUSED_STREAM]:
        raise InputError(f"--contact-windows {contact_windows}: no run of windows of one texture is that long in "
                         "these recordings, so there is no contact to score; give fewer windows per contact")
    out = {}
    for name in windows:
        lps, ys = scored[name]
        report = calibration_report(np.array(lps), np.array(ys)) if ys else None
        out[name] = {"window_accuracy": float(np.mean(windows[name])), "windows": len(windows[name]),
                     "contact_accuracy": float(np.mean(contacts[name])) if contacts[name] else None,
                     "contacts": len(contacts[name]), "contact_windows": contact_windows,
                     "labels": list(classes[name]), "confusion": _confusion(decided[name], classes[name]),
                     "unknown": sum(d not in classes[name] for _, d in decided[name]),
                     "calibration": None if report is None else
                     {k: report[k] for k in ("n", "accuracy", "log_loss", "brier", "ece", "sure", "sure_count",
                                             "sure_wrong")} | {"confidence": mean_confidence(report),
                                                               "ece_if_calibrated": ece_if_calibrated(report)},
                     "scored": what.get(name, [])}
        out[name].update(decision_checks(decided_runs.get(name, []), classes[name], what.get(name, [])))
    return out


def _contact_runs(events: list[WindowEvent]) -> list[list[WindowEvent]]:
    """Return the node's contacts in one stream's decided windows (in order, labelled or not).

    Each run of consecutive windows in contact, as its decider pooled them (a lift-off or a missing window
    ends one).
    """
    runs: list[list[WindowEvent]] = []
    for e in events:
        if not e.in_contact:
            continue
        if runs and runs[-1][-1].window == e.window - 1 and runs[-1][-1].in_contact:
            runs[-1].append(e)
        else:
            runs.append([e])
    return runs


def _filled_truths(run: list[WindowEvent]) -> list:
    """Return a contact's truths with each unlabelled window given the label before it.

    The first label, before any: a gap in the labels is no change of texture.
    """
    known = next((e.truth for e in run if e.truth is not None), None)
    out = []
    for e in run:
        known = e.truth if e.truth is not None else known
        out.append(known)
    return out


def decision_checks(runs: list[list[WindowEvent]], classes, scored: list[dict]) -> dict:
    """Return what a stream's decision rules did against the truth.

    Over its contacts' windows (``runs``, :func:`_contact_runs`) and the rules each scene asked
    (``scored``'s ``asked``).

    Returns
    -------
    dict
        ``false_unknown``: windows of a known texture decided "unknown" (``{"windows", "of", "asked"}``,
        ``asked`` the ``[decision] unknown`` rate, None when off), and, with pooled decisions,
        contacts of one known texture whose pooled decision at their end was "unknown"
        (``"contacts"``, ``"contacts_of"``). With ``[decision] change`` asked: ``changes`` (see
        :func:`~supramodal.evaluation.change_detections`): ``boundaries`` (texture changes within a
        contact), ``detected`` (signalled within :data:`~supramodal.evaluation.DETECT_WITHIN` windows),
        ``delays`` (windows, of every detection), ``false`` (changes signalled that detect none),
        ``minutes`` (the contacts' time), ``asked`` (false changes per minute allowed).
    """
    from supramodal.decisions import UNKNOWN
    from supramodal.evaluation import DETECT_WITHIN, change_detections

    asked = [e.get("asked", {}) for e in scored]
    unknown_asked = next((a["unknown"] for a in asked if a.get("unknown")), None)
    change_asked = next((a["change"] for a in asked if a.get("change")), None)
    known = [e for run in runs for e in run if e.truth in classes]
    out: dict = {"false_unknown": {"windows": sum(e.decision == UNKNOWN for e in known), "of": len(known),
                                   "asked": unknown_asked}}
    ends = [run[-1].pooled for run in runs if len(labels := {e.truth for e in run} - {None}) == 1
            and labels <= set(classes)]         # contacts of one known texture (unlabelled windows aside)
    said = [pooled.label for pooled in ends if pooled is not None]      # each contact's pooled decision at its end
    if said:
        out["false_unknown"].update(contacts=sum(label == UNKNOWN for label in said), contacts_of=len(said))
    if change_asked is not None:
        report = {"boundaries": 0, "detected": 0, "delays": [], "false": 0, "minutes": 0.0, "asked": change_asked}
        for run in runs:
            boundaries, false = change_detections(_filled_truths(run),
                                                  [k for k, e in enumerate(run) if e.pooled and e.pooled.change])
            report["boundaries"] += len(boundaries)
            report["delays"] += [t - b + 1 for b, t in boundaries if t is not None]
            report["false"] += false
            if len(run) > 1:        # a run's time: its windows at their spacing on common time
                report["minutes"] += len(run) * (run[-1].end - run[0].end) / (len(run) - 1) / 60.0
        report["detected"] = sum(d <= DETECT_WITHIN for d in report["delays"])
        out["changes"] = report
    return out


def _scored(scene, graph) -> dict[str, dict]:
    """Return what one scene's run scored, per stream.

    A sense's model file, the fusion's method, weight, sharpness, correlation and files (see
    :func:`evaluate_fused`).
    """
    def file(path):
        return None if path is None else str(scene.resolve(path))

    def asked(decider) -> dict:          # the rules whose rates the evaluation checks
        rules = decider.rules
        return {"unknown": rules.unknown or None, "change": rules.change or None}

    models = {spec.name: file(spec.model.path) for spec in scene.streams}
    deciders = {s.name: s.decider for s in graph.streams}
    out: dict[str, dict] = {name: {"scene": scene.source, "model": path,
                                   "asked": asked(deciders[name]) if deciders[name] is not None else {}}
                            for name, path in models.items()}
    f = graph.fusion
    early = f.method == "early"
    out[FUSED_STREAM] = {"scene": scene.source, "method": f.method, "asked": asked(f.decider),
                         "weight": None if early else float(f.weight),
                         "sharpness": None if early else float(f.sharpness),
                         "correlation": float(f.correlation),
                         "model": file(scene.fusion.model) if early else None,
                         "senses": {name: models.get(name) for name in f.inputs}}
    return out


def _confusion(pairs, classes) -> list[list[int]]:
    """Return the window counts, rows the truth and columns the decision, in the model's class order.

    A window decided "unknown" is in no column.
    """
    index = {c: k for k, c in enumerate(classes)}
    counts = np.zeros((len(classes), len(classes)), dtype=int)
    for truth, decision in pairs:
        if truth in index and decision in index:
            counts[index[truth], index[decision]] += 1
    return counts.tolist()


def _contacts(events, n: int | None = None) -> list[bool]:
    """Return whether each contact was decided right when its windows are pooled by summed log-posteriors.

    The decision's class order is the event's; a tie is wrong. A contact is each run of consecutive windows of
    one truth (``n`` None), or each ``n`` consecutive windows of a run from its start (a shorter rest left
    out).
    """
    out: list[bool] = []
    run: list[WindowEvent] = []
    for e in events + [None]:
        if run and (e is None or e.truth != run[-1].truth or e.window != run[-1].window + 1):
            size = len(run) if n is None else n
            for a in range(0, len(run) - size + 1, size):
                part = run[a : a + size]
                k = int(winner(np.sum([log_posteriors_of(r) for r in part], axis=0)))
                out.append(k >= 0 and part[-1].classes[k] == part[-1].truth)
            run = []
        if e is not None:
            run.append(e)
    return out


def format_fused_evaluation(result: dict) -> str:
    """Return the table ``evaluate --scene`` prints.

    Per stream its windows and contacts right and its calibration, then what was scored (the fusion's method,
    weight, sharpness and files; each sense's model) and what a contact is.
    """
    from supramodal.node.workflows.reports import confidence_verdict, contact_text, scored_text

    lines = [f"{'stream':<12} {'windows right':>14} {'of':>6}  {'contacts right':>15} {'of':>5}  {'log loss':>8} "
             f"{'ECE':>6} {'>= 0.99 wrong':>14}"]
    for name, r in result.items():
        c = r.get("calibration")
        calib = "" if c is None else (f"  {c['log_loss']:>8.3f} {c['ece']:>6.3f} "
                                      f"{_share(c['sure_wrong']):>6} of {c['sure_count']:<5}")
        lines.append(f"{name:<12} {r['window_accuracy']:>14.3f} {r['windows']:>6}  {_share(r['contact_accuracy']):>15} "
                     f"{r['contacts']:>5}{calib}")
    for name, r in result.items():
        lines.append(f"{name}: {scored_text(r['scored'])}")
        if r.get("calibration") is not None:
            lines.append(f"{name}: {confidence_verdict(r['calibration'], fused=name == FUSED_STREAM)}")
        lines += [f"{name}: {line}" for line in decision_check_lines(r)]
    lines.append(f"contacts: {contact_text(next(iter(result.values()))['contact_windows'])}")
    return "\n".join(lines)


def decision_check_lines(r: dict) -> list[str]:
    """Return a stream's :func:`decision_checks` in words.

    The false-unknown rate where "unknown" was asked or said, and the texture changes where
    ``[decision] change`` was asked.
    """
    from supramodal.evaluation import DETECT_WITHIN

    lines = []
    u = r.get("false_unknown")
    if u and (u["asked"] is not None or u["windows"]) and u["of"]:
        line = (f"said \"unknown\" on {u['windows']} of {u['of']} windows of known textures "
                f"({u['windows'] / u['of']:.3f}")
        if u.get("contacts_of"):
            line += f"; {u['contacts']} of {u['contacts_of']} contacts, {u['contacts'] / u['contacts_of']:.3f}"
        asked = u["asked"]
        lines.append(line + (f"; asked {asked:g})" if asked is not None else "; not asked: ties and unsure windows)"))
    c = r.get("changes")
    if c:
        found = (f"{c['detected']} of {c['boundaries']} detected within {DETECT_WITHIN} windows"
                 + (f" (median delay {np.median(c['delays']):g} windows)" if c["delays"] else "")
                 if c["boundaries"] else "no texture changed within a contact")
        rate = f"{c['false'] / c['minutes']:.2f} per minute" if c["minutes"] > 0 else "-"
        lines.append(f"texture changes within a contact: {found}; {c['false']} false in {c['minutes']:.2f} min "
                     f"({rate}; asked at most {c['asked']:g})")
    return lines


def _share(v) -> str:
    return "-" if v is None else f"{v:.3f}"
