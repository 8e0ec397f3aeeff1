"""A scene is typed, frozen values (node/scene/specs.py, issue 24 item 3): what a stream reads is the
stream's (``mapping`` on ``[[stream]]``), nothing is changed after loading, and no spec is a dict."""

from __future__ import annotations

import dataclasses
import tomllib
import typing

import numpy as np
import pytest

from supramodal.banks import whisker_bank
from supramodal.decisions import DecisionRules
from supramodal.errors import InputError
from supramodal.node.runtime.sinks import ListSink
from supramodal.node.scene import specs
from supramodal.node.scene.build import build_node
from supramodal.node.scene.schema import SceneError, scene_from_dict, scene_to_toml
from supramodal.pipeline import extract_features
from supramodal.replay.session import save_session

SPECS = [specs.Scene, specs.SourceSpec, specs.StreamSpec, specs.BankSpec, specs.FeaturesSpec, specs.ModelSpec,
         specs.BufferSpec, specs.FusionSpec, specs.SinkSettings, DecisionRules]


def _two_readers(path: str) -> dict:
    """One 20-channel source read by two whisker streams: each vibrissa by its own filter, and
    channel 3 alone fanned out to every filter."""
    return {"source": [{"name": "board", "type": "replay", "path": path, "speed": "max", "block": 123}],
            "stream": [{"name": "all", "source": "board", "mapping": "per-channel", "features": {"names": ["A"]}},
                       {"name": "three", "source": "board", "mapping": 3, "features": {"names": ["A"]}}]}


def test_two_streams_read_one_source_each_by_its_own_mapping(tmp_path):
    x = 0.1 * np.random.default_rng(0).standard_normal((5000, 20))
    save_session(tmp_path / "s", x, 5000, "test")
    sink = ListSink()
    build_node(scene_from_dict(_two_readers("s.wav"), str(tmp_path / "g.toml"), tmp_path),
               sinks_override=[sink]).run()
    got = {name: np.array([e.features["A"] for e in sink.windows if e.stream == name]) for name in ("all", "three")}
    # The session stores float32: the reference reads the same samples.
    x32 = x.astype(np.float32).astype(np.float64)
    every = extract_features(x32.T, whisker_bank(), ("A",)).values[:, 0]
    fanned = extract_features(np.repeat(x32[:, 3:4], 20, axis=1).T, whisker_bank(), ("A",)).values[:, 0]
    assert got["all"].shape == every.shape == got["three"].shape
    np.testing.assert_allclose(got["all"], every, rtol=1e-12)
    np.testing.assert_allclose(got["three"], fanned, rtol=1e-12)
    assert not np.allclose(every, fanned)                    # the two mappings do differ


def test_a_mapping_on_a_source_is_refused_with_where_it_belongs():
    d = _two_readers("s.wav")
    d["source"][0]["mapping"] = "per-channel"
    with pytest.raises(SceneError, match=r"\[\[source\]\] #1 mapping: .*move it to the \[\[stream\]\]"):
        scene_from_dict(d, "g.toml")


def test_a_one_source_scenes_driver_mapping_is_its_streams_and_prints_back(tmp_path):
    scene = scene_from_dict({"driver": {"type": "synth", "mapping": "mean"}}, "one.toml")
    assert scene.only_stream().mapping == "mean" and "mapping" not in scene.only_source().options
    again = scene_from_dict(tomllib.loads(scene_to_toml(scene)), "one.toml")
    assert again.only_stream() == scene.only_stream() and again.only_source() == scene.only_source()


def test_graph_mappings_print_back_on_their_streams(tmp_path):
    scene = scene_from_dict(_two_readers("s.wav"), "g.toml")
    d = tomllib.loads(scene_to_toml(scene))
    assert [s.get("mapping") for s in d["stream"]] == ["per-channel", 3]
    assert all("mapping" not in s for s in d["source"])
    assert scene_from_dict(d, "g.toml").streams == scene.streams


def test_a_loaded_scene_cannot_be_changed_in_place():
    scene = scene_from_dict({"driver": {"type": "synth"}, "sink": [{"type": "text"}]}, "one.toml")
    with pytest.raises(dataclasses.FrozenInstanceError):
        scene.only_stream().features.window = 0.2         # type: ignore[misc]
    with pytest.raises(TypeError):
        scene.only_source().options["seconds"] = 1.0      # type: ignore[index]
    with pytest.raises(TypeError):
        scene.sinks[0].options["path"] = "x"              # type: ignore[index]
    # A variant is a new value; the loaded one stays as it was.
    stream = scene.only_stream()
    shorter = dataclasses.replace(stream, features=dataclasses.replace(stream.features, window=0.2))
    assert shorter.features.window == 0.2 and scene.only_stream().features.window == 0.1


def test_a_scene_with_one_more_sink_has_the_sink_its_file_would_give():
    """node/scene/variants.py: a sink added in code (``--view``'s) is checked and filled as a
    ``[[sink]]`` table is, and the scene it is added to stays as it was."""
    from supramodal.node.runtime.sinks.view import ViewError
    from supramodal.node.scene.variants import with_sink, with_view

    one = {"driver": {"type": "synth"}, "sink": [{"type": "text"}]}
    scene = scene_from_dict(one, "one.toml")
    more = with_sink(scene, "jsonl", path="w.jsonl")
    filed = scene_from_dict({**one, "sink": [{"type": "text"}, {"type": "jsonl", "path": "w.jsonl"}]}, "one.toml")
    assert more.sinks == filed.sinks and scene.sinks == filed.sinks[:1]
    assert [dict(s.options) for s in more.sinks] == [dict(s.options) for s in filed.sinks]
    with pytest.raises(SceneError, match=r"one.toml: \[\[sink\]\] #2 type: expected one of \[.*'jsonl'"):
        with_sink(scene, "nowhere")
    with pytest.raises(SceneError, match=r"one.toml: \[\[sink\]\] #2 path: expected"):
        with_sink(scene, "jsonl", path=3)
    viewed = with_view(scene, 0)
    assert viewed.sinks[-1].type == "view" and viewed.sinks[-1].options["port"] == 0
    with pytest.raises(ViewError, match='has a \\[\\[sink\\]\\] type = "view" already'):
        with_view(viewed, 0)


def _annotations(cls) -> list:
    hints = typing.get_type_hints(cls, vars(specs) | {"DecisionRules": DecisionRules})
    return list(hints.values())


@pytest.mark.parametrize("cls", SPECS, ids=lambda c: c.__name__)
def test_no_spec_field_is_a_dict(cls):
    """What crosses from the schema to the builder, the command line and the workflows: frozen
    dataclasses, tuples, and read-only mappings only for a driver's or a sink's own keys."""
    assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen
    for hint in _annotations(cls):
        for part in (hint, *typing.get_args(hint)):
            assert typing.get_origin(part) is not dict and part is not dict, f"{cls.__name__}: {hint}"
            assert typing.get_origin(part) is not list and part is not list, f"{cls.__name__}: {hint}"


def _fused_graph(folder) -> dict:
    """A graph with a file in every kind of place a scene names one, each relative to its folder."""
    return {"source": [{"name": "board", "type": "replay", "path": "rec/board.wav", "speed": "max"},
                       {"name": "mic", "type": "replay", "path": "rec/mic.wav", "speed": "max"}],
            "stream": [{"name": "touch", "source": "board", "model": {"path": "models/touch.npz"}},
                       {"name": "sound", "source": "mic", "bank": {"kind": "cochlea"},
                        "model": {"path": "models/sound.npz"}}],
            "fusion": {"streams": ["touch", "sound"], "method": "early", "model": "models/fused.npz"},
            "sink": [{"type": "text"}, {"type": "jsonl", "path": "out/w.jsonl"}]}


def test_a_scene_with_absolute_paths_is_the_file_with_its_paths_written_absolute(tmp_path):
    """variants.with_absolute_paths: every key marked ``path`` (a driver's, a sink's), a bank file, the models
    and the early fusion's model, resolved against the scene's folder; stdout ("-") stays."""
    from supramodal.node.scene.variants import with_absolute_paths

    d = _fused_graph(tmp_path)
    scene = scene_from_dict(d, str(tmp_path / "s.toml"), tmp_path)
    got = with_absolute_paths(scene)
    here = tmp_path.resolve()
    want = _fused_graph(tmp_path)
    for src in want["source"]:
        src["path"] = str(here / src["path"])
    for st in want["stream"]:
        st["model"]["path"] = str(here / st["model"]["path"])
    want["fusion"]["model"] = str(here / "models/fused.npz")
    want["sink"][1]["path"] = str(here / "out/w.jsonl")
    assert got == scene_from_dict(want, str(tmp_path / "s.toml"), tmp_path)
    assert got.sinks[0].options["path"] == "-"
    assert scene == scene_from_dict(d, str(tmp_path / "s.toml"), tmp_path)      # the scene itself unchanged
    banked = scene_from_dict({"driver": {"type": "synth"}, "bank": {"file": "b/bank.json"}}, "one.toml", tmp_path)
    assert with_absolute_paths(banked).only_stream().bank.file == str(here / "b/bank.json")


def test_a_relocated_scene_names_its_new_file_and_resolves_against_its_folder(tmp_path):
    from supramodal.node.scene.variants import relocated

    scene = scene_from_dict(_fused_graph(tmp_path), str(tmp_path / "s.toml"), tmp_path)
    moved = relocated(scene, tmp_path / "elsewhere" / "n.toml")
    assert moved.source == str(tmp_path / "elsewhere" / "n.toml")
    assert moved.base_dir == (tmp_path / "elsewhere").resolve()
    assert moved.stream_named("touch").where == f"{moved.source}: [[stream]] touch"
    assert moved.source_named("mic").where == f"{moved.source}: [[source]] mic"
    assert moved.resolve("rec/mic.wav") == (tmp_path / "elsewhere").resolve() / "rec/mic.wav"
    assert relocated(scene, "n.toml", base_dir=tmp_path / "there").base_dir == tmp_path / "there"


def test_models_and_a_fusion_given_in_code_are_those_the_file_would_give(tmp_path):
    """variants.with_models / with_fusion: model files (checked, made absolute) and a [fusion] table
    filled and checked as the scene file's would be."""
    from supramodal.node.scene.variants import with_fusion, with_models

    d = _fused_graph(tmp_path)
    del d["fusion"]
    for st in d["stream"]:
        del st["model"]
    scene = scene_from_dict(d, "g.toml", tmp_path)
    for name in ("a.npz", "b.npz"):
        (tmp_path / name).write_bytes(b"")
    got = with_models(scene, {"touch": tmp_path / "a.npz", "sound": str(tmp_path / "b.npz")})
    filed = dict(d, stream=[dict(d["stream"][0], model={"path": str((tmp_path / "a.npz").resolve())}),
                            dict(d["stream"][1], model={"path": str((tmp_path / "b.npz").resolve())})],
                 fusion={"streams": ["touch", "sound"]})
    assert got == scene_from_dict(filed, "g.toml", tmp_path)
    assert got.fusion is not None and got.fusion.method == "late"
    with pytest.raises(InputError, match=r"--model names stream\(s\) \['nose'\]; its streams are \['touch', 'sound'\]"):
        with_models(scene, {"nose": tmp_path / "a.npz"})
    with pytest.raises(InputError, match="--model touch=.*: no model file there; train it first"):
        with_models(scene, {"touch": tmp_path / "none.npz"})
    early = with_fusion(got, streams=["sound", "touch"], method="early", model="f.npz")
    assert early.fusion == scene_from_dict(dict(filed, fusion={"streams": ["sound", "touch"], "method": "early",
                                                               "model": "f.npz"}), "g.toml", tmp_path).fusion
    with pytest.raises(SceneError, match=r"g.toml: \[fusion\] weight: expected"):
        with_fusion(got, streams=["touch", "sound"], weight=2.0)
    with pytest.raises(SceneError, match=r"g.toml: \[fusion\] streams: stream 'touch' has no model to fuse"):
        with_fusion(scene, streams=["touch", "sound"])


def test_a_scene_as_a_replay_reads_each_source_from_its_session(tmp_path):
    from supramodal.node.scene.variants import as_replay

    d = {"source": [{"name": "board", "type": "synth", "buffer": {"overrun": "drop-oldest", "seconds": 3}}],
         "stream": [{"name": "touch", "source": "board", "mapping": 2}]}
    scene = scene_from_dict(d, "g.toml", tmp_path)
    got = as_replay(scene, {"board": "rec.board.wav"})
    filed = dict(d, source=[{"name": "board", "type": "replay", "path": "rec.board.wav", "timing": "recorded",
                             "speed": "max", "buffer": {"overrun": "auto", "seconds": 3}}])
    assert got == scene_from_dict(filed, "g.toml", tmp_path)
    with pytest.raises(InputError, match=r"no session given for source\(s\) \['board'\]"):
        as_replay(scene, {})


def test_no_workflow_varies_a_scene_by_writing_it_out_and_reading_it_back():
    """Issue 37, item 4: variants are made on the frozen specs (node/scene/variants.py); a scene's TOML is
    parsed only where a file is read (the schema's load_scene)."""
    import ast
    from pathlib import Path

    import supramodal.node

    root = Path(supramodal.node.__file__).parent
    offenders = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "loads"
                    and isinstance(node.func.value, ast.Name) and node.func.value.id == "tomllib"
                    and path.name != "schema.py"):
                offenders.append(f"{path.relative_to(root)}:{node.lineno}")
    assert not offenders, f"TOML parsed outside the schema (a scene varied by a round trip?): {offenders}"


def test_a_driver_spec_says_which_recorded_session_its_source_replays(tmp_path):
    """What `train --scene` and `label` read of a source comes from its driver's spec (``replays``), not
    from its options by string key: a replay names its session, and whether it plays in step."""
    from supramodal.drivers.spec import ReplayedSession
    from supramodal.node.scene.registry import driver_spec

    def replays(table):
        src = scene_from_dict({"source": [{"name": "a", **table}], "stream": [{"name": "s", "source": "a"}]},
                              "g.toml", tmp_path).sources[0]
        return driver_spec(src.type).replays(src.options)

    assert replays({"type": "replay", "path": "r.wav", "timing": "recorded"}) == ReplayedSession("r.wav", True)
    assert replays({"type": "replay", "path": "r.wav"}) == ReplayedSession("r.wav", False)
    assert replays({"type": "synth"}) is None


def test_a_texture_set_file_is_made_absolute_and_the_built_in_set_is_a_word(tmp_path):
    """A path key's words name no file: a synthesised source's "reference" stays, its JSON file does not."""
    from supramodal.node.scene.variants import with_absolute_paths

    def textures(value):
        scene = scene_from_dict({"driver": {"type": "synth", "textures": value}}, "one.toml", tmp_path)
        return with_absolute_paths(scene).only_source().options["textures"]

    assert textures("reference") == "reference"
    assert textures("sets/my.json") == str(tmp_path.resolve() / "sets/my.json")


def test_the_fused_scene_keeps_the_live_scenes_way_of_deciding_on_the_fused_windows(tmp_path):
    """train --fusion's scene: the fusion learned, the live scene's [fusion.decision] and max_wait kept."""
    from supramodal.node.scene.schema import load_scene
    from supramodal.node.workflows.fused_training import write_fused_scene

    d = _fused_graph(tmp_path)
    d["fusion"] = {"streams": ["touch", "sound"], "max_wait": 0.5,
                   "decision": {"scope": "contact", "n": 0, "confidence": 0.99, "change": 1.0}}
    (tmp_path / "live.toml").write_text(scene_to_toml(scene_from_dict(d, "live.toml", tmp_path)))
    models = {}
    for name in ("touch", "sound"):
        models[name] = str(tmp_path / f"{name}.npz")
        (tmp_path / f"{name}.npz").write_bytes(b"")
    (tmp_path / "out").mkdir()
    out = write_fused_scene(tmp_path / "live.toml", ["touch", "sound"], models, tmp_path / "out" / "f.toml",
                            method="late", weight=0.6, sharpness=1.5, correlation=0.2)
    fused = load_scene(out).fusion
    live = load_scene(tmp_path / "live.toml").fusion
    assert (fused.weight, fused.sharpness, fused.correlation, fused.method) == (0.6, 1.5, 0.2, "late")
    assert fused.decision == live.decision and fused.max_wait == 0.5
    assert load_scene(out).source_named("board").options["path"] == str(tmp_path.resolve() / "rec/board.wav")


# -- gain augmentation of a model trained on start (issue 34): [model] augment_copies, augment_spread, augment_gains --

def _augmented(model: dict, graph: bool = False) -> dict:
    if graph:
        return {"source": [{"name": "s", "type": "synth", "seconds": 1.0}],
                "stream": [{"name": "w", "source": "s", "model": model}]}
    return {"driver": {"type": "synth", "seconds": 1.0}, "model": model}


@pytest.mark.parametrize("graph", [False, True])
def test_a_streams_model_asks_for_gain_augmentation_and_prints_back(graph):
    from supramodal.model import GainAugment

    plain = scene_from_dict(_augmented({"train_on_start": True}, graph)).streams[0].model
    assert plain.gain_augment() is None                                      # opt-in: none unless asked
    asked = {"train_on_start": True, "augment_copies": 4, "augment_spread": 0.05, "augment_gains": "shared"}
    scene = scene_from_dict(_augmented(asked, graph))
    assert scene.streams[0].model.gain_augment() == GainAugment(4, 0.05, False)
    by_bank = scene_from_dict(_augmented({"train_on_start": True, "augment_copies": 2}, graph))
    assert by_bank.streams[0].model.gain_augment() == GainAugment(2, 0.03, None)     # "auto": by the bank
    again = scene_from_dict(tomllib.loads(scene_to_toml(scene)))
    assert again.streams[0].model == scene.streams[0].model
    assert scene_from_dict(tomllib.loads(scene_to_toml(scene_from_dict(_augmented({"path": "m.npz"}, graph)))))


@pytest.mark.parametrize("model, says", [
    ({"augment_copies": -1}, "augment_copies: expected"),
    ({"augment_copies": 1.5}, "augment_copies: expected"),
    ({"augment_copies": 33}, "augment_copies: expected"),
    ({"augment_copies": True}, "augment_copies: expected"),
    ({"augment_copies": 4, "augment_spread": -0.01}, "augment_spread: expected"),
    ({"augment_copies": 4, "augment_spread": 2.0}, "augment_spread: expected"),
    ({"augment_copies": 4, "augment_spread": float("nan")}, "augment_spread: expected"),
    ({"augment_copies": 4, "augment_gains": "per-vibrissa"}, "augment_gains: expected"),
    ({"augment_copies": 4, "augment_gains": "per-vibrissa"}, '"per-channel"'),
    ({"augment_spread": 0.05}, "augment_spread = 0.05 has no effect without gain augmentation: set augment_copies"),
    ({"augment_gains": "shared"}, 'augment_gains = "shared" has no effect'),
])
def test_bad_gain_augmentation_keys_are_refused_naming_the_key(model, says):
    with pytest.raises(SceneError) as refused:
        scene_from_dict(_augmented({"train_on_start": True, **model}))
    assert says in str(refused.value) and "[model]" in str(refused.value)


@pytest.mark.parametrize("graph", [False, True])
def test_gain_augmentation_of_a_model_the_node_does_not_train_is_refused_with_the_fix(graph):
    with pytest.raises(SceneError) as refused:
        scene_from_dict(_augmented({"path": "m.npz", "augment_copies": 4}, graph))
    said = str(refused.value)
    assert "augment_copies = 4" in said and "set train_on_start = true" in said
    assert "supramodal train --augment-gains 4,0.03" in said


def test_an_early_fusion_trained_on_start_refuses_streams_asking_for_different_numbers_of_copies():
    """The early network copies a pair's two windows together (each stream's by its own [model] augment_*)."""
    from supramodal.node.scene.schema import SceneError

    def scene(copies_a, copies_b):
        models = [{"train_on_start": True, **({"augment_copies": c} if c else {})} for c in (copies_a, copies_b)]
        return {"source": [{"name": "w", "type": "twosense", "sense": "whiskers", "seconds": 1.0},
                           {"name": "m", "type": "twosense", "sense": "microphone", "seconds": 1.0}],
                "stream": [{"name": "w", "source": "w", "bank": {"kind": "whisker"}, "model": models[0]},
                           {"name": "m", "source": "m", "bank": {"kind": "cochlea"}, "model": models[1]}],
                "fusion": {"streams": ["w", "m"], "method": "early"}}

    with pytest.raises(SceneError, match=r'method = "early": the streams\' \[model\] augment_copies differ \(w 4, m 2\)'):
        scene_from_dict(scene(4, 2))
    for ok in ((4, 4), (4, 0), (0, 0)):
        scene_from_dict(scene(*ok))
    late = scene(4, 2)
    late["fusion"]["method"] = "late"
    scene_from_dict(late)                 # a late fusion trains no network of its own
