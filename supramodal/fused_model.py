"""The supramodal network (the paper's Sect. 5): one classifier on two senses' aligned windows.

An :class:`EarlyFusionModel` takes, for each pair of aligned windows, both senses' feature windows
(e.g. 20 whisker + 50 cochlea channels of Af), flattened and set side by side
(:func:`supramodal.fusion.early_inputs`), standardised with the training windows' mean and scale,
into one MLP trained with iRPROP-; winner-take-all as for one sense.

Its file is an ``.npz`` archive like a :class:`~supramodal.model.TextureModel`'s (read with
``allow_pickle=False``, every member bounded, every shape checked against the header), whose
header names the format ``supramodal-early-model`` and, under ``senses``, what each sense's
inputs are (bank, features, window, peak settings, and the sense's name), in input order.

Version 2 adds the network's calibration, as a one-sense model file's version 2 does
(:mod:`supramodal.model`): the header's ``calibration`` (fitted on out-of-fold windows of the
concatenated inputs, :func:`supramodal.model.train_deployed`) and ``novelty`` (with the arrays
``novelty_means``, ``novelty_precision``, ``novelty_quantiles``). A version 1 file still loads,
uncalibrated. The calibration's ``changes`` (:class:`~supramodal.calibration.HeldOutChanges`, what a change
detector did on its held-out windows) is written by this version's training; a file without them loads,
and its node keeps the change detector's bound. Version 3 adds ``networks``, as a one-sense model file's
version 3 does: a calibrated model deploys its calibration's fold networks.

Late fusion learns its weight from windows that neither sense's network trained on:
:func:`out_of_fold_logits` scores each window with a copy of a sense model's configuration trained
on the other folds, and :func:`learn_late_fusion_out_of_fold` learns the weight and sharpness on
those windows and scores the fusion on each fold with a weight learned without it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from supramodal.banks import Bank
from supramodal.calibration import (
    DEFAULT_CALIBRATION_FOLDS,
    POOLING_RUN,
    Calibration,
    HeldOutLogits,
    Novelty,
    OutOfFold,
    calibration_folds,
    calibration_report,
    fit_pooling,
    fit_window_calibration,
    normalised_log_posteriors,
    train_fold_networks,
)
from supramodal.errors import InputError
from supramodal.fusion import early_inputs, fuse_late, learn_late_fusion
from supramodal.mlp import DEFAULT_EPOCHS, EARLY_STOP_PATIENCE, MLP, Ensemble
from supramodal.model import (
    NOVELTY_ARRAYS,
    SENSE_KEYS,
    GainAugment,
    GainCopies,
    ModelError,
    TextureModel,
    calibration_from_parts,
    calibration_header,
    check_header_keys,
    check_sense_fits,
    check_training_patience,
    classes_from_header,
    log_posteriors_of,
    network_from_arrays,
    networks_of,
    novelty_arrays,
    read_model_archive,
    save_model_archive,
    sense_from_header,
    sense_header,
    touch_allowance,
    train_deployed,
)

EARLY_FORMAT = "supramodal-early-model"
EARLY_VERSION = 3
#: Versions this program reads (1: before calibration, its networks load uncalibrated; 2: one network).
EARLY_VERSIONS = (1, 2, 3)


@dataclass(frozen=True)
class Sense:
    """What one sense's input windows are: its name and the pipeline settings that make them."""

    name: str
    bank: Bank
    features: tuple[str, ...]
    window_samples: int
    peak_mode: str = "maxima"
    peak_threshold: float = 0.0

    @classmethod
    def of(cls, name: str, pipeline) -> Sense:
        """Return the sense a :class:`~supramodal.pipeline.FeaturePipeline` computes."""
        return cls(name, pipeline.bank, tuple(pipeline.features), pipeline.window_samples, pipeline.peaks.mode,
                   float(pipeline.peaks.threshold))

    @property
    def n_inputs(self) -> int:
        """The sense's inputs per window: features x channels."""
        return len(self.features) * self.bank.channels

    def check_pipeline(self, pipeline, in_fusion: bool = True) -> None:
        """Raise :class:`ModelError` naming what differs if ``pipeline`` does not make this sense's windows.

        Checked as a one-sense model checks its pipeline. ``in_fusion``: the pipeline is a
        ``[fusion]`` stream's, and the message asks whether the streams were given in the other order.
        """
        try:
            check_sense_fits((self.bank, self.features, self.window_samples, self.peak_mode, self.peak_threshold),
                             pipeline.bank, pipeline.features, pipeline.window_samples, pipeline.peaks.mode,
                             pipeline.peaks.threshold)
        except ModelError as exc:
            hint = (" (the model's senses feed [fusion] streams in their order: are the two streams given the "
                    "other way round?)") if in_fusion else ""
            raise ModelError(f"sense {self.name!r}: {exc}{hint}") from None


#: What :meth:`EarlyFusionModel.train` takes for gain augmentation: one for both senses (each resolved by
#: its own bank), or one per sense in input order (None: that sense's columns copied unchanged).
EarlyAugment = GainAugment | tuple[GainAugment | None, GainAugment | None] | None


def early_augment(augment: EarlyAugment, senses) -> tuple[GainAugment, GainAugment] | None:
    """Return one :class:`~supramodal.model.GainAugment` per sense, each resolved by its bank, or None.

    ``augment`` as :meth:`EarlyFusionModel.train` takes it. A sense given None (or ``copies`` 0) next
    to one augmented gets the other's copies with spread 0: its columns copied unchanged, so that both
    senses make the same rows. No copies in either: None.

    Raises
    ------
    InputError
        Two senses asking for different numbers of copies (the rows of one pair must be copied alike).
    """
    pair = (augment, augment) if augment is None or isinstance(augment, GainAugment) else tuple(augment)
    if len(pair) != 2:
        raise InputError(f"early fusion's gain augmentation: one, or one per sense (two), got {len(pair)}")
    asked = [a for a in pair if a is not None and a.copies]
    if not asked:
        return None
    copies = {a.copies for a in asked}
    if len(copies) > 1:
        raise InputError(f"early fusion's gain augmentation: the senses ask for {sorted(copies)} copies; a pair's "
                         "two windows are copied together: give both senses the same augment_copies")
    first = asked[0]
    out = []
    for a, sense in zip(pair, senses):
        if a is None or not a.copies:
            a = GainAugment(first.copies, 0.0, False, first.seed)     # copies unchanged: exp(N(0, 0)) = 1
        out.append(a.resolved(sense.bank.kind))
    return out[0], out[1]


@dataclass(frozen=True)
class EarlyGainCopies:
    """Gain augmentation of early-fusion inputs: each sense's columns copied by its own :class:`GainCopies`.

    Called ``(rows, labels, stream)`` as a :class:`~supramodal.model.GainCopies` is (for
    :func:`~supramodal.model.train_deployed`'s networks);
    each sense draws its own gains (a touch's whisker gains and microphone level are independent).
    """

    parts: tuple[GainCopies, GainCopies]

    @classmethod
    def of(cls, augments: tuple[GainAugment, GainAugment], senses) -> EarlyGainCopies:
        """Return the copies of resolved ``augments`` (:func:`early_augment`) for ``senses``' inputs."""
        return cls(tuple(GainCopies(a, tuple(s.features), s.bank.channels, part)          # type: ignore[arg-type]
                         for part, (a, s) in enumerate(zip(augments, senses))))

    @property
    def factor(self) -> int:
        """Rows out per row in (the same for both senses: :func:`early_augment` sees to it)."""
        return self.parts[0].factor

    def __call__(self, x, y, stream: int):
        """Return the rows ``x`` and their copies, and the labels ``y`` repeated, for network ``stream``."""
        x = np.asarray(x)
        split = len(self.parts[0].features) * self.parts[0].channels
        xa, xb = self.parts[0](x[:, :split], y, stream)[0], self.parts[1](x[:, split:], y, stream)[0]
        # a sense without a gain-linear feature (f alone) comes back uncopied: its windows repeated, unchanged
        xa, xb = (np.tile(v, (self.factor, 1)) if len(v) == len(x) else v for v in (xa, xb))
        return np.concatenate([xa, xb], axis=1), np.tile(np.asarray(y), self.factor)


@dataclass
class EarlyFusionModel:
    """One MLP on two senses' aligned feature windows.

    Attributes
    ----------
    senses : (Sense, Sense)
        In input order.
    classes : tuple of str
    mean, scale : ndarray, shape (inputs,)
        Standardisation of the concatenated inputs (from the training windows).
    mlp : MLP or Ensemble
        One network (uncalibrated), or the calibration's fold networks.
    training : dict
        How it was trained (algorithm, epochs, seed, windows).
    calibration : Calibration or None
        The map from the network's logits to calibrated posteriors and its contact pooling
        (None: a version 1 file, or trained without calibration folds).
    novelty : Novelty or None
        How unlike every training texture a pair of windows is.
    out_of_fold : OutOfFold or None
        The calibration's held-out logits, in memory after training only (never in a file): what
        ``train --fusion early`` scores the network's held-out windows by.
    """

    senses: tuple[Sense, Sense]
    classes: tuple[str, ...]
    mean: np.ndarray
    scale: np.ndarray
    mlp: MLP | Ensemble
    training: dict = field(default_factory=dict)
    calibration: Calibration | None = None
    novelty: Novelty | None = None
    out_of_fold: OutOfFold | None = field(default=None, repr=False, compare=False)

    @property
    def calibrated(self) -> bool:
        """Whether the posteriors are calibrated (not so for a version 1 file)."""
        return self.calibration is not None

    @property
    def augment(self) -> tuple[GainAugment, GainAugment] | None:
        """Return the gain augmentation its networks were trained with, one per sense in input order, or None.

        From ``training["augment"]``, checked when the file was read; None: none, or a file from before it.
        """
        d = self.training.get("augment")
        if d is None:
            return None
        return tuple(GainAugment.from_dict(part, ModelError) for part in d)      # type: ignore[return-value]

    @classmethod
    def train(cls, senses, values_a: np.ndarray, values_b: np.ndarray, labels, classes,
              epochs: int = DEFAULT_EPOCHS, seed: int = 0, hidden: int | None = None, groups=None,
              calibration_folds: int = DEFAULT_CALIBRATION_FOLDS, calibration_progress=None,
              augment: EarlyAugment = None, jobs: int = 1,
              patience: int | None = EARLY_STOP_PATIENCE) -> EarlyFusionModel:
        """Fit the scaling and the networks on aligned windows, and their calibration.

        ``values_a[k]`` and ``values_b[k]`` cover the same time, shapes (n, features, channels) of
        each sense; ``labels`` (n,) index ``classes``. ``groups``, ``calibration_folds`` and
        ``calibration_progress`` as for :meth:`supramodal.model.TextureModel.train`: the calibration
        is fitted on out-of-fold windows of the fold networks that the model deploys
        (:func:`~supramodal.model.train_deployed` on the concatenated inputs; ``jobs`` its worker processes),
        grouped by ``groups`` (each pair's recording or contact, pairs of one recording consecutive and in
        time order; default one per label); 0 folds: no calibration. The calibration carries what a change
        detector did on those held-out windows (:func:`~supramodal.model.with_held_out_changes`), for a
        node's change threshold.

        ``augment``: gain augmentation of every network's training windows (the model's and the
        calibration's fold networks; :func:`early_augment`): one :class:`~supramodal.model.GainAugment`
        for both senses, each resolved by its bank (per vibrissa for a whisker array, one level for a
        microphone), or one per sense; each sense draws its own gains. Scaling, calibration and novelty
        are fitted on the original windows, as a one-sense model's are. The model keeps it
        (:attr:`augment`). ``patience``: each fold network stops early on its held-out windows, as a
        one-sense model's do (None: every epoch).
        """
        senses = tuple(senses)
        x = early_inputs(cls._check(senses[0], values_a), cls._check(senses[1], values_b))
        augments = early_augment(augment, senses)
        # as a one-sense model: the calibration's fold networks deployed, the change detector's held-out
        # statistics kept (a node's early fusion then fits its change threshold, not the detector's bound)
        d = train_deployed(x, labels, len(classes), hidden, epochs, seed, groups, calibration_folds, jobs,
                           None if augments is None else EarlyGainCopies.of(augments, senses),
                           early_touch_allowance(senses, augments), calibration_progress=calibration_progress,
                           patience=patience)
        if augments is not None:
            d.training["augment"] = [a.to_dict() for a in augments]
        return cls(senses, tuple(classes), d.mean, d.scale, d.network, d.training, d.calibration, d.novelty,
                   d.out_of_fold)

    @staticmethod
    def _check(sense: Sense, values) -> np.ndarray:
        values = np.asarray(values, dtype=np.float64)
        expected = (len(sense.features), sense.bank.channels)
        if values.ndim != 3 or values.shape[1:] != expected:
            raise InputError(f"sense {sense.name!r}: feature windows must have shape (n, {expected[0]}, "
                             f"{expected[1]}), got {values.shape}")
        return values

    def _inputs(self, values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
        x = early_inputs(self._check(self.senses[0], values_a), self._check(self.senses[1], values_b))
        return (x - self.mean) / self.scale

    def outputs(self, values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
        """Output activations in [0, 1], shape (n, classes), for aligned windows of both senses."""
        return self.mlp.outputs(self._inputs(values_a, values_b))

    def logits(self, values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
        """Return the output units' logits, shape (n, classes) (finite where the outputs round to 0 or 1)."""
        return self.mlp.logits(self._inputs(values_a, values_b))

    def log_posteriors(self, values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
        """Log-posteriors per pair of windows, shape (n, classes).

        Calibrated when the model is (:attr:`calibrated`), else the normalised outputs; finite,
        never clipped.
        """
        return log_posteriors_of(self.logits(values_a, values_b), self.calibration)

    def posteriors(self, values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
        """Posteriors per pair of windows (rows sum to 1), shape (n, classes)."""
        return np.exp(self.log_posteriors(values_a, values_b))

    def novelty_score(self, values_a: np.ndarray, values_b: np.ndarray) -> np.ndarray:
        """How unlike every training texture each pair of windows is, shape (n,).

        A model without a novelty score (a version 1 file) raises :class:`ModelError`.
        """
        if self.novelty is None:
            raise ModelError("this early-fusion model has no novelty score (trained before version 2, or without "
                             "calibration): retrain it with `supramodal train --fusion early`")
        return self.novelty.score(self._inputs(values_a, values_b))

    # -- files ---------------------------------------------------------------------------------

    def header(self) -> dict:
        """Return the model file's JSON header: format, version, each sense, classes, layers, training, calibration."""
        return {"format": EARLY_FORMAT, "version": EARLY_VERSION,
                "senses": [{"name": s.name, **sense_header(s.bank, s.features, s.window_samples, s.peak_mode,
                                                           s.peak_threshold)} for s in self.senses],
                "classes": list(self.classes), "layers": list(self.mlp.shape), "networks": networks_of(self.mlp),
                "training": self.training,
                **calibration_header(self.calibration, self.novelty)}

    def save(self, path) -> Path:
        """Write the model to exactly ``path`` (an ``.npz`` archive); returns the path."""
        return save_model_archive(path, self.header(), self.mlp, self.mean, self.scale, novelty_arrays(self.novelty))

    @classmethod
    def load(cls, path) -> EarlyFusionModel:
        """Read and validate an early-fusion model file; :class:`ModelError` says what is wrong."""
        path = Path(path)
        header, arrays = read_model_archive(path, optional=NOVELTY_ARRAYS)

        def bad(msg):
            return ModelError(f"{path}: {msg}")

        if not isinstance(header, dict) or header.get("format") != EARLY_FORMAT:
            found = header.get("format") if isinstance(header, dict) else None
            raise bad(f"not a {EARLY_FORMAT} file (format is {found!r})"
                      + ("; it is a one-sense model: give it to a [[stream]], not to [fusion]"
                         if found == "supramodal-model" else ""))
        if type(header.get("version")) is not int or header["version"] not in EARLY_VERSIONS:   # true == 1 in Python
            raise bad(f"format version {header.get('version')!r} is not supported (this program reads versions "
                      f"{', '.join(map(str, EARLY_VERSIONS))}); retrain the model with this version")
        check_header_keys(header, {"senses", "classes"}, bad)
        raw = header.get("senses")
        if not (isinstance(raw, list) and len(raw) == 2 and all(isinstance(s, dict) for s in raw)):
            raise bad("'senses' must be a list of the two senses' descriptions")
        senses = []
        for i, s in enumerate(raw):
            extra = set(s) - {"name", *SENSE_KEYS}
            if extra or not isinstance(s.get("name"), str) or not s["name"]:
                raise bad(f"senses[{i}] must have a non-empty 'name' and the keys {list(SENSE_KEYS)} only")
            senses.append(Sense(s["name"], *sense_from_header(s, lambda m, i=i: bad(f"senses[{i}]: {m}"))))
        if senses[0].name == senses[1].name:
            raise bad(f"the two senses are both named {senses[0].name!r}")
        classes = classes_from_header(header, bad)
        n_in = senses[0].n_inputs + senses[1].n_inputs
        mlp, mean, scale = network_from_arrays(header, arrays, n_in, len(classes), bad,
                                               f"{senses[0].n_inputs} + {senses[1].n_inputs} inputs of the two senses")
        training = header.get("training", {})
        if not isinstance(training, dict):
            raise bad("'training' must be an object")
        check_training_patience(training, bad)
        if training.get("augment") is not None:        # a file from before it has none
            parts = training["augment"]
            if not (isinstance(parts, list) and len(parts) == 2):
                raise bad(f"'training' 'augment' must be a list of the two senses' gain augmentation, got {parts!r}")
            augments = [GainAugment.from_dict(part, bad) for part in parts]
            # as early_augment makes them: a pair's two windows copied together, each sense's gains said
            if augments[0].copies != augments[1].copies or None in (a.per_channel for a in augments):
                raise bad("'training' 'augment': the two senses' gain augmentation must have the same copies and "
                          f"per_channel true or false, got {parts!r}")
        calibration, novelty = calibration_from_parts(header, arrays, n_in, len(classes), bad)
        touch = None if novelty is None else novelty.touch
        if touch is not None and touch.parts and touch.parts != input_senses(senses):
            raise bad(f"'novelty.touch.parts' must say each input's sense as the header's senses split them: "
                      f"{senses[0].n_inputs} of {senses[0].name!r} (0), then {senses[1].n_inputs} of "
                      f"{senses[1].name!r} (1)")
        return cls((senses[0], senses[1]), tuple(classes), mean, scale, mlp, training, calibration, novelty)


# -- late fusion learned from windows the senses' networks never trained on ------------------------------

def out_of_fold_logits(model: TextureModel, values, labels, classes, folds, progress=None) -> np.ndarray:
    """Each window's logits from a network that never trained on its fold.

    Per fold, a copy of ``model``'s configuration (inputs, hidden units, epochs, seed, gain augmentation
    and early stopping, as :func:`supramodal.node.workflows.training.cross_validate_model` copies it) is
    trained on the windows of the other folds, as a fold network of the model's own calibration is
    (:func:`~supramodal.calibration.fold_tasks`: stopped early on the fold's windows where the model's
    networks were), and scores the fold's windows (never augmented).

    Parameters
    ----------
    model : TextureModel
        The sense model whose configuration is copied (its own weights are not used).
    values : ndarray, shape (n, features, channels)
    labels : ndarray of int, shape (n,)
        Index into ``classes`` of each window.
    classes : sequence of str
        The copies' classes, in the order of the columns returned (``model``'s textures, in any
        order).
    folds : ndarray of int, shape (n,)
        Each window's fold (e.g. :func:`supramodal.calibration.calibration_folds`).
    progress : callable(str), optional
        One line per fold.

    Returns
    -------
    ndarray, shape (n, classes)
    """
    if sorted(classes) != sorted(model.classes):
        raise InputError(f"the model knows {list(model.classes)}, the windows are labelled with {list(classes)}")
    values = np.asarray(values, dtype=np.float64)
    y = np.asarray(labels)
    folds = np.asarray(folds)
    epochs = int(model.training.get("epochs", DEFAULT_EPOCHS))
    seed = int(model.training.get("seed", 0))
    parts = np.unique(folds)
    if len(parts) < 2:
        raise InputError("out-of-fold windows need at least two folds")
    kept = model.out_of_fold
    if kept is not None and tuple(classes) == tuple(model.classes) and kept.matches(values, y, folds):
        # The model's own calibration trained these very fold networks on these windows.
        if progress:
            progress(f"the {len(parts)} fold networks of the model's calibration, {len(y)} held-out windows, "
                     f"{float(np.mean(np.argmax(kept.logits, axis=1) == y)):.3f} right")
        return kept.logits.copy()
    expected = (len(model.features), model.bank.channels)
    if values.ndim != 3 or values.shape[1:] != expected or len(y) != len(values) or len(folds) != len(values):
        raise InputError(f"out-of-fold windows must have shape (n, {expected[0]}, {expected[1]}) with a label and "
                         f"a fold each, got {values.shape}, {len(y)} labels, {len(folds)} folds")
    x, fold_of = values.reshape(len(values), -1), np.searchsorted(parts, folds)
    augment = model.augment
    held = HeldOutLogits(y, fold_of, len(parts), len(classes), progress, what="fold")
    # the copies are fold networks as this version makes a model's: augmented, stopped early together (a
    # file from before early stopping has no patience: every epoch, as its networks were trained)
    train_fold_networks(x, y, len(classes), fold_of, len(parts), model.mlp.shape[1], epochs, seed,
                        None if augment is None else augment.for_inputs(model.features, model.bank.channels),
                        model.training.get("patience"), done=held.told, redone=held.retold)
    return held.logits


def out_of_fold_log_posteriors(model: TextureModel, values, labels, classes, folds, progress=None) -> np.ndarray:
    """Log-posteriors of each window from :func:`out_of_fold_logits`, mapped as ``model`` maps its own.

    When ``model`` is calibrated, by a window map fitted on these out-of-fold logits (as
    :func:`~supramodal.calibration.fit_network_calibration` fits a model's; the model's own map
    where these are the very logits it was fitted on), else the normalised outputs (a version 1
    model's posteriors). Shape (n, classes).
    """
    y = np.asarray(labels)
    kept = model.out_of_fold
    own = kept is not None and tuple(classes) == tuple(model.classes) and kept.matches(values, y, folds)
    z = out_of_fold_logits(model, values, y, classes, folds, progress)
    if model.calibration is None:          # not calibrated (model.calibrated)
        return normalised_log_posteriors(z)
    if own:
        return model.calibration.log_posteriors(z)
    return Calibration(*fit_window_calibration(z, y), 0.0).log_posteriors(z)


def senses_out_of_fold(models, values, labels, classes, groups=None, k: int = DEFAULT_CALIBRATION_FOLDS,
                       seed: int = 0, progress=None, names=None) -> tuple[list[np.ndarray], np.ndarray, str]:
    """Out-of-fold log-posteriors of two (or more) senses on the same aligned windows, on the same folds.

    Parameters
    ----------
    models : sequence of TextureModel
        Each sense's model (its configuration is copied per fold).
    values : sequence of ndarray, each (n, features, channels)
        Each sense's windows, aligned: row ``i`` of every sense covers the same time.
    labels : ndarray of int, shape (n,)
        Index into ``classes``.
    groups : sequence, length n, optional
        Each window's recording or contact (windows of one consecutive and in time order): the
        folds are whole groups where there are enough
        (:func:`~supramodal.calibration.calibration_folds`); default one per label.
    k, seed
        Folds and their shuffle.
    progress : callable(str), optional
        One line per sense and fold, naming the sense by ``names`` (default "sense 1 of 2", ...).

    Returns
    -------
    log_posteriors : list of ndarray, each (n, classes)
    folds : ndarray of int, shape (n,)
    by : {"recording", "span"}
        How the folds were made.
    """
    y = np.asarray(labels)
    groups = y if groups is None else np.asarray(groups)
    folds, by = calibration_folds(y, groups, k, seed)
    out = []
    for i, (model, v) in enumerate(zip(models, values)):
        name = f"sense {i + 1} of {len(models)}" if names is None else names[i]
        say = None if progress is None else (lambda m, name=name: progress(f"{name}: {m}"))
        out.append(out_of_fold_log_posteriors(model, v, y, classes, folds, say))
    return out, folds, by


def learn_late_fusion_out_of_fold(log_posteriors_a, log_posteriors_b, labels, folds) -> dict:
    """Learn the late fusion's ``(weight, sharpness)`` on both senses' out-of-fold log-posteriors, and score it.

    The log-posteriors are :func:`senses_out_of_fold`'s; the score is the fusion's own held-out
    one.

    The weight and sharpness kept are learned on every window
    (:func:`supramodal.fusion.learn_late_fusion`). The fused log-posteriors returned are
    cross-fitted: each fold's windows fused with a weight and sharpness learned on the other
    folds only, so that their score is a held-out score of the fusion as learned, not of the
    windows it was learned on.

    Returns
    -------
    dict
        ``weight``, ``sharpness``, ``fused`` (ndarray (n, classes), cross-fitted), ``fold_weights``
        (the weight learned without each fold, in fold order).
    """
    a = np.asarray(log_posteriors_a, dtype=np.float64)
    b = np.asarray(log_posteriors_b, dtype=np.float64)
    y = np.asarray(labels)
    folds = np.asarray(folds)
    weight, sharpness = learn_late_fusion(a, b, y)
    fused = np.empty_like(a)
    fold_weights = []
    for f in np.unique(folds):
        test = folds == f
        w, s = learn_late_fusion(a[~test], b[~test], y[~test])
        fused[test] = fuse_late(a[test], b[test], w, s)
        fold_weights.append(w)
    return {"weight": weight, "sharpness": sharpness, "fused": fused, "fold_weights": fold_weights}


def held_out_scores(log_posteriors: dict, labels) -> dict:
    """``{name: {"accuracy", "log_loss", "brier", "ece", "sure_count", "sure_wrong"}}`` of each named set.

    Each set is of held-out log-posteriors (a tie is wrong).
    """
    keys = ("n", "accuracy", "log_loss", "brier", "ece", "sure_count", "sure_wrong")
    return {name: {k: v for k, v in calibration_report(lp, labels).items() if k in keys}
            for name, lp in log_posteriors.items()}


def fused_pooling(log_posteriors, labels, folds, groups=None) -> float:
    """Fit the correlation ``rho`` of the fused decisions' contact pooling (:func:`supramodal.calibration.fit_pooling`).

    Fitted on runs of up to :data:`~supramodal.calibration.POOLING_RUN` consecutive held-out
    windows of one group (default: one per label) and one fold, the windows one held-out network
    scored in a row.
    """
    lp = np.asarray(log_posteriors, dtype=np.float64)
    y = np.asarray(labels)
    folds = np.asarray(folds)
    groups = y if groups is None else np.asarray(groups)
    runs = []
    for g, f in dict.fromkeys(zip(groups.tolist(), folds.tolist())):
        idx = np.flatnonzero((groups == g) & (folds == f))
        runs += [idx[s:s + POOLING_RUN] for s in range(0, len(idx), POOLING_RUN)]
    return fit_pooling([lp[r] for r in runs], [int(y[r[0]]) for r in runs])


#: Mean log loss per window (nats) by which a fusion may trail a sense on held-out windows before
#: :func:`worse_than_a_sense` calls it worse.
WORSE_MARGIN = 0.01


def worse_than_a_sense(fused, senses: dict, labels) -> tuple[str, float, float] | None:
    """Whether a fusion's held-out log-posteriors ``fused`` (n, classes) do worse than one of the ``senses`` alone.

    ``senses`` is ``{name: log-posteriors (n, classes)}`` of the same held-out windows.

    Worse: a higher mean log loss than the sense's by more than :data:`WORSE_MARGIN` plus two
    standard errors of the per-window difference (the windows of one contact are alike, so the
    error is, if anything, too small: the refusal errs towards refusing; the margin spares a fusion
    that learned to follow one sense and differs from it by its rounding). Returns ``(sense, its log
    loss, the fusion's)`` for the sense with the lowest log loss that the fusion does worse than, else
    None.
    """
    y = np.asarray(labels)
    rows = np.arange(len(y))
    lost = -np.asarray(fused, dtype=np.float64)[rows, y]
    found = []
    for name, lp in senses.items():
        own = -np.asarray(lp, dtype=np.float64)[rows, y]
        d = lost - own
        error = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else 0.0
        if d.mean() > WORSE_MARGIN + 2.0 * error:
            found.append((float(own.mean()), name))
    if not found:
        return None
    own_loss, name = min(found)
    return name, own_loss, float(lost.mean())


def early_touch_allowance(senses, augments: tuple[GainAugment, GainAugment] | None = None
                          ) -> tuple[tuple[int, ...], tuple[float, float], tuple[int, ...]]:
    """Return the novelty's allowance for a new touch of an early-fusion network.

    Which inputs share a gain, each sense's least spread, and each input's sense (part 0 or 1:
    :func:`supramodal.calibration.fit_novelty`'s ``touch_groups``, ``touch_floor``, ``touch_parts``). Each
    sense's as :func:`supramodal.model.touch_allowance` gives it, by its own gain augmentation (``augments``,
    :func:`early_augment`; a sense copied unchanged, spread 0, as none); the second sense's groups follow the
    first's (a touch's gains are each sensor's own), and each sense's spread is estimated and allowed for on
    its own (a whisker array's touches may vary five times as much as a microphone's level).
    """
    parts = [touch_allowance(s.features, s.bank, a)
             for s, a in zip(senses, augments if augments is not None else (None, None))]
    (first, floor_a), (second, floor_b) = parts
    shift = max(first, default=-1) + 1
    return first + tuple(g + shift if g >= 0 else -1 for g in second), (floor_a, floor_b), input_senses(senses)


def input_senses(senses) -> tuple[int, ...]:
    """Return each input's sense (0 or 1) of an early network's inputs, the two senses' side by side."""
    return (0,) * senses[0].n_inputs + (1,) * senses[1].n_inputs
