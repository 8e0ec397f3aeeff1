"""Scene -> Node: the one place that knows which driver, bank, model and sinks a scene means.

Only what a scene needs is imported or built: a scene without a microphone never
imports sounddevice, one without a serial port never imports pyserial, features
not asked for are not computed, and there is no classifier without a model.
"""

from __future__ import annotations


import numpy as np

from supramodal.node.band import warn_if_beyond_band
from supramodal.node.graph import Labels, Node
from supramodal.node.scene import Scene, SceneError
from supramodal.node.sinks import QueuedSink, make_sink
from supramodal.bankfile import BANK_KEYS, BankFileError, bank_from_description, load_bank
from supramodal.banks import Bank
from supramodal.errors import InputError
from supramodal.model import ModelError, TextureModel
from supramodal.pipeline import FeaturePipeline
from supramodal.training import split, texture_features


def _given(options: dict, names: dict) -> dict:
    """The scene options the scene sets, renamed to keyword arguments; a None option is left
    out so that the driver's or the bank's own default applies (its one home)."""
    return {arg: options[key] for key, arg in names.items() if options[key] is not None}


def bank_for(scene: Scene) -> Bank:
    """The scene's bank: its [bank] file, or its kind's recipe with the keys the scene sets."""
    b = scene.bank
    try:
        if b["file"] is not None:
            return load_bank(scene.resolve(b["file"]))
        keys = BANK_KEYS[b["kind"]]
        return bank_from_description({"kind": b["kind"], **{k: v for k, v in b.items() if k in keys and v is not None}},
                                     f"{scene.source}: [bank]")
    except BankFileError as exc:
        raise SceneError(str(exc) if b["file"] is None else f"{scene.source}: [bank] file: {exc}") from None


def pipeline_for(scene: Scene, bank: Bank) -> FeaturePipeline:
    f = scene.features
    try:
        return FeaturePipeline(bank, f["names"], f["window"], dtype=np.dtype(f["dtype"]), peak_mode=f["peak_mode"],
                               nonfinite=f["nonfinite"], peak_threshold=f["peak_threshold"])
    except ValueError as exc:
        raise SceneError(f"{scene.source}: [features] {exc}") from None


def _texture_set(scene: Scene, spec: str):
    from supramodal.textures import load_texture_set, reference_texture_set

    return reference_texture_set(scene.bank["kind"]) if spec == "reference" else load_texture_set(scene.resolve(spec))


def synth_session(scene: Scene, bank: Bank):
    """The synth driver's signal: each texture for ``seconds`` in ``order``, with its labels.

    With ``held_out`` the segment is the *last* ``seconds`` of the texture's full-length
    signal: the part a model trained on the spot (on the first ``TRAIN_FRACTION``) has never seen.
    """
    from supramodal.training import TRAIN_FRACTION

    d = scene.driver
    ts = _texture_set(scene, d["textures"])
    if abs(ts.fs - bank.fs) > 1e-9 * bank.fs:
        raise SceneError(f"{scene.source}: [driver] texture set {ts.name!r} is at {ts.fs:g} Hz, the bank at {bank.fs:g} Hz")
    order = d["order"] or list(ts.names)
    unknown = [n for n in order if n not in ts.names]
    if unknown:
        raise SceneError(f"{scene.source}: [driver] order: unknown texture(s) {unknown}; the set has {list(ts.names)}")
    n = int(round(d["seconds"] * ts.fs))
    parts, labels, t = [], [], 0.0
    for name in order:
        i = ts.names.index(name)
        if d["held_out"]:
            full = ts.synthesize(i)
            held_out = 1 - TRAIN_FRACTION
            if n > held_out * full.size + 1:
                raise SceneError(f"{scene.source}: [driver] seconds: held-out segments are at most the last "
                                 f"{held_out:.0%} of the set's {ts.duration:g} s; ask for {held_out * ts.duration:g} s "
                                 "or less")
            seg = full[-n:]
        else:
            seg = ts.synthesize(i, duration=d["seconds"])
        parts.append(seg)
        labels.append((t, t + seg.size / ts.fs, name))
        t += seg.size / ts.fs
    return ts, np.concatenate(parts)[:, None], Labels(labels)


def train_on_texture_set(ts, pipeline: FeaturePipeline, progress=None) -> TextureModel:
    """The model the default scene trains on the spot: Fig. 3's training part of each texture,
    computed with the scene's own pipeline settings."""
    p = pipeline
    values, _ = texture_features(ts, p.bank, p.features, p.window, peak_mode=p.peaks.mode,
                                 peak_threshold=p.peaks.threshold)
    x_train, y_train, _, _ = split(values)
    if progress:
        progress(f"trained on {len(x_train)} windows of {len(ts.textures)} textures ({', '.join(p.features)})")
    return TextureModel.train_for(p, x_train, y_train, ts.names, seed=0)


def driver_for(scene: Scene, bank: Bank, speed_override=None):
    """Build the scene's driver; returns ``(driver, labels, texture_set_or_None)``."""
    d = scene.driver
    kind = d["type"]
    if kind in ("synth", "replay"):
        # Speed and block size: the replay driver's defaults unless the scene or --speed sets them.
        replay = _given({**d, "speed": speed_override if speed_override is not None else d["speed"]},
                        {"speed": "speed", "block": "block_size"})
    if kind == "synth":
        from supramodal.replay.driver import ReplayDriver

        ts, data, labels = synth_session(scene, bank)
        return ReplayDriver((data, bank.fs), on_notice=None, **replay), labels, ts
    if kind == "replay":
        from supramodal.replay.driver import ReplayDriver

        path = scene.resolve(d["path"])
        if not path.exists():
            raise SceneError(f"{scene.source}: [driver] path: no recording at {path} (a relative path is taken from "
                             "the scene file's folder)")
        drv = ReplayDriver(str(path), rate=bank.fs, loop=d["loop"],
                           on_notice=None, **replay)  # notices reach the sinks as events
        warn_if_beyond_band(bank, drv.source_rate, f"{scene.source}: [driver] path {d['path']}")
        return drv, Labels.of(drv), None
    if kind == "serial":
        from supramodal.drivers.serial_whisker import SerialWhiskerDriver

        return SerialWhiskerDriver(d["port"], rate=d["rate"], channels=d["channels"], on_notice=None,
                                   **_given(d, {"baudrate": "baudrate"})), Labels(), None
    if kind == "microphone":
        from supramodal.drivers.microphone import MicrophoneDriver

        options = _given(d, {"device": "device", "rate": "rate", "channels": "channels", "block": "blocksize",
                             "dtype": "dtype", "buffer_seconds": "buffer_seconds"})
        return MicrophoneDriver(**options), Labels(), None
    raise SceneError(f"{scene.source}: [driver] type {kind!r} is not supported")


def build_node(scene: Scene, speed=None, sinks_override=None, progress=None, recorder=None,
               overwrite: bool = False) -> Node:
    """Everything a scene describes, wired and ready to :meth:`Node.run`.

    ``overwrite``: whether the scene's file sinks may replace existing files (``run --force``).
    Sink files are checked here, before any training, and created only when first written.
    """
    bank = bank_for(scene)
    pipeline = pipeline_for(scene, bank)
    paths = [s["path"] if s["path"] == "-" else str(scene.resolve(s["path"])) for s in scene.sinks]
    sinks = sinks_override
    if sinks is None:
        sinks = []
        for i, (s, p) in enumerate(zip(scene.sinks, paths)):
            try:
                # Behind its own queue: processing never waits on a slow disk or a stalled terminal.
                sinks.append(QueuedSink(make_sink(s["type"], p, overwrite)))
            except InputError as exc:
                raise SceneError(f"{scene.source}: [[sink]] #{i + 1} path: {exc}") from None
    driver, labels, ts = driver_for(scene, bank, speed)
    model = None
    m = scene.model
    if m["train_on_start"]:
        # Synthesised textures: the model is made on the spot (the default scene does this); a
        # live or replayed source gets the bank's reference set (the mock board plays it).
        if ts is None:
            from supramodal.textures import reference_texture_set

            ts = reference_texture_set(bank.kind)
            if abs(ts.fs - bank.fs) > 1e-9 * bank.fs:
                raise SceneError(f"{scene.source}: [model] train_on_start: the {bank.kind} reference textures are "
                                 f"at {ts.fs:g} Hz, the bank at {bank.fs:g} Hz; give a [model] path instead")
        model = train_on_texture_set(ts, pipeline, progress)
        if m["path"] is not None:
            model.save(scene.resolve(m["path"]))
    elif m["path"] is not None:
        model = TextureModel.load(scene.resolve(m["path"]))
    if model is not None:
        try:
            model.check_pipeline(pipeline)
        except ModelError as exc:
            raise SceneError(f"{scene.source}: [model] {exc}") from None
    mapping = scene.driver.get("mapping", "auto")
    overrun = scene.buffer["overrun"]
    if overrun == "auto":
        overrun = "block" if scene.driver["type"] in ("replay", "synth") else "drop-oldest"
    try:
        return Node(driver, pipeline, sinks, model=model, decision=scene.decision, mapping=mapping, labels=labels,
                    buffer_seconds=scene.buffer["seconds"], overrun=overrun, recorder=recorder)
    except ValueError as exc:
        # A refused scene leaves nothing behind: its sinks have written nothing, so no file exists.
        if sinks_override is None:
            for sink in sinks:
                sink.close()
        raise SceneError(f"{scene.source}: {exc}") from None
