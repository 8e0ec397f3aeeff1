"""Pieces shared by the experiments: classification rates and the plain-data description of their runs.

The runs are described by :class:`Run` and :class:`Plan`. The training data (texture features,
the train/test split, the default epochs) come from :mod:`supramodal.training`.
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from supramodal.banks import Bank, bank_by_name
from supramodal.features import DEFAULT_WINDOW, FEATURES
from supramodal.mlp import DEFAULT_EPOCHS, train_mlp
from supramodal.model import TextureModel
from supramodal.pipeline import window_length
from supramodal.textures import TextureSet
from supramodal.training import split, texture_features

#: Seconds per texture in ``--quick`` mode (40 windows: 30 to train, 10 to test).
QUICK_DURATION = 4.0
BANKS = ("whisker", "cochlea")
#: The help of the ``--augment`` flag of the experiments whose networks may train on gain-augmented windows
#: (``newtouch``, ``change``: :func:`two_sense_sets_main`, ``supramodal experiment``).
AUGMENT_HELP = ("gain augmentation of every network's training windows (supramodal.model.GainAugment: 4 more "
                "copies of each, gains exp(N(0, 0.03)); per vibrissa for the whiskers, one level for the "
                "microphone; seeded by --seed); the networks cost 5 times the CPU (default: none)")


@dataclass(frozen=True)
class Run:
    """One independent run of an experiment, as data (executed by :mod:`.runner`).

    Attributes
    ----------
    key : tuple
        Names the run, unique within a plan; made of str, int and float. With
        ``seeded``, the run's seed is derived from the experiment's seed and this key.
    fn : callable
        A module-level function, called as ``fn(**kwargs, progress=...)`` (and
        ``seed=...`` if ``seeded``); returns plain data.
    kwargs : dict
        Picklable arguments.
    cost : float
        Relative cost estimate, in seconds of one core (only the schedule depends on it).
    seeded : bool
        Whether ``fn`` takes a ``seed``.
    """

    key: tuple
    fn: Callable
    kwargs: dict = field(default_factory=dict)
    cost: float = 1.0
    seeded: bool = True


@dataclass(frozen=True)
class Plan:
    """An experiment: its runs, and how to assemble their results (``{key: result}``) into one dict."""

    runs: list
    assemble: Callable


def quick_set(texture_set: TextureSet, quick: bool) -> TextureSet:
    """Return the texture set, shortened to :data:`QUICK_DURATION` seconds per texture in quick mode."""
    return dataclasses.replace(texture_set, duration=QUICK_DURATION) if quick else texture_set


def estimate_cost(texture_set: TextureSet, bank: Bank, n_features: int, epochs: int = DEFAULT_EPOCHS) -> float:
    """Rough seconds of one core for :func:`rates_of` (features, then one network per feature)."""
    samples = len(texture_set.textures) * texture_set.duration * texture_set.fs
    windows = len(texture_set.textures) * texture_set.duration / DEFAULT_WINDOW
    c = bank.channels
    return samples * c * 5e-8 + n_features * windows * (c * c + 8 * c) * epochs * 2e-9 + 0.5


def two_sense_sets_main(argv, module: str, description: str, run: Callable, table: Callable[[dict], str],
                        quick: str, augment: str | None = None) -> int:
    """Run the command line of an experiment over random two-sense sets (``python -m supramodal.experiments.NAME``).

    Its options are ``--quick`` (its help: ``quick``; 2 sets), ``--sets``, ``--seed``, ``--epochs``,
    ``--jobs``; it runs ``run(sets, quick, epochs, seed, progress, jobs)`` and prints ``table`` of
    its result. ``augment``: the help of an ``--augment`` flag, for a ``run`` that takes ``augment`` (a
    :class:`~supramodal.model.GainAugment` of the default copies and spread, seeded by ``--seed``); None:
    no such flag.
    """
    import argparse

    p = argparse.ArgumentParser(prog=f"python -m supramodal.experiments.{module}", description=description)
    p.add_argument("--quick", action="store_true", help=f"{quick} and 2 sets (default: --sets)")
    p.add_argument("--sets", type=int, default=5, help="random two-sense texture sets (default 5)")
    p.add_argument("--seed", type=int, default=0, help="first set's seed and the networks' seed (default 0)")
    p.add_argument("--epochs", type=int, default=DEFAULT_EPOCHS, help=f"iRPROP- epochs (default {DEFAULT_EPOCHS})")
    p.add_argument("--jobs", type=int, help="worker processes (default: all cores)")
    if augment is not None:
        p.add_argument("--augment", action="store_true", help=augment)
    args = p.parse_args(argv)
    more = {}
    if getattr(args, "augment", False):
        from supramodal.model import GainAugment

        more["augment"] = GainAugment(seed=args.seed)
    print(table(run(2 if args.quick else args.sets, args.quick, args.epochs, args.seed, progress_to_stderr,
                    args.jobs, **more)))
    return 0


def augment_line(result: dict) -> str:
    """Return the line of an experiment's table that says its networks' gain augmentation (``result["augment"]``)."""
    augment = result.get("augment")
    return ("gain augmentation of the networks' training windows: "
            + ("none" if augment is None else f"{augment['copies']} copies, spread {augment['spread']:g} "
               "(per vibrissa for the whiskers, one level for the microphone)"))


def progress_to_stderr(message: str) -> None:
    """Default progress reporter of long experiments: one line on stderr, in one write.

    One write, so that the lines of parallel worker processes do not interleave.
    """
    sys.stderr.write(message + "\n")
    sys.stderr.flush()


def default_bank(texture_set: TextureSet, **kwargs) -> Bank:
    """Return the bank a texture set was made for, at the set's sample rate."""
    return bank_by_name(texture_set.bank, fs=texture_set.fs, **kwargs)


def rates_of(texture_set: TextureSet, bank: Bank, features=FEATURES, epochs: int = DEFAULT_EPOCHS, seed: int = 0,
             progress=None, standardise: bool = True) -> dict:
    """Features of every texture through ``bank``, then one network per feature alone.

    Returns
    -------
    dict
        ``{"features": {feature: {"mean_rate", "per_texture"}}, "timing": {...}}``.
    """
    values, timing = texture_features(texture_set, bank, features, progress=progress)
    return {"features": rates_per_feature(values, texture_set.names, bank, features, epochs, seed, progress,
                                          standardise), "timing": timing}


def rates_per_feature(values: np.ndarray, classes, bank: Bank, features, epochs: int = DEFAULT_EPOCHS,
                      seed: int = 0, progress=None, standardise: bool = True) -> dict:
    """:func:`classification_rates` of each feature alone.

    ``values`` as from :func:`~supramodal.training.texture_features`.
    """
    wlen = window_length(DEFAULT_WINDOW, bank.fs)
    results = {}
    for k, feature in enumerate(features):
        if progress:
            progress(f"{bank.kind} ({bank.channels} channels): training and testing on {feature}")
        results[feature] = classification_rates(values[:, :, k : k + 1], classes, bank, (feature,), wlen,
                                                epochs=epochs, seed=seed, standardise=standardise)
    return results


def classification_rates(values: np.ndarray, classes, bank: Bank, features, window_samples: int,
                         epochs: int = DEFAULT_EPOCHS, seed: int = 0, standardise: bool = True) -> dict:
    """Train on the first part of each texture, test on the rest.

    ``standardise=False`` (an ablation, not the model) feeds the raw feature values to the
    network, without the per-input scaling :class:`~supramodal.model.TextureModel` applies.

    Returns ``{"mean_rate": r, "per_texture": {name: r}}``, rates in [0, 1].
    """
    x_train, y_train, x_test, y_test = split(values)
    if standardise:
        # The rates need the winner alone, which calibration never changes: no calibration folds.
        model = TextureModel.train(x_train, y_train, classes, bank, features, window_samples, epochs=epochs,
                                   seed=seed, calibration_folds=0)
        predicted = model.predict(x_test)
    else:
        mlp, _ = train_mlp(x_train.reshape(len(x_train), -1), y_train, len(classes), epochs=epochs, seed=seed)
        predicted = mlp.predict(x_test.reshape(len(x_test), -1))
    correct = predicted == y_test
    per = {name: float(np.mean(correct[y_test == k])) for k, name in enumerate(classes)}
    return {"mean_rate": float(np.mean(correct)), "per_texture": per}
