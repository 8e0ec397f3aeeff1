"""Models trained on start, kept on disk: a node that starts again with the same scene reads its model.

It reads it instead of training it again (the default scene's model takes 1 to 5 s to train; reading it,
10 ms).

A model trained on start (``[model] train_on_start``) depends on nothing but what :func:`cache_key`
digests: the texture set it was trained on (every field of its description: peaks, rate, duration,
seed, or a two-sense set's surfaces; the signals themselves for any other kind of set), the bank,
the features, the window and the peak settings, the training's epochs, seed and gain augmentation
(``[model] augment_copies``, ...: a model trained with it is never served to a scene without it), the model file's
format version, the versions of this package, numpy and scipy, and the source of the model package
and of the node's build (a changed training or feature code is another key). Each cached model is one
file, ``KEY.npz`` in :func:`cache_folder`'s ``models/``: a model file as ``supramodal train`` writes it
(``TextureModel.load`` reads it, validated like any model file: plain arrays, never a pickle), with
members of its own beside it (ignored by ``TextureModel.load``): the key, the training and held-out
windows (a fusion trained on start learns from them) and the held-out logits of the calibration's
fold networks (a learned late-fusion weight is fitted on them; without them it trains its fold networks
again). Reading checks all of it: a file that is not a model, is of another key, or whose parts do
not fit is refused with a message and the model trained again (and the file replaced).

Files are written to a temporary name and renamed (a reader never sees half a file, two writers
never mix theirs); a process that trains a model holds a lock on its key (``fcntl.flock``, where
there is one), so that a node started beside it waits for the model instead of training it too.
The folder is bounded (:data:`MAX_CACHE_BYTES`): after a write, the least recently used files go
first. Nothing in the cache is needed: a folder that cannot be written is said once per write and
the node goes on.

The folder: ``$SUPRAMODAL_CACHE`` if set, else ``$XDG_CACHE_HOME/supramodal``, else
``~/.cache/supramodal``. ``SUPRAMODAL_CACHE=off`` turns the cache off (every start trains).
docs/node.md, "Models trained on start are cached".
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from supramodal.calibration import OutOfFold
from supramodal.digest import feed
from supramodal.model import (
    MODEL_VERSION,
    GainAugment,
    ModelError,
    TextureModel,
    novelty_arrays,
    read_model_archive,
    save_model_archive,
)

__all__ = ["CACHE_ENV", "CACHE_FORMAT", "MAX_CACHE_BYTES", "CacheRefused", "cache_folder", "cache_key",
           "trained_on_start"]

#: The environment variable naming the cache folder (``off``: no cache).
CACHE_ENV = "SUPRAMODAL_CACHE"
#: The value of :data:`CACHE_ENV` that turns the cache off.
OFF = "off"
#: The version of the cache's own members and key; a change in what a key means bumps it.
CACHE_FORMAT = 1
#: Bytes the models folder may hold; past it, the least recently used files are removed after a
#: write (the default scene's model with its windows takes 0.5 MB, a 64-channel cochlea's about 3 MB).
MAX_CACHE_BYTES = 256 * 2**20
#: The members a cache file holds beside the model's.
_KEY = "cache_key"
_WINDOWS = ("cache_x_train", "cache_y_train", "cache_x_test", "cache_y_test")
_OUT_OF_FOLD = ("cache_oof_logits", "cache_oof_folds", "cache_oof_fingerprint")


class CacheRefused(ModelError):
    """A cache file that is not what its name says: it is trained again and replaced."""


def cache_folder() -> Path | None:
    """Return the folder models trained on start are kept in, or None where :data:`CACHE_ENV` is ``off``."""
    given = os.environ.get(CACHE_ENV)
    if given:
        return None if given.strip().lower() == OFF else Path(given).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg and os.path.isabs(xdg) else Path.home() / ".cache") / "supramodal"


# -- the key ------------------------------------------------------------------------------------------

@functools.cache
def _code_digest() -> str:
    """Return a digest of the source the model and its windows come from.

    That source is the model package's modules (filterbank, peaks, features, pipeline, network, calibration,
    textures, training) and the node's build (which splits the windows and calls the training).
    """
    import supramodal

    h = hashlib.sha256()
    # the builder by its path beside this module, not imported: it imports this module to read the cache
    files = sorted(Path(supramodal.__file__).parent.glob("*.py")) + [Path(__file__).with_name("build.py")]
    for path in files:
        h.update(path.name.encode() + b"\0")
        try:
            h.update(path.read_bytes())
        except OSError:                 # a package without its sources: its version still counts
            h.update(b"?")
    return h.hexdigest()


def _texture_set_digest(ts) -> str:
    """Return a digest of what ``ts`` is.

    Its description where it is a dataclass of plain values (a texture set, a two-sense set), else the
    signals it synthesises (the bytes the training reads).
    """
    h = hashlib.sha256()
    try:
        feed(h, ts)
    except TypeError:
        h = hashlib.sha256(b"signals;")
        feed(h, (tuple(ts.names), float(ts.fs)))
        for i in range(len(ts.textures)):
            feed(h, np.asarray(ts.synthesize(i)))
    return h.hexdigest()


def cache_key(ts, pipeline, augment: GainAugment | None = None) -> str:
    """Return the key of the model :func:`supramodal.node.scene.build.train_on_texture_set` trains on ``ts``.

    The model trained with ``pipeline``'s settings and ``augment``; the key is a hex digest of everything that
    model depends on.
    """
    import scipy

    import supramodal
    from supramodal.mlp import DEFAULT_EPOCHS
    from supramodal.training import TRAIN_FRACTION

    p = pipeline
    parts = {
        "cache_format": CACHE_FORMAT, "model_version": MODEL_VERSION, "supramodal": supramodal.__version__,
        "numpy": np.__version__, "scipy": scipy.__version__, "code": _code_digest(),
        "texture_set": _texture_set_digest(ts), "bank": p.bank.to_dict(), "features": list(p.features),
        "window_samples": int(p.window_samples), "peak_mode": p.peaks.mode, "peak_threshold": float(p.peaks.threshold),
        "epochs": DEFAULT_EPOCHS, "seed": 0, "train_fraction": TRAIN_FRACTION,
    }
    if augment is not None:             # only then: the keys of models trained without it stay as they were
        parts["augment"] = augment.resolved(p.bank.kind).to_dict()
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=repr).encode()).hexdigest()[:40]


# -- a cache file -------------------------------------------------------------------------------------

def _write(path: Path, key: str, model: TextureModel, train_part, test_part) -> None:
    """Write ``model`` with its windows and held-out logits to ``path``.

    First to a temporary file in the same folder, then renamed over it.
    """
    extra = {**novelty_arrays(model.novelty), _KEY: np.array(key)}
    extra.update(zip(_WINDOWS, (np.asarray(train_part[0], dtype=np.float64), np.asarray(train_part[1], dtype=np.int64),
                                np.asarray(test_part[0], dtype=np.float64), np.asarray(test_part[1], dtype=np.int64))))
    oof = model.out_of_fold
    if isinstance(oof, OutOfFold):
        extra[_OUT_OF_FOLD[0]] = np.asarray(oof.logits, dtype=np.float64)
        extra[_OUT_OF_FOLD[1]] = np.asarray(oof.folds, dtype=np.int64)
        extra[_OUT_OF_FOLD[2]] = np.array(oof.fingerprint)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        save_model_archive(tmp, model.header(), model.mlp, model.mean, model.scale, extra)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _read(path: Path, key: str, ts, pipeline, augment: GainAugment | None = None):
    """Return ``(model, (x_train, y_train), (x_test, y_test))`` from a cache file, every part checked.

    FileNotFoundError where there is none, :class:`CacheRefused` where it is not what ``key`` names.
    """
    if not path.is_file():
        raise FileNotFoundError(path)
    try:
        model = TextureModel.load(path)                              # validated as any model file
        _, parts = read_model_archive(path, (_KEY, *_WINDOWS), optional=_OUT_OF_FOLD)
    except ModelError as exc:
        raise CacheRefused(str(exc)) from None
    stored = parts[_KEY]
    if stored.dtype.kind != "U" or stored.ndim != 0 or str(stored) != key:
        raise CacheRefused(f"{path}: the file is of another key (it holds {str(stored)[:40]!r})")
    try:
        model.check_pipeline(pipeline)
    except ModelError as exc:
        raise CacheRefused(f"{path}: {exc}") from None
    asked = None if augment is None else augment.resolved(model.bank.kind)
    if model.augment != asked:
        raise CacheRefused(f"{path}: the model was trained with gain augmentation {model.augment}, the scene asks "
                           f"for {asked}")
    if tuple(model.classes) != tuple(ts.names):
        raise CacheRefused(f"{path}: the model's classes {list(model.classes)} are not the texture set's "
                           f"{list(ts.names)}")
    inputs = (len(model.features), model.bank.channels)
    x_train, y_train, x_test, y_test = (parts[k] for k in _WINDOWS)
    for x, y, which in ((x_train, y_train, "training"), (x_test, y_test, "held-out")):
        if (x.dtype != np.float64 or x.ndim != 3 or x.shape[1:] != inputs or y.dtype != np.int64
                or y.shape != (len(x),) or not len(x)):
            raise CacheRefused(f"{path}: the {which} windows have shape {x.shape} ({x.dtype}) and labels "
                               f"{y.shape} ({y.dtype}); expected float64 (n, {inputs[0]}, {inputs[1]}) and int64 (n,)")
        if not np.isfinite(x).all() or y.min() < 0 or y.max() >= len(model.classes):
            raise CacheRefused(f"{path}: the {which} windows hold NaN or Inf, or labels outside the classes")
    if model.training.get("windows") != len(x_train):
        raise CacheRefused(f"{path}: the model was trained on {model.training.get('windows')!r} windows, the file "
                           f"holds {len(x_train)}")
    if all(k in parts for k in _OUT_OF_FOLD) and model.calibration is not None:
        logits, folds, fingerprint = (parts[k] for k in _OUT_OF_FOLD)
        if (logits.dtype != np.float64 or logits.shape != (len(x_train), len(model.classes))
                or folds.dtype != np.int64 or folds.shape != (len(x_train),) or not np.isfinite(logits).all()
                or fingerprint.dtype.kind != "U" or fingerprint.ndim != 0):
            raise CacheRefused(f"{path}: the held-out logits have shape {logits.shape} ({logits.dtype}) and folds "
                               f"{folds.shape}; expected ({len(x_train)}, {len(model.classes)}) and "
                               f"({len(x_train)},), with a fingerprint of the training windows")
        oof = OutOfFold(logits, folds, str(fingerprint))
        if not oof.matches(x_train, y_train, folds):
            raise CacheRefused(f"{path}: the held-out logits were not computed on the training windows it holds")
        model.out_of_fold = oof
    return model, (x_train, y_train), (x_test, y_test)


@contextlib.contextmanager
def _lock(path: Path, progress=None):
    """Hold ``path``'s lock file (fcntl.flock) while a model is trained; nothing where there is no flock.

    OSError where the lock file cannot be made (before anything is held). Where another process holds it
    (training the same model), ``progress`` is told so before the wait (issue 35: a node waited silently).
    """
    try:
        import fcntl
    except ImportError:                 # Windows: two nodes started at once may both train
        yield
        return
    lock = path.with_name(path.name + ".lock")
    fd = os.open(lock, os.O_CREAT | os.O_RDWR, 0o600)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if progress:
                progress(f"model cache: another process is training this model (it holds {lock}); waiting for it, "
                         "then reading its model (Ctrl-C stops the wait)")
            fcntl.flock(fd, fcntl.LOCK_EX)  # interruptible: Ctrl-C raises KeyboardInterrupt here
        yield
    finally:
        os.close(fd)                    # lets the lock go


#: A cache file's name: its key (:func:`cache_key`, 40 hex digits) and ``.npz``; the only files the cache removes.
_KEY_FILE = re.compile(r"[0-9a-f]{40}\.npz")


def _bound(folder: Path, keep: Path, limit: int) -> None:
    """Remove the least recently used cache files of ``folder`` (not ``keep``) until they hold at most ``limit`` bytes.

    Only the cache's own key files count and go: a folder the user named as the cache may hold files of
    theirs, which are never touched.
    """
    files = []
    for p in folder.glob("*.npz"):
        if not _KEY_FILE.fullmatch(p.name):
            continue
        try:
            st = p.stat()
        except FileNotFoundError:
            continue
        files.append((st.st_mtime, st.st_size, p))
    total = sum(size for _, size, _ in files)
    for _, size, p in sorted(files, key=lambda f: f[0]):
        if total <= limit:
            break
        if p == keep:
            continue
        p.unlink(missing_ok=True)
        p.with_name(p.name + ".lock").unlink(missing_ok=True)
        total -= size


def hand_over(model, train_part, test_part, ts, features, held_out: list | None, trained: list | None,
              progress=None, where: str = "") -> None:
    """Give the caller of a model trained on start what it gets besides the model, trained or read.

    The held-out part to ``held_out`` and the training part to ``trained`` (lists, or None), and to
    ``progress`` the line that says what it was trained on and how it is calibrated (``where``: appended, e.g.
    the cache file read).
    """
    if held_out is not None:
        held_out.append(test_part)
    if trained is not None:
        trained.append(train_part)
    if progress:
        from supramodal.calibration import calibration_line

        progress(f"trained on {len(train_part[0])} windows of {len(ts.textures)} textures ({', '.join(features)}); "
                 + calibration_line(None if model.calibration is None else model.calibration.fitted_on) + where)
        if model.augment is not None:
            progress(model.augment.describe())


# -- the node's use -----------------------------------------------------------------------------------

def trained_on_start(ts, pipeline, train, progress=None, held_out: list | None = None,
                     trained: list | None = None, folder: Path | None = None,
                     augment: GainAugment | None = None) -> TextureModel:
    """Return the model trained on start on ``ts`` with ``pipeline``'s settings, from the cache or trained now.

    Read from the cache where it holds it, else ``train(held_out, trained)``
    (:func:`~supramodal.node.scene.build.train_on_texture_set` with ``ts`` and ``pipeline`` bound) and written
    to it. ``held_out`` and ``trained`` receive the held-out and training windows either way; ``progress``
    gets the training's line (or the same line for a model read, naming the file) and a line for a cache file
    refused or not written. ``folder``: the cache's folder (default :func:`cache_folder`; None there: no
    cache). ``augment``: the gain augmentation ``train`` trains with (part of the key).
    """
    folder = cache_folder() if folder is None else folder
    if folder is None:
        return train(held_out, trained)
    key = cache_key(ts, pipeline, augment)
    path = folder / "models" / f"{key}.npz"

    def hit():
        model, train_part, test_part = _read(path, key, ts, pipeline, augment)
        try:
            os.utime(path)              # recently used: kept longest
        except OSError:
            pass
        hand_over(model, train_part, test_part, ts, pipeline.features, held_out, trained, progress,
                  f" (read from the model cache: {path})")
        return model

    def refused(exc: CacheRefused) -> None:
        if progress:
            progress(f"model cache: refused {exc}; training the model again")

    try:
        return hit()
    except FileNotFoundError:
        pass
    except CacheRefused as exc:
        refused(exc)
    lock = _lock(path, progress)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        lock.__enter__()
    except OSError as exc:
        if progress:
            progress(f"model cache: {folder} cannot be used ({exc}); training without it")
        return train(held_out, trained)
    with contextlib.ExitStack() as held:
        held.push(lock)                 # left when the model is written (or the training raised)
        try:
            return hit()                # another process trained it while this one waited
        except FileNotFoundError:
            pass
        except CacheRefused:
            pass                        # said above
        mine_held_out: list = []
        mine_trained: list = []
        model = train(mine_held_out, mine_trained)
        if held_out is not None:
            held_out.extend(mine_held_out)
        if trained is not None:
            trained.extend(mine_trained)
        try:
            _write(path, key, model, mine_trained[0], mine_held_out[0])
            _bound(path.parent, path, MAX_CACHE_BYTES)
        except OSError as exc:
            if progress:
                progress(f"model cache: {path} not written ({exc})")
        return model
