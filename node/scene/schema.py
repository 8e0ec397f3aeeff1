"""Scenes: what a node runs, as a TOML file validated before anything starts.

A scene names the driver and its options, the bank, the features and window,
the model (optional: without one the node emits feature windows), how decisions
are pooled, and the sinks. Every key is checked against the schema below;
an unknown key, a wrong type or a value out of range is refused with a message
naming the key. Nothing in a scene is executed.

Example (the embedded default is ``default_scene()``)::

    [driver]
    type = "replay"            # a driver type (node.scene.registry; docs/node.md lists each with its keys)
    path = "session.wav"       # replay: WAV file or recorded session
    speed = 1.0                # replay/synth: 1.0 real time (default), 2.0 twice as fast, "max"
    block = 50                 # frames per block (default: 10 ms)

    [bank]
    kind = "whisker"           # whisker | cochlea
    rows = "ABCDE"             # whisker rows

    [features]
    names = ["Af"]
    window = 0.1               # seconds (default 0.1)

    [model]
    path = "whisker.npz"

    [decision]
    scope = "contact"          # window | last | contact
    n = 10

    [[sink]]
    type = "text"              # text | jsonl
    path = "-"                 # "-" is stdout
"""

from __future__ import annotations

import json
import math
import os
import tomllib
from dataclasses import asdict
from pathlib import Path

from supramodal.bankfile import BANK_KEYS
from supramodal.checks import NAME_HELP, Key, fill, flag, integer, is_name, non_negative, number, one_of, positive, text
from supramodal.decisions import DEFAULT_DECISION, METHODS, SCOPES, DecisionRules
from supramodal.drivers.contact import check_contact_from
from supramodal.drivers.spec import OptionError
from supramodal.errors import InputError
from supramodal.features import DEFAULT_WINDOW, FEATURE_TABLE
from supramodal.model import DEFAULT_AUGMENT_SPREAD, GAIN_MODES, MAX_AUGMENT_COPIES, MAX_AUGMENT_SPREAD
from supramodal.node.runtime.events import FUSED_STREAM, MAIN_STREAM
from supramodal.node.runtime.fusion import DEFAULT_MAX_WAIT, DEFAULT_WEIGHT
from supramodal.node.runtime.sinks.spec import sink_keys
from supramodal.node.scene.registry import driver_spec, driver_types, sink_spec, source_keys
from supramodal.node.scene.specs import (
    BankSpec,
    BufferSpec,
    FeaturesSpec,
    FusionSpec,
    ModelSpec,
    Scene,
    SceneError,
    SinkSettings,
    SourceSpec,
    StreamSpec,
    frozen,
)
from supramodal.peaks import DEFAULT_PEAK_MODE, PEAK_MODES

# Scene and SceneError live with the other specs (node.scene.specs); they are read from here too.
__all__ = ["FUSION_KEYS", "LEARN", "MAPPING", "ONE_SOURCE_KEYS", "SECTIONS", "SOURCE_KEYS", "STREAM_KEYS", "Scene",
           "SceneError", "default_scene", "driver_table", "fusion_from_table", "load_scene", "scene_from_dict",
           "scene_to_toml"]


#: Longest ring a scene may ask for, seconds of its source (node.scene.build also bounds its bytes).
MAX_BUFFER_SECONDS = 600.0


def _features(v):
    # the table itself, not a copy of its names made at import: a row added later (a test's) is a feature too
    return isinstance(v, list) and v and all(f in FEATURE_TABLE for f in v) and len(set(v)) == len(v)


def _rows(v):
    return isinstance(v, str) and v and set(v) <= set("ABCDE") and len(set(v)) == len(v)


# section -> key -> Key(check, what is expected, default; REQUIRED; or None). Every default has one
# home: a key whose default belongs to the driver or the bank is None here ("the owner's default":
# build.py does not pass it on); the others import their owner's constant. The drivers' keys are
# their specs' (node.scene.registry).
SECTIONS = {
    # A recipe's keys are the bank file's (supramodal.bankfile): one check for both.
    "bank": {
        "kind": Key(one_of("whisker", "cochlea"), '"whisker" or "cochlea"', "whisker"),
        **{k: Key(v.check, v.expected + f" (default: the {kind} bank's)", None)
           for kind in ("whisker", "cochlea") for k, v in BANK_KEYS[kind].items() if k != "fs"},
        "fs": Key(BANK_KEYS["whisker"]["fs"].check, BANK_KEYS["whisker"]["fs"].expected + " (default: the bank's)",
                  None),
        "file": Key(text, "a bank file (supramodal-bank JSON, e.g. from a fit), relative to the scene; "
                          "the [bank] table then holds nothing else", None, path=True),
    },
    "features": {
        "names": Key(_features, "a list of distinct names drawn from "
                     + "; ".join(f"{f.name} ({f.description})" for f in FEATURE_TABLE.values()), ["Af"]),
        "window": Key(positive(), "seconds, > 0 (at most MAX_WINDOW_SAMPLES samples)", DEFAULT_WINDOW),
        "peak_mode": Key(one_of(*PEAK_MODES), f"one of {list(PEAK_MODES)}", DEFAULT_PEAK_MODE),
        "peak_threshold": Key(non_negative(), "smallest peak amplitude counted, >= 0", 0.0),
        "dtype": Key(one_of("float64", "float32"), '"float64" or "float32"', "float64"),
        # Not the pipeline's default (whole windows): a live node runs each 10 ms as it comes, so
        # that only a window's last 10 ms is left to run when it closes (its decision latency).
        "chunk": Key(non_negative(), "seconds of each window run as soon as they are in, at fixed stream "
                                     "indices, >= 0 (0: each window whole when it closes)", 0.01),
        # Not the pipeline's default ("raise"): a live node replaces and counts a bad sample
        # rather than stopping.
        "nonfinite": Key(one_of("raise", "zero"), '"raise" or "zero"', "zero"),
    },
    "model": {
        "path": Key(text, "a model .npz path (loaded; or written when train_on_start)", None, path=True),
        "train_on_start": Key(flag, "true or false: train at start-up on the synth driver's texture set, or with "
                                    "another driver on the bank's reference set", False),
        # Gain augmentation of the model trained on start (supramodal.model.GainAugment; issue 34): opt-in, it
        # multiplies the training's CPU. A model file keeps what it was trained with (train --augment-gains).
        "augment_copies": Key(integer(0, MAX_AUGMENT_COPIES), "with train_on_start: gain augmentation, more copies "
                              "of each training window, each with its own random gains (a new touch's), an integer "
                              f"0..{MAX_AUGMENT_COPIES} (0: none; the networks cost 1 + copies times the CPU)", 0),
        "augment_spread": Key(non_negative(MAX_AUGMENT_SPREAD), "with augment_copies: the gains' spread, the standard "
                              f"deviation of their natural log, 0..{MAX_AUGMENT_SPREAD:g}", DEFAULT_AUGMENT_SPREAD),
        "augment_gains": Key(one_of("auto", *GAIN_MODES), 'with augment_copies: "per-channel" (each channel its own '
                             'gain: a whisker array\'s vibrissae), "shared" (one level for all channels: a microphone) '
                             'or "auto" (per-channel for a whisker bank, shared for a cochlea or a custom bank: say '
                             'per-channel for an array of your own)', "auto"),
    },
    "decision": {
        "scope": Key(one_of(*SCOPES), f"one of {list(SCOPES)}", DEFAULT_DECISION.scope),
        "n": Key(integer(0), "windows, an integer >= 0", DEFAULT_DECISION.n),
        "method": Key(one_of(*METHODS), f"one of {list(METHODS)}", DEFAULT_DECISION.method),
        "contact_threshold": Key(non_negative(), "input RMS, >= 0", DEFAULT_DECISION.contact_threshold),
        # The rules of issue 23, each off at 0; their meaning is supramodal.decisions.Decider's.
        "confidence": Key(number(0.0, 1.0, hi_open=True), "calibrated pooled confidence at which a contact's "
                          "decision is final, 0 <= c < 1 (0: never; needs scope = \"contact\")",
                          DEFAULT_DECISION.confidence),
        "unknown": Key(number(0.0, 1.0, hi_open=True), "share of windows of known textures allowed to be called "
                       "unknown by the novelty score, 0 <= r < 1 (0: off)", DEFAULT_DECISION.unknown),
        "unknown_below": Key(number(0.0, 1.0, hi_open=True), "calibrated confidence below which a window is unknown, "
                             "0 <= c < 1 (0: off)", DEFAULT_DECISION.unknown_below),
        "change": Key(number(0.0, 60.0), "false changes of texture per minute allowed within a contact, 0 <= f <= 60 "
                      "(0: off; needs scope = \"contact\", method = \"log\" and n = 0)", DEFAULT_DECISION.change),
        # Not a DecisionRules field: where the node reads contacts (supramodal.drivers.contact), not how it decides.
        "contact_from": Key(text, 'the robot\'s contact signal, in place of the input\'s RMS: '
                            '"ros2:TOPIC" (std_msgs/Bool) or "lsl:NAME" (a marker stream); needs scope = "contact"',
                            None),
    },
    "buffer": {
        "seconds": Key(positive(MAX_BUFFER_SECONDS), f"ring buffer capacity, seconds, up to {MAX_BUFFER_SECONDS:g} "
                                                     "(and at most MAX_RING_BYTES of samples)", 2.0),
        # "auto": "block" (lossless back-pressure) for files, "drop-oldest" for live drivers.
        "overrun": Key(one_of("auto", "drop-oldest", "drop-newest", "block"),
                       '"auto", "drop-oldest", "drop-newest" or "block"', "auto"),
    },
}


#: Longest wait of a live window for its partner, seconds (a window waits in memory).
MAX_FUSION_WAIT = 60.0
#: Largest tempering of fused log-posteriors (learned ones are about 2).
MAX_SHARPNESS = 1000.0

#: [fusion] weight: learned at start-up on the models' held-out training windows.
LEARN = "learn"

# The graph form: [[source]] (a driver's keys, and its ring), [[stream]] (a source through a
# bank, features and a model: the one-source sections as sub-tables), [fusion].
_NAME_HELP = NAME_HELP

#: Highest channel index a mapping may name.
MAX_CHANNEL_INDEX = 4095


def _mapping(v: object) -> bool:
    return v in ("auto", "mono", "per-channel", "mean") or (isinstance(v, int) and not isinstance(v, bool)
                                                             and 0 <= v <= MAX_CHANNEL_INDEX)


#: How a stream reads its source's channels into its bank's
#: (``supramodal.node.runtime.streams.channel_mapper``): a key of ``[[stream]]``, and of a one-source
#: scene's ``[driver]`` (which stands for its source and its only stream).
MAPPING = Key(_mapping, f'"auto", "mono", "per-channel", "mean" or a channel index 0..{MAX_CHANNEL_INDEX}', "auto")

SOURCE_KEYS = {"name": Key(is_name, NAME_HELP)}
STREAM_KEYS = {
    "name": Key(is_name, NAME_HELP + f" (not {FUSED_STREAM!r})"),
    "source": Key(is_name, "the name of a [[source]]"),
    "mapping": MAPPING,
}
#: A one-source scene's ``[driver]``: its driver's keys and these.
ONE_SOURCE_KEYS = {"mapping": MAPPING}
STREAM_SECTIONS = ("bank", "features", "model", "decision")
FUSION_KEYS = {
    "streams": Key(lambda v: isinstance(v, list) and len(v) == 2 and all(is_name(x) for x in v) and v[0] != v[1],
                   "the names of two different [[stream]]s, each with a model"),
    "method": Key(one_of("late", "early"), '"late" (weighted log-posteriors) or "early" (one network on both '
                                             "streams' features: the supramodal network)", "late"),
    "model": Key(text, 'with method = "early": an early-fusion model file (default: the network trained on the '
                       "spot on both streams' training windows, which needs both models trained on the spot)", None,
                  path=True),
    "weight": Key(lambda v: v == LEARN or number(0.0, 1.0)(v),
                  f'the first stream\'s weight, in [0, 1], or "{LEARN}" (learned on the held-out training windows '
                  'of two models trained on the spot)', DEFAULT_WEIGHT),
    "max_wait": Key(positive(MAX_FUSION_WAIT), "seconds a window of a live source waits for its partner before it is "
                                               f"decided alone, > 0 and at most {MAX_FUSION_WAIT:g} (file sources "
                                               "wait for each other)", DEFAULT_MAX_WAIT),
    # With a numeric weight (as `train --fusion late` prints them); "learn" learns both.
    "sharpness": Key(positive(MAX_SHARPNESS),
                     f"tempering of the fused log-posteriors, > 0 and at most {MAX_SHARPNESS:g} "
                     "(printed by `supramodal train --fusion late`)", 1.0),
    "correlation": Key(number(0.0, 1.0), "correlation of neighbouring fused windows for pooling them, in [0, 1] "
                                         "(printed by `supramodal train --fusion late`)", 0.0),
}


def _fill(where: str, given, schema: dict) -> dict:
    return fill(where, given, schema, SceneError)


def _bank(section: dict) -> BankSpec:
    keys = BANK_KEYS[section["kind"]]
    return BankSpec(section["kind"], section["file"],
                    frozen({k: v for k, v in section.items() if k in keys and v is not None}))


def _features_spec(section: dict) -> FeaturesSpec:
    return FeaturesSpec(**{**section, "names": tuple(section["names"])})


def _decision_rules(section: dict) -> DecisionRules:
    """Return the rules of a validated ``[decision]`` section (``contact_from`` is the spec's own field)."""
    return DecisionRules(**{k: v for k, v in section.items() if k != "contact_from"})


def _stream(name: str, source: str, mapping, sections: dict, where: str) -> StreamSpec:
    """Return a stream from its validated sections (``where``: how messages name it)."""
    return StreamSpec(name, source, mapping, _bank(sections["bank"]), _features_spec(sections["features"]),
                      ModelSpec(**sections["model"]), _decision_rules(sections["decision"]), where,
                      contact_from=sections["decision"]["contact_from"])


def scene_from_dict(d: dict, source: str = "<scene>", base_dir: Path | None = None) -> Scene:
    """Validate a parsed scene and fill in defaults."""
    if not isinstance(d, dict):
        raise SceneError(f"{source}: a scene is a TOML table")
    if "source" in d or "stream" in d:
        return _graph_scene(d, source, base_dir or Path.cwd())
    allowed = {"driver", "sink", *SECTIONS}
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise SceneError(f"{source}: unknown section(s) {unknown}; sections are {sorted(allowed)}"
                         + ("; a scene of several sources uses [[source]] and [[stream]]"
                            if "fusion" in unknown else ""))
    driver = d.get("driver")
    if not isinstance(driver, dict) or "type" not in driver:
        raise SceneError(f"{source}: [driver] type is required, one of {driver_types()}")
    kind, options = driver_table(f"{source}: [driver]", driver, ONE_SOURCE_KEYS)
    mapping = options.pop("mapping")
    sections = {name: _fill(f"{source}: [{name}]", d.get(name, {}), schema) for name, schema in SECTIONS.items()}
    _check_sections(source, sections, d.get("bank", {}), "")
    base = base_dir or Path.cwd()
    sinks = _sinks(d, source, (MAIN_STREAM,), base_dir=base)
    # Desugared: one source and one stream, both "main".
    src = SourceSpec(MAIN_STREAM, kind, frozen(options), BufferSpec(**sections["buffer"]), f"{source}: [driver]")
    stream = _stream(MAIN_STREAM, MAIN_STREAM, mapping, sections, source)
    return Scene((src,), (stream,), sinks, None, source, base, form="one-source")


def driver_table(where: str, table, extra: dict | None = None) -> tuple[str, dict]:
    """Return a source's table validated against its driver's keys and ``extra`` ones.

    The table is a ``[driver]`` or a ``[[source]]``, named by ``where``; the driver's keys are from
    node.scene.registry. Returns ``(driver type, its keys with defaults filled in)``, without ``type``
    and ``buffer``.
    """
    if not isinstance(table, dict):
        raise SceneError(f"{where} must be a table")
    kind = table.get("type")
    try:
        spec = driver_spec(kind)
    except InputError as exc:
        raise SceneError(f"{where} type: {exc}") from None
    kind = spec.type
    given = {k: v for k, v in table.items() if k not in ("type", "buffer")}
    if "mapping" in given and "mapping" not in (extra or {}):
        raise SceneError(f"{where} mapping: how a stream reads its source's channels is the stream's: move it to "
                         "the [[stream]] that reads this source")
    options = _fill(f"{where} ({kind})", given, {**(extra or {}), **source_keys(spec)})
    try:
        spec.check({k: v for k, v in options.items() if k not in (extra or {})})
    except OptionError as exc:
        raise SceneError(f"{where} {exc}") from None
    return kind, options


def _check_sections(source: str, sections: dict, bank_given: dict, where: str) -> None:
    """Check across keys of the one-source sections (``where``: the stream they belong to)."""
    bank = sections["bank"]
    if bank["file"] is not None and set(bank_given) - {"file"}:
        raise SceneError(f"{source}: {where}[bank] file: a bank file describes the whole bank; remove "
                         f"{sorted(set(bank_given) - {'file'})} or the file")
    if bank["file"] is None:
        kind = bank["kind"]
        foreign = sorted(set(bank_given) - {"kind"} - set(BANK_KEYS[kind]))
        if foreign:
            raise SceneError(f"{source}: {where}[bank] {foreign[0]}: a {kind} bank has no {foreign[0]!r} (its keys: "
                             f"{sorted(BANK_KEYS[kind])}); remove it, or choose the kind it belongs to")
    if sections["decision"]["scope"] == "last" and sections["decision"]["n"] < 1:
        raise SceneError(f"{source}: {where}[decision] n must be >= 1 with scope = \"last\"")
    _check_decision(source, sections["decision"], f"{where}[decision]")
    if sections["model"]["path"] is None and not sections["model"]["train_on_start"]:
        _check_no_decision(source, sections["decision"], f"{where}[decision]")
    _check_augment(source, sections["model"], f"{where}[model]")


def _check_augment(source: str, model: dict, where: str) -> None:
    """Refuse gain augmentation of a model the node does not train, and a spread or gains without copies.

    Gain augmentation is for a model the node trains (``train_on_start``), and its spread and gains for
    ``augment_copies`` >= 1; checked by value, not by presence: a scene written back states every default,
    and passes.
    """
    if model["augment_copies"] and not model["train_on_start"]:
        raise SceneError(f"{source}: {where} augment_copies = {model['augment_copies']}: gain augmentation is part of "
                         "training, and this stream's model is not trained here (a model file keeps what it was "
                         "trained with); set train_on_start = true, or train the file with `supramodal train "
                         f"--augment-gains {model['augment_copies']},{model['augment_spread']:g}"
                         + ("" if model["augment_gains"] == "auto" else f",{model['augment_gains']}")
                         + "`, or remove "
                         "augment_copies")
    idle = [k for k in ("augment_spread", "augment_gains") if model[k] != SECTIONS["model"][k].default]
    if idle and not model["augment_copies"]:
        k = idle[0]
        raise SceneError(f"{source}: {where} {k} = {_toml_value(model[k])} has no effect without gain augmentation: "
                         "set augment_copies (e.g. 4) with train_on_start = true, or remove it")


def _check_no_decision(source: str, decision: dict, where: str) -> None:
    """Refuse ``[decision]`` rules a stream without a model would silently ignore.

    A stream without a model gives feature windows: of its ``[decision]`` only ``contact_from`` (with
    ``scope = "contact"``) does anything, putting the robot's contacts on the windows. Any other rule
    set away from its default would be silently ignored: refused (a scene written back states every
    default, and passes).
    """
    defaults = asdict(DEFAULT_DECISION)
    idle = [k for k in defaults if k != "scope" and decision[k] != defaults[k]]
    if decision["scope"] != defaults["scope"] and decision["contact_from"] is None:
        idle.append("scope")                # named last: a rule that needs it is the likelier slip
    if idle:
        k = idle[0]
        raise SceneError(f"{source}: {where} {k} = {_toml_value(decision[k])}: this stream has no model, so it decides "
                         "nothing (its windows carry features); give it a [model] (path or train_on_start), or "
                         f"remove {k}" + (" (without a model, a decision table only carries contact_from, "
                                          "with scope = \"contact\")" if k == "scope" else ""))


def _check_decision(source: str, decision: dict, where: str) -> None:
    if decision["contact_from"] is not None:
        try:
            check_contact_from(decision["contact_from"])
        except InputError as exc:
            raise SceneError(f"{source}: {where} {exc}") from None
        if decision["scope"] != "contact":
            raise SceneError(f"{source}: {where} contact_from = {decision['contact_from']!r} says when the robot "
                             f"touches: it needs scope = \"contact\" (scope is {decision['scope']!r})")
    if decision["change"] and (decision["scope"] != "contact" or decision["method"] != "log" or decision["n"]):
        raise SceneError(f"{source}: {where} change = {decision['change']:g} re-decides when the texture changes "
                         f"within a contact: it needs scope = \"contact\", method = \"log\" and n = 0 (scope is "
                         f"{decision['scope']!r}, method {decision['method']!r}, n {decision['n']}; with n > 0 the "
                         "pooled decision forgets older windows by itself)")
    if decision["confidence"] and decision["scope"] != "contact":
        raise SceneError(f"{source}: {where} confidence = {decision['confidence']:g} decides a contact as soon as it "
                         f"is sure: it needs scope = \"contact\" (scope is {decision['scope']!r})")
    if decision["confidence"] and decision["method"] != "log":
        raise SceneError(f"{source}: {where} confidence needs method = \"log\": a vote's share is no probability "
                         "(one window is a unanimous vote)")


def _sinks(d: dict, source: str, streams, sources=(MAIN_STREAM,), base_dir: Path | None = None
           ) -> tuple[SinkSettings, ...]:
    """Return the [[sink]] tables, with ``from`` checked against the streams and ``source`` against the sources.

    ``source`` is filled in when there is only one; two sinks may not write one file.
    """
    sinks_in = d.get("sink", [{"type": "text"}])
    if not isinstance(sinks_in, list) or not sinks_in:
        raise SceneError(f"{source}: [[sink]] must be a list of at least one sink table")
    sinks: list[dict] = []
    for i, s in enumerate(sinks_in):
        where = f"{source}: [[sink]] #{i + 1}"
        if not isinstance(s, dict):
            raise SceneError(f"{where} must be a table")
        try:
            spec = sink_spec(s.get("type"))
        except InputError as exc:
            raise SceneError(f"{where} type: {exc}") from None
        sink = {"type": s["type"], **_fill(where, {k: v for k, v in s.items() if k != "type"}, sink_keys(spec))}
        if spec.listens == "samples":
            if sink["source"] is None and len(sources) > 1:
                raise SceneError(f"{where} source: the scene has sources {list(sources)}; name the one whose samples "
                                 "it sends")
            sink["source"] = sink["source"] or sources[0]
            if sink["source"] not in sources:
                raise SceneError(f"{where} source: no source {sink['source']!r}; the scene's sources are "
                                 f"{list(sources)}")
        same = next((k for k, o in enumerate(sinks) if spec.unique and o["type"] == sink["type"]
                     and all(o[u] == sink[u] for u in spec.unique)), None)
        if same is not None:
            said = " with ".join(f"{u} {sink[u]!r}" for u in spec.unique)
            raise SceneError(f"{where} sends {said} as [[sink]] #{same + 1} does: one stream name for two outlets; "
                             "change one, or remove one")
        if spec.listens == "samples":
            sinks.append(sink)
            continue
        if sink.get("path", "-") != "-":
            target = os.path.normpath((base_dir or Path.cwd()) / Path(sink["path"]).expanduser())
            same = next((k for k, o in enumerate(sinks) if o.get("path", "-") != "-" and target == os.path.normpath(
                (base_dir or Path.cwd()) / Path(o["path"]).expanduser())), None)
            if same is not None:
                raise SceneError(f"{source}: [[sink]] #{i + 1} path: {sink['path']!r} is the file of "
                                 f"[[sink]] #{same + 1} "
                                 "too; two sinks writing one file would interleave their lines: give each its own "
                                 "path, or one sink several streams (from = [...])")
        listens = [sink["from"]] if isinstance(sink["from"], str) else sink["from"] or []
        unknown = [n for n in listens if n not in streams]
        if unknown:
            raise SceneError(f"{source}: [[sink]] #{i + 1} from: no stream {unknown[0]!r}; the scene's streams are "
                             f"{list(streams)}")
        sinks.append(sink)
    return tuple(SinkSettings(s.pop("type"), frozen(s), i) for i, s in enumerate(sinks))


def _graph_scene(d: dict, source: str, base_dir: Path) -> Scene:
    """Return a scene in the graph form: [[source]], [[stream]], [fusion], [[sink]]."""
    one_source = sorted(set(d) & {"driver", *STREAM_SECTIONS})
    if one_source:
        raise SceneError(f"{source}: {one_source} belong to a one-source scene; with [[source]] and [[stream]], "
                         "give each stream its own bank, features, model and decision as [stream.bank], ... "
                         "and each source its driver keys")
    unknown = sorted(set(d) - {"source", "stream", "fusion", "sink", "buffer"})
    if unknown:
        raise SceneError(f"{source}: unknown section(s) {unknown}; a scene of several sources has [[source]], "
                         "[[stream]], [fusion] and [[sink]]")
    if "buffer" in d:
        raise SceneError(f"{source}: [buffer] belongs to a one-source scene; give each [[source]] its own "
                         "[source.buffer]")
    sources = []
    for i, t in enumerate(_table_list(d, "source", source)):
        where = f"{source}: [[source]] #{i + 1}"
        kind, options = driver_table(where, t, SOURCE_KEYS)
        name = options.pop("name")
        buffer = _fill(f"{where} [source.buffer]", t.get("buffer", {}), SECTIONS["buffer"])
        sources.append(SourceSpec(name, kind, frozen(options), BufferSpec(**buffer), f"{source}: [[source]] {name}"))
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        raise SceneError(f"{source}: [[source]] name: each source needs its own name, got {names}")
    streams = []
    # A relay (every source sent on as it is, [[sink]] type = "lsl-signal") has no stream.
    for i, t in enumerate(_table_list(d, "stream", source) if "stream" in d else ()):
        where = f"{source}: [[stream]] #{i + 1}"
        if not isinstance(t, dict):
            raise SceneError(f"{where} must be a table")
        given = {k: v for k, v in t.items() if k not in STREAM_SECTIONS}
        head = _fill(where, given, STREAM_KEYS)
        if head["name"] == FUSED_STREAM:
            raise SceneError(f"{where} name: {FUSED_STREAM!r} is the fusion block's; choose another name")
        if head["source"] not in names:
            raise SceneError(f"{where} source: no source {head['source']!r}; the scene's sources are {names}")
        sections = {name: _fill(f"{where} [stream.{name}]", t.get(name, {}), SECTIONS[name])
                    for name in STREAM_SECTIONS}
        _check_sections(source, sections, t.get("bank", {}), f"[[stream]] {head['name']} ")
        streams.append(_stream(head["name"], head["source"], head["mapping"], sections,
                               f"{source}: [[stream]] {head['name']}"))
    stream_names = [s.name for s in streams]
    if len(set(stream_names)) != len(stream_names):
        raise SceneError(f"{source}: [[stream]] name: each stream needs its own name, got {stream_names}")
    fusion = _fusion(d, source, streams) if "fusion" in d else None
    sinks = _sinks(d, source, stream_names + ([FUSED_STREAM] if fusion else []), names, base_dir)
    sent = {s.source for s in sinks if sink_spec(s.type).listens == "samples"}
    unused = [n for n in names if n not in {s.source for s in streams} | sent]
    if unused:
        raise SceneError(f"{source}: [[source]] {unused[0]!r} feeds no [[stream]]: add a stream that reads it, "
                         "send its samples on ([[sink]] type = \"lsl-signal\"), or remove it")
    return Scene(tuple(sources), tuple(streams), sinks, fusion, source, base_dir, form="graph")


def _fusion(d: dict, source: str, streams: list[StreamSpec]) -> FusionSpec:
    """Return the ``[fusion]`` table of a graph scene (of ``streams``), validated."""
    return fusion_from_table(d["fusion"], source, streams)


def fusion_from_table(given, source: str, streams) -> FusionSpec:
    """Return a ``[fusion]`` table over a scene's ``streams`` (StreamSpecs), validated and filled in.

    ``given`` is the table as parsed, defaults left out; ``source`` names the scene file in messages.
    """
    if not isinstance(given, dict):
        raise SceneError(f"{source}: [fusion] must be a table")
    stream_names = [s.name for s in streams]
    fusion = _fill(f"{source}: [fusion]", {k: v for k, v in given.items() if k != "decision"}, FUSION_KEYS)
    decision = _fill(f"{source}: [fusion.decision]", given.get("decision", {}), SECTIONS["decision"])
    _check_decision(source, decision, "[fusion.decision]")
    if decision["unknown"]:
        raise SceneError(f"{source}: [fusion.decision] unknown: a fused window is unknown when either sense's "
                         "window is novel; set unknown in each [[stream]]'s [decision] instead")
    given_learned = sorted({"sharpness", "correlation"} & set(given))
    if fusion["weight"] == LEARN and given_learned:
        raise SceneError(f"{source}: [fusion] {', '.join(given_learned)}: weight = \"{LEARN}\" learns them "
                         "with the weight; give a numeric weight to set them, or leave them out")
    late_only = sorted({"weight", "sharpness", "correlation"} & set(given))
    if fusion["method"] == "early" and late_only:
        raise SceneError(f"{source}: [fusion] {late_only[0]}: {', '.join(late_only)} belong to late fusion; early "
                         "fusion is one network on both streams' features (remove them, or set method = \"late\")")
    if fusion["method"] == "late" and fusion["model"] is not None:
        raise SceneError(f"{source}: [fusion] model: a model file is for method = \"early\"; late fusion has a "
                         "weight (leave model out, or set method = \"early\")")
    for n in fusion["streams"]:
        spec = next((s for s in streams if s.name == n), None)
        if spec is None:
            raise SceneError(f"{source}: [fusion] streams: no stream {n!r}; the scene's streams are {stream_names}")
        if not spec.model.exists:
            raise SceneError(f"{source}: [fusion] streams: stream {n!r} has no model to fuse; give it "
                             "[stream.model] path or train_on_start")
    if fusion["method"] == "early" and fusion["model"] is None:
        # The early network trained on start copies each pair's two windows together, each stream's by its
        # own [model] augment_*: one number of copies for both
        copies = {n: s.model.augment_copies for n in fusion["streams"] for s in streams if s.name == n}
        if len(set(copies.values()) - {0}) > 1:
            raise SceneError(f"{source}: [fusion] method = \"early\": the streams' [model] augment_copies differ "
                             f"({', '.join(f'{n} {c}' for n, c in copies.items())}); the early network copies a "
                             "pair's two windows together: give both streams the same augment_copies (or one none)")
    return FusionSpec(**{**fusion, "streams": tuple(fusion["streams"])}, decision=_decision_rules(decision),
                      contact_from=decision["contact_from"])


def _table_list(d: dict, key: str, source: str) -> list:
    tables = d.get(key)
    if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
        raise SceneError(f"{source}: [[{key}]] must be a list of at least one table (write [[{key}]], "
                         "with two brackets)")
    return tables


def load_scene(path) -> Scene:
    """Read and validate a scene file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise SceneError(f"no scene file at {path}") from None
    except OSError as exc:                  # a folder, no permission, ...: the user's path, one line
        raise SceneError(f"cannot read the scene file {path}: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path} is not valid TOML: {exc}") from None
    return scene_from_dict(data, str(path), path.resolve().parent)


def default_scene() -> Scene:
    """Return the embedded default scene.

    The whisker array replaying a synthesised session of the reference textures (their held-out last
    10 s), with a model trained on the spot.
    """
    return scene_from_dict({
        "driver": {"type": "synth", "textures": "reference", "seconds": 10.0, "held_out": True, "block": 50},
        "bank": {"kind": "whisker"},
        "features": {"names": ["Af"]},
        "model": {"train_on_start": True},
        "decision": {"scope": "window"},
        "sink": [{"type": "text"}],
    }, "<default scene>")


def _toml_value(v) -> str:
    """One scene value as TOML: strings (JSON's escapes are TOML's), booleans, numbers, lists."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "inf" if v == math.inf else "-inf" if v == -math.inf else "nan" if v != v else repr(v)
    if isinstance(v, (int, str)):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise SceneError(f"a scene value {v!r} ({type(v).__name__}) has no TOML form")


def scene_to_toml(scene: Scene) -> str:
    """Return the scene as a TOML file that :func:`load_scene` reads back to the same scene.

    Every key with its value (defaults filled in), keys whose default belongs to the driver or the bank
    (None) left out, so that they keep following their owner.
    """
    def table(header: str, values) -> list[str]:
        return [header] + [f"{k} = {_toml_value(v)}" for k, v in values.items() if v is not None] + [""]

    def sections(stream: StreamSpec, prefix: str) -> list[str]:
        return (table(f"[{prefix}bank]", stream.bank.table())
                + table(f"[{prefix}features]", asdict(stream.features))
                + table(f"[{prefix}model]", asdict(stream.model))
                + table(f"[{prefix}decision]", {**asdict(stream.decision), "contact_from": stream.contact_from}))

    lines = [f"# supramodal scene, from {scene.source} (supramodal run --print-scene).",
             "# Paths are relative to this file's folder; docs/node.md lists every key.", ""]
    if scene.is_graph:
        for src in scene.sources:
            lines += table("[[source]]", src.table())
            lines += table("[source.buffer]", asdict(src.buffer))
        for stream in scene.streams:
            lines += table("[[stream]]", {"name": stream.name, "source": stream.source, "mapping": stream.mapping})
            lines += sections(stream, "stream.")
        f = scene.fusion
        if f is not None:
            # Keys a scene may not give: those "learn" learns, and late fusion's with early fusion; and those
            # of [fusion.decision].
            learned = {"decision", "contact_from"} | ({"sharpness", "correlation"} if f.weight == LEARN else set()) \
                | ({"weight", "sharpness", "correlation"} if f.method == "early" else set())
            lines += table("[fusion]", {k: v for k, v in asdict(f).items() if k not in learned})
            lines += table("[fusion.decision]", {**asdict(f.decision), "contact_from": f.contact_from})
    else:                                   # in its own form: [driver], [bank], ...
        src, stream = scene.only_source(), scene.only_stream()
        lines += table("[driver]", {"type": src.type, **src.options, "mapping": stream.mapping})
        lines += sections(stream, "") + table("[buffer]", asdict(src.buffer))
    for sink in scene.sinks:
        lines += table("[[sink]]", {"type": sink.type, **sink.options})
    return "\n".join(lines)
