"""Files a user may receive ask for bounded things: each crafted file is refused with the file, the key and the limit.

One test per crafted file (float WAV far beyond full scale, model header, texture set,
session sidecar), each asserting the error class (a SupramodalError) and that the
message names the key; the JSON nesting scanner is checked against the parsed value's
depth; the model header validator is fuzzed.
"""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.io import wavfile

from supramodal.replay import ReplayDriver, ReplayError, SessionError, WavFormatError, load_session, save_session
from supramodal.replay.wavio import MAX_FLOAT_MAGNITUDE, read_wav, write_wav
from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.errors import InputError, SupramodalError
from supramodal.jsondata import nesting_depth
from supramodal.model import MAX_CLASSES, ModelError, TextureModel
from supramodal.pipeline import MAX_WINDOW_SAMPLES
from supramodal.textures import (MAX_TEXTURE_SAMPLES, MAX_TEXTURES, TextureSetError, load_texture_set, synthesize,
                                 texture_set_from_dict)


# -- float WAVs -----------------------------------------------------------------------------------

def _float_wav(path, values, dtype=np.float32):
    wavfile.write(path, 5000, np.asarray(values, dtype=dtype))   # scipy writes what it is given
    return path


@pytest.mark.parametrize("peak, dtype", [(1e30, np.float32), (-3e38, np.float32), (1e300, np.float64),
                                         (2e6, np.float64)])
def test_float_wav_far_beyond_full_scale_is_refused_with_its_peak(tmp_path, peak, dtype):
    path = _float_wav(tmp_path / "loud.wav", [0.0, 0.5, peak, -0.25], dtype)
    with pytest.raises(WavFormatError) as info:
        read_wav(path)
    message = str(info.value)
    assert str(path) in message and f"peak |x| = {abs(float(dtype(peak))):.6g}" in message
    assert "1e+06 times full scale" in message and "rescale" in message
    with pytest.raises(ReplayError, match="times full scale"):       # replay (training, `run`) refuses too
        ReplayDriver(str(path), speed="max")


@pytest.mark.parametrize("peak", [1.0, 3.0, -1000.0, MAX_FLOAT_MAGNITUDE])
def test_float_wav_above_full_scale_within_the_bound_is_read_as_is(tmp_path, peak):
    x, _ = read_wav(_float_wav(tmp_path / "f.wav", [0.0, peak, 0.5], np.float64))
    assert x[:, 0].tolist() == [0.0, peak, 0.5]


def test_write_wav_refuses_what_read_wav_would_refuse(tmp_path):
    with pytest.raises(ReplayError, match=r"peak \|x\| = 1e\+30"):
        write_wav(tmp_path / "w.wav", np.array([[0.0], [1e30]]), 5000)
    assert not (tmp_path / "w.wav").exists()


# -- model files ------------------------------------------------------------------------------------

BANK = whisker_bank(rows="A")
FEATURES = ("Af",)


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(1)
    values = rng.gamma(2.0, 1.0, (60, 1, 4))
    labels = np.repeat([0, 1, 2], 20)
    values[:, 0, 0] *= 1 + labels
    return TextureModel.train(values, labels, ("a", "b", "c"), BANK, FEATURES, 500, epochs=5, seed=0)


def _parts(model):
    w1, b1, w2, b2 = model.mlp.stacked()               # a calibrated model's networks, on a first axis
    arrays = dict(w1=w1, b1=b1, w2=w2, b2=b2, mean=model.mean, scale=model.scale)
    return model.header(), arrays


def _write_model(path, header, arrays, header_text=None):
    text = json.dumps(header) if header_text is None else header_text
    with open(path, "wb") as fh:
        np.savez(fh, header=np.array(text), **arrays)
    return path


def _with(header, **changes):
    return {**header, **changes}


@pytest.mark.parametrize("change, key, words", [
    (dict(window_samples=10**12), "'window_samples'", [str(MAX_WINDOW_SAMPLES), "MAX_WINDOW_SAMPLES"]),
    (dict(classes=[f"c{i}" for i in range(MAX_CLASSES + 1)]), "'classes'", ["MAX_CLASSES"]),
    (dict(bank={"kind": "custom", "fs": 44100.0, "cf": [1000.0 + i for i in range(1500)], "b": [100.0] * 1500,
                "names": [f"c{i}" for i in range(1500)]}), "'bank'", ["1500 channels", "MAX_CHANNELS"]),
    (dict(layers=[4, 99, 3]), "'layers'", ["array w1", "4, 99)", "99 hidden units"]),
    (dict(layers=[5, 4, 3]), "'layers'", ["[4, hidden >= 1, 3]"]),
    (dict(layers=[4, 16]), "'layers'", ["[inputs, hidden, outputs]"]),
])
def test_model_header_asking_too_much_is_refused(tmp_path, model, change, key, words):
    header, arrays = _parts(model)
    path = _write_model(tmp_path / "m.npz", _with(header, **change), arrays)
    with pytest.raises(ModelError) as info:
        TextureModel.load(path)
    message = str(info.value)
    assert str(path) in message and key in message
    for w in words:
        assert w in message


def test_model_header_saying_cochlea_over_whisker_channels_is_refused(tmp_path, model):
    header, arrays = _parts(model)
    path = _write_model(tmp_path / "m.npz", _with(header, bank={**header["bank"], "kind": "cochlea"}), arrays)
    with pytest.raises(ModelError, match=r"'bank': kind 'cochlea' does not fit its channels.*'A1'"):
        TextureModel.load(path)
    # and the other way round: a cochlea relabelled as whiskers
    coch = cochlea_bank(n=4, f_low=100, f_high=2000, fs=5000)
    path = _write_model(tmp_path / "m.npz", _with(header, bank={**coch.to_dict(), "kind": "whisker"}), arrays)
    with pytest.raises(ModelError, match=r"'bank': kind 'whisker' does not fit its channels.*'ch00'"):
        TextureModel.load(path)
    path = _write_model(tmp_path / "m.npz", _with(header, bank={**header["bank"], "kind": "antenna"}), arrays)
    with pytest.raises(ModelError, match=r"'bank': kind 'antenna'"):
        TextureModel.load(path)


def test_deeply_nested_model_header_is_refused_not_a_recursion_error(tmp_path, model):
    header, arrays = _parts(model)
    text = json.dumps(_with(header, training=None)).replace('"training": null',
                                                            '"training": ' + "[" * 100_000 + "]" * 100_000)
    path = _write_model(tmp_path / "m.npz", header, arrays, header_text=text)
    with pytest.raises(ModelError, match=r"model header: JSON nested 100001 levels deep.*MAX_HEADER_DEPTH"):
        TextureModel.load(path)


def _npz_declaring(path, parts: dict, huge: str, shape, descr="<f8"):
    """An .npz whose ``huge`` member's .npy header declares ``shape`` but holds 16 bytes of data."""
    with zipfile.ZipFile(path, "w") as z:
        for name, a in parts.items():
            buf = io.BytesIO()
            if name == huge:
                np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
                buf.write(b"\0" * 16)
            else:
                np.save(buf, a)
            z.writestr(name + ".npy", buf.getvalue())
    return path


@pytest.mark.parametrize("member, shape, descr, limit", [
    ("w1", (10**6, 10**6), "<f8", "MAX_ARRAY_BYTES"),
    ("mean", (2**40,), "<f4", "MAX_ARRAY_BYTES"),
    ("header", (), "<U100000000", "MAX_HEADER_BYTES"),
])
def test_model_member_declaring_a_huge_array_is_refused_before_it_is_read(tmp_path, model, member, shape, descr,
                                                                            limit):
    header, arrays = _parts(model)
    path = _npz_declaring(tmp_path / "m.npz", {"header": np.array(json.dumps(header)), **arrays}, member, shape,
                          descr)
    with pytest.raises(ModelError) as info:
        TextureModel.load(path)
    assert f"array {member!r} declares shape" in str(info.value) and limit in str(info.value)


JSON = st.recursive(st.none() | st.booleans() | st.integers(-10**15, 10**15) | st.floats(allow_nan=False)
                    | st.text(max_size=8),
                    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
                    max_leaves=12)
KEYS = ["format", "version", "bank", "features", "window_samples", "peak_mode", "peak_threshold", "classes",
        "layers", "training", "extra"]


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(changes=st.dictionaries(st.sampled_from(KEYS), JSON, min_size=1, max_size=3),
       drop=st.lists(st.sampled_from(KEYS), max_size=2))
def test_fuzzed_model_headers_load_or_raise_model_error_only(tmp_path, model, changes, drop):
    header, arrays = _parts(model)
    header = {**header, **changes}
    for k in drop:
        header.pop(k, None)
    path = _write_model(tmp_path / "fuzz.npz", header, arrays)
    try:
        loaded = TextureModel.load(path)
    except ModelError:
        return
    # Accepted: then it is the model its header declares, and it works on inputs of that shape.
    assert set(KEYS) - set(header) >= {"extra"}                      # no unknown key, and every required one:
    assert set(header) >= set(KEYS) - {"training", "peak_threshold", "extra"}
    assert "extra" not in header and header["format"] == "supramodal-model" and header["version"] == 1
    assert loaded.window_samples == header["window_samples"] <= MAX_WINDOW_SAMPLES
    assert loaded.classes == tuple(header["classes"]) and loaded.peak_mode == header["peak_mode"]
    out = loaded.outputs(np.ones((2, len(loaded.features), loaded.bank.channels)))
    assert out.shape == (2, len(loaded.classes)) and np.all(np.isfinite(out))


# -- texture sets -----------------------------------------------------------------------------------

def _texture_dict(**changes):
    return {"format": "supramodal-textures", "version": 1, "name": "t", "bank": "whisker", "fs": 5000,
            "duration": 1.0, "width": 0.2, "seed": 3,
            "textures": [{"name": "a", "peaks": [100, 200, 300]}, {"name": "b", "peaks": [110, 220, 330]}],
            **changes}


@pytest.mark.parametrize("changes, key, limit", [
    (dict(duration=1e9), "'duration'", "MAX_TEXTURE_SAMPLES"),
    (dict(fs=1e12), "'duration'", "MAX_TEXTURE_SAMPLES"),
    (dict(duration=MAX_TEXTURE_SAMPLES / 5000 + 1), "'duration'", "MAX_TEXTURE_SAMPLES"),
    (dict(textures=[{"name": f"T{i}", "peaks": [100, 200, 300]} for i in range(MAX_TEXTURES + 1)]),
     "'textures'", "MAX_TEXTURES"),
])
def test_texture_set_asking_too_much_is_refused(tmp_path, changes, key, limit):
    path = tmp_path / "set.json"
    path.write_text(json.dumps(_texture_dict(**changes)))
    with pytest.raises(TextureSetError) as info:
        load_texture_set(path)
    message = str(info.value)
    assert str(path) in message and key in message and limit in message
    assert isinstance(info.value, InputError)


def test_texture_set_at_the_bound_is_accepted():
    ts = texture_set_from_dict(_texture_dict(duration=MAX_TEXTURE_SAMPLES / 5000))
    assert ts.duration * ts.fs == MAX_TEXTURE_SAMPLES


def test_deep_or_oversized_texture_set_files_are_refused(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text('{"format": "supramodal-textures", "textures": ' + "[" * 50_000 + "]" * 50_000 + "}")
    with pytest.raises(TextureSetError, match=r"deep\.json: JSON nested 50001 levels deep.*MAX_TEXTURE_SET_DEPTH"):
        load_texture_set(path)
    path = tmp_path / "big.json"
    path.write_text(json.dumps(_texture_dict(name="x" * 2**20)))
    with pytest.raises(TextureSetError, match=r"big\.json: \d+ bytes.*MAX_TEXTURE_SET_BYTES"):
        load_texture_set(path)


@pytest.mark.parametrize("duration", [1e9, float("nan"), float("inf"), -1.0])
def test_synthesize_refuses_an_unbounded_duration(duration):
    with pytest.raises(InputError, match="duration"):
        synthesize([100, 200, 300], 5000, duration)


# -- session sidecars --------------------------------------------------------------------------------

def test_deeply_nested_sidecar_is_refused_not_a_recursion_error(tmp_path):
    save_session(tmp_path / "s", np.zeros((100, 1)), 5000, "test")
    (tmp_path / "s.json").write_text('{"labels": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(SessionError) as info:
        load_session(tmp_path / "s")
    assert str(tmp_path / "s.json") in str(info.value) and "MAX_SIDECAR_DEPTH" in str(info.value)
    assert "100001 levels" in str(info.value)


def test_oversized_sidecar_is_refused_before_it_is_read(tmp_path, monkeypatch):
    import supramodal.replay.session

    save_session(tmp_path / "s", np.zeros((100, 1)), 5000, "test")
    size = (tmp_path / "s.json").stat().st_size
    monkeypatch.setattr(supramodal.replay.session, "MAX_SIDECAR_BYTES", size - 1)
    with pytest.raises(SessionError, match=rf"s\.json: {size} bytes.*MAX_SIDECAR_BYTES"):
        load_session(tmp_path / "s")
    monkeypatch.setattr(supramodal.replay.session, "MAX_SIDECAR_BYTES", size)
    assert load_session(tmp_path / "s").frames == 100


# -- the nesting scanner, against the parsed value ------------------------------------------------

def _depth(value) -> int:
    if isinstance(value, (list, dict)):
        children = value.values() if isinstance(value, dict) else value
        return 1 + max((_depth(c) for c in children), default=0)
    return 0


TRICKY_TEXT = st.text(st.sampled_from(list('[]{}"\\ab,: \n\u00e9')), max_size=6)
TRICKY_JSON = st.recursive(st.none() | st.integers() | TRICKY_TEXT,
                           lambda inner: st.lists(inner, max_size=3) | st.dictionaries(TRICKY_TEXT, inner, max_size=3),
                           max_leaves=20)


@settings(max_examples=300, deadline=None)
@given(value=TRICKY_JSON, indent=st.sampled_from([None, 1]), ascii_only=st.booleans())
def test_nesting_depth_matches_the_parsed_value(value, indent, ascii_only):
    text = json.dumps(value, indent=indent, ensure_ascii=ascii_only)
    assert nesting_depth(text)[0] == _depth(value)


def test_every_refusal_here_is_a_supramodal_error():
    for cls in (WavFormatError, ReplayError, SessionError, ModelError, TextureSetError):
        assert issubclass(cls, SupramodalError)


@pytest.mark.parametrize("section, key, value, named", [
    ("features", "window", 1e9, "MAX_WINDOW_SAMPLES"),
    ("bank", "channels", 10**6, "MAX_CHANNELS"),
])
def test_a_scene_asking_for_an_unbounded_window_or_bank_is_refused_before_allocating(section, key, value, named):
    """A scene is data a user may receive: its window and channel count are bounded like a model's."""
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import scene_from_dict

    bank = {"kind": "cochlea"} if section == "bank" else {}
    with pytest.raises(InputError, match=named):         # when the scene is read, or when it is built
        build_node(scene_from_dict({section: {**bank, key: value}, "driver": {"type": "synth", "seconds": 1.0}}))
