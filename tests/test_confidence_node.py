"""The node's calibrated decisions (issue 23): a contact decided as soon as it is sure, "unknown" for a
texture the model never met, ties never named, in the events and counted in the summary; and the
scene's rules refused where the model cannot follow them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from supramodal.banks import whisker_bank
from supramodal.errors import InputError
from supramodal.model import TextureModel
from supramodal.decisions import UNKNOWN, Decider, DecisionRules
from supramodal.node.runtime.graph import Node
from supramodal.node.scene.schema import SceneError, scene_from_dict
from supramodal.node.runtime.sinks import ListSink
from supramodal.pipeline import FeaturePipeline, extract_features
from supramodal.replay.driver import ReplayDriver, random_block_sizes
from supramodal.textures import reference_texture_set

FS = 5000
KNOWN = (0, 4, 7)           # reference textures the model knows (well apart: ~0.97 of windows right)


@pytest.fixture(scope="module")
def model():
    ts = reference_texture_set("whisker")
    bank = whisker_bank()
    values, labels = [], []
    for k, i in enumerate(KNOWN):
        v = extract_features(ts.synthesize(i, duration=12.0)[: 8 * FS], bank, ("Af",)).values
        values.append(v)
        labels.append(np.full(len(v), k))
    return TextureModel.train(np.concatenate(values), np.concatenate(labels), [ts.names[i] for i in KNOWN], bank,
                              ("Af",), 500, epochs=200, seed=1)


@pytest.fixture(scope="module")
def touches():
    """Three touches of known textures (their last 4 s, never trained on) and one of a texture far
    from all of them (white noise, 20x the level), 0.5 s of silence between touches."""
    ts = reference_texture_set("whisker")
    gap = np.zeros(FS // 2)
    parts, truth = [], []
    for i in KNOWN:
        parts += [ts.synthesize(i, duration=12.0)[8 * FS:], gap]
        truth += [ts.names[i]] * 40 + [None] * 5
    parts.append(np.random.default_rng(5).standard_normal(4 * FS) * 20 * np.std(parts[0]))
    truth += ["noise"] * 40
    return np.concatenate(parts), truth


def _run(model, x, decision, block_size):
    sink = ListSink()
    driver = ReplayDriver((x[:, None], float(FS)), block_size=block_size, seed=2, speed="max", on_notice=None)
    Node(driver, FeaturePipeline(whisker_bank(), ("Af",)), [sink], model=model,
         decision=DecisionRules(**decision), overrun="block").run()
    return sink


DECISION = {"scope": "contact", "n": 0, "contact_threshold": 0.01, "confidence": 0.95, "unknown": 0.05}


def test_each_touch_is_decided_once_as_soon_as_it_is_sure_and_the_new_texture_is_unknown(model, touches):
    x, truth = touches
    sink = _run(model, x, DECISION, random_block_sizes(1, 700))
    events = sink.events
    assert len(events) == len(truth)
    # per touch: the final decision, when it came, and that it stands for the rest of the touch
    for t in range(3):
        touch = events[45 * t: 45 * t + 40]
        first = next(i for i, e in enumerate(touch) if e["accumulated"].get("decided"))
        final = touch[first]["accumulated"]
        assert final["label"] == truth[45 * t] and final["confidence"] >= 0.95
        assert final["decided_after"] == first + 1 <= 30          # sure within 3 s of a texture it knows
        assert all(e["accumulated"] == final for e in touch[first:])
        assert all(e["accumulated"]["windows"] == i + 1 and not e["accumulated"]["decided"] for i, e in
                   enumerate(touch[:first]))
        assert all(e["accumulated"]["label"] is None for e in events[45 * t + 40: 45 * t + 45])   # silence
    noise = events[135:]
    novel = [e for e in noise if e.get("unknown") == "novel"]
    assert len(novel) >= 0.9 * len(noise)
    assert all(e["predicted"] == UNKNOWN and e["guess"] in model.classes for e in novel)
    assert noise[-1]["accumulated"]["label"] == UNKNOWN and not noise[-1]["accumulated"]["decided"]
    known_unknown = sum(e.get("unknown") == "novel" for e, t in zip(events[:135], truth) if t is not None)
    assert known_unknown <= 0.15 * 120
    s = sink.final
    assert s["unknown_windows"]["novel"] == sum(e.get("unknown") == "novel" for e in events)
    assert s["contacts_decided"] == 3
    assert s["windows_to_decide_median"] == np.median(
        [next(e["accumulated"]["decided_after"] for e in events[45 * t: 45 * t + 40] if e["accumulated"].get("decided"))
         for t in range(3)])


def test_decisions_do_not_depend_on_block_sizes(model, touches):
    x, _ = touches
    a = _run(model, x[: 6 * FS], DECISION, 50).events
    b = _run(model, x[: 6 * FS], DECISION, random_block_sizes(1, 999)).events
    keys = ("predicted", "unknown", "guess", "accumulated")
    assert [[e.get(k) for k in keys] for e in a] == [[e.get(k) for k in keys] for e in b]


def test_confidence_now_says_how_often_the_window_is_right(model, touches):
    """Today's complaint: 1.00 on wrong windows. Among the windows of known textures, the wrong ones
    are not sure, and none says 1.00. (The wrong ones were 0.1 less sure than the right ones on average
    until the fold networks stopped early, 2026-11-30: on this small model, 80 windows a texture, the
    margin is now 0.06 to 0.09 over network seeds 1-3, 0.14 trained every epoch; on the whisker
    reference, 300 a texture, it is 0.25 either way: docs/model.md.)"""
    x, truth = touches
    events = _run(model, x[: 135 * 500], {"scope": "window"}, 500).events
    conf = np.array([e["confidence"] for e, t in zip(events, truth) if t is not None])
    right = np.array([e["predicted"] == t for e, t in zip(events, truth) if t is not None])
    assert len(conf) == 120
    assert conf.max() < 1.0 and (~right).sum() >= 5          # (0.85 of them right)
    assert conf[~right].mean() < conf[right].mean() - 0.05    # the wrong ones say so: less sure
    assert conf.mean() <= right.mean() + 0.05                 # and it does not overclaim


def test_a_tie_is_said_unknown_and_counted():
    d = Decider(("a", "b", "c"), DecisionRules(scope="window"))
    said = d.decide(np.log(np.array([0.45, 0.45, 0.1])))
    assert (said.decision, said.reason, said.guess) == (UNKNOWN, "tie", None)
    said = d.decide(np.log(np.array([0.1, 0.45, 0.45])))
    assert said.decision == UNKNOWN
    assert d.summary()["unknown_windows"] == {"novel": 0, "unsure": 0, "tie": 2}


def test_unknown_below_names_no_texture_when_unsure():
    d = Decider(("a", "b"), DecisionRules(scope="window", unknown_below=0.8))
    assert d.decide(np.log(np.array([0.7, 0.3]))).decision == UNKNOWN
    assert d.decide(np.log(np.array([0.9, 0.1]))).decision == "a"


def test_rules_the_model_cannot_follow_are_refused_before_start(model, touches):
    from supramodal.node.runtime.streams import decider_for
    import dataclasses

    old = dataclasses.replace(model, calibration=None, novelty=None)
    with pytest.raises(InputError, match="uncalibrated.*retrain"):
        decider_for(old, DecisionRules(scope="contact", confidence=0.99))
    no_novelty = dataclasses.replace(model, novelty=None)
    with pytest.raises(InputError, match="novelty score"):
        decider_for(no_novelty, DecisionRules(unknown=0.05))
    assert decider_for(old, DecisionRules(scope="contact")).accumulator.correlation == 0.0     # pooling as before


@pytest.mark.parametrize("decision, needle", [
    ({"scope": "window", "confidence": 0.99}, "needs scope = \"contact\""),
    ({"scope": "contact", "confidence": 1.0}, "confidence"),
    ({"unknown": -0.1}, "unknown"),
    ({"unknown_below": 1.5}, "unknown_below"),
])
def test_scene_decision_rules_are_validated(decision, needle):
    with pytest.raises(SceneError, match=needle):
        scene_from_dict({"driver": {"type": "synth"}, "model": {"train_on_start": True}, "decision": decision},
                        "<test>")


def _fusion_scene(**fusion):
    import tomllib
    from pathlib import Path

    d = tomllib.loads((Path(__file__).resolve().parents[1] / "examples" / "two_sense_world.toml").read_text())
    d["fusion"] = {"streams": ["whiskers", "mic"], **fusion}
    return d


def test_fusion_keys_printed_by_train_fusion_are_scene_keys_and_learn_refuses_them():
    scene = scene_from_dict(_fusion_scene(weight=0.4, sharpness=2.2, correlation=0.6), "<test>")
    assert (scene.fusion.weight, scene.fusion.sharpness, scene.fusion.correlation) == (0.4, 2.2, 0.6)
    with pytest.raises(SceneError, match="learns them with the weight"):
        scene_from_dict(_fusion_scene(weight="learn", sharpness=2.0), "<test>")
    with pytest.raises(SceneError, match="sharpness"):
        scene_from_dict(_fusion_scene(weight=0.5, sharpness=0.0), "<test>")
    with pytest.raises(SceneError, match="needs scope"):
        scene_from_dict(_fusion_scene(weight=0.5, decision={"confidence": 0.9}), "<test>")


def test_a_model_trained_on_the_spot_is_trained_once_per_cache(monkeypatch, tmp_path):
    """Calibration trains eleven networks: a second scene with the same texture set and pipeline
    gets the same model from the node's one cache (on disk: node/scene/model_cache.py) without
    training again; another pipeline trains its own. (Was: once per process, from a cache in
    memory beside the disk's, which issue 37 removed.)"""
    from supramodal.node.scene import build
    from supramodal.node.scene.model_cache import trained_on_start
    from supramodal.textures import reference_texture_set

    calls = []
    real = build.texture_set_model
    monkeypatch.setattr(build, "texture_set_model", lambda *a, **k: calls.append(1) or real(*a, **k))
    ts = reference_texture_set("whisker")
    short = type(ts)(**{**ts.__dict__, "duration": 4.0})

    def start(features, held_out):
        pipeline = FeaturePipeline(whisker_bank(), features)
        return trained_on_start(short, pipeline, lambda h, t: build.train_on_texture_set(short, pipeline, None, h, t),
                                None, held_out, [], folder=tmp_path)

    held_a, held_b = [], []
    a, b = start(("Af",), held_a), start(("Af",), held_b)
    assert len(calls) == 1
    np.testing.assert_array_equal(a.mlp.stacked()[0], b.mlp.stacked()[0])
    np.testing.assert_array_equal(held_a[0][0], held_b[0][0])
    c = start(("A",), [])
    assert c.features == ("A",) and len(calls) == 2


def test_the_node_keeps_no_model_in_memory_between_builds():
    """Issue 37, item 2: one cache of models trained on start, the disk's; the builder keeps none of its own."""
    from supramodal.node.scene import build

    assert not any(isinstance(v, dict) and not k.startswith("__") for k, v in vars(build).items()
                   if k.startswith("_trained")), "a module-level model store in node/scene/build.py"
    assert not hasattr(build, "TRAINED_ON_THE_SPOT")


def test_a_fusion_deciding_per_contact_gives_its_streams_contact_detectors(tmp_path):
    """The fusion's contacts are its streams' touches: with [fusion.decision] scope = "contact", each
    fused stream detects contacts even where its own decisions are per window (otherwise a fused
    contact would never end, and its first final decision would stand for the whole run)."""
    from supramodal.node.scene.build import build_node

    d = _fusion_scene(weight=0.5, decision={"scope": "contact", "confidence": 0.99, "contact_threshold": 0.02})
    graph = build_node(scene_from_dict(d, "<test>", tmp_path), sinks_override=[ListSink()], progress=None)
    try:
        assert [s.contact.threshold for s in graph.streams] == [0.02, 0.02]
        assert all(s.decision.scope == "window" for s in graph.streams)
    finally:
        for sink in graph.sinks:
            sink.close()


def test_fusion_unknown_is_set_per_stream():
    with pytest.raises(SceneError, match="each \\[\\[stream\\]\\]'s \\[decision\\]"):
        scene_from_dict(_fusion_scene(weight=0.5, decision={"unknown": 0.05}), "<test>")


def test_the_nodes_contact_pooling_is_the_models_calibrated_pooling(model, touches):
    """The contact decision the node streams, window after window, is the model's calibrated
    contact pooling (`Calibration.pool`: its caps per pair of classes and their correlation) of the
    touch's windows so far: the posterior the calibration figures were measured on."""
    x, truth = touches
    # This small model's fit kept no contact caps (they did not earn their numbers): give it some,
    # tight enough to change every pooled confidence of the touch.
    caps = ((0.0, 2.0, 3.0), (1.5, 0.0, 2.5), (2.0, 4.0, 0.0))
    model = dataclasses.replace(model, calibration=dataclasses.replace(model.calibration, contact_caps=caps,
                                                                       contact_correlation=0.3))
    events = _run(model, x[: 45 * 500], {"scope": "contact", "n": 0, "contact_threshold": 0.01},
                  random_block_sizes(1, 700)).events
    lp = model.log_posteriors(extract_features(x[: 40 * 500], whisker_bank(), ("Af",)).values)
    for i in range(40):
        pooled = model.calibration.pool(lp[: i + 1])
        acc = events[i]["accumulated"]
        assert acc["windows"] == i + 1 and acc["label"] == model.classes[int(np.argmax(pooled))]
        assert acc["confidence"] == pytest.approx(np.exp(pooled.max()), abs=6e-5)   # said to 4 decimals


def test_the_nodes_novelty_allows_for_a_new_touch_in_any_block_sizes(model, touches):
    """A model trained now allows for a new touch's gains in its novelty (issue 34); the node scores every
    window with it as the model does offline, in any block sizes, and calls "unknown" exactly the windows
    above its threshold."""
    x, _ = touches
    nov = model.novelty
    assert nov.touch is not None and nov.touch.spread >= 0.03
    threshold = nov.threshold(DECISION["unknown"])
    runs = [_run(model, x, DECISION, size).events for size in (64, random_block_sizes(3, 997))]
    scores = [[e["novelty"] for e in events] for events in runs]
    assert scores[0] == scores[1]
    offline = model.novelty_score(extract_features(x, whisker_bank(), ("Af",)).values)
    np.testing.assert_allclose(scores[0], offline, atol=1e-4)
    for e, s in zip(runs[1], offline):
        if abs(s - threshold) > 1e-6:
            assert (e.get("unknown") == "novel") == (s > threshold)
