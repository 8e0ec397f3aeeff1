"""Scene -> Node or Graph: the one place that knows which drivers, banks, models and sinks a scene means.

Only what a scene needs is imported or built: a scene without a microphone never
imports sounddevice, one without a serial port never imports pyserial, features
not asked for are not computed, and there is no classifier without a model.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from supramodal.bankfile import BankFileError, bank_from_description, load_bank
from supramodal.banks import Bank
from supramodal.calibration import DEFAULT_CALIBRATION_FOLDS, winner
from supramodal.decisions import ContactDetector
from supramodal.drivers.contact import ContactListener, contact_listener
from supramodal.drivers.spec import BuildContext, OptionError
from supramodal.errors import InputError
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.model import GainAugment, ModelError, TextureModel
from supramodal.node.runtime.contacts import ContactTimeline
from supramodal.node.runtime.events import MAIN_STREAM
from supramodal.node.runtime.graph import Graph
from supramodal.node.runtime.labels import Labels
from supramodal.node.runtime.sinks.spec import SinkContext, SinkSpec, SourcePlan, StreamPlan
from supramodal.node.runtime.sources import Source
from supramodal.node.runtime.streams import Stream, refuse_uncalibrated
from supramodal.node.runtime.ticker import Ticker
from supramodal.node.scene.band import warn_if_beyond_band
from supramodal.node.scene.model_cache import hand_over, trained_on_start
from supramodal.node.scene.registry import driver_spec, sink_spec
from supramodal.node.scene.schema import LEARN
from supramodal.node.scene.specs import Scene, SceneError, SinkSettings, SourceSpec, StreamSpec
from supramodal.parallel import default_jobs
from supramodal.pipeline import FeaturePipeline, window_length
from supramodal.training import split, texture_features

if TYPE_CHECKING:   # for annotations only: a scene without fusion does not load it
    from supramodal.node.runtime.fusion import LateFusion


def bank_for(scene: Scene, stream: StreamSpec | None = None) -> Bank:
    """Return the bank of ``stream`` (default: the scene's only one).

    Its [bank] file, or its kind's recipe with the keys the scene sets.
    """
    stream = stream or scene.only_stream()
    b = stream.bank
    try:
        if b.file is not None:
            return load_bank(scene.resolve(b.file))
        return bank_from_description({"kind": b.kind, **b.recipe}, f"{stream.where}: [bank]")
    except BankFileError as exc:
        raise SceneError(str(exc) if b.file is None else f"{stream.where}: [bank] file: {exc}") from None


def pipeline_for(scene: Scene, bank: Bank, stream: StreamSpec | None = None) -> FeaturePipeline:
    """Return the feature pipeline of ``stream`` (default: the scene's only one) on ``bank``."""
    stream = stream or scene.only_stream()
    f = stream.features
    try:
        return FeaturePipeline(bank, f.names, f.window, dtype=np.dtype(f.dtype), peak_mode=f.peak_mode,
                               nonfinite=f.nonfinite, peak_threshold=f.peak_threshold, chunk=f.chunk)
    except ValueError as exc:
        raise SceneError(f"{stream.where}: [features] {exc}") from None


def train_on_texture_set(ts, pipeline: FeaturePipeline, progress=None, held_out: list | None = None,
                         trained: list | None = None, augment: GainAugment | None = None) -> TextureModel:
    """Return the model the default scene trains on the spot, on Fig. 3's training part of each texture.

    It is computed with the scene's own pipeline settings, calibrated on out-of-fold windows of that training
    part (:meth:`TextureModel.train`: each texture's training windows cut into spans in time, one per fold).
    ``held_out``, a list, receives the held-out part ``(x_test, y_test)`` (windows the model never saw: a
    fusion is scored on them); ``trained`` the training part ``(x_train, y_train)`` (an early-fusion network
    learns on it, a late-fusion weight on its out-of-fold windows). ``augment``: the gain augmentation of its
    networks' training windows (``[model] augment_copies``, ...; default none).

    It trains every time: the node keeps what it trains on start in one cache, on disk
    (:func:`~supramodal.node.scene.model_cache.trained_on_start`, which calls this on a miss).
    """
    p = pipeline
    model, train_part, test_part = texture_set_model(ts, p.bank, p.features, p.window, p.peaks.mode,
                                                     float(p.peaks.threshold), progress=progress, augment=augment)
    hand_over(model, train_part, test_part, ts, p.features, held_out, trained, progress)
    return model


def texture_set_model(ts, bank: Bank, features: tuple[str, ...], window: float, peak_mode: str,
                      peak_threshold: float, progress=None, augment: GainAugment | None = None
                      ) -> tuple[TextureModel, tuple, tuple]:
    """Train and return what :func:`train_on_texture_set` trains: ``(model, (x_train, y_train), (x_test, y_test))``.

    From nothing but the texture set, the pipeline's settings (``window`` in seconds) and ``augment``, with
    progress told every few seconds to ``progress`` (None: silent).
    """
    with _ticker(progress, f"the {bank.kind} bank's model ({', '.join(features)}) on {len(ts.textures)} "
                           "textures") as tell:
        values, _ = texture_features(ts, bank, features, window, peak_mode=peak_mode,
                                     peak_threshold=peak_threshold, progress=tell.features)
        x_train, y_train, x_test, y_test = split(values)
        tell.networks_begin()
        model = TextureModel.train(x_train, y_train, ts.names, bank, features,
                                   window_length(window, bank.fs), peak_mode=peak_mode,
                                   peak_threshold=peak_threshold, seed=0, progress=tell.epoch,
                                   calibration_progress=tell.fold, jobs=default_jobs(), augment=augment)
    return model, (x_train, y_train), (x_test, y_test)


class _TrainingTold:
    """The training's callbacks, each telling a :class:`~supramodal.node.runtime.ticker.Ticker` its stage.

    ``ticker`` None: no one is told. The networks are the calibration's fold networks, side by side on the
    cores, the last one's epochs told as they go (:meth:`supramodal.model.TextureModel.train`); then the
    calibration's fitting.
    """

    def __init__(self, ticker: Ticker | None, epochs: int, folds: int) -> None:
        self.ticker, self.epochs, self.folds = ticker, epochs, folds

    def features(self, line: str) -> None:
        """Tell the stage of making the features (``line``: the training's own line about them)."""
        if self.ticker is not None:
            self.ticker.stage("features, " + line.strip())

    def networks_begin(self) -> None:
        """Note that the features are made: the networks' time, which the time left is told from, begins now."""
        if self.ticker is not None:
            self.ticker.stage(f"0 of {self.folds} networks trained", 0.0)

    def epoch(self, epoch: int, mse: float) -> None:
        """Tell the last network's epoch ``epoch`` (from 0) done (:meth:`fold` then tells the network done).

        The epochs are the most it trains: a fold network stops early once its held-out error stops
        falling, so the time left told from them is the longest it can be.
        """
        if self.ticker is not None:
            self.ticker.stage(f"network {self.folds} of {self.folds}, epoch {epoch + 1} of at most {self.epochs}",
                              (epoch + 1) / self.epochs)

    def fold(self, line: str) -> None:
        """Tell one more of the calibration's fold networks trained, then the fitting of the calibration."""
        if self.ticker is not None:
            self.ticker.network_done()
            k = self.ticker.done
            self.ticker.stage(f"{k} of {self.folds} networks trained" if k < self.folds else
                              "fitting the calibration on the folds' held-out windows")


@contextlib.contextmanager
def _ticker(progress, what: str) -> Iterator[_TrainingTold]:
    """Tell ``progress`` how training ``what`` on start goes: a line at once and every few seconds.

    Told by a :class:`~supramodal.node.runtime.ticker.Ticker`; nothing when ``progress`` is None.
    """
    if progress is None:
        yield _TrainingTold(None, DEFAULT_EPOCHS, DEFAULT_CALIBRATION_FOLDS)
        return
    with Ticker(progress, what, DEFAULT_CALIBRATION_FOLDS) as ticker:
        yield _TrainingTold(ticker, DEFAULT_EPOCHS, DEFAULT_CALIBRATION_FOLDS)


def driver_for(scene: Scene, bank: Bank | None, speed_override=None, shared: dict | None = None,
               source: SourceSpec | None = None):
    """Build the driver of ``source`` (default: the scene's only one) from its spec (node.scene.registry).

    Returns ``(driver, labels, texture_set_or_None)``.

    ``bank``: the bank that reads the source (a file is resampled to its rate, a stream at
    another rate is refused), or None for a source that no bank reads (a relay's): then the
    source keeps its own rate. ``shared``: a dict the caller keeps while it builds several
    sources, so that what they share is made once (one XDF file read once for all its sources).
    """
    src = source or scene.only_source()
    spec = driver_spec(src.type)
    context = BuildContext(rate=None if bank is None else bank.fs, resolve=scene.resolve, speed=speed_override,
                           shared=shared if shared is not None else {},
                           channels=None if bank is None else bank.channels, bank=bank)
    try:
        built = spec.build(src.options, context)
    except OptionError as exc:
        raise SceneError(f"{src.where} {exc}") from None
    if bank is not None and built.source_rate is not None:
        warn_if_beyond_band(bank, built.source_rate, f"{src.where} path {src.options.get('path', src.type)}")
    labels = Labels(list(built.labels), built.label_period) if built.labels else Labels.of(built.driver)
    return built.driver, labels, built.training_set


def _make_sinks(scene: Scene, needs: str, made: list, overwrite: bool, **context) -> None:
    """Make the scene's sinks whose spec needs ``needs`` (node.runtime.sinks.spec.NEEDS).

    Each is appended as ``(settings, spec, sink or tap)`` to ``made``; ``context``: the rest of the
    :class:`~supramodal.node.runtime.sinks.spec.SinkContext` (the streams, the sources).
    """
    for settings in scene.sinks:
        spec = sink_spec(settings.type)
        if spec.needs != needs:
            continue
        where = f"{scene.source}: [[sink]] #{settings.index + 1}"
        try:
            made.append((settings, spec, spec.build(settings.options, SinkContext(
                where, scene.resolve, overwrite, stream_names=scene.window_names, **context))))
        except OptionError as exc:
            raise SceneError(f"{where} {exc}") from None


def _source_plan(src: SourceSpec, driver, read_by: list) -> SourcePlan:
    """Return what a sink of ``src``'s samples is told of it.

    Its built ``driver``, its driver type, options and signal type (its driver's spec's), and the
    ``(bank, mapping)`` of the streams that read it.
    """
    return SourcePlan(driver, src.type, src.options, driver_spec(src.type).signal_type(src.options), tuple(read_by))


def _planned_classes(stream: StreamSpec, bank: Bank, ts, loaded: TextureModel | None) -> tuple[str, ...]:
    """Return the classes ``stream``'s model will decide among; empty without a model.

    Known before it is trained (the texture set :func:`_model_for` trains on) or as ``loaded``
    (:func:`_model_file`).
    """
    if stream.model.train_on_start:
        if ts is None:
            from supramodal.textures import reference_texture_set

            ts = reference_texture_set(bank.kind)
        return tuple(ts.names)
    return () if loaded is None else tuple(loaded.classes)


def _model_file(scene: Scene, stream: StreamSpec) -> TextureModel | None:
    """Return ``stream``'s model read from its file, or None where it is trained on the spot or there is none.

    Read once: the plans and the stream both take it.
    """
    m = stream.model
    if m.train_on_start or m.path is None:
        return None
    return TextureModel.load(scene.resolve(m.path))


def _model_for(scene: Scene, stream: StreamSpec, bank: Bank, pipeline: FeaturePipeline, ts, progress,
               held_out: list | None = None, trained: list | None = None,
               loaded: TextureModel | None = None) -> TextureModel | None:
    """Return ``stream``'s model, trained on the spot or ``loaded``, checked against the pipeline.

    Trained on the spot, its held-out and training windows are appended to ``held_out`` and ``trained``;
    ``loaded``: :func:`_model_file`.
    """
    model = loaded
    m = stream.model
    if m.train_on_start:
        # Synthesised textures: the model is made on the spot (the default scene does this); a
        # live or replayed source gets the bank's reference set (the mock board plays it).
        if ts is None:
            from supramodal.textures import reference_texture_set

            ts = reference_texture_set(bank.kind)
            if abs(ts.fs - bank.fs) > 1e-9 * bank.fs:
                raise SceneError(f"{stream.where}: [model] train_on_start: the {bank.kind} reference textures are "
                                 f"at {ts.fs:g} Hz, the bank at {bank.fs:g} Hz; give a [model] path instead")
        # Read from the cache of models trained on start where it holds this one (docs/node.md).
        augment = m.gain_augment()
        model = trained_on_start(ts, pipeline,
                                 lambda h, t: train_on_texture_set(ts, pipeline, progress, h, t, augment),
                                 progress, held_out, trained, augment=augment)
        if m.path is not None:
            model.save(scene.resolve(m.path))
    if model is not None:
        try:
            model.check_pipeline(pipeline)
        except ModelError as exc:
            raise SceneError(f"{stream.where}: [model] {exc}") from None
    return model


#: Bytes of samples one source's ring may hold (float64): a bound on what ``[buffer] seconds`` can
#: make the node allocate, whatever the source's rate and channels.
MAX_RING_BYTES = 2**30


def _check_ring(src: SourceSpec, driver, where: str) -> None:
    """Refuse a ring (``src``'s ``[buffer] seconds`` of ``driver``) beyond :data:`MAX_RING_BYTES`, naming the key.

    ``where``: the buffer's table.
    """
    seconds = src.buffer.seconds
    size = seconds * driver.rate * driver.channels * 8
    if size > MAX_RING_BYTES:
        raise SceneError(f"{where} seconds: {seconds:g} s of {driver.channels} channels at {driver.rate:g} Hz "
                         f"is a ring of {size / 2**30:.3g} GiB, more than the {MAX_RING_BYTES / 2**30:g} GiB "
                         "a source may hold "
                         "(MAX_RING_BYTES); give fewer seconds")


def _source(src: SourceSpec, driver, where: str) -> Source:
    """Return the source of ``driver`` with its ring as ``src``'s ``[buffer]`` says (``where``: its table)."""
    _check_ring(src, driver, where)
    return Source(src.name, driver, src.buffer.seconds, _overrun(src), *_timebase(src, driver))


def _overrun(src: SourceSpec) -> str:
    """Return the ring's policy: "auto" is the driver's.

    The driver's is lossless back-pressure for files, drop-oldest for live devices (node.scene.registry).
    """
    overrun = src.buffer.overrun
    return driver_spec(src.type).overrun if overrun == "auto" else overrun


def _timebase(src: SourceSpec, driver) -> tuple[str, float, float]:
    """Return ``(timebase, time_offset, time_rate)`` of a source (see node.runtime.sources.Source).

    As its driver's spec says: files keep their own time, a live driver's samples are put on host time by a
    clock model.
    """
    return driver_spec(src.type).timebase_of(src.options, driver)


def _model(stream: Stream) -> TextureModel:
    """Return the model of a fused stream (the schema refuses to fuse a stream without one)."""
    assert stream.model is not None, f"stream {stream.name!r} is fused: the schema requires its model"
    return stream.model


def _aligned_windows(scene: Scene, a: Stream, b: Stream, windows: dict, asked: str, instead: str):
    """Return ``((x_a, y), (x_b, y))``: windows kept when both streams' models were trained on the spot.

    Checked to be the two senses of the same contacts (what learning a fusion on them needs).
    """
    if not (windows[a.name] and windows[b.name]):
        raise SceneError(f"{scene.source}: [fusion] {asked} needs both streams' models trained on the spot "
                         f"(train_on_start) on the same textures; give {instead} instead")
    (xa, ya), (xb, yb) = windows[a.name][0], windows[b.name][0]
    if _model(a).classes != _model(b).classes or len(xa) != len(xb) or not np.array_equal(ya, yb):
        raise SceneError(f"{scene.source}: [fusion] {asked}: the two streams were not trained on the two senses of "
                         f"the same contacts (a two-sense set); give {instead} instead")
    return (xa, ya), (xb, yb)


def _early_model(scene: Scene, a: Stream, b: Stream, held_out: dict, trained: dict, progress):
    """Return the early-fusion network, loaded from ``[fusion] model`` or trained on the spot.

    Loaded, it is checked against both streams' pipelines; trained on the spot, it learns on both streams'
    aligned training windows (the two senses of the same training contacts) and is calibrated on their
    out-of-fold windows, its accuracy on their held-out windows said beside each stream's.
    """
    from supramodal.fused_model import EarlyFusionModel, Sense

    assert scene.fusion is not None, "an early fusion is built for a scene with a [fusion]"
    path = scene.fusion.model
    if path is not None:
        try:
            model = EarlyFusionModel.load(scene.resolve(path))
            for sense, stream in zip(model.senses, (a, b)):
                sense.check_pipeline(stream.pipeline)
        except ModelError as exc:
            raise SceneError(f"{scene.source}: [fusion] model: {exc}") from None
        return model
    (xa, ya), (xb, _) = _aligned_windows(scene, a, b, trained, 'method = "early"', "a [fusion] model file")
    # Augmented as each stream's model was asked to be ([model] augment_*), each sense's columns by its bank
    specs = {spec.name: spec for spec in scene.streams}
    try:
        model = EarlyFusionModel.train((Sense.of(a.name, a.pipeline), Sense.of(b.name, b.pipeline)), xa, xb, ya,
                                       _model(a).classes, jobs=default_jobs(),
                                       augment=(specs[a.name].model.gain_augment(), specs[b.name].model.gain_augment()))
    except InputError as exc:
        raise SceneError(f"{scene.source}: [fusion] method = \"early\": {exc}") from None
    if progress:
        from supramodal.calibration import calibration_line

        (ta, tya), (tb, _) = held_out[a.name][0], held_out[b.name][0]
        right = {a.name: _model(a).log_posteriors(ta),
                 b.name: _model(b).log_posteriors(tb)[:, _order(_model(b), _model(a))],
                 "early": model.log_posteriors(ta, tb)}
        progress(f"fusion: early network trained on {len(ya)} aligned windows of {a.name} and {b.name}, "
                 + calibration_line(None if model.calibration is None else model.calibration.fitted_on))
        progress(f"fusion: {len(tya)} held-out windows right: "
                 + ", ".join(f"{name} {np.mean(winner(lp) == tya):.3f}" for name, lp in right.items()))
    return model


def _contacts(scene: Scene, streams: list[Stream], fusion: LateFusion | None) -> dict[str, tuple[ContactListener,
                                                                                                ContactTimeline]]:
    """Return the listener and timeline of each contact signal the scene names (``[decision] contact_from``).

    One per signal, given to the streams and the fusion that read it. Their sources must be on the host's
    clock: the signal's edges are.
    """
    contacts: dict[str, tuple[ContactListener, ContactTimeline]] = {}
    by_name = {s.name: s for s in streams}
    readers: list[tuple[str, str, list[Stream], Stream | LateFusion]] = [
        (spec.contact_from, spec.where, [by_name[spec.name]], by_name[spec.name])
        for spec in scene.streams if spec.contact_from is not None]
    if scene.fusion is not None and scene.fusion.contact_from is not None and fusion is not None:
        readers.append((scene.fusion.contact_from, f"{scene.source}: [fusion]",
                        [by_name[n] for n in scene.fusion.streams], fusion))
    for address, where, read, reader in readers:
        for stream in read:
            if stream.source.timebase != "host":
                raise SceneError(f"{where}: [decision] contact_from = {address!r}: the robot's contacts are on this "
                                 f"host's clock, and source {stream.source.name!r} keeps its own time (a file "
                                 "replayed at max speed): replay it in real time (--speed 1), or leave contact_from "
                                 "out and let the input's level say the contacts (contact_threshold)")
        if address not in contacts:
            contacts[address] = (contact_listener(address), ContactTimeline(address))
        reader.touches = contacts[address][1]
    return contacts


def _check_fusion_decision(scene: Scene, models) -> None:
    """Refuse ``[fusion.decision]`` rules the fusion cannot follow with these ``models``, naming the fix.

    ``models``: the two senses', or the early network. Refused before anything starts.
    """
    assert scene.fusion is not None, "checked for a scene with a [fusion]"
    try:
        refuse_uncalibrated(scene.fusion.decision, models, f"{scene.source}: [fusion.decision]")
    except InputError as exc:
        raise SceneError(str(exc)) from None


def _order(model: TextureModel, reference: TextureModel) -> NDArray[np.intp]:
    """Columns of ``model``'s posteriors in ``reference``'s class order."""
    return np.array([list(model.classes).index(c) for c in reference.classes], dtype=np.intp)


def _learned_weight(scene: Scene, a: Stream, b: Stream, held_out: dict, trained: dict, progress) -> dict[str, float]:
    """Return the late fusion learned for two models trained on the spot.

    The weight and sharpness (:func:`supramodal.fused_model.learn_late_fusion_out_of_fold`) on out-of-fold
    log-posteriors of their training windows (aligned: the two senses of the same training contacts), each
    from a copy of the stream's model trained without the window's fold, never from the models on their own
    training windows; the fused decisions' pooling fitted on the same windows. Said beside each stream's and
    the fusion's accuracy on the held-out windows.

    Returns ``{"weight", "sharpness", "correlation"}``.
    """
    from supramodal.fused_model import fused_pooling, learn_late_fusion_out_of_fold, senses_out_of_fold
    from supramodal.fusion import fuse_late

    (xa, ya), (xb, _) = _aligned_windows(scene, a, b, trained, f'weight = "{LEARN}"', "a number")
    say = None if progress is None else (lambda m: progress(f"fusion: out-of-fold windows, {m}"))
    (la, lb), folds, _ = senses_out_of_fold((_model(a), _model(b)), (xa, xb), ya, _model(a).classes, progress=say,
                                            names=(a.name, b.name))
    late = learn_late_fusion_out_of_fold(la, lb, ya, folds)
    correlation = fused_pooling(late["fused"], ya, folds)
    if progress:
        progress(f"fusion: learned weight {late['weight']:.2f} of {a.name} (and {1 - late['weight']:.2f} of {b.name}), "
                 f"sharpness {late['sharpness']:.3g}, on {len(ya)} out-of-fold training windows "
                 f"({len(np.unique(folds))} folds)")
        (ta, tya), (tb, _) = held_out[a.name][0], held_out[b.name][0]
        ha, hb = _model(a).log_posteriors(ta), _model(b).log_posteriors(tb)[:, _order(_model(b), _model(a))]
        fused = fuse_late(ha, hb, late["weight"], late["sharpness"])
        progress(f"fusion: {len(tya)} held-out windows right: "
                 + ", ".join(f"{name} {np.mean(winner(lp) == tya):.3f}"
                             for name, lp in ((a.name, ha), (b.name, hb), ("fused", fused))))
    return {"weight": late["weight"], "sharpness": late["sharpness"], "correlation": correlation}


def build_node(scene: Scene, speed=None, sinks_override=None, progress=None, recorder=None,
               overwrite: bool = False) -> Graph:
    """Build everything a scene describes, wired and ready to :meth:`Graph.run`.

    Its sources, the streams that read them, the fusion and the sinks (one builder for both forms of a scene;
    a one-source scene is the graph of one source and one stream, both ``"main"``).

    ``speed``: the command line's ``--speed``. ``sinks_override``: sinks that replace the scene's
    (its file sinks are then not made). ``recorder``: a :class:`~supramodal.node.runtime.taps.recorder.SessionRecorder`
    for a one-source scene, or ``{source name: recorder}``. ``overwrite``: whether the scene's file
    sinks may replace existing files (``run --force``). Sink files are checked here, before any
    training, and created only when first written; a refused scene leaves no file and no outlet.
    """
    from supramodal.node.runtime.fusion import EarlyFusion, LateFusion

    made: list[tuple[SinkSettings, SinkSpec, Any]] = []     # the scene's sinks and taps, as made
    try:
        if sinks_override is None:              # files checked before any training
            _make_sinks(scene, "nothing", made, overwrite)
        sources: dict[str, tuple[Source, Labels, object]] = {}
        streams = []
        held_out: dict[str, list] = {}          # stream -> [(x_test, y_test)] of a model trained on the spot
        trained: dict[str, list] = {}           # stream -> [(x_train, y_train)] of it
        shared: dict = {}                       # what the sources share, made once (node.scene.registry)
        plans: dict[str, StreamPlan] = {}
        banks: dict[str, Bank] = {}
        loaded: dict[str, TextureModel | None] = {}     # stream -> its model file, read once
        for spec in scene.streams:              # every driver and pipeline first, no model yet
            bank = bank_for(scene, spec)
            pipeline = pipeline_for(scene, bank, spec)
            if spec.source not in sources:      # one driver per source, whatever reads it
                src = scene.source_named(spec.source)
                driver, labels, ts = driver_for(scene, bank, speed, shared, src)
                sources[spec.source] = (_source(src, driver, scene.buffer_table(src.name)), labels, ts)
            loaded[spec.name] = _model_file(scene, spec)
            plans[spec.name] = StreamPlan(pipeline, _planned_classes(spec, bank, sources[spec.source][2],
                                                                     loaded[spec.name]))
            banks[spec.name] = bank
        if sinks_override is None:              # outlets up before any training: consumers resolve them meanwhile
            f = scene.fusion
            _make_sinks(scene, "plans", made, overwrite, plans=plans,
                        fused_classes=None if f is None else plans[f.streams[0]].classes,
                        fused_inputs=() if f is None else tuple(f.streams))
        for spec in scene.streams:
            pipeline, bank = plans[spec.name].pipeline, banks[spec.name]
            source, labels, ts = sources[spec.source]
            held_out[spec.name], trained[spec.name] = [], []
            model = _model_for(scene, spec, bank, pipeline, ts, progress, held_out[spec.name], trained[spec.name],
                               loaded[spec.name])
            if (() if model is None else tuple(model.classes)) != plans[spec.name].classes:
                raise AssertionError(f"stream {spec.name}: the model's classes are not the planned "
                                     f"{plans[spec.name].classes}")
            try:
                # where a refused mapping is set: [driver] in a one-source scene, the stream's table in a graph
                setting = ("the scene's [driver] mapping" if len(scene.sources) == 1 and spec.name == MAIN_STREAM
                           else f"[[stream]] {spec.name}'s mapping")
                streams.append(Stream(spec.name, source, pipeline, model, spec.decision, spec.mapping, labels,
                                      mapping_setting=setting))
            except ValueError as exc:
                raise SceneError(f"{spec.where}: {exc}") from None
        for src in scene.sources:               # sources only sent on (a relay's): no bank, their own rate
            if src.name not in sources:
                driver, labels, ts = driver_for(scene, None, speed, shared, src)
                sources[src.name] = (_source(src, driver, scene.buffer_table(src.name)), labels, ts)
        del shared                              # the drivers hold what they need
        fusion: LateFusion | None = None         # (an EarlyFusion is a LateFusion)
        f = scene.fusion
        if f is not None:
            a, b = (next(s for s in streams if s.name == n) for n in f.streams)
            # Two files keep their own time: waiting on the host's clock would make their
            # fused decisions depend on how fast this machine runs them.
            files = {a.source.timebase, b.source.timebase} <= {"stream", "recorded"}
            max_wait = None if files else f.max_wait
            _check_fusion_decision(scene, (_model(a), _model(b)))
            if f.decision.scope == "contact" and f.contact_from is None:
                for s in (a, b):                # the fusion's contacts are its streams' touches
                    if s.contact is None:
                        s.contact = ContactDetector(s.pipeline.window_samples, f.decision.contact_threshold)
            try:
                if f.method == "early":
                    model = _early_model(scene, a, b, held_out, trained, progress)
                    _check_fusion_decision(scene, (model,))
                    fusion = EarlyFusion((a.name, b.name), (_model(a).classes, _model(b).classes), model, max_wait,
                                         f.decision, window_seconds=_window_seconds(a))
                else:
                    # A number: the scene's weight (and sharpness, where the scene gives one);
                    # "learn": learned with the sharpness and the fused pooling on out-of-fold windows.
                    if f.weight == LEARN:
                        late = _learned_weight(scene, a, b, held_out, trained, progress)
                    else:
                        late = {"weight": float(f.weight), "sharpness": f.sharpness, "correlation": f.correlation}
                    fusion = LateFusion((a.name, b.name), (_model(a).classes, _model(b).classes), late["weight"],
                                        max_wait, f.decision, sharpness=late["sharpness"],
                                        correlation=late["correlation"], window_seconds=_window_seconds(a))
            except SceneError:
                raise                           # says its table already
            except ValueError as exc:
                raise SceneError(f"{scene.source}: [fusion] {exc}") from None
        contacts = _contacts(scene, streams, fusion)
        if sinks_override is None:
            _make_sinks(scene, "streams", made, overwrite, streams={s.name: s for s in streams},
                        fused_classes=None if fusion is None else fusion.classes,
                        fused_inputs=() if fusion is None else tuple(fusion.inputs))
            readers: dict[str, list] = {}
            for stream, spec in zip(streams, scene.streams):
                readers.setdefault(spec.source, []).append((stream.pipeline.bank, spec.mapping))
            _make_sinks(scene, "sources", made, overwrite,
                        sources={name: _source_plan(scene.source_named(name), s.driver, readers.get(name, []))
                                 for name, (s, _, _) in sources.items()})
        made.sort(key=lambda m: m[0].index)     # the scene's order
        windows = [(settings, sink) for settings, spec, sink in made if spec.listens == "windows"]
        taps = []
        for settings, sink_spec, tap in made:
            if sink_spec.listens == "samples":
                assert settings.source is not None, "a sink of samples names its source (the schema's SOURCE key)"
                taps.append((settings.source, tap))
        if sinks_override is not None:
            sinks, routes = list(sinks_override), None
        else:
            sinks, routes = [sink for _, sink in windows], [settings.routes for settings, _ in windows]
        return Graph([s for s, _, _ in sources.values()], streams, sinks, routes=routes, fusion=fusion,
                     recorder=recorder, taps=taps, contacts=contacts.values())
    except BaseException:
        for _, _, sink in made:                 # a refused scene leaves no file behind, no outlet open
            sink.close()
        raise


def _window_seconds(stream) -> float:
    """Seconds between a stream's windows (its pipeline's window at its bank's rate)."""
    return stream.pipeline.window_samples / stream.pipeline.bank.fs
