"""A trained texture classifier with everything needed to use it, stored as data.

A model file is a NumPy ``.npz`` archive read with ``allow_pickle=False``: the
arrays ``w1, b1, w2, b2, mean, scale`` and ``header``, a JSON text with the
format name and version, the bank, the features, the window, the peak mode, the
class names and how it was trained. Nothing in it is ever executed; every part
is validated on load and anything that does not fit is refused with
:class:`ModelError`.

What a file may ask for is bounded: every member's declared size is checked
before it is read (:data:`MAX_HEADER_BYTES`, :data:`MAX_ARRAY_BYTES`), the
header's nesting before it is parsed (:data:`MAX_HEADER_DEPTH`), and the header's
window, channels and classes against
:data:`supramodal.pipeline.MAX_WINDOW_SAMPLES`,
:data:`supramodal.banks.MAX_CHANNELS` and :data:`MAX_CLASSES`. Every array's shape must follow
from the header: ``layers = [features x channels, hidden, classes]``, ``w1``
(inputs, hidden), ``b1`` (hidden,), ``w2`` (hidden, classes), ``b2`` (classes,),
``mean`` and ``scale`` (inputs,); and the bank's ``kind`` must fit its channels
(a whisker bank's centre frequencies are the whisker table's, a cochlea's
bandwidths the Glasberg-Moore rule's).

Version 2 adds the model's calibration (:mod:`supramodal.calibration`): the header's
``calibration`` object (the window map and the contact pooling, fitted on held-out windows)
and ``novelty`` (false, or the novelty score's method and warp, and since 2026-11-30 its allowance for
a new touch, :meth:`Novelty.header`; ``true`` in files of before the warp; the file then holds the
arrays ``novelty_means`` (classes, inputs), ``novelty_precision`` (inputs, inputs) and
``novelty_quantiles``, validated by :meth:`Novelty.from_parts`). Version 3 (2026-11-30) adds the header's
``networks``: how many networks the model deploys (a calibrated model, its calibration's fold
networks, :class:`~supramodal.mlp.Ensemble`), each of ``w1 b1 w2 b2`` then stacked on a first axis of
that length. A version 2 file holds one network and loads as it did. A version 1 file still
loads: its model is *uncalibrated* (:attr:`TextureModel.calibrated` is False), its posteriors
the normalised outputs, and it cannot say "unknown".
"""

from __future__ import annotations

import json
import math
import zipfile
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from supramodal.banks import COCHLEA_B_MIN, COCHLEA_Q_EAR, ERB_TO_B, WHISKER_TABLE, Bank, erb
from supramodal.calibration import (
    DEFAULT_CALIBRATION_FOLDS,
    NOVELTY_TOUCH_SPREAD,
    Calibration,
    HeldOutLogits,
    Novelty,
    OutOfFold,
    calibration_line,
    calibration_of_held_out,
    fold_scaling,
    input_scaling,
    normalised_log_posteriors,
    recalibrate,
    train_fold_networks,
)
from supramodal.calibration import calibration_folds as calibration_folds_of
from supramodal.checks import CLASS_NAME_HELP, is_class_name
from supramodal.errors import InputError
from supramodal.features import check_features
from supramodal.jsondata import parse_json_text
from supramodal.mlp import DEFAULT_EPOCHS, EARLY_STOP_PATIENCE, MLP, Ensemble, NetworkTask, rescaled, train_networks
from supramodal.peaks import PEAK_MODES
from supramodal.pipeline import MAX_WINDOW_SAMPLES

MODEL_FORMAT = "supramodal-model"
MODEL_VERSION = 3
#: Versions this program reads (1: before calibration, its models load uncalibrated; 2: one network).
MODEL_VERSIONS = (1, 2, 3)
#: The first version whose header says its ``networks`` (an :class:`~supramodal.mlp.Ensemble`'s members).
NETWORKS_VERSION = 3
#: Most networks a model file may hold (a model deploys its calibration's fold networks, 3 by default).
MAX_NETWORKS = 64
_ARRAYS = ("w1", "b1", "w2", "b2", "mean", "scale")
#: Arrays of a model's novelty score, present when its header says ``"novelty": true``.
NOVELTY_ARRAYS = ("novelty_means", "novelty_precision", "novelty_quantiles")

#: Most classes a model may name.
MAX_CLASSES = 1024
#: Largest header member, bytes as stored (numpy stores text as 4 bytes a character: 1 M characters).
MAX_HEADER_BYTES = 2**22
#: Deepest nesting of the header's JSON (the format nests 3 levels; ``training`` is free-form).
MAX_HEADER_DEPTH = 16
#: Largest array member a model file may declare, bytes (a 1024-channel, 1024-class model
#: with 1024 hidden units takes 25 MB).
MAX_ARRAY_BYTES = 2**28


class ModelError(InputError):
    """A model file is missing, corrupt, of another format, or does not fit the scene."""


def _check_member_size(npz, name: str, max_bytes: int, path) -> None:
    """Refuse a member whose declared array (its .npy header, read alone) is larger than ``max_bytes``.

    numpy allocates an array of the declared shape before reading a member's data,
    so a few bytes declaring a huge shape would otherwise end in a MemoryError.
    """
    member = name + ".npy" if name + ".npy" in npz.zip.namelist() else name
    with npz.zip.open(member) as f:
        version = np.lib.format.read_magic(f)          # ValueError if not a .npy member
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ModelError(f"{path}: member {name!r} uses .npy format version {version}; this program reads "
                             "1.0 and 2.0 (as numpy.savez writes)")
    size = math.prod(shape) * dtype.itemsize
    if size > max_bytes:
        raise ModelError(f"{path}: array {name!r} declares shape {shape} of {dtype}, {size} bytes, more than the "
                         f"{max_bytes} a model file may hold "
                         f"({'MAX_HEADER_BYTES' if name == 'header' else 'MAX_ARRAY_BYTES'}"
                         "); the file is damaged or not a supramodal model")


def _bank_kind_problem(bank: Bank) -> str | None:
    """Return what makes ``bank``'s channels contradict its ``kind``, or None if they fit."""
    if bank.kind == "whisker":
        table = {f"{row}{arc + 1}": cf for row, cfs in WHISKER_TABLE.items() for arc, cf in enumerate(cfs)}
        for name, cf in zip(bank.names, bank.cf):
            if name not in table or not np.isclose(cf, table[name], rtol=1e-9, atol=0):
                return (f"channel {name!r} at {cf:g} Hz is not a whisker of the table "
                        f"(whiskers are {', '.join(list(table)[:3])}, ... at their resonances)")
    elif bank.kind == "cochlea":
        want = ERB_TO_B * erb(bank.cf, COCHLEA_Q_EAR, COCHLEA_B_MIN)
        k = np.flatnonzero(~np.isclose(bank.b, want, rtol=1e-9, atol=0))
        if k.size:
            i = int(k[0])
            return (f"channel {bank.names[i]!r} has b = {bank.b[i]:g} Hz, but a cochlea channel at "
                    f"{bank.cf[i]:g} Hz has b = {want[i]:g} Hz (Glasberg-Moore)")
    elif bank.kind != "custom":
        return "the kind is none of 'whisker', 'cochlea', 'custom'"
    return None


#: Features that scale linearly with a channel's gain (a touch's gain multiplies every peak's
#: amplitude A_k, not its frequency f_k).
GAIN_LINEAR_FEATURES = ("Af", "A")
#: How a :class:`GainAugment` draws its gains, as scenes and ``train --augment-gains`` name it: one per
#: channel (a whisker array: each vibrissa its own gain) or one for all channels (a microphone: one level).
GAIN_MODES = ("per-channel", "shared")
#: Most copies of each training window a :class:`GainAugment` may make (its networks cost ``1 + copies``
#: times the CPU and the memory of their training rows).
MAX_AUGMENT_COPIES = 32
#: Largest spread (standard deviation of the log gains) of a :class:`GainAugment`: ``exp(N(0, 1))``
#: already gains of 0.37..2.7 within one standard deviation, past any touch's.
MAX_AUGMENT_SPREAD = 1.0
#: A :class:`GainAugment`'s default spread (the two-sense world's per-touch spread, ``WHISKER_TOUCH_SPREAD``).
DEFAULT_AUGMENT_SPREAD = 0.03


@dataclass(frozen=True)
class GainAugment:
    """Gain augmentation of training windows (opt-in, :meth:`TextureModel.train`'s ``augment``).

    ``copies`` more copies of every training window, each with its own gains ``exp(N(0, spread))``, one
    per channel (``per_channel``: a vibrissa's own gain) or one for all channels (a microphone's level),
    multiplying the columns of the gain-linear features (:data:`GAIN_LINEAR_FEATURES`); ``f`` is left as it is.
    ``per_channel = None``: by the bank (:meth:`resolved`): per channel for a whisker bank, one level for
    a cochlea. Drawn from ``seed`` and the network's stream (0: the model's, ``f + 1``: calibration fold
    ``f``'s), so the same for any number of workers.

    Why: each touch of a surface has gains of its own; a network that met every texture on one or two
    touches learns their gains, and its calibration, fitted on held-out touches, says less than a new
    touch gives. On the two-sense world's new touch (``python -m supramodal.experiments.newtouch --augment``,
    5 sets, 2026-11-30) the late fusion's ECE went from 0.07-0.16 to 0.03-0.07 and its log loss from
    0.30-0.68 to 0.14-0.25, each sense's accuracy unchanged on average; the networks cost ``1 + copies``
    times the CPU (a set's training, 4 times). A scene asks for it in ``[model]`` (``augment_copies``,
    ...), ``supramodal train`` with ``--augment-gains``; the model file keeps it (``training["augment"]``,
    :attr:`TextureModel.augment`), and copies of a model's configuration
    (:func:`supramodal.fused_model.out_of_fold_logits`, ``evaluate --cv``) are augmented alike.
    ``spread = 0`` gives the model without it, to the bit (iRPROP- follows the gradients' signs, which
    exact copies do not change).
    """

    copies: int = 4
    spread: float = DEFAULT_AUGMENT_SPREAD
    per_channel: bool | None = True
    seed: int = 0

    def resolved(self, kind: str) -> GainAugment:
        """Return the augmentation with ``per_channel`` said.

        Where it is None, by a bank of ``kind``: per channel for ``"whisker"``, one level for ``"cochlea"`` and
        for any other bank (a custom bank's channels may be one sensor's: say ``per_channel`` for an array).
        """
        if self.per_channel is not None:
            return self
        return replace(self, per_channel=kind == "whisker")

    @property
    def gains(self) -> str:
        """``per_channel`` in the words of :data:`GAIN_MODES` (``"by bank"`` where it is None)."""
        return "by bank" if self.per_channel is None else GAIN_MODES[0] if self.per_channel else GAIN_MODES[1]

    def to_dict(self) -> dict:
        """Return what a model file keeps of it (``training["augment"]``): plain JSON values."""
        return {"copies": int(self.copies), "spread": float(self.spread), "per_channel": self.per_channel,
                "seed": int(self.seed)}

    @classmethod
    def from_dict(cls, d, bad) -> GainAugment:
        """Return the augmentation a model file says (:meth:`to_dict`), every value checked.

        ``bad(message)`` makes the error to raise.
        """
        if not isinstance(d, dict) or set(d) != {"copies", "spread", "per_channel", "seed"}:
            raise bad(f"'training' 'augment' must be an object of copies, spread, per_channel and seed, got {d!r}")
        copies, spread, per_channel, seed = d["copies"], d["spread"], d["per_channel"], d["seed"]
        if not (type(copies) is int and 0 <= copies <= MAX_AUGMENT_COPIES):
            raise bad(f"'training' 'augment' copies must be an integer 0..{MAX_AUGMENT_COPIES}, got {copies!r}")
        if isinstance(spread, bool) or not isinstance(spread, (int, float)) or not 0 <= spread <= MAX_AUGMENT_SPREAD:
            raise bad(f"'training' 'augment' spread must be a number 0..{MAX_AUGMENT_SPREAD:g}, got {spread!r}")
        if per_channel not in (True, False, None) or not (type(seed) is int and 0 <= seed < 2**32):
            raise bad(f"'training' 'augment': per_channel must be true, false or null and seed an integer "
                      f"0..2**32 - 1, got {per_channel!r} and {seed!r}")
        return cls(copies, float(spread), per_channel, seed)

    def describe(self) -> str:
        """In words, one line (``train`` prints it)."""
        one = {True: "one gain per channel", False: "one gain for all channels", None: "gains by bank"}
        return (f"gain augmentation: {self.copies} more copies of each training window, {one[self.per_channel]}, "
                f"exp(N(0, {self.spread:g})) (seed {self.seed}); held-out windows, scaling and calibration on "
                f"the originals; the networks cost {1 + self.copies} times the CPU")

    def for_inputs(self, features, channels: int) -> GainCopies:
        """Return the callable ``(rows (n, features x channels), labels, stream) -> (rows, labels)``.

        It is for :func:`supramodal.calibration.fold_tasks` and a model's network of all the windows.
        """
        return GainCopies(self, tuple(features), int(channels))


def touch_allowance(features, bank: Bank, augment: GainAugment | None = None) -> tuple[tuple[int, ...], float]:
    """Return the novelty's allowance for a new touch of a model: which inputs share a gain, and the least spread.

    The gains are those a :class:`GainAugment` draws (per channel for a whisker bank, one level for
    any other, or as ``augment`` says), on the gain-linear features' inputs (feature-major, as the
    model flattens a window); the least spread is
    :data:`~supramodal.calibration.NOVELTY_TOUCH_SPREAD`, or ``augment``'s spread where larger
    (:func:`supramodal.calibration.fit_novelty`'s ``touch_groups`` and ``touch_floor``).
    """
    if augment is not None and not (augment.copies and augment.spread > 0):
        augment = None              # copies of gains 1 are the model without it, to the bit: its allowance too
    per_channel = (augment if augment is not None else GainAugment(per_channel=None)).resolved(bank.kind).per_channel
    groups = tuple((c if per_channel else 0) if f in GAIN_LINEAR_FEATURES else -1
                   for f in features for c in range(bank.channels))
    return groups, max(NOVELTY_TOUCH_SPREAD, 0.0 if augment is None else float(augment.spread))


@dataclass(frozen=True)
class GainCopies:
    """A :class:`GainAugment` on inputs of ``features`` x ``channels``.

    Called ``(rows, labels, stream)``, it gives the rows and their copies, and their labels;
    :attr:`factor`, how many rows it makes of one. ``part``: which sense's columns these are in an early
    fusion's inputs (:class:`~supramodal.fused_model.EarlyGainCopies`): each sense draws its own gains
    (part 0 draws as a one-sense model does).
    """

    augment: GainAugment
    features: tuple[str, ...]
    channels: int
    part: int = 0

    @property
    def factor(self) -> int:
        """Rows out per row in (the networks' work grows by it)."""
        return 1 + self.augment.copies

    def __call__(self, x, y, stream: int):
        """Return the rows ``x`` and their copies, and the labels ``y`` repeated, for network ``stream``."""
        a = self.augment
        linear = np.array([f in GAIN_LINEAR_FEATURES for f in self.features])
        if not a.copies or not linear.any():
            return x, y
        if a.per_channel is None:
            raise ValueError("GainAugment.per_channel is None (by bank): resolve it with .resolved(kind) first")
        # part 0's key is a one-sense model's own: its gains, and so its models, are those of before
        key = [a.seed, stream] if self.part == 0 else [a.seed, stream, self.part]
        rng = np.random.default_rng(np.random.SeedSequence(key))
        v = np.asarray(x).reshape(len(x), len(self.features), self.channels)
        out = [v]
        for _ in range(a.copies):
            g = np.exp(rng.normal(0.0, a.spread, (len(v), self.channels if a.per_channel else 1)))
            c = v.copy()
            c[:, linear, :] *= g[:, None, :]
            out.append(c)
        return (np.concatenate(out).reshape(len(x) * (1 + a.copies), -1),
                np.tile(np.asarray(y), 1 + a.copies))


class Deployed(NamedTuple):
    """What :func:`train_deployed` trains: a model's networks, their input scaling, training and calibration."""

    network: MLP | Ensemble
    mean: np.ndarray
    scale: np.ndarray
    training: dict
    calibration: Calibration | None
    novelty: Novelty | None
    out_of_fold: OutOfFold | None


def train_deployed(x, labels, n_classes: int, hidden: int | None, epochs: int, seed: int, groups, folds: int,
                   jobs: int = 1, augment=None, touch=None, progress=None, calibration_progress=None,
                   patience: int | None = EARLY_STOP_PATIENCE) -> Deployed:
    """Train what a model deploys on raw input rows ``x`` (n, inputs): its network(s) and their calibration.

    With ``folds`` (> 0), the calibration's fold networks (:func:`~supramodal.calibration.fold_tasks`),
    each trained on all folds but one and scoring that one's windows; the calibration, the novelty score
    and the change detector's held-out statistics are fitted on those held-out logits
    (:func:`~supramodal.calibration.calibration_of_held_out`, :func:`with_held_out_changes`), and the model
    deploys the fold networks themselves, as an :class:`~supramodal.mlp.Ensemble` (the mean of their
    logits) on ``x``'s own scaling. No network of all the windows is trained: the calibration is then fitted on the
    deployed networks' own held-out logits (applied to their mean), and the model costs its fold networks (3 by
    default, stopped early: about one network of all the windows trained every epoch; with 10 folds and a
    network of its own, as before 2026-11-30, about 11 times).
    Without folds (0): one network of all the windows, uncalibrated.

    Parameters
    ----------
    x : ndarray, shape (n, inputs)
    labels : array of int, shape (n,)
    n_classes, hidden, epochs, seed
        As :func:`supramodal.mlp.train_mlp`'s, for every network.
    groups : sequence, length n, or None
        Each window's recording (None: one per label): the folds (:func:`~supramodal.calibration.calibration_folds`).
    folds : int
        The calibration's folds; 0: none.
    jobs : int
        Worker processes (:func:`supramodal.mlp.train_networks`; the result is the same for any).
    augment : callable, optional
        Each network's training rows augmented (:meth:`GainAugment.for_inputs`; stream 0 is the one network
        of all the windows, ``f + 1`` fold ``f``'s); the held-out rows, scaling, calibration and novelty
        see the originals.
    touch : (groups, floor) or (groups, floors, parts), optional
        The novelty's allowance for a new touch (:func:`touch_allowance`; an early fusion's, each sense its
        own spread: :func:`supramodal.fused_model.early_touch_allowance`). Default None: none.
    progress : callable(epoch, mse), optional
        The last network's epochs (from workers: the last epoch of the network kept, alone).
    calibration_progress : callable(str), optional
        One line per fold network.
    patience : int or None
        Each fold network stops early on its own held-out windows once their error has not fallen for
        ``patience`` epochs, and all are deployed at the epochs best for them together
        (:func:`~supramodal.calibration.train_fold_networks`; default
        :data:`~supramodal.mlp.EARLY_STOP_PATIENCE`). None: every epoch, as before
        2026-11-30. A network without folds has no held-out windows and trains every epoch.

    Returns
    -------
    Deployed
        The network (an ensemble of the fold networks, or one), the input scaling of ``x`` they take, the
        ``training`` a model file keeps (algorithm, epochs, seed, final_mse: the networks' mean, windows;
        with folds ``patience`` and ``network_epochs``, each fold network's) and the calibration, novelty
        and held-out logits (None without folds).
    """
    y = np.asarray(labels)
    mean, scale = input_scaling(x)         # a constant input carries nothing; scale 1 keeps it at 0
    info = {"algorithm": "iRPROP-", "seed": seed, "windows": int(len(x))}
    if not folds:
        xm, ym = (x, y) if augment is None else augment(x, y, 0)
        one, = train_networks([NetworkTask((xm - mean) / scale, ym, n_classes, hidden, epochs, seed)], jobs,
                              watch=(0, progress))
        return Deployed(one.network, mean, scale, {**info, "epochs": len(one.history), "final_mse": one.history[-1]},
                        None, None, None)
    g = y if groups is None else np.asarray(groups)
    fold_of, by = calibration_folds_of(y, g, folds, seed)
    held_out = HeldOutLogits(y, fold_of, folds, n_classes, calibration_progress)
    results = train_fold_networks(x, y, n_classes, fold_of, folds, hidden, epochs, seed, augment, patience, jobs,
                                  done=held_out.told, redone=held_out.retold, watch=(held_out.networks - 1, progress))
    allowance = dict(zip(("touch_groups", "touch_floor", "touch_parts"), touch or ()))
    calibration, novelty, out_of_fold = calibration_of_held_out(x, y, n_classes, g, fold_of, by, folds,
                                                                held_out.logits, **allowance, scaling=(mean, scale))
    calibration = with_held_out_changes(calibration, held_out.logits, y, g, fold_of)
    # each fold network standardised its rows by their own mean and scale: re-expressed on the model's
    members = [rescaled(r.network, *fold_scaling(x, fold_of, f), mean, scale) for f, r in zip(held_out.order, results)]
    info.update(epochs=epochs, patience=patience, network_epochs=[len(r.history) for r in results],
                final_mse=float(np.mean([r.history[-1] for r in results])))
    return Deployed(Ensemble(tuple(members)), mean, scale, info, calibration, novelty, out_of_fold)


@dataclass
class TextureModel:
    """Input scaling + MLP + the metadata that says what the inputs mean.

    Inputs are feature windows of shape (n, features, channels), flattened
    feature-major, standardised with the training set's mean and scale.
    """

    bank: Bank
    features: tuple[str, ...]
    window_samples: int
    peak_mode: str
    classes: tuple[str, ...]
    mean: np.ndarray
    scale: np.ndarray
    mlp: MLP | Ensemble
    training: dict = field(default_factory=dict)
    peak_threshold: float = 0.0
    calibration: Calibration | None = None
    novelty: Novelty | None = None
    #: The calibration's held-out logits of the training windows (in memory after :meth:`train`,
    #: never in the file; :class:`~supramodal.calibration.OutOfFold`), or None.
    out_of_fold: OutOfFold | None = field(default=None, repr=False, compare=False)

    @property
    def n_inputs(self) -> int:
        """The network's inputs per window: features x channels."""
        return len(self.features) * self.bank.channels

    @property
    def calibrated(self) -> bool:
        """Whether the posteriors are calibrated.

        A model trained by this version is; a version 1 file is not.
        """
        return self.calibration is not None

    @classmethod
    def train(cls, values: np.ndarray, labels, classes, bank: Bank, features, window_samples: int,
              peak_mode: str = "maxima", epochs: int = DEFAULT_EPOCHS, seed: int = 0, hidden: int | None = None,
              progress=None, peak_threshold: float = 0.0, groups=None,
              calibration_folds: int = DEFAULT_CALIBRATION_FOLDS, calibration_progress=None,
              jobs: int = 1, augment: GainAugment | None = None,
              patience: int | None = EARLY_STOP_PATIENCE) -> TextureModel:
        """Fit the scaling and the networks on feature windows, and their calibration (:func:`train_deployed`).

        A calibrated model deploys its calibration's fold networks, the mean of their logits
        (:class:`~supramodal.mlp.Ensemble`); without calibration folds, one network of all the windows.

        Parameters
        ----------
        values : ndarray, shape (n, features, channels)
        labels : array of int, shape (n,)
            Index into ``classes`` of each window.
        classes : sequence of str
        epochs, seed, hidden
            See :func:`supramodal.mlp.train_mlp`.
        progress : callable(epoch, mse), optional
            The last network's epochs.
        groups : sequence, length n, optional
            Each window's recording (windows of one recording consecutive, in time order): the
            calibration's held-out windows are whole recordings where there are enough of
            them (:func:`supramodal.calibration.calibration_folds`). Default: one per label.
        calibration_folds : int
            Folds whose held-out windows fit the calibration and the novelty score, each trained by
            a network of the others that the model deploys (default
            :data:`~supramodal.calibration.DEFAULT_CALIBRATION_FOLDS`). 0: one network of all the
            windows, no calibration (the normalised outputs, as version 1).
        calibration_progress : callable(str), optional
            One line per calibration fold.
        jobs : int
            Worker processes for the networks, trained side by side
            (:func:`supramodal.mlp.train_networks`): the model is the same for any; with more
            than one, ``progress`` is told the network's last epoch alone.
        augment : GainAugment, optional
            Gain augmentation of the training windows of every network (default None: none); the
            held-out windows, the scaling,
            the calibration map and the novelty score see the original windows only. Its gains by bank
            (``per_channel`` None) are resolved with ``bank``'s kind; the model keeps it
            (:attr:`augment`).
        patience : int or None
            Each fold network stops early on its held-out windows (:func:`train_deployed`; default
            :data:`~supramodal.mlp.EARLY_STOP_PATIENCE` epochs); None: every epoch.
        """
        features = check_features(features)
        values = np.asarray(values, dtype=np.float64)
        expected = (len(features), bank.channels)
        if values.ndim != 3 or values.shape[1:] != expected:
            raise InputError(f"feature windows must have shape (n, {expected[0]}, {expected[1]}), got {values.shape}")
        x = values.reshape(len(values), -1)
        augment = None if augment is None else augment.resolved(bank.kind)
        d = train_deployed(x, labels, len(classes), hidden, epochs, seed, groups, calibration_folds, jobs,
                           None if augment is None else augment.for_inputs(features, bank.channels),
                           touch_allowance(features, bank, augment), progress, calibration_progress, patience)
        if augment is not None:
            d.training["augment"] = augment.to_dict()
        return cls(bank, features, int(window_samples), peak_mode, tuple(classes), d.mean, d.scale, d.network,
                   d.training, float(peak_threshold), d.calibration, d.novelty, d.out_of_fold)

    @property
    def augment(self) -> GainAugment | None:
        """Return the gain augmentation its networks were trained with, or None.

        From ``training["augment"]``, checked when the file was read; None: none, or a model file from before it.
        """
        d = self.training.get("augment")
        return None if d is None else GainAugment.from_dict(d, ModelError)

    def _inputs(self, values: np.ndarray) -> np.ndarray:
        values = np.asarray(values, dtype=np.float64)
        expected = (len(self.features), self.bank.channels)
        if values.ndim != 3 or values.shape[1:] != expected:
            raise InputError(f"feature windows must have shape (n, {expected[0]}, {expected[1]}), got {values.shape}")
        return (values.reshape(len(values), -1) - self.mean) / self.scale

    def outputs(self, values: np.ndarray) -> np.ndarray:
        """Output unit activations in [0, 1], shape (n, classes)."""
        return self.mlp.outputs(self._inputs(values))

    def logits(self, values: np.ndarray) -> np.ndarray:
        """Return the output units' logits, shape (n, classes) (finite where the outputs round to 0 or 1)."""
        return self.mlp.logits(self._inputs(values))

    def log_posteriors(self, values: np.ndarray) -> np.ndarray:
        """Log-posteriors of the classes per window, shape (n, classes).

        Calibrated when the model is (:attr:`calibrated`), else the normalised outputs; finite,
        computed without clipping.
        """
        return log_posteriors_of(self.logits(values), self.calibration)

    def posteriors(self, values: np.ndarray) -> np.ndarray:
        """Posteriors per window (rows sum to 1), shape (n, classes); see :meth:`log_posteriors`."""
        return np.exp(self.log_posteriors(values))

    def novelty_score(self, values: np.ndarray) -> np.ndarray:
        """How unlike every training texture each window is, shape (n,).

        The score is :class:`~supramodal.calibration.Novelty`'s; a model without a novelty score
        raises.
        """
        if self.novelty is None:
            raise ModelError("this model has no novelty score (trained before version 2, or without "
                             "calibration): retrain it with `supramodal train` to detect unknown textures")
        return self.novelty.score(self._inputs(values))

    def recalibrated(self, values: np.ndarray, labels, groups=None, what: str = "") -> TextureModel:
        """Return the model with its calibration and novelty thresholds fitted anew, its network kept.

        The calibration (window map, caps, contact pooling) and the novelty thresholds are fitted
        on labelled windows of a new touch, session or sensor (:func:`supramodal.calibration.recalibrate`).

        Parameters
        ----------
        values : ndarray, shape (n, features, channels)
            Windows the network never trained on.
        labels : array of int, shape (n,)
            Index into :attr:`classes`; every class at least once.
        groups : sequence, length n, optional
            Each window's recording (default: one per label).
        what : str
            What the windows were, kept in the calibration's ``fitted_on``.
        """
        y = np.asarray(labels)
        x = self._inputs(values)
        groups = y if groups is None else np.asarray(groups)
        z = self.mlp.logits(x)
        calibration, novelty = recalibrate(z, y, groups, x, self.novelty, what)
        calibration = with_held_out_changes(calibration, z, y, groups, np.zeros(len(y), dtype=int))
        if self.calibration is not None:        # what it replaces, in words: the file says both
            before = calibration_line(self.calibration.fitted_on)
            calibration = replace(calibration, fitted_on={**calibration.fitted_on, "recalibrated_from": before})
        return replace(self, calibration=calibration, novelty=novelty, out_of_fold=None, training=dict(self.training))

    def predict(self, values: np.ndarray) -> np.ndarray:
        """Winner-take-all class index per window, shape (n,).

        The largest logit: the largest output wherever that is unique, and a winner still where outputs
        tie at 1.0 (as an ensemble's mean of sure logits often does), as the node decides.
        """
        return np.argmax(self.logits(values), axis=1)

    @classmethod
    def train_for(cls, pipeline, values, labels, classes, **kwargs) -> TextureModel:
        """:meth:`train` with the bank, features, window and peak settings of a FeaturePipeline."""
        return cls.train(values, labels, classes, pipeline.bank, pipeline.features, pipeline.window_samples,
                         peak_mode=pipeline.peaks.mode, peak_threshold=pipeline.peaks.threshold, **kwargs)

    def pipeline(self, **kwargs):
        """Return a FeaturePipeline computing exactly the inputs this model takes.

        Extra keyword arguments such as ``dtype`` or ``nonfinite`` are passed on.
        """
        from supramodal.pipeline import FeaturePipeline

        return FeaturePipeline(self.bank, self.features, self.window_samples / self.bank.fs, peak_mode=self.peak_mode,
                               peak_threshold=self.peak_threshold, **kwargs)

    def check_pipeline(self, pipeline) -> None:
        """:meth:`check_fits` against everything a FeaturePipeline computes with."""
        self.check_fits(pipeline.bank, pipeline.features, pipeline.window_samples, pipeline.peaks.mode,
                        pipeline.peaks.threshold)

    def check_fits(self, bank: Bank, features, window_samples: int, peak_mode: str | None = None,
                   peak_threshold: float | None = None) -> None:
        """Raise :class:`ModelError` naming what differs if the model was not made for this pipeline.

        ``peak_mode`` and ``peak_threshold`` are checked when given.
        """
        check_sense_fits((self.bank, self.features, self.window_samples, self.peak_mode, self.peak_threshold),
                         bank, features, window_samples, peak_mode, peak_threshold)

    # -- files ---------------------------------------------------------------------------------

    def header(self) -> dict:
        """Return the model file's JSON header: format, version, sense, classes, layers, training, calibration."""
        return {
            "format": MODEL_FORMAT,
            "version": MODEL_VERSION,
            **sense_header(self.bank, self.features, self.window_samples, self.peak_mode, self.peak_threshold),
            "classes": list(self.classes),
            "layers": list(self.mlp.shape),
            "networks": networks_of(self.mlp),
            "training": self.training,
            **calibration_header(self.calibration, self.novelty),
        }

    def save(self, path) -> Path:
        """Write the model, an ``.npz`` archive, to exactly ``path``; return the path written.

        No suffix is added, so that :meth:`load` reads it back from the same name.
        """
        return save_model_archive(path, self.header(), self.mlp, self.mean, self.scale, novelty_arrays(self.novelty))

    @classmethod
    def load(cls, path) -> TextureModel:
        """Read and validate a model file; :class:`ModelError` says what is wrong with it."""
        header, arrays = read_model_archive(path, _ARRAYS, optional=NOVELTY_ARRAYS)
        return cls._from_parts(Path(path), header, arrays)

    @classmethod
    def _from_parts(cls, path, header, arrays) -> TextureModel:
        def bad(msg):
            return ModelError(f"{path}: {msg}")

        if not isinstance(header, dict) or header.get("format") != MODEL_FORMAT:
            raise bad(f"not a {MODEL_FORMAT} file "
                      f"(format is {header.get('format') if isinstance(header, dict) else None!r})")
        if type(header.get("version")) is not int or header["version"] not in MODEL_VERSIONS:   # true == 1 in Python
            raise bad(f"model format version {header.get('version')!r} is not supported (this program reads "
                      f"versions {', '.join(map(str, MODEL_VERSIONS))}); retrain the model with this version")
        check_header_keys(header, {*SENSE_KEYS, "classes"}, bad)
        bank, features, window, peak_mode, threshold = sense_from_header(header, bad)
        classes = classes_from_header(header, bad)
        n_in = len(features) * bank.channels
        mlp, mean, scale = network_from_arrays(header, arrays, n_in, len(classes), bad,
                                               f"{len(features)} feature(s) x {bank.channels} channels")
        training = header.get("training", {})
        if not isinstance(training, dict):
            raise bad("'training' must be an object")
        if training.get("augment") is not None:        # a file from before it has none
            GainAugment.from_dict(training["augment"], bad)
        check_training_patience(training, bad)
        calibration, novelty = calibration_from_parts(header, arrays, n_in, len(classes), bad)
        return cls(bank, features, window, peak_mode, tuple(classes), mean, scale, mlp, training, threshold,
                   calibration, novelty)


def check_sense_fits(trained, bank: Bank, features, window_samples: int, peak_mode: str | None = None,
                     peak_threshold: float | None = None) -> None:
    """Raise :class:`ModelError` naming what differs if windows made so are not the ``trained`` sense's.

    The windows are made with ``bank``, ``features``, ``window_samples`` (and, when given,
    ``peak_mode`` and ``peak_threshold``); ``trained`` is
    ``(bank, features, window_samples, peak_mode, peak_threshold)``.
    """
    t_bank, t_features, t_window, t_mode, t_threshold = trained
    features = check_features(features)
    if not t_bank.matches(bank):
        raise ModelError(
            f"the model was trained on a {t_bank.kind} bank of {t_bank.channels} channels at "
            f"{t_bank.fs:g} Hz, but the pipeline uses a {bank.kind} bank of {bank.channels} channels at "
            f"{bank.fs:g} Hz (or other centre frequencies/bandwidths): use a model trained for this bank"
        )
    if features != tuple(t_features):
        raise ModelError(f"the model takes features {list(t_features)}, the pipeline computes {list(features)}")
    if int(window_samples) != t_window:
        raise ModelError(
            f"the model was trained on windows of {t_window} samples, the pipeline makes "
            f"{window_samples}: set the window to {t_window / t_bank.fs:g} s"
        )
    if peak_mode is not None and peak_mode != t_mode:
        raise ModelError(f"the model was trained on peak mode {t_mode!r}, the pipeline uses {peak_mode!r}")
    if peak_threshold is not None and float(peak_threshold) != t_threshold:
        raise ModelError(f"the model was trained with peak threshold {t_threshold:g}, the pipeline uses "
                         f"{peak_threshold:g}: set [features] peak_threshold = {t_threshold:g}")


#: Header keys that say what one sense's inputs are.
SENSE_KEYS = ("bank", "features", "window_samples", "peak_mode", "peak_threshold")


def sense_header(bank: Bank, features, window_samples: int, peak_mode: str, peak_threshold: float) -> dict:
    """Return the :data:`SENSE_KEYS` of a header: what a sense's feature windows are."""
    return {"bank": bank.to_dict(), "features": list(features), "window_samples": int(window_samples),
            "peak_mode": peak_mode, "peak_threshold": float(peak_threshold)}


def sense_from_header(header: dict, bad) -> tuple[Bank, tuple[str, ...], int, str, float]:
    """``(bank, features, window_samples, peak_mode, peak_threshold)`` from a header's :data:`SENSE_KEYS`.

    Each is validated; ``bad(message)`` makes the error to raise.
    """
    try:
        bank = Bank.from_dict(header["bank"])
        if not (isinstance(header["features"], list) and all(isinstance(f, str) for f in header["features"])):
            raise InputError(f"'features' must be a list of names, got {header['features']!r}")
        features = check_features(header["features"])
    except (KeyError, ValueError) as exc:
        raise bad(f"invalid 'bank' or 'features' in the header: {exc}") from exc
    problem = _bank_kind_problem(bank)
    if problem:
        raise bad(f"'bank': kind {bank.kind!r} does not fit its channels ({problem}); the header does not "
                  "describe the bank the model was trained on: retrain it")
    window = header.get("window_samples")
    if not (isinstance(window, int) and not isinstance(window, bool) and window >= 2):
        raise bad(f"'window_samples' must be an integer >= 2, got {window!r}")
    if window > MAX_WINDOW_SAMPLES:
        raise bad(f"'window_samples' is {window}, more than the {MAX_WINDOW_SAMPLES} samples a window may have "
                  f"(MAX_WINDOW_SAMPLES, {MAX_WINDOW_SAMPLES / bank.fs:g} s at {bank.fs:g} Hz)")
    if header.get("peak_mode") not in PEAK_MODES:
        raise bad(f"'peak_mode' must be one of {PEAK_MODES}")
    threshold = header.get("peak_threshold", 0.0)
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not (0 <= threshold < float("inf")):
        raise bad(f"'peak_threshold' must be a finite number >= 0, got {threshold!r}")
    return bank, features, window, header["peak_mode"], float(threshold)


def classes_from_header(header: dict, bad) -> list[str]:
    """Return a header's ``classes``: a non-empty list of at most :data:`MAX_CLASSES` distinct names."""
    classes = header.get("classes")
    if not (isinstance(classes, list) and classes and all(isinstance(c, str) for c in classes)
            and len(set(classes)) == len(classes)):
        raise bad("'classes' must be a non-empty list of distinct names")
    if len(classes) > MAX_CLASSES:
        raise bad(f"'classes' names {len(classes)} classes, more than the {MAX_CLASSES} a model may have "
                  "(MAX_CLASSES)")
    odd = next((c for c in classes if not is_class_name(c)), None)
    if odd is not None:
        raise bad(f"'classes' holds {odd[:80]!r}, which is not {CLASS_NAME_HELP}: a class name is printed, shown "
                  "and published as it is; train the model again with labels that are plain text")
    return classes


def network_from_arrays(header: dict, arrays: dict, n_in: int, n_classes: int, bad, inputs_are: str):
    """``(MLP, mean, scale)`` from a header's ``layers`` and the arrays :data:`_ARRAYS`.

    Every shape is checked against ``n_in`` inputs (``inputs_are`` says what they are) and
    ``n_classes``.
    """
    layers = header.get("layers")
    if not (isinstance(layers, list) and len(layers) == 3
            and all(isinstance(n, int) and not isinstance(n, bool) for n in layers)
            and layers[0] == n_in and layers[1] >= 1 and layers[2] == n_classes):
        raise bad(f"'layers' is {layers!r}; it must be [inputs, hidden, outputs] = [{n_in}, hidden >= 1, "
                  f"{n_classes}] for {inputs_are} and {n_classes} classes")
    hidden = layers[1]
    # a file of before NETWORKS_VERSION holds one network's arrays; since, each network's on a first axis
    stacked = "networks" in header
    networks = header.get("networks", 1)
    if not (type(networks) is int and 1 <= networks <= MAX_NETWORKS):
        raise bad(f"'networks' must be an integer 1..{MAX_NETWORKS} (MAX_NETWORKS), got {networks!r}")
    lead = (networks,) if stacked else ()
    shapes = {"w1": (*lead, n_in, hidden), "b1": (*lead, hidden), "w2": (*lead, hidden, n_classes),
              "b2": (*lead, n_classes), "mean": (n_in,), "scale": (n_in,)}
    for k, want in shapes.items():
        a = arrays[k]
        if a.dtype.kind != "f" or a.shape != want:
            raise bad(f"array {k} has shape {a.shape} and dtype {a.dtype}; expected float {want} for "
                      f"{inputs_are}, {hidden} hidden units ('layers' {layers}), {n_classes} classes"
                      + (f" and {networks} network(s) ('networks')" if stacked else ""))
        if not np.isfinite(a).all():
            raise bad(f"array {k} contains NaN or Inf")
    if np.any(arrays["scale"] <= 0):
        raise bad("input scale must be > 0 everywhere")
    params = [arrays[k].astype(np.float64) for k in ("w1", "b1", "w2", "b2")]
    members = tuple(MLP(*(p[i] for p in params)) for i in range(networks)) if stacked else (MLP(*params),)
    mlp = members[0] if len(members) == 1 else Ensemble(members)
    return mlp, arrays["mean"].astype(np.float64), arrays["scale"].astype(np.float64)


def check_training_patience(training: dict, bad) -> None:
    """Refuse a model file's ``training.patience`` unless absent, null or a whole number of epochs >= 1.

    What copies of the model's networks stop early by (:func:`supramodal.fused_model.out_of_fold_logits`).
    """
    patience = training.get("patience")
    if patience is not None and (isinstance(patience, bool) or not isinstance(patience, int) or patience < 1):
        raise bad(f"'training.patience' must be null or a whole number of epochs >= 1, got {patience!r}")


def check_header_keys(header: dict, own: set, bad) -> None:
    """Refuse a model header (of a known ``version``) with a key its version does not have, or without ``networks``.

    ``own``: the keys of the file's kind beside those every model file has (format, version, layers,
    training; from version 2 :data:`CALIBRATION_KEYS`, from :data:`NETWORKS_VERSION` ``networks``, which
    it must then say: its arrays would otherwise be read as one network's, with a calibration fitted for
    several).
    """
    version = header["version"]
    known = {"format", "version", "layers", "training", *own}
    if version >= 2:
        known |= set(CALIBRATION_KEYS)
    if version >= NETWORKS_VERSION:
        known.add("networks")
    unknown = set(header) - known
    if unknown:
        raise bad(f"unknown header key(s) {sorted(unknown)}")
    if version >= NETWORKS_VERSION and "networks" not in header:
        raise bad(f"a version {version} header must say its 'networks' (how many networks its arrays hold); the "
                  "file is damaged or was not written by supramodal")


def networks_of(mlp: MLP | Ensemble) -> int:
    """Return how many networks a model's ``mlp`` is (its header's ``networks``)."""
    return len(mlp.members) if isinstance(mlp, Ensemble) else 1


def save_model_archive(path, header: dict, mlp: MLP | Ensemble, mean: np.ndarray, scale: np.ndarray,
                       extra: dict | None = None) -> Path:
    """Write ``header`` (as JSON text), the network's arrays and any ``extra`` named arrays to exactly ``path``.

    The file is an ``.npz``. The networks' arrays are stacked on a first axis (one per network,
    :meth:`~supramodal.mlp.Ensemble.stacked`) where ``header`` says its ``networks``, as every header of
    this version does; else (a header of before) one network's.
    """
    path = Path(path)
    if "networks" in header:
        params = (mlp if isinstance(mlp, Ensemble) else Ensemble((mlp,))).stacked()
    elif isinstance(mlp, Ensemble) and len(mlp.members) > 1:
        raise ValueError("a header without 'networks' holds one network's arrays: give it 'networks' to write "
                         f"an ensemble of {len(mlp.members)}")
    else:
        params = (mlp.members[0] if isinstance(mlp, Ensemble) else mlp).params()
    arrays = {**dict(zip(_ARRAYS, (*params, mean, scale))), **(extra or {})}
    with open(path, "wb") as fh:
        np.savez(fh, header=np.array(json.dumps(header)), **arrays)
    return path


def read_model_archive(path, names=_ARRAYS, optional=()) -> tuple[object, dict]:
    """``(header, arrays)`` of a model file: the parsed JSON header and the named arrays.

    The arrays are those named and those of ``optional`` that it holds, read with
    ``allow_pickle=False``, every member's size bounded before it is read; anything else is a
    :class:`ModelError` that says what the file is not.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"no model file at {path}: train one with `supramodal train` or give the right path")
    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise ModelError(f"{path} is not a supramodal model: it holds a single array (.npy), "
                             "not an .npz archive")
        with loaded as npz:
            missing = {"header", *names} - set(npz.files)
            if missing:
                raise ModelError(f"{path} is not a supramodal model: it lacks {sorted(missing)}")
            names = (*names, *(k for k in optional if k in npz.files))
            for k in ("header", *names):
                _check_member_size(npz, k, MAX_HEADER_BYTES if k == "header" else MAX_ARRAY_BYTES, path)
            header_text = npz["header"]
            arrays = {k: npz[k] for k in names}
    except ModelError:
        raise
    except ValueError as exc:
        # numpy's own message advises an unsafe load, which this program never does nor repeats: say what
        # the file is not. numpy calls any file that is neither .npy nor .npz "pickled data"; a pickle
        # (protocol 2 and on) starts with 0x80, and an archive's member of objects is named by numpy.
        with open(path, "rb") as f:
            pickle_file = f.read(1) == b"\x80"
        if "Object arrays" in str(exc) or pickle_file:
            raise ModelError(f"{path} is not a supramodal model file: it holds a pickled Python object, which this "
                             "program never loads (a model file holds only plain arrays); train a model with "
                             "`supramodal train`") from None
        raise ModelError(f"{path} is not a readable model file: not an .npz archive of plain arrays (truncated, "
                         "or another kind of file); train a model with `supramodal train`") from None
    except (zipfile.BadZipFile, OSError, EOFError, NotImplementedError, zlib.error) as exc:
        # NotImplementedError, zlib.error: a member's compression method damaged (zipfile's own words for it)
        raise ModelError(f"{path} is not a readable model file ({exc}); "
                         "it may be truncated or of another kind") from exc
    if header_text.dtype.kind != "U" or header_text.ndim != 0:
        raise ModelError(f"{path}: the model header must be one text, got a {header_text.dtype} array "
                         f"of shape {header_text.shape}")
    header = parse_json_text(str(header_text), f"{path}: the model header", max_depth=MAX_HEADER_DEPTH,
                             error=ModelError, limit_name="supramodal.model.MAX_HEADER_DEPTH")
    return header, arrays


# -- calibration in a model file (version 2) ----------------------------------------------------

#: Header keys of a version 2 file's calibration.
CALIBRATION_KEYS = ("calibration", "novelty")


def log_posteriors_of(logits: np.ndarray, calibration: Calibration | None) -> np.ndarray:
    """Log-posteriors from a network's logits.

    Calibrated with ``calibration``, else the normalised outputs
    (:func:`~supramodal.calibration.normalised_log_posteriors`).
    """
    if calibration is None:
        return normalised_log_posteriors(logits)
    return calibration.log_posteriors(logits)


def calibration_header(calibration: Calibration | None, novelty: Novelty | None) -> dict:
    """Return the :data:`CALIBRATION_KEYS` of a header."""
    return {"calibration": None if calibration is None else calibration.to_dict(),
            "novelty": False if novelty is None else novelty.header()}


def novelty_arrays(novelty: Novelty | None) -> dict:
    """Return the :data:`NOVELTY_ARRAYS` a model file holds for ``novelty`` (none without one)."""
    if novelty is None:
        return {}
    return novelty.arrays()


def calibration_from_parts(header: dict, arrays: dict, n_in: int, n_classes: int, bad):
    """``(Calibration or None, Novelty or None)`` of a header and its arrays, each validated.

    Both are None for a version 1 file or one saved without them.
    """
    raw = header.get("calibration")
    calibration = None if raw is None else Calibration.from_dict(raw, bad, n_classes)
    return calibration, Novelty.from_parts(header.get("novelty", False), arrays, n_in, n_classes, bad)


def with_held_out_changes(calibration: Calibration, logits, labels, groups, folds) -> Calibration:
    """``calibration`` with its :class:`~supramodal.calibration.HeldOutChanges`.

    They hold the change detector's statistic on the held-out windows it was fitted on (``logits`` of
    windows no network that scored them trained on, ``folds`` saying which network), so that a node sets
    its change threshold for the rate a scene asks (:func:`supramodal.decisions.change_threshold`)
    instead of the detector's bound.
    """
    from supramodal.decisions import held_out_changes

    rho, caps = calibration.contact_pooling
    return replace(calibration, changes=held_out_changes(calibration.log_posteriors(logits), labels, groups, folds,
                                                         rho, caps))

