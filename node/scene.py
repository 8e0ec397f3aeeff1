"""Scenes: what a node runs, as a TOML file validated before anything starts.

A scene names the driver and its options, the bank, the features and window,
the model (optional: without one the node emits feature windows), how decisions
are pooled, and the sinks. Every key is checked against the schema below;
an unknown key, a wrong type or a value out of range is refused with a message
naming the key. Nothing in a scene is executed.

Example (the embedded default is ``default_scene()``)::

    [driver]
    type = "replay"            # replay | synth | serial | microphone
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
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from supramodal.banks import WHISKER_RATE, WHISKER_ROWS, whisker_bank
from supramodal.decisions import (DEFAULT_CONTACT_THRESHOLD, DEFAULT_METHOD, DEFAULT_POOLED, DEFAULT_SCOPE, METHODS,
                                  SCOPES)
from supramodal.errors import InputError
from supramodal.features import DEFAULT_WINDOW, FEATURE_TABLE, FEATURES
from supramodal.peaks import DEFAULT_PEAK_MODE, PEAK_MODES


class SceneError(InputError):
    """A scene file is unreadable or does not fit the schema; the message names the key."""


def _number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _positive(v):
    return _number(v) and math.isfinite(v) and v > 0


def _non_negative(v):
    return _number(v) and math.isfinite(v) and v >= 0


def _int_min(lo):
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= lo


def _one_of(*choices):
    return lambda v: v in choices


def _str(v):
    return isinstance(v, str) and v != ""


#: The replay speed that releases every block at once (in a scene and after ``--speed``).
SPEED_MAX = "max"
SPEED_HELP = f'1.0 (real time), a positive factor, or "{SPEED_MAX}"'


def is_speed(v) -> bool:
    """Whether ``v`` is a replay speed: a positive number or :data:`SPEED_MAX`."""
    return v == SPEED_MAX or _positive(v)


def _features(v):
    return isinstance(v, list) and v and all(f in FEATURES for f in v) and len(set(v)) == len(v)


def _rows(v):
    return isinstance(v, str) and v and set(v) <= set("ABCDE") and len(set(v)) == len(v)


def _mapping(v):
    return v in ("auto", "mono", "per-channel", "mean") or (isinstance(v, int) and not isinstance(v, bool) and v >= 0)


def _texture_list(v):
    return isinstance(v, list) and all(isinstance(t, str) for t in v)


# section -> key -> (check, description of what is expected, default or REQUIRED).
# Every default has one home: a key whose default belongs to the driver or the bank is None
# here ("the owner's default": build.py does not pass it on); the others import their owner's
# constant.
REQUIRED = object()
_WHISKER_CHANNELS = whisker_bank().channels
DRIVER_KEYS = {
    "replay": {
        "path": (_str, "a WAV file or session path", REQUIRED),
        "speed": (is_speed, SPEED_HELP + " (default: the replay driver's)", None),
        "block": (_int_min(1), "frames per block, an integer >= 1 (default: the replay driver's)", None),
        "loop": (lambda v: isinstance(v, bool), "true or false", False),
        "mapping": (_mapping, '"auto", "mono", "per-channel", "mean" or a channel index', "auto"),
    },
    "synth": {
        "textures": (_str, '"reference" or a texture-set JSON path', "reference"),
        "seconds": (_positive, "seconds per texture, > 0", 10.0),
        "order": (_texture_list, "a list of texture names", None),
        "speed": (is_speed, SPEED_HELP + " (default: the replay driver's)", None),
        "block": (_int_min(1), "frames per block, an integer >= 1 (default: the replay driver's)", None),
        "held_out": (lambda v: isinstance(v, bool), "true or false", True),
    },
    "serial": {
        "port": (_str, "a serial port path or pyserial URL", REQUIRED),
        "rate": (_positive, "frames per second, Hz", WHISKER_RATE),
        "channels": (_int_min(1), "an integer >= 1", _WHISKER_CHANNELS),
        "baudrate": (_int_min(1), "bit/s on a real UART, an integer (default: the serial driver's "
                                  "DEFAULT_BAUDRATE)", None),
        "mapping": (_mapping, '"auto", "mono", "per-channel", "mean" or a channel index', "auto"),
    },
    "microphone": {
        "device": (lambda v: isinstance(v, (str, int)) and not isinstance(v, bool),
                   "a device name or index (default: the system's default input)", None),
        # None: the microphone driver's default (drivers.microphone.MicrophoneDriver).
        "rate": (_positive, "Hz (default: the microphone driver's)", None),
        "channels": (_int_min(1), "an integer >= 1 (default: the microphone driver's)", None),
        "block": (_int_min(1), "frames per block (default: the microphone driver's)", None),
        "dtype": (_one_of("float32", "int16"), '"float32" or "int16" (capture format; default: the driver\'s)', None),
        "buffer_seconds": (_positive, "seconds the driver buffers between PortAudio and the node "
                                      "(default: the driver's)", None),
        "mapping": (_mapping, '"auto", "mono", "per-channel", "mean" or a channel index', "auto"),
    },
}
SECTIONS = {
    "bank": {
        "kind": (_one_of("whisker", "cochlea"), '"whisker" or "cochlea"', "whisker"),
        "rows": (_rows, 'whisker rows, e.g. "ABCDE"', "".join(WHISKER_ROWS)),
        # None: the bank's own default (supramodal.banks.whisker_bank / cochlea_bank).
        "mean_B": (_positive, "mean Slaney bandwidth, > 0 (default: the paper's bandwidths)", None),
        "channels": (_int_min(1), "cochlea channels, an integer >= 1 (default: the cochlea bank's)", None),
        "f_low": (_positive, "Hz (default: the cochlea bank's)", None),
        "f_high": (_positive, "Hz, above f_low (default: the cochlea bank's)", None),
        "fs": (_positive, "sample rate, Hz (default: the bank's)", None),
        "file": (_str, "a bank file (supramodal-bank JSON, e.g. from a fit), relative to the scene; "
                       "the [bank] table then holds nothing else", None),
    },
    "features": {
        "names": (_features, "a list of distinct names drawn from "
                  + "; ".join(f"{f.name} ({f.description})" for f in FEATURE_TABLE.values()), ["Af"]),
        "window": (_positive, "seconds, > 0", DEFAULT_WINDOW),
        "peak_mode": (_one_of(*PEAK_MODES), f"one of {list(PEAK_MODES)}", DEFAULT_PEAK_MODE),
        "peak_threshold": (_non_negative, "smallest peak amplitude counted, >= 0", 0.0),
        "dtype": (_one_of("float64", "float32"), '"float64" or "float32"', "float64"),
        # Not the pipeline's default ("raise"): a live node replaces and counts a bad sample
        # rather than stopping.
        "nonfinite": (_one_of("raise", "zero"), '"raise" or "zero"', "zero"),
    },
    "model": {
        "path": (_str, "a model .npz path (loaded; or written when train_on_start)", None),
        "train_on_start": (lambda v: isinstance(v, bool), "true or false: train at start-up on the synth driver's texture set, or with another "
                           "driver on the bank's reference set", False),
    },
    "decision": {
        "scope": (_one_of(*SCOPES), f"one of {list(SCOPES)}", DEFAULT_SCOPE),
        "n": (_int_min(0), "windows, an integer >= 0", DEFAULT_POOLED),
        "method": (_one_of(*METHODS), f"one of {list(METHODS)}", DEFAULT_METHOD),
        "contact_threshold": (_non_negative, "input RMS, >= 0", DEFAULT_CONTACT_THRESHOLD),
    },
    "buffer": {
        "seconds": (_positive, "ring buffer capacity, seconds", 2.0),
        # "auto": "block" (lossless back-pressure) for replay and synth, "drop-oldest" for live drivers.
        "overrun": (_one_of("auto", "drop-oldest", "drop-newest", "block"),
                    '"auto", "drop-oldest", "drop-newest" or "block"', "auto"),
    },
}
SINK_KEYS = {
    "text": {"path": (_str, '"-" (stdout) or a file path', "-")},
    "jsonl": {"path": (_str, '"-" (stdout) or a file path', "-")},
}


@dataclass
class Scene:
    """A validated scene: plain dicts with every default filled in."""

    driver: dict[str, Any]
    bank: dict[str, Any]
    features: dict[str, Any]
    model: dict[str, Any]
    decision: dict[str, Any]
    buffer: dict[str, Any]
    sinks: list[dict[str, Any]] = field(default_factory=list)
    source: str = "<scene>"
    base_dir: Path = field(default_factory=Path.cwd)

    def resolve(self, path: str) -> Path:
        """A path from the scene, relative to the scene file's folder."""
        p = Path(path).expanduser()
        return p if p.is_absolute() else self.base_dir / p


def _fill(where: str, given: dict, schema: dict) -> dict:
    if not isinstance(given, dict):
        raise SceneError(f"{where} must be a table")
    unknown = sorted(set(given) - set(schema))
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {unknown}; allowed keys: {sorted(schema)}")
    out = {}
    for key, (check, expected, default) in schema.items():
        if key in given:
            value = given[key]
            if not check(value):
                raise SceneError(f"{where} {key}: expected {expected}, got {value!r}")
            out[key] = value
        elif default is REQUIRED:
            raise SceneError(f"{where}: missing required key {key!r} ({expected})")
        else:
            out[key] = default
    return out


def scene_from_dict(d: dict, source: str = "<scene>", base_dir: Path | None = None) -> Scene:
    """Validate a parsed scene and fill in defaults."""
    if not isinstance(d, dict):
        raise SceneError(f"{source}: a scene is a TOML table")
    allowed = {"driver", "sink", *SECTIONS}
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise SceneError(f"{source}: unknown section(s) {unknown}; sections are {sorted(allowed)}")
    driver = d.get("driver")
    if not isinstance(driver, dict) or "type" not in driver:
        raise SceneError(f"{source}: [driver] type is required, one of {sorted(DRIVER_KEYS)}")
    dtype_ = driver["type"]
    if dtype_ not in DRIVER_KEYS:
        raise SceneError(f"{source}: [driver] type: expected one of {sorted(DRIVER_KEYS)}, got {dtype_!r}")
    drv = {"type": dtype_, **_fill(f"{source}: [driver] ({dtype_})", {k: v for k, v in driver.items() if k != "type"},
                                   DRIVER_KEYS[dtype_])}
    sections = {name: _fill(f"{source}: [{name}]", d.get(name, {}), schema) for name, schema in SECTIONS.items()}
    sinks_in = d.get("sink", [{"type": "text"}])
    if not isinstance(sinks_in, list) or not sinks_in:
        raise SceneError(f"{source}: [[sink]] must be a list of at least one sink table")
    sinks = []
    for i, s in enumerate(sinks_in):
        if not isinstance(s, dict) or s.get("type") not in SINK_KEYS:
            raise SceneError(f"{source}: [[sink]] #{i + 1} type: expected one of {sorted(SINK_KEYS)}, got "
                             f"{s.get('type') if isinstance(s, dict) else s!r}")
        sinks.append({"type": s["type"], **_fill(f"{source}: [[sink]] #{i + 1}", {k: v for k, v in s.items() if k != "type"},
                                                 SINK_KEYS[s["type"]])})
    bank = sections["bank"]
    if bank["file"] is not None and set(d.get("bank", {})) - {"file"}:
        raise SceneError(f"{source}: [bank] file: a bank file describes the whole bank; remove "
                         f"{sorted(set(d['bank']) - {'file'})} or the file")
    if sections["decision"]["scope"] == "last" and sections["decision"]["n"] < 1:
        raise SceneError(f"{source}: [decision] n must be >= 1 with scope = \"last\"")
    return Scene(drv, bank, sections["features"], sections["model"], sections["decision"], sections["buffer"],
                 sinks, source, base_dir or Path.cwd())


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
    """The embedded default: the whisker array replaying a synthesised session of the
    reference textures (their held-out last 10 s), with a model trained on the spot."""
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
    """The scene as a TOML file that :func:`load_scene` reads back to the same scene: every key
    with its value (defaults filled in), keys whose default belongs to the driver or the bank
    (None) left out, so that they keep following their owner."""
    def table(header: str, values: dict) -> list[str]:
        return [header] + [f"{k} = {_toml_value(v)}" for k, v in values.items() if v is not None] + [""]

    lines = [f"# supramodal scene, from {scene.source} (supramodal run --print-scene).",
             "# Paths are relative to this file's folder; docs/node.md lists every key.", ""]
    lines += table("[driver]", scene.driver)
    for name in SECTIONS:
        lines += table(f"[{name}]", getattr(scene, name))
    for sink in scene.sinks:
        lines += table("[[sink]]", sink)
    return "\n".join(lines)
