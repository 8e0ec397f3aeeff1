"""Training data from texture sets: features and the train/test split.

What the node's on-the-spot training (the default scene), the manifest training, the experiments
and the benchmarks share. Pure numpy: no devices, no threads.
"""

from __future__ import annotations

import time

import numpy as np

from supramodal.banks import Bank
from supramodal.errors import InputError
from supramodal.features import DEFAULT_WINDOW, FEATURES
from supramodal.pipeline import FeaturePipeline
from supramodal.textures import TextureSet

#: Fraction of each texture's windows used for training (paper: 300 of 400), the rest for testing.
TRAIN_FRACTION = 0.75


def texture_features(texture_set: TextureSet, bank: Bank, features=FEATURES, window: float = DEFAULT_WINDOW,
                     progress=None, **pipeline_kwargs) -> tuple[np.ndarray, dict]:
    """Synthesise every texture of the set and compute its feature windows.

    Parameters
    ----------
    texture_set : TextureSet
        Textures to synthesise, each for the set's duration at its sample rate.
    bank : Bank
        The filters; the set's sample rate must be the bank's.
    features : sequence of str, optional
        Feature names (default: every feature, :data:`supramodal.features.FEATURES`).
    window : float, optional
        Window length, seconds (default :data:`supramodal.pipeline.DEFAULT_WINDOW`).
    progress : callable or None, optional
        Called with one line of text per texture.
    **pipeline_kwargs
        Passed to :class:`~supramodal.pipeline.FeaturePipeline` (peak mode, threshold, backend...).

    Returns
    -------
    values : ndarray, shape (textures, windows, features, channels)
        Every texture cut to the shortest texture's number of windows.
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
            progress(f"  {texture_set.name}: texture {i + 1}/{len(texture_set.textures)} ({tex.name}) "
                     f"-> {len(w)} windows")
    n = min(len(v) for v in out)
    signal = len(texture_set.textures) * texture_set.duration
    return np.stack([v[:n] for v in out]), {"signal_seconds": signal, "compute_seconds": compute}


def split(values: np.ndarray, train_fraction: float = TRAIN_FRACTION):
    """First ``train_fraction`` of each texture's windows for training, the rest for testing.

    Parameters
    ----------
    values : ndarray, shape (textures, windows, ...)
        As from :func:`texture_features`.
    train_fraction : float, optional
        Share of each texture's windows (the first ones) used for training; default
        :data:`TRAIN_FRACTION`.

    Returns
    -------
    x_train, y_train, x_test, y_test : ndarray
        The texture axis folded into the window axis; labels are texture indices.

    Raises
    ------
    InputError
        If a texture has too few windows for both parts to hold one.
    """
    n_tex, n_win = values.shape[:2]
    n_train = int(round(train_fraction * n_win))
    if not 0 < n_train < n_win:
        raise InputError(f"{n_win} windows per texture cannot be split {train_fraction:.0%} / rest: "
                         "synthesise longer textures")
    labels = np.arange(n_tex)
    x_train = values[:, :n_train].reshape((-1,) + values.shape[2:])
    x_test = values[:, n_train:].reshape((-1,) + values.shape[2:])
    return x_train, np.repeat(labels, n_train), x_test, np.repeat(labels, n_win - n_train)


def grouped_folds(groups, labels, k: int, seed: int = 0) -> np.ndarray:
    """Assign items to ``k`` cross-validation folds, every item of one group in the same fold.

    A group is one recording (one trial): its windows are alike, so a window in the test fold
    whose neighbours trained the model would flatter the score. Groups are dealt to the folds
    label by label, shuffled by ``seed``, so each fold holds about the same share of each label.

    Parameters
    ----------
    groups : sequence of hashable, length n
        The group of each item (e.g. the recording's path).
    labels : sequence of str, length n
        The label of each item; a group is dealt under the label of its first item.
    k : int
        Number of folds, >= 2.
    seed : int, optional
        Seed of the shuffle (default 0): the folds depend on nothing else.

    Returns
    -------
    ndarray of int, shape (n,)
        The fold of each item, 0 .. k-1.

    Raises
    ------
    InputError
        If ``k < 2``, if there are fewer groups than folds, or if a label has fewer than two
        groups (one fold's model would then never see it).
    """
    groups, labels = list(groups), list(labels)
    if len(groups) != len(labels):
        raise InputError(f"{len(groups)} groups for {len(labels)} labels: give one of each per item")
    if not (isinstance(k, (int, np.integer)) and k >= 2):
        raise InputError(f"cross-validation needs k >= 2 folds, got {k!r}")
    first_label: dict = {}
    for g, lab in zip(groups, labels):
        first_label.setdefault(g, lab)
    if len(first_label) < k:
        raise InputError(f"{k} folds need at least {k} recordings; there are {len(first_label)}: "
                         "lower --cv or add recordings")
    by_label: dict[str, list] = {}
    for g, lab in first_label.items():
        by_label.setdefault(lab, []).append(g)
    thin = sorted(lab for lab, gs in by_label.items() if len(gs) < 2)
    if thin:
        raise InputError(f"label(s) {thin} have one trial (manifest line) each: a fold without it would train a "
                         "model that never saw the label; record each texture at least twice, or split a long "
                         "recording into several lines with start and end")
    rng = np.random.default_rng(seed)
    fold_of, turn = {}, 0
    for lab in sorted(by_label):
        gs = sorted(by_label[lab], key=str)
        for i in rng.permutation(len(gs)):
            fold_of[gs[i]] = turn % k
            turn += 1
    return np.array([fold_of[g] for g in groups], dtype=int)
