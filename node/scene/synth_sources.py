"""Sources the model synthesises: the ``synth`` and ``twosense`` driver types.

Both generate their whole signal with the model's texture synthesis (:mod:`supramodal.textures`,
:mod:`supramodal.twosense`) and play it through the replay driver, so their specs live in the
node (a driver module knows no DSP). Each is a :class:`~supramodal.drivers.spec.DriverSpec`
registered in :mod:`supramodal.node.scene.registry`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from supramodal.checks import Key, flag, integer, non_negative, number, one_of, positive, text, texts
from supramodal.drivers.spec import BuildContext, Built, DriverSpec, OptionError
from supramodal.errors import InputError
from supramodal.replay.driver import DeviceClock, ReplayDriver, block_key, pacing, speed_key

__all__ = ["MAX_SYNTH_SAMPLES", "SYNTH", "TWOSENSE", "synth_session", "twosense_session"]

#: Most pairs of a two-sense set (each pair of pairs is 4 textures to synthesise and train on).
MAX_PAIRS = 25
#: Latest start of a two-sense source after the graph's, seconds: a device that starts later than
#: a minute after its partner pairs no window with it.
MAX_OFFSET = 60.0
#: Samples a synthesised source may hold in memory, all its textures together (1 GiB of float64):
#: a synth or two-sense source is generated whole before it plays.
MAX_SYNTH_SAMPLES = 2**27


def _checked_length(options: Mapping[str, Any], order: list, fs: float) -> int:
    """Return the samples per texture of a synthesised source.

    A length that cannot be held is refused naming ``seconds`` (and ``order`` when it is the number of textures).
    """
    from supramodal.textures import texture_samples

    try:
        n = texture_samples(options["seconds"], fs)
    except InputError as exc:
        raise OptionError(f"seconds: {exc}") from None
    if n * len(order) > MAX_SYNTH_SAMPLES:
        raise OptionError(f"seconds x order: {len(order)} textures of {options['seconds']:g} s at {fs:g} Hz are "
                          f"{n * len(order):.3g} samples, more than the {MAX_SYNTH_SAMPLES} a synthesised source may "
                          f"hold ({MAX_SYNTH_SAMPLES / fs / 60:.0f} min at this rate); give fewer seconds per texture"
                          + (" or set loop = true" if "loop" in options else ""))
    return n


def _order(options: Mapping[str, Any], names) -> list:
    order = options["order"] or list(names)
    unknown = [n for n in order if n not in names]
    if unknown:
        raise OptionError(f"order: unknown texture(s) {unknown}; the set has {list(names)}")
    return order


def _texture_set(options: Mapping[str, Any], context: BuildContext):
    from supramodal.textures import load_texture_set, reference_texture_set

    spec = options["textures"]
    kind = context.bank.kind if context.bank is not None else "whisker"
    return reference_texture_set(kind) if spec == "reference" else load_texture_set(context.resolve(spec))


def synth_session(options: Mapping[str, Any], context: BuildContext):
    """Return the synth driver's signal: each texture for ``seconds`` in ``order``, with its labels.

    With ``held_out`` the segment is the *last* ``seconds`` of the texture's full-length
    signal: the part a model trained on the spot (on the first ``TRAIN_FRACTION``) has never seen.

    Returns
    -------
    (TextureSet, ndarray of shape (samples, 1), tuple of (start_s, end_s, name))
    """
    from supramodal.training import TRAIN_FRACTION

    ts = _texture_set(options, context)
    bank = context.bank
    if bank is not None and abs(ts.fs - bank.fs) > 1e-9 * bank.fs:
        raise OptionError(f"texture set {ts.name!r} is at {ts.fs:g} Hz, the bank at {bank.fs:g} Hz")
    order = _order(options, ts.names)
    n = _checked_length(options, order, ts.fs)
    parts, labels, t = [], [], 0.0
    for name in order:
        i = ts.names.index(name)
        if options["held_out"]:
            full = ts.synthesize(i)
            held_out = 1 - TRAIN_FRACTION
            if n > held_out * full.size + 1:
                raise OptionError(f"seconds: held-out segments are at most the last {held_out:.0%} of the set's "
                                  f"{ts.duration:g} s; ask for {held_out * ts.duration:g} s or less")
            seg = full[-n:]
        else:
            seg = ts.synthesize(i, duration=options["seconds"])
        parts.append(seg)
        labels.append((t, t + seg.size / ts.fs, name))
        t += seg.size / ts.fs
    return ts, np.concatenate(parts)[:, None], tuple(labels)


def _build_synth(options: Mapping[str, Any], context: BuildContext) -> Built:
    ts, data, labels = synth_session(options, context)
    return Built(ReplayDriver((data, ts.fs), on_notice=None, **pacing(options, context)), labels=labels,
                 training_set=ts)


SYNTH = DriverSpec(
    type="synth",
    summary="the model's synthesised textures (a texture set), played as the device would deliver them",
    keys={
        "textures": Key(text, '"reference" or a texture-set JSON path', "reference", path=True, words=("reference",)),
        "seconds": Key(positive(), "seconds per texture, > 0", 10.0),
        "order": Key(texts, "a list of texture names", None),
        "speed": speed_key(),
        "block": block_key(),
        "held_out": Key(flag, "true or false", True),
    },
    build=_build_synth, live=False)


def twosense_session(options: Mapping[str, Any], context: BuildContext):
    """Return a two-sense source's signal: one sense of the two-sense world (supramodal.twosense).

    Each texture for ``seconds`` in ``order``, contact ``take`` (by default 1: contacts the model trained
    on the spot never met).

    Returns
    -------
    (OneSense, ndarray of shape (samples, 1), tuple of (start_s, end_s, name), float)
        The sense's training set, the signal, its labels and the labels' period when it loops
        (None otherwise).
    """
    from supramodal.twosense import OneSense, two_sense_set

    surfaces = two_sense_set(options["pairs"], options["set_seed"])
    train = OneSense(surfaces, options["sense"], seed=options["set_seed"])
    bank = context.bank
    if bank is not None and abs(train.fs - bank.fs) > 1e-9 * bank.fs:
        raise OptionError(f"sense {options['sense']!r} is sampled at {train.fs:g} Hz, the bank at {bank.fs:g} Hz: "
                          "give the whiskers a whisker bank and the microphone a cochlea bank")
    order = _order(options, train.names)
    n = _checked_length(options, order, train.fs)
    played = OneSense(surfaces, options["sense"], options["seconds"], options["set_seed"], take=options["take"])
    parts = [played.synthesize(train.names.index(name)) for name in order]
    step = n / train.fs                  # each texture's samples, in stream seconds
    labels = tuple((k * step, (k + 1) * step, name) for k, name in enumerate(order))
    return train, np.concatenate(parts)[:, None], labels, (len(order) * step if options["loop"] else None)


def _build_twosense(options: Mapping[str, Any], context: BuildContext) -> Built:
    ts, data, labels, period = twosense_session(options, context)
    # Paced like a live device on its own crystal: the node sees only the arrivals.
    clock = DeviceClock(options["clock_ppm"], options["offset"], options["jitter"],
                        seed=options["set_seed"] * 2 + (options["sense"] == "whiskers"))
    driver = ReplayDriver((data, ts.fs), on_notice=None, device_clock=clock, loop=options["loop"],
                          **pacing(options, context))
    return Built(driver, labels=labels, label_period=period, training_set=ts)


def _twosense_timebase(options: Mapping[str, Any], driver) -> tuple[str, float, float]:
    """Return a two-sense source's ``(timebase, time_offset, time_rate)``, by its speed.

    At ``max`` speed a two-sense source is a file whose true timing is known (its offset and
    clock error); at a finite speed it is paced like a live device, and the node sees only arrivals.
    """
    if driver.speed == math.inf:
        return "stream", options["offset"], driver.rate * (1.0 + options["clock_ppm"] * 1e-6)
    return "host", 0.0, driver.rate * driver.speed


TWOSENSE = DriverSpec(
    type="twosense",
    summary="one sense of the two-sense world (whiskers or microphone), on a simulated device clock",
    keys={
        "sense": Key(one_of("whiskers", "microphone"), '"whiskers" or "microphone": which side of the two-sense '
                                                        'world this source plays'),
        "set_seed": Key(integer(0), "the two-sense set's seed, an integer >= 0", 0),
        "pairs": Key(integer(1, MAX_PAIRS), f"heard pairs and felt pairs in the set, 1..{MAX_PAIRS} (4 textures "
                                            "a pair of pairs)", 2),
        "seconds": Key(positive(), "seconds per texture, > 0", 10.0),
        "order": Key(texts, "a list of texture names", None),
        "offset": Key(non_negative(MAX_OFFSET), "seconds after the graph's start at which this source's first "
                                                "sample is taken, 0 to " + f"{MAX_OFFSET:g}", 0.0),
        "take": Key(integer(0), "which contact of each texture it plays, an integer >= 0 (0: the one a model "
                                "trained on the spot learns from)", 1),
        "loop": Key(flag, "true or false: play the contacts again and again", False),
        "clock_ppm": Key(number(-1000, 1000), "the simulated device's crystal error, ppm, within +-1000", 0.0),
        "jitter": Key(non_negative(1.0), "mean delivery delay of a block, seconds, 0 to 1 (at a finite speed)", 0.0),
        "speed": speed_key(),
        "block": block_key(),
    },
    build=_build_twosense, live=False, timebase=_twosense_timebase,
    signal_type=lambda options: "Whiskers" if options["sense"] == "whiskers" else "Audio")
