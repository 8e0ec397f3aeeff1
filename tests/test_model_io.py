"""A trained model as data: save/load round trip, and every refusal of a bad file."""

import json
import pathlib
import zipfile

import numpy as np
import pytest

from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.model import MODEL_FORMAT, MODEL_VERSION, ModelError, TextureModel

BANK = whisker_bank(rows="AB")          # 8 channels
FEATURES = ("Af", "A")
CLASSES = ("rough", "smooth", "medium")


def training_data(seed=0, n=40):
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(3), n)
    values = rng.gamma(2.0, 1.0, (3 * n, 2, 8)) * 100.0
    values[:, 0, :] *= 1 + labels[:, None]           # Af of class k scaled by k + 1
    values[:, 1, 2] += 300.0 * (labels == 2)
    return values, labels


@pytest.fixture(scope="module")
def model():
    values, labels = training_data()
    return TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=100, seed=3)


@pytest.fixture()
def saved(model, tmp_path):
    return model.save(tmp_path / "m.npz")


def read_parts(path):
    with np.load(path, allow_pickle=False) as npz:
        return json.loads(str(npz["header"])), {k: npz[k] for k in npz.files if k != "header"}


def write_parts(path, header, arrays, header_is_text=True):
    head = np.array(json.dumps(header)) if header_is_text else header
    with open(path, "wb") as fh:
        np.savez(fh, header=head, **arrays)
    return path


# -- round trip --------------------------------------------------------------------------------

def test_model_learns_its_training_data(model):
    values, labels = training_data()
    assert np.mean(model.predict(values) == labels) > 0.9
    assert model.n_inputs == 16 and model.mlp.shape == (16, 16, 3)
    assert model.training["epochs"] == 100 and model.training["seed"] == 3


def test_save_load_round_trip_gives_identical_outputs(model, saved):
    assert saved.suffix == ".npz" and saved.is_file()
    loaded = TextureModel.load(saved)
    values, _ = training_data(seed=9)
    np.testing.assert_array_equal(loaded.outputs(values), model.outputs(values))
    np.testing.assert_array_equal(loaded.predict(values), model.predict(values))
    assert loaded.bank.matches(model.bank)
    assert loaded.features == FEATURES and loaded.classes == CLASSES
    assert loaded.window_samples == 500 and loaded.peak_mode == "maxima"
    assert loaded.training == model.training
    for a, b in zip(loaded.mlp.params(), model.mlp.params()):
        np.testing.assert_array_equal(a, b)
    loaded.check_fits(BANK, FEATURES, 500)           # fits the pipeline it was made for


@pytest.mark.parametrize("name", ["model", "model.npz", "model.bin"])
def test_save_writes_exactly_the_path_given_and_load_reads_it(model, tmp_path, name):
    """`train --out X` then `evaluate X` must find the model: no suffix is added on save."""
    path = model.save(tmp_path / name)
    assert path == tmp_path / name
    assert [p.name for p in tmp_path.iterdir()] == [name]
    assert TextureModel.load(tmp_path / name).classes == model.classes


def test_saved_file_is_plain_data(saved):
    """Readable with allow_pickle=False; every member a plain .npy of a non-object dtype."""
    header, arrays = read_parts(saved)
    assert header["format"] == MODEL_FORMAT and header["version"] == MODEL_VERSION
    assert header["features"] == list(FEATURES) and header["classes"] == list(CLASSES)
    assert sorted(arrays) == ["b1", "b2", "mean", "novelty_means", "novelty_precision", "novelty_quantiles", "scale",
                              "w1", "w2"]
    assert all(a.dtype.kind == "f" for a in arrays.values())


# -- refusals ----------------------------------------------------------------------------------

def test_missing_file(tmp_path):
    with pytest.raises(ModelError, match="no model file"):
        TextureModel.load(tmp_path / "nope.npz")
    with pytest.raises(ModelError, match="no model file"):
        TextureModel.load(tmp_path)                   # a directory is not a model file


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.9, 0.999])
def test_truncated_file(saved, keep):
    data = saved.read_bytes()
    saved.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ModelError, match="not a readable model file|lacks"):
        TextureModel.load(saved)


def test_corrupted_member(saved):
    data = bytearray(saved.read_bytes())
    k = data.find(b"\x93NUMPY", data.find(b"w1.npy"))     # the w1 member's array header
    data[k : k + 6] = b"garbag"
    saved.write_bytes(bytes(data))
    with pytest.raises(ModelError):
        TextureModel.load(saved)


def test_empty_file(tmp_path):
    p = tmp_path / "m.npz"
    p.write_bytes(b"")
    with pytest.raises(ModelError, match="not a readable model file"):
        TextureModel.load(p)


def test_text_file(tmp_path):
    p = tmp_path / "m.npz"
    p.write_text("format: supramodal-model\n")
    with pytest.raises(ModelError, match="not a readable model file: not an .npz archive of plain arrays"):
        TextureModel.load(p)


def test_npy_file_instead_of_npz(tmp_path):
    p = tmp_path / "m.npy"
    np.save(p, np.zeros((16, 16)))
    with pytest.raises(ModelError, match="not a supramodal model|not a readable model file"):
        TextureModel.load(p)


def test_zip_of_something_else(tmp_path):
    p = tmp_path / "m.npz"
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("readme.txt", "hello")
    with pytest.raises(ModelError, match="lacks"):
        TextureModel.load(p)


@pytest.mark.parametrize("drop", ["header", "w1", "b1", "w2", "b2", "mean", "scale"])
def test_missing_arrays(saved, drop):
    header, arrays = read_parts(saved)
    p = saved.with_name("broken.npz")
    with open(p, "wb") as fh:
        parts = {"header": np.array(json.dumps(header)), **arrays}
        del parts[drop]
        np.savez(fh, **parts)
    with pytest.raises(ModelError, match=rf"lacks \['{drop}'\]"):
        TextureModel.load(p)


@pytest.mark.parametrize("name, bad", [
    ("w1", np.zeros((15, 16))),                 # inputs do not match features x channels
    ("w1", np.zeros(16)),                       # not a matrix
    ("w1", np.zeros((16, 0))),                  # no hidden unit
    ("b1", np.zeros(15)),
    ("w2", np.zeros((16, 4))),                  # outputs do not match the classes
    ("b2", np.zeros((3, 1))),
    ("mean", np.zeros(8)),
    ("scale", np.ones(17)),
    ("w2", np.zeros((16, 3), dtype=np.int64)),  # not floats
    ("b1", np.zeros(16, dtype=complex)),
    ("mean", np.array(["a"] * 16)),
])
def test_wrong_shapes_and_dtypes(saved, name, bad):
    header, arrays = read_parts(saved)
    arrays[name] = bad
    p = write_parts(saved.with_name("bad.npz"), header, arrays)
    with pytest.raises(ModelError, match=rf"array {name}|array w1"):
        TextureModel.load(p)


@pytest.mark.parametrize("name, value", [("w1", np.nan), ("b2", np.inf), ("mean", -np.inf), ("scale", np.nan)])
def test_nonfinite_arrays(saved, name, value):
    header, arrays = read_parts(saved)
    arrays[name] = arrays[name].copy()
    arrays[name].flat[3 if arrays[name].size > 3 else 0] = value
    p = write_parts(saved.with_name("bad.npz"), header, arrays)
    with pytest.raises(ModelError, match=rf"array {name} contains NaN or Inf"):
        TextureModel.load(p)


def test_nonpositive_scale(saved):
    header, arrays = read_parts(saved)
    arrays["scale"] = arrays["scale"].copy()
    arrays["scale"][0] = 0.0
    with pytest.raises(ModelError, match="scale must be > 0"):
        TextureModel.load(write_parts(saved.with_name("bad.npz"), header, arrays))


@pytest.mark.parametrize("change, match", [
    ({"format": "other-model"}, "not a supramodal-model file"),
    ({"format": None}, "not a supramodal-model file"),
    ({"version": 4}, "version 4 is not supported"),
    ({"version": "1"}, "version '1' is not supported"),
    ({"extra": 1}, r"unknown header key\(s\) \['extra'\]"),
    ({"bank": {"kind": "whisker"}}, "invalid 'bank' or 'features'"),
    ({"bank": "whisker"}, "invalid 'bank' or 'features'"),
    ({"features": ["A", "B"]}, "invalid 'bank' or 'features'"),
    ({"features": 5}, "invalid 'bank' or 'features'"),
    ({"features": None}, "invalid 'bank' or 'features'"),
    ({"classes": []}, "classes"),
    ({"classes": ["a", "a", "b"]}, "classes"),
    ({"classes": "abc"}, "classes"),
    # issue 35 item 5: a class name is printed raw by the text sink (a terminal escape from a data file)
    ({"classes": ["felt\x1b[31mRED\x1b[0m", "b"]}, r"'classes' holds 'felt\\x1b\[31mRED.*not printable text"),
    ({"classes": ["x\ny", "b"]}, r"'classes' holds 'x\\ny'.*plain text"),
    ({"classes": ["a\u202eb", "b"]}, r"'classes' holds .*not printable text"),
    ({"classes": ["x" * 201, "b"]}, r"at most 200 characters"),
    ({"window_samples": 1}, "window_samples"),
    ({"window_samples": 500.0}, "window_samples"),
    ({"window_samples": True}, "window_samples"),
    ({"peak_mode": "minima"}, "peak_mode"),
    ({"training": [1, 2]}, "training"),
])
def test_bad_headers(saved, change, match):
    header, arrays = read_parts(saved)
    header.update(change)
    p = write_parts(saved.with_name("bad.npz"), header, arrays)
    with pytest.raises(ModelError, match=match):
        TextureModel.load(p)


def test_header_missing_keys(saved):
    for key in ("format", "version", "bank", "features", "classes", "window_samples", "peak_mode"):
        header, arrays = read_parts(saved)
        del header[key]
        with pytest.raises(ModelError):
            TextureModel.load(write_parts(saved.with_name("bad.npz"), header, arrays))


@pytest.mark.parametrize("header", [np.array("not json {"), np.array(5.0), np.array(json.dumps([1, 2]))])
def test_header_not_a_json_object(saved, header):
    _, arrays = read_parts(saved)
    p = write_parts(saved.with_name("bad.npz"), header, arrays, header_is_text=False)
    with pytest.raises(ModelError):
        TextureModel.load(p)


class _Touch:
    """Unpickling this creates a file: proof of whether anything was unpickled."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (pathlib.Path.touch, (pathlib.Path(self.path),))


@pytest.mark.parametrize("where", ["header", "w1"])
def test_pickle_inside_the_npz_is_refused_without_unpickling(saved, tmp_path, where):
    marker = tmp_path / f"unpickled-{where}"
    header, arrays = read_parts(saved)
    evil = np.empty(1, dtype=object)
    evil[0] = _Touch(marker)
    parts = {"header": np.array(json.dumps(header)), **arrays}
    parts[where] = evil
    p = tmp_path / "evil.npz"
    with open(p, "wb") as fh:
        np.savez(fh, **parts)                           # numpy pickles object arrays
    with pytest.raises(ModelError, match="not a supramodal model file: it holds a pickled Python object") as err:
        TextureModel.load(p)
    assert "allow_pickle" not in str(err.value)          # numpy's advice to load it unsafely is not passed on
    assert not marker.exists(), "the model loader unpickled an object"
    # control: the file really does carry a live pickle
    with np.load(p, allow_pickle=True) as npz:
        npz[where]
    assert marker.exists()


# -- fitting the scene -------------------------------------------------------------------------

def test_check_fits_refusals_name_the_problem(model):
    with pytest.raises(ModelError, match=r"whisker bank of 8 channels.*cochlea bank of 50 channels"):
        model.check_fits(cochlea_bank(), FEATURES, 500)
    with pytest.raises(ModelError, match="bank"):
        model.check_fits(whisker_bank(rows="AB", mean_B=50.0), FEATURES, 500)     # same size, other b
    with pytest.raises(ModelError, match=r"bank of 8 channels at 5000 Hz.*at 8000 Hz"):
        model.check_fits(whisker_bank(rows="AB", fs=8000.0), FEATURES, 500)
    with pytest.raises(ModelError, match=r"features \['Af', 'A'\].*computes \['A', 'Af'\]"):
        model.check_fits(BANK, ("A", "Af"), 500)
    with pytest.raises(ModelError, match=r"windows of 500 samples.*makes 441.*0\.1 s"):
        model.check_fits(BANK, FEATURES, 441)
    with pytest.raises(ValueError, match="unknown feature"):
        model.check_fits(BANK, ("X",), 500)


def test_inputs_of_the_wrong_shape_are_refused(model):
    with pytest.raises(ValueError, match=r"shape \(n, 2, 8\)"):
        model.predict(np.zeros((4, 3, 8)))
    with pytest.raises(ValueError, match=r"shape \(n, 2, 8\)"):
        model.predict(np.zeros((4, 16)))


def test_train_refuses_values_of_the_wrong_shape():
    values, labels = training_data()
    with pytest.raises(ValueError, match=r"shape \(n, 1, 8\)"):
        TextureModel.train(values, labels, CLASSES, BANK, ("A",), 500, epochs=1)


def test_constant_inputs_keep_a_unit_scale():
    values, labels = training_data()
    values[:, 1, 4] = 7.0
    m = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=2)
    assert m.scale[8 + 4] == 1.0 and np.all(m.scale > 0)


def test_peak_settings_travel_with_the_model_and_are_checked(tmp_path):
    from supramodal.pipeline import FeaturePipeline

    x, y = training_data()
    pipeline = FeaturePipeline(BANK, FEATURES, 0.1, peak_mode="extrema", peak_threshold=1e-3)
    m = TextureModel.train_for(pipeline, x, y, CLASSES, epochs=20, seed=0)
    back = TextureModel.load(m.save(tmp_path / "m"))
    assert (back.peak_mode, back.peak_threshold) == ("extrema", 1e-3)
    back.check_pipeline(back.pipeline())                      # the model's own pipeline fits
    with pytest.raises(ModelError, match="peak mode 'extrema'"):
        back.check_pipeline(FeaturePipeline(BANK, FEATURES, 0.1, peak_threshold=1e-3))
    with pytest.raises(ModelError, match="peak threshold 0.001"):
        back.check_pipeline(FeaturePipeline(BANK, FEATURES, 0.1, peak_mode="extrema"))


def test_negative_peak_threshold_in_a_header_is_refused(saved):
    header, arrays = read_parts(saved)
    header["peak_threshold"] = -1
    write_parts(saved, header, arrays)
    with pytest.raises(ModelError, match="peak_threshold"):
        TextureModel.load(saved)


@pytest.mark.parametrize("content", [b"hello, I am a text file\n", b"PICKLE", "pickle"])
def test_a_text_file_or_a_pickle_given_as_a_model_gets_no_advice_to_load_it_unsafely(tmp_path, content):
    """Issue 35, item 28: numpy's own message (load it with allow_pickle=True, or pickle.load()) was passed on
    to the user for a text file or a pickle given as a model. Refused, saying what the file is not."""
    import pickle

    p = tmp_path / "m.npz"
    if content == "pickle":
        p.write_bytes(pickle.dumps(_Touch(tmp_path / "unpickled")))
    else:
        p.write_bytes(content)
    said = "m.npz is not a supramodal model file: it holds a pickled" if content == "pickle" else \
        "m.npz is not a readable model file: not an .npz archive"
    with pytest.raises(ModelError, match=said) as err:
        TextureModel.load(p)
    assert "allow_pickle" not in str(err.value) and "pickle.load" not in str(err.value)
    assert not (tmp_path / "unpickled").exists()


# -- the gain augmentation a model was trained with (issue 34) -----------------------------------------

def test_a_models_gain_augmentation_travels_with_its_file_and_a_file_without_one_loads(model, saved, tmp_path):
    from supramodal.model import GainAugment

    values, labels = training_data()
    augmented = TextureModel.train(values, labels, CLASSES, BANK, FEATURES, 500, epochs=20, seed=3,
                                   augment=GainAugment(copies=2, spread=0.05, per_channel=None, seed=3))
    loaded = TextureModel.load(augmented.save(tmp_path / "aug.npz"))
    assert loaded.augment == GainAugment(2, 0.05, True, 3) == augmented.augment      # by bank: whisker, per channel
    assert read_parts(tmp_path / "aug.npz")[0]["training"]["augment"] == {"copies": 2, "spread": 0.05,
                                                                         "per_channel": True, "seed": 3}
    np.testing.assert_array_equal(loaded.outputs(values), augmented.outputs(values))
    assert "augment" not in read_parts(saved)[0]["training"]                          # as every earlier file
    assert TextureModel.load(saved).augment is None and model.augment is None


@pytest.mark.parametrize("augment", [{"copies": -1, "spread": 0.03, "per_channel": True, "seed": 0},
                                     {"copies": 4, "spread": "wide", "per_channel": True, "seed": 0},
                                     {"copies": 4}, "yes"])
def test_a_bad_gain_augmentation_in_a_header_is_refused(saved, augment):
    header, arrays = read_parts(saved)
    header["training"]["augment"] = augment
    with pytest.raises(ModelError, match="'training' 'augment'"):
        TextureModel.load(write_parts(saved.with_name("bad.npz"), header, arrays))
