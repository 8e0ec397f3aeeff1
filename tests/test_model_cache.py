"""The cache of models trained on start (node/scene/model_cache.py, docs/node.md): a hit is the model
a fresh training gives, with the same windows; any part of the key changed misses; a corrupt, foreign or
pickled file is refused with a message and the model trained again; writers and readers side by side
never see half a file; the cache can be turned off and is bounded."""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from supramodal.banks import whisker_bank
from supramodal.model import TextureModel
from supramodal.node.scene import build
from supramodal.node.scene import model_cache
from supramodal.node.scene.model_cache import CACHE_ENV, cache_folder, cache_key, trained_on_start
from supramodal.pipeline import FeaturePipeline
from supramodal.textures import reference_texture_set


def _short_set(**changes):
    """The whisker reference set, 4 s a texture (the training takes a few seconds)."""
    ts = reference_texture_set("whisker")
    return dataclasses.replace(ts, **{"duration": 4.0, **changes})


def _pipeline(features=("Af",), window=0.1, **kwargs):
    return FeaturePipeline(whisker_bank(), features, window, **kwargs)


class Trainer:
    """``train(held_out, trained)`` as the node's build binds it, counting its calls (the trainings
    of build.train_on_texture_set are shared by the suite's processes: each call still returns the
    model, windows and held-out logits a training gives)."""

    def __init__(self, ts, pipeline):
        self.ts, self.pipeline, self.calls = ts, pipeline, 0

    def __call__(self, held_out, trained):
        self.calls += 1
        return build.train_on_texture_set(self.ts, self.pipeline, None, held_out, trained)


def _lookup(folder, ts, pipeline, trainer=None, messages=None):
    held_out, trained = [], []
    trainer = trainer or Trainer(ts, pipeline)
    model = trained_on_start(ts, pipeline, trainer, (messages.append if messages is not None else None),
                             held_out, trained, folder=folder)
    return model, held_out[0], trained[0], trainer


def test_a_hit_is_the_fresh_models_decisions_windows_and_held_out_logits(tmp_path):
    ts, p = _short_set(), _pipeline()
    fresh, held_fresh, trained_fresh, first = _lookup(tmp_path, ts, p)
    assert first.calls == 1
    [path] = (tmp_path / "models").glob("*.npz")
    assert path.stem == cache_key(ts, p)
    assert TextureModel.load(path).classes == fresh.classes          # a model file like any other

    said = []
    cached, held, trained, second = _lookup(tmp_path, ts, p, messages=said)
    assert second.calls == 0 and cached is not fresh
    x_test = held_fresh[0]
    np.testing.assert_array_equal(cached.posteriors(x_test), fresh.posteriors(x_test))
    np.testing.assert_array_equal(cached.predict(x_test), fresh.predict(x_test))
    np.testing.assert_array_equal(cached.novelty_score(x_test), fresh.novelty_score(x_test))
    assert cached.calibration.to_dict() == fresh.calibration.to_dict()
    for got, want in zip((*held, *trained), (*held_fresh, *trained_fresh)):
        np.testing.assert_array_equal(got, want)
    # a late-fusion weight learned on start finds the calibration's fold networks' logits (not ten trainings)
    assert cached.out_of_fold.matches(trained[0], trained[1], fresh.out_of_fold.folds)
    np.testing.assert_array_equal(cached.out_of_fold.logits, fresh.out_of_fold.logits)
    assert len(said) == 1 and said[0].startswith(f"trained on {len(trained[0])} windows of 8 textures (Af); ")
    assert said[0].endswith(f"(read from the model cache: {path})")


@pytest.mark.parametrize("change", ["texture seed", "texture peaks", "bank", "features", "window", "peak mode",
                                    "peak threshold", "code", "cache format"])
def test_a_changed_part_of_the_key_misses(tmp_path, monkeypatch, change):
    ts, p = _short_set(), _pipeline()
    key = cache_key(ts, p)
    assert cache_key(_short_set(), _pipeline()) == key                # the same content: the same key
    if change == "texture seed":
        ts = _short_set(seed=ts.seed + 1)
    elif change == "texture peaks":
        first = ts.textures[0]
        ts = _short_set(textures=(dataclasses.replace(first, peaks=(first.peaks[0] + 1, *first.peaks[1:])),
                                  *ts.textures[1:]))
    elif change == "bank":
        p = FeaturePipeline(whisker_bank(rows="ABCD"), ("Af",), 0.1)
    elif change == "features":
        p = _pipeline(("Af", "A"))
    elif change == "window":
        p = _pipeline(window=0.05)
    elif change == "peak mode":
        p = _pipeline(peak_mode="extrema")
    elif change == "peak threshold":
        p = _pipeline(peak_threshold=0.01)
    elif change == "code":
        monkeypatch.setattr(model_cache, "_code_digest", lambda: "another version of the training's source")
    else:
        monkeypatch.setattr(model_cache, "CACHE_FORMAT", model_cache.CACHE_FORMAT + 1)
    assert cache_key(ts, p) != key


def test_a_key_missed_trains_and_the_other_keys_file_is_kept(tmp_path):
    ts = _short_set()
    _lookup(tmp_path, ts, _pipeline())
    *_, trainer = _lookup(tmp_path, ts, _pipeline(("A",)))
    assert trainer.calls == 1
    assert len(list((tmp_path / "models").glob("*.npz"))) == 2
    *_, again = _lookup(tmp_path, ts, _pipeline())
    assert again.calls == 0


def _pickled_archive(path):
    """The cache file with its header replaced by a pickled object (which loading would run)."""
    with np.load(path, allow_pickle=False) as npz:
        members = {k: npz[k] for k in npz.files if k != "header"}
    with open(path, "wb") as f:
        np.savez(f, header=np.array({"format": "supramodal-model"}, dtype=object), **members)


@pytest.mark.parametrize("damage, says", [
    ("garbage", "not a readable model file"),
    ("truncated", "not a readable model file"),
    ("pickled", "pickled Python object, which this program never loads"),
    ("another key", "of another key"),
    ("windows", "the training windows have shape"),
    ("held-out logits", "the held-out logits were not computed on the training windows it holds"),
])
def test_a_corrupt_or_foreign_cache_file_is_refused_with_a_message_and_trained_again(tmp_path, damage, says):
    ts, p = _short_set(), _pipeline()
    fresh, *_ = _lookup(tmp_path, ts, p)
    path = tmp_path / "models" / f"{cache_key(ts, p)}.npz"
    good = path.read_bytes()
    if damage == "garbage":
        path.write_bytes(b"not a model at all" * 10)
    elif damage == "truncated":
        path.write_bytes(good[: len(good) // 2])
    elif damage == "pickled":
        _pickled_archive(path)
    elif damage == "another key":
        other = _pipeline(("A",))
        _lookup(tmp_path, ts, other)
        shutil.copyfile(tmp_path / "models" / f"{cache_key(ts, other)}.npz", path)
    elif damage == "windows":                 # a model file whose windows do not fit its model
        model = TextureModel.load(path)
        model_cache._write(path, cache_key(ts, p), model, (np.zeros((5, 2, 3)), np.zeros(5, dtype=np.int64)),
                           (np.zeros((5, 1, 20)), np.zeros(5, dtype=np.int64)))
    else:                                     # held-out logits of other windows than those it holds
        _, trained, held = model_cache._read(path, cache_key(ts, p), ts, p)
        other = dataclasses.replace(fresh, out_of_fold=dataclasses.replace(fresh.out_of_fold, fingerprint="0" * 32))
        model_cache._write(path, cache_key(ts, p), other, trained, held)
    said = []
    model, held, trained, trainer = _lookup(tmp_path, ts, p, messages=said)
    assert trainer.calls == 1
    refusals = [m for m in said if m.startswith("model cache: refused")]
    assert len(refusals) == 1 and says in refusals[0] and str(path) in refusals[0]
    assert refusals[0].endswith("training the model again")
    np.testing.assert_array_equal(model.posteriors(held[0]), fresh.posteriors(held[0]))
    *_, after = _lookup(tmp_path, ts, p)      # the file was replaced by a good one
    assert after.calls == 0


def _write_many(path, key, model, train_part, test_part, n):
    for _ in range(n):
        model_cache._write(Path(path), key, model, train_part, test_part)


def _read_many(path, key, ts, pipeline, n, out):
    seen = {"read": 0, "absent": 0}
    for _ in range(n):
        try:
            model_cache._read(Path(path), key, ts, pipeline)
            seen["read"] += 1
        except FileNotFoundError:
            seen["absent"] += 1
    with open(out, "wb") as f:
        pickle.dump(seen, f)


def test_writers_and_readers_side_by_side_never_see_half_a_file(tmp_path):
    """Four processes write the same key 15 times each while two read it: every read finds either no
    file or a whole one (a refused file would raise CacheRefused in a reader), and no temporary
    file is left."""
    ts, p = _short_set(), _pipeline()
    model, held, trained, _ = _lookup(tmp_path / "first", ts, p)
    key = cache_key(ts, p)
    path = tmp_path / "models" / f"{key}.npz"
    ctx = multiprocessing.get_context("fork")
    writers = [ctx.Process(target=_write_many, args=(path, key, model, trained, held, 15)) for _ in range(4)]
    readers = [ctx.Process(target=_read_many, args=(path, key, ts, p, 60, tmp_path / f"r{i}")) for i in range(2)]
    for proc in writers + readers:
        proc.start()
    for proc in writers + readers:
        proc.join(120)
        assert proc.exitcode == 0
    for i in range(2):
        with open(tmp_path / f"r{i}", "rb") as f:
            assert sum(pickle.load(f).values()) == 60
    got, _, _ = model_cache._read(path, key, ts, p)
    np.testing.assert_array_equal(got.posteriors(held[0]), model.posteriors(held[0]))
    assert sorted(q.name for q in path.parent.iterdir()) == [path.name]


def _start(folder, ts, pipeline, log, result):
    """A node starting: looks its model up, training it (slowly, as a loaded machine would) on a miss."""
    def train(held_out, trained):
        with open(log, "a") as f:
            f.write(f"{os.getpid()}\n")
        model = build.train_on_texture_set(ts, pipeline, None, held_out, trained)
        time.sleep(0.5)
        return model

    model = trained_on_start(ts, pipeline, train, None, [], [], folder=Path(folder))
    np.save(result, model.mlp.stacked()[0])


def test_nodes_started_together_train_the_model_once(tmp_path):
    ts, p = _short_set(), _pipeline()
    fresh, *_ = _lookup(tmp_path / "fresh", ts, p)
    ctx = multiprocessing.get_context("fork")
    log = tmp_path / "trainings"
    procs = [ctx.Process(target=_start, args=(tmp_path / "cache", ts, p, log, tmp_path / f"w1-{i}.npy"))
             for i in range(3)]
    for proc in procs:
        proc.start()
    for proc in procs:
        proc.join(300)
        assert proc.exitcode == 0
    assert len(log.read_text().split()) == 1
    for i in range(3):
        np.testing.assert_array_equal(np.load(tmp_path / f"w1-{i}.npy"), fresh.mlp.stacked()[0])


def test_the_cache_is_off_with_its_variable_and_never_in_the_home_under_the_suite(tmp_path, monkeypatch):
    assert Path(os.environ[CACHE_ENV]).resolve() != (Path.home() / ".cache" / "supramodal").resolve()
    assert cache_folder() == Path(os.environ[CACHE_ENV])             # the harness: the run's own folder
    monkeypatch.setenv(CACHE_ENV, "off")
    assert cache_folder() is None
    ts, p = _short_set(), _pipeline()
    trainer = Trainer(ts, p)
    for _ in range(2):
        trained_on_start(ts, p, trainer, None, [], [])
    assert trainer.calls == 2
    monkeypatch.delenv(CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_folder() == tmp_path / "xdg" / "supramodal"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/is/ignored")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_folder() == tmp_path / "home" / ".cache" / "supramodal"


def test_a_folder_that_cannot_be_written_is_said_and_the_node_trains(tmp_path):
    blocker = tmp_path / "a file"
    blocker.write_text("")
    ts, p = _short_set(), _pipeline()
    said = []
    model, *_, trainer = _lookup(blocker, ts, p, messages=said)
    assert trainer.calls == 1 and model is not None
    assert any(m.startswith(f"model cache: {blocker} cannot be used") for m in said)


def test_the_folder_is_bounded_least_recently_used_first(tmp_path):
    folder = tmp_path / "models"
    folder.mkdir()
    names = {name: f"{i:x}" * 40 for i, name in enumerate(["old", "mid", "new", "kept"], start=10)}   # key files
    for i, key in enumerate(names.values()):
        (folder / f"{key}.npz").write_bytes(b"x" * 1000)
        os.utime(folder / f"{key}.npz", (1000 + i, 1000 + i))
    kept = folder / f"{names['kept']}.npz"
    os.utime(kept, (1, 1))                          # the one just written is never removed
    model_cache._bound(folder, kept, 2500)
    assert sorted(p.stem for p in folder.glob("*.npz")) == sorted([names["kept"], names["new"]])


def test_the_bound_never_removes_a_file_that_is_not_the_cache_s_own(tmp_path):
    """Issue 35, item 3: SUPRAMODAL_CACHE set to a project folder whose models/ holds the user's own
    300 MB model (an old mtime): the cache's bound counts and removes only its own key files."""
    folder = tmp_path / "models"
    folder.mkdir()
    mine = folder / "my_big_dataset.npz"
    with mine.open("wb") as f:
        f.truncate(300 * 2**20)                     # sparse: 300 MB in name only
    os.utime(mine, (1, 1))
    also = folder / ("a" * 39 + ".npz")             # not a key (39 digits)
    also.write_bytes(b"x" * 10)
    os.utime(also, (1, 1))
    key = folder / ("b" * 40 + ".npz")
    key.write_bytes(b"x" * 1000)
    model_cache._bound(folder, key, 500)
    assert mine.exists() and also.exists() and key.exists()


def test_the_node_reads_its_model_from_the_cache_on_its_second_start(tmp_path, monkeypatch):
    """build_node with a scene that trains on start: the first build trains (or, in this suite, finds
    the model the run's cache already holds), the second reads it from the cache and says so."""
    from supramodal.node.runtime.sinks import ListSink
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import scene_from_dict

    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    _short_set().save(tmp_path / "short.json")
    d = {"driver": {"type": "synth", "textures": "short.json", "seconds": 1.0},
         "model": {"train_on_start": True}}
    said = []
    for _ in range(2):
        graph = build_node(scene_from_dict(d, str(tmp_path / "s.toml"), tmp_path), sinks_override=[ListSink()],
                           progress=said.append)
        for sink in graph.sinks:
            sink.close()
    lines = [m for m in said if m.startswith("trained on")]
    assert len(lines) == 2 and "read from the model cache" not in lines[0]
    assert lines[1].endswith(".npz)") and "read from the model cache" in lines[1]
    assert lines[1].split(" (read from")[0] == lines[0]


def test_a_wait_for_another_process_s_training_is_said_before_it_starts(tmp_path):
    """Issue 35, item 12: a node waited silently for a cache lock another process held. The wait is said
    first (what holds it, that Ctrl-C stops it); the lock taken once the other lets it go."""
    import fcntl
    import threading

    path = tmp_path / ("c" * 40 + ".npz")
    other = os.open(path.with_name(path.name + ".lock"), os.O_CREAT | os.O_RDWR, 0o600)
    fcntl.flock(other, fcntl.LOCK_EX)                       # another process trains it
    said, held = [], threading.Event()

    def take():
        with model_cache._lock(path, said.append):
            held.set()

    taker = threading.Thread(target=take, daemon=True)
    taker.start()
    try:
        deadline = time.monotonic() + 10
        while not said and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(said) == 1 and "another process is training this model" in said[0] and ".lock" in said[0]
        assert not held.is_set()
    finally:
        os.close(other)                                      # the other lets it go
    taker.join(10)
    assert held.is_set()
    with model_cache._lock(path, said.append):               # free: nothing said
        pass
    assert len(said) == 1


def test_the_key_holds_the_gain_augmentation_the_model_is_trained_with():
    """Issue 34: a model trained with gain augmentation is another model; its key is another key (and a
    model trained without it keeps the key it had)."""
    from supramodal.model import GainAugment

    ts, p = _short_set(), _pipeline()
    plain = cache_key(ts, p)
    asked = GainAugment(4, 0.03, None)
    assert cache_key(ts, p, None) == plain and cache_key(ts, p, asked) != plain
    assert cache_key(ts, p, asked) == cache_key(ts, p, GainAugment(4, 0.03, True))      # by bank: whisker, per channel
    others = [GainAugment(3, 0.03, True), GainAugment(4, 0.05, True), GainAugment(4, 0.03, False),
              GainAugment(4, 0.03, True, seed=1), GainAugment(4, 0.0, True)]
    assert len({cache_key(ts, p, a) for a in [asked, *others]} | {plain}) == 2 + len(others)


def test_a_scene_with_gain_augmentation_is_never_served_the_model_of_one_without_it(tmp_path, monkeypatch):
    """build_node: the scene without augmentation trains (or reads) its model; the same scene with
    [model] augment_copies trains another, which says so, and is read back from the cache on its next start."""
    from supramodal.model import GainAugment
    from supramodal.node.runtime.sinks import ListSink
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import scene_from_dict

    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    _short_set(duration=2.0).save(tmp_path / "short.json")

    def start(model):
        said = []
        graph = build_node(scene_from_dict({"driver": {"type": "synth", "textures": "short.json", "seconds": 0.5},
                                            "model": {"train_on_start": True, **model}},
                                           str(tmp_path / "s.toml"), tmp_path),
                           sinks_override=[ListSink()], progress=said.append)
        for sink in graph.sinks:
            sink.close()
        [stream] = graph.streams
        return stream.model, [m for m in said if m.startswith(("trained on", "gain augmentation"))]

    plain, _ = start({})
    augmented, said = start({"augment_copies": 1, "augment_spread": 0.05})
    assert plain.augment is None and augmented.augment == GainAugment(1, 0.05, True)
    assert "read from the model cache" not in said[0] and said[1].startswith("gain augmentation: 1 more copies")
    assert not np.array_equal(augmented.mlp.stacked()[0], plain.mlp.stacked()[0])
    again, said = start({"augment_copies": 1, "augment_spread": 0.05})
    assert "read from the model cache" in said[0] and again.augment == augmented.augment
    assert len(list((tmp_path / "cache" / "models").glob("*.npz"))) == 2
