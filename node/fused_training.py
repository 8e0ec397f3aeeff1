"""Training and scoring a fusion of two senses on recorded two-sense sessions.

The sessions are those `supramodal record` writes for a graph (each source's session with its
blocks' times, and ``NAME.toml``, the scene that replays them in step). Each scene is run at
``max`` speed, so the two streams' windows are paired on common time exactly as the node pairs
them live; the pairs whose truth is known are the data:

* :func:`train_fused` fits the supramodal network (early fusion) on the pairs' feature windows,
  or learns the late-fusion weight on their per-stream posteriors;
* :func:`evaluate_fused` scores each stream and the fusion, per window and per contact (a run of
  windows of one texture, its decisions pooled by summed log-posteriors, as the node pools a
  contact).
"""

from __future__ import annotations

import numpy as np

from supramodal.errors import InputError
from supramodal.fused_model import EarlyFusionModel, Sense
from supramodal.fusion import learn_late_weight
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.model import ModelError
from supramodal.node.build import build_node
from supramodal.node.events import FUSED_STREAM
from supramodal.node.scene import SceneError, load_scene
from supramodal.node.sinks import ListSink

#: How a fusion is learned from sessions.
FUSION_METHODS = ("early", "late")


def _graph_for(path, fused_model=None):
    scene = load_scene(path)
    if not scene.is_graph or scene.fusion is None:
        raise SceneError(f"{scene.source}: a scene with a [fusion] block of two streams is needed (the scene "
                         "`supramodal record` writes for a graph replays a two-sense recording)")
    if fused_model is not None:
        scene.fusion = {**scene.fusion, "method": "early", "model": str(fused_model)}
    return scene


def scene_pairs(path, progress=None):
    """Run the scene at ``max`` speed; return ``(graph, pairs)``: the fused pairs of window events
    ``(event_a, event_b)`` whose truth is known, in order. Pairing does not depend on the fusion
    method, so the scene's fusion is run as late fusion here (its own model is not needed)."""
    scene = _graph_for(path)
    scene.fusion = {**scene.fusion, "method": "late", "model": None, "weight": 0.5}
    graph = build_node(scene, speed="max", sinks_override=[])
    graph.fusion.kept_pairs = []
    graph.run()
    pairs = [(a, b) for a, b in graph.fusion.kept_pairs if a.truth is not None and a.truth == b.truth]
    if progress:
        progress(f"{scene.source}: {len(pairs)} labelled pairs of {graph.fusion.paired} paired windows")
    return graph, pairs


def train_fused(paths, method: str = "early", epochs: int = DEFAULT_EPOCHS, seed: int = 0, progress=None):
    """Learn a fusion on the labelled pairs of the scenes at ``paths``.

    Returns
    -------
    (EarlyFusionModel, dict) or (float, dict)
        The network (``method="early"``) or the first stream's late-fusion weight, and what it was
        learned on (``pairs``, ``classes``, ``streams``, ``train_accuracy``).
    """
    if method not in FUSION_METHODS:
        raise InputError(f"the fusion method is one of {FUSION_METHODS}, got {method!r}")
    senses = classes = None
    va, vb, truth, oa, ob = [], [], [], [], []
    for path in paths:
        graph, pairs = scene_pairs(path, progress)
        a, b = (next(s for s in graph.streams if s.name == n) for n in graph.fusion.inputs)
        if senses is None:
            senses, classes = (Sense.of(a.name, a.pipeline), Sense.of(b.name, b.pipeline)), graph.fusion.classes
        else:
            try:
                for sense, stream in zip(senses, (a, b)):
                    sense.check_pipeline(stream.pipeline)
            except ModelError as exc:
                raise InputError(f"{path}: its streams differ from the first scene's ({exc}); train on recordings "
                                 "of one graph") from None
            if sorted(graph.fusion.classes) != sorted(classes):
                raise InputError(f"{path}: its textures {list(graph.fusion.classes)} differ from the first scene's "
                                 f"{list(classes)}; train on recordings of one graph")
        for ea, eb in pairs:
            va.append(np.stack([ea.features[f] for f in senses[0].features]))
            vb.append(np.stack([eb.features[f] for f in senses[1].features]))
            truth.append(classes.index(ea.truth))
            oa.append(_in_order(ea, classes))
            ob.append(_in_order(eb, classes))
    if not truth:
        raise InputError("no labelled pair of windows in these recordings: record with a source that labels its "
                         "stream, or label the sessions")
    missing = sorted(set(classes) - {classes[k] for k in truth})
    if missing:
        raise InputError(f"the recordings have no labelled pair of {missing}: record every texture")
    y = np.array(truth)
    info = {"pairs": len(y), "classes": list(classes), "streams": [s.name for s in senses]}
    if method == "early":
        model = EarlyFusionModel.train(senses, np.array(va), np.array(vb), y, classes, epochs=epochs, seed=seed)
        info["train_accuracy"] = float(np.mean(np.argmax(model.outputs(np.array(va), np.array(vb)), axis=1) == y))
        return model, info
    weight = learn_late_weight(np.array(oa), np.array(ob), y)
    info["train_accuracy"] = None
    return weight, info


def _in_order(event, classes) -> np.ndarray:
    """An event's posteriors in ``classes`` order (its stream's model may list them otherwise)."""
    return np.asarray(event.posteriors)[[list(event.classes).index(c) for c in classes]]


def evaluate_fused(paths, fused_model=None, progress=None) -> dict:
    """Each stream's and the fusion's accuracy over the scenes at ``paths`` (run at ``max``): per
    window, and per contact (each run of windows of one texture, pooled by summed
    log-posteriors). ``fused_model``: an early-fusion model file to use instead of the scenes'
    own fusion."""
    windows: dict[str, list] = {}
    contacts: dict[str, list] = {}
    decided: dict[str, list] = {}           # stream -> [(truth, decision)] of its labelled windows
    classes: dict[str, tuple] = {}
    for path in paths:
        scene = _graph_for(path, fused_model)
        sink = ListSink()
        build_node(scene, speed="max", sinks_override=[sink]).run()
        if progress:
            progress(f"{scene.source}: {len(sink.windows)} window events")
        by_stream: dict[str, list] = {}
        for e in sink.windows:
            if e.truth is not None and e.posteriors is not None:
                by_stream.setdefault(e.stream, []).append(e)
        for name, events in by_stream.items():
            windows.setdefault(name, []).extend(e.decision == e.truth for e in events)
            contacts.setdefault(name, []).extend(_contacts(events))
            decided.setdefault(name, []).extend((e.truth, e.decision) for e in events)
            classes.setdefault(name, tuple(events[0].classes))
    if FUSED_STREAM not in windows:
        raise InputError("no labelled window in these recordings: record with a source that labels its stream")
    return {name: {"window_accuracy": float(np.mean(windows[name])), "windows": len(windows[name]),
                   "contact_accuracy": float(np.mean(contacts[name])), "contacts": len(contacts[name]),
                   "labels": list(classes[name]), "confusion": _confusion(decided[name], classes[name])}
            for name in windows}


def _confusion(pairs, classes) -> list[list[int]]:
    """Window counts, rows the truth and columns the decision, in the model's class order."""
    index = {c: k for k, c in enumerate(classes)}
    counts = np.zeros((len(classes), len(classes)), dtype=int)
    for truth, decision in pairs:
        counts[index[truth], index[decision]] += 1
    return counts.tolist()


def _contacts(events) -> list[bool]:
    """Whether each run of consecutive windows of one truth was decided right when pooled by
    summed log-posteriors (the decision's class order is the event's posteriors')."""
    out, run = [], []
    for e in events + [None]:
        if run and (e is None or e.truth != run[-1].truth or e.window != run[-1].window + 1):
            pooled = np.sum([np.log(np.clip(r.posteriors, 1e-300, None)) for r in run], axis=0)
            out.append(run[-1].classes[int(np.argmax(pooled))] == run[-1].truth)
            run = []
        if e is not None:
            run.append(e)
    return out


def format_fused_evaluation(result: dict) -> str:
    lines = [f"{'stream':<12} {'windows right':>14} {'of':>6}  {'contacts right':>15} {'of':>5}"]
    for name, r in result.items():
        lines.append(f"{name:<12} {r['window_accuracy']:>14.3f} {r['windows']:>6}  {r['contact_accuracy']:>15.3f} "
                     f"{r['contacts']:>5}")
    return "\n".join(lines)
