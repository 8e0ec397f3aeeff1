"""Pieces shared by the experiments: texture features, train/test split, classification rates."""

from __future__ import annotations

import sys
import time

import numpy as np

from supramodal.banks import Bank, bank_by_name
from supramodal.features import FEATURES
from supramodal.model import TextureModel
from supramodal.pipeline import DEFAULT_WINDOW, FeaturePipeline
from supramodal.textures import TextureSet

#: Fraction of each texture's windows used for training (paper: 300 of 400), the rest for testing.
TRAIN_FRACTION = 0.75
DEFAULT_EPOCHS = 500


def progress_to_stderr(message: str) -> None:
    """Default progress reporter of long experiments: one line on stderr."""
    print(message, file=sys.stderr, flush=True)


def default_bank(texture_set: TextureSet, **kwargs) -> Bank:
    """The bank a texture set was made for, at the set's sample rate."""
    return bank_by_name(texture_set.bank, fs=texture_set.fs, **kwargs)


def texture_features(texture_set: TextureSet, bank: Bank, features=FEATURES, window: float = DEFAULT_WINDOW,
                     progress=None, **pipeline_kwargs) -> tuple[np.ndarray, dict]:
    """Synthesise every texture of the set and compute its feature windows.

    Returns
    -------
    values : ndarray, shape (textures, windows, features, channels)
    timing : dict
        ``signal_seconds`` processed and ``compute_seconds`` spent in the pipeline.
    """
    out, compute = [], 0.0
    for i, tex in enumerate(texture_set.textures):
        x = texture_set.synthesize(i)
        t0 = time.perf_counter()
        w = FeaturePipeline(bank, features, window, **pipeline_kwargs).run(x, block=65536)
        compute += time.perf_counter() - t0
        out.append(w.values)
        if progress:
            progress(f"  {texture_set.name}: texture {i + 1}/{len(texture_set.textures)} ({tex.name}) -> {len(w)} windows")
    n = min(len(v) for v in out)
    signal = len(texture_set.textures) * texture_set.duration
    return np.stack([v[:n] for v in out]), {"signal_seconds": signal, "compute_seconds": compute}


def split(values: np.ndarray, train_fraction: float = TRAIN_FRACTION):
    """First ``train_fraction`` of each texture's windows for training, the rest for testing.

    ``values`` has shape (textures, windows, ...). Returns ``(x_train, y_train, x_test, y_test)``
    with the texture axis folded into the window axis.
    """
    n_tex, n_win = values.shape[:2]
    n_train = int(round(train_fraction * n_win))
    if not 0 < n_train < n_win:
        raise ValueError(f"{n_win} windows per texture cannot be split {train_fraction:.0%} / rest")
    labels = np.arange(n_tex)
    x_train = values[:, :n_train].reshape((-1,) + values.shape[2:])
    x_test = values[:, n_train:].reshape((-1,) + values.shape[2:])
    return x_train, np.repeat(labels, n_train), x_test, np.repeat(labels, n_win - n_train)


def classification_rates(values: np.ndarray, classes, bank: Bank, features, window_samples: int,
                         epochs: int = DEFAULT_EPOCHS, seed: int = 0) -> dict:
    """Train on the first part of each texture, test on the rest.

    Returns ``{"mean_rate": r, "per_texture": {name: r}}``, rates in [0, 1].
    """
    x_train, y_train, x_test, y_test = split(values)
    model = TextureModel.train(x_train, y_train, classes, bank, features, window_samples, epochs=epochs, seed=seed)
    correct = model.predict(x_test) == y_test
    per = {name: float(np.mean(correct[y_test == k])) for k, name in enumerate(classes)}
    return {"mean_rate": float(np.mean(correct)), "per_texture": per}
