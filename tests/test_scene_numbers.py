"""Every numeric key of a scene, driven with the numbers a typo or a hostile file gives (issue 25):
0, negative, 1e300, nan, inf and a huge integer. Each is refused naming the key (exit 2), or runs
to the end within a time bound, and nothing is left on disk.

The keys come from the schema (node.scene's sections and node.registry's driver specs), so a
key added tomorrow is driven too. The runs use the synth driver, which needs no device.
"""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from supramodal.node.scene.build import build_node
from supramodal.node.scene.registry import driver_spec, source_keys
from supramodal.node.runtime.sinks import ListSink
from supramodal.node.scene.schema import ONE_SOURCE_KEYS, SECTIONS, SceneError, scene_from_dict, scene_to_toml

BAD = {"zero": 0, "negative": -1.5, "huge": 1e300, "nan": math.nan, "inf": math.inf, "huge-int": 10**30}
#: A run that is accepted must end within this (wall seconds, on a loaded CI machine).
TIME_BOUND = 90.0
BASE = {"driver": {"type": "synth", "seconds": 0.5, "order": ["T1", "T2"], "speed": "max"},
        "features": {"names": ["Af"]}}


def _numeric(key) -> bool:
    """Whether a key takes numbers: its check accepts one of a few ordinary ones."""
    return any(key.check(v) for v in (1, 2, 10, 0.5, 1.0, 100.0, 0.01))


def _cases():
    for name, key in {**source_keys(driver_spec("synth")), **ONE_SOURCE_KEYS}.items():
        if _numeric(key):
            yield "driver", name
    for section, keys in SECTIONS.items():
        for name, key in keys.items():
            if _numeric(key):
                yield section, name


CASES = [(section, key, label) for section, key in _cases() for label in BAD]


def _scene(section: str, key: str, value) -> dict:
    d = {k: dict(v) for k, v in BASE.items()}
    d.setdefault(section, {})[key] = value
    if section == "bank" and key in ("channels", "f_low", "f_high"):
        d["bank"]["kind"] = "cochlea"                       # keys of the cochlea recipe
        d["driver"]["textures"] = "reference"
    if section == "decision":
        d["model"] = {"train_on_start": True}              # a decision's rules apply to a stream with a model
    if section == "decision" and key in ("confidence",):
        d["decision"]["scope"] = "contact"
    return d


def _load_only_cases():
    """Numeric keys of the drivers that need a device or a stream (serial, microphone, lsl, xdf),
    of every sink and of the fusion: driven at load (a run needs what a test machine lacks)."""
    from supramodal.node.runtime.sinks.spec import sink_keys
    from supramodal.node.scene.registry import driver_types, sink_spec, sink_types
    from supramodal.node.scene.schema import FUSION_KEYS, STREAM_KEYS

    for kind in driver_types():
        if kind in ("synth",):
            continue
        for name, key in source_keys(driver_spec(kind)).items():
            if _numeric(key):
                yield ("driver", kind), name
    for kind in sink_types():
        for name, key in sink_keys(sink_spec(kind)).items():
            if _numeric(key):
                yield ("sink", kind), name
    for name, key in FUSION_KEYS.items():
        if _numeric(key):
            yield ("fusion", None), name
    for name, key in STREAM_KEYS.items():
        if _numeric(key):
            yield ("stream", None), name


#: Bad values a schema accepts on purpose, with why (a run, where it is possible, decides).
ACCEPTED = {
    ("driver", "microphone", "device", "zero"): "device index 0 is a real device",
    ("driver", "microphone", "device", "huge-int"): "an index no card has: refused when the stream opens",
    ("driver", "twosense", "set_seed", "zero"): "a seed", ("driver", "twosense", "set_seed", "huge-int"): "a seed",
    ("driver", "twosense", "take", "zero"): "the first contact", ("driver", "twosense", "take", "huge-int"): "",
    ("driver", "twosense", "offset", "zero"): "no offset", ("driver", "twosense", "clock_ppm", "zero"): "",
    ("driver", "twosense", "jitter", "zero"): "no jitter", ("driver", "twosense", "clock_ppm", "negative"): "",
    ("sink", "lsl-signal", "wait_for_consumer", "zero"): "start at once",
    ("sink", "lsl", "wait_for_consumer", "zero"): "start at once", ("sink", "view", "port", "zero"): "any free port",
    ("sink", "ros2", "wait_for_subscribers", "zero"): "start at once",
    ("fusion", None, "weight", "zero"): "all on the second stream", ("fusion", None, "correlation", "zero"): "",
    ("stream", None, "mapping", "zero"): "channel 0",
    ("driver", "twosense", "seconds", "huge"): "build", ("driver", "twosense", "seconds", "huge-int"): "build",
}


#: Values the usual checks of a required key take (a path, a port, a topic, a name, a choice of the two-sense
#: world's): a driver's required keys get the first their check accepts, so that a new driver needs no line here.
SOME_VALUES = ("x", "/x", "whiskers", 1, 1.0)


def _required(keys) -> dict:
    """A value for each required key of ``keys`` (a driver's), from :data:`SOME_VALUES`."""
    out = {}
    for name, k in keys.items():
        if k.required:
            out[name] = next((v for v in SOME_VALUES if k.check(v)), None)
            assert out[name] is not None, f"required key {name!r}: none of SOME_VALUES is {k.expected}; add one"
    return out


#: The rule this file holds every numeric key to, as docs/architecture.md ("Where a change goes") writes it.
BOUNDS_RULE = ("every numeric key of a scene has both bounds: 0 (where it means nothing), negatives, nan, inf and "
               "numbers beyond an upper bound are refused at load, naming the key (docs/architecture.md, 'Where a "
               "change goes'); a bad value a key takes on purpose is listed in ACCEPTED, with why")


def _two_sense(section, kind, key, value) -> dict:
    d = {"source": [{"name": "w", "type": "twosense", "sense": "whiskers", "seconds": 0.5},
                    {"name": "m", "type": "twosense", "sense": "microphone", "seconds": 0.5}],
         "stream": [{"name": "w", "source": "w", "model": {"path": "w.npz"}},
                    {"name": "m", "source": "m", "bank": {"kind": "cochlea"}, "model": {"path": "m.npz"}}],
         "fusion": {"streams": ["w", "m"]}}
    if section == "fusion":
        d["fusion"][key] = value
    elif section == "stream":
        d["stream"][0][key] = value
    elif section == "sink":
        d["sink"] = [{"type": kind, key: value, **({"source": "w"} if kind == "lsl-signal" else {})}]
    return d


@pytest.mark.parametrize("where, key, label", [(w, k, label) for w, k in _load_only_cases() for label in BAD])
def test_every_other_numeric_key_refuses_bad_numbers_naming_the_key(tmp_path, where, key, label):
    section, kind = where
    value = BAD[label]
    if section == "driver":
        d = {"driver": {"type": kind, **_required(source_keys(driver_spec(kind))), key: value}}
    else:
        d = _two_sense(section, kind, key, value)
    try:
        scene_from_dict(d, str(tmp_path / "s.toml"), tmp_path)
    except SceneError as exc:
        assert key in str(exc), str(exc)
        return
    why = ACCEPTED.get((section, kind, key, label))
    assert why is not None, f"[{section}] {kind} {key} = {value!r} is accepted, against the rule: {BOUNDS_RULE}"
    if why == "build":                       # refused when built, before anything is allocated
        with pytest.raises(SceneError, match=key):
            build_node(scene_from_dict(d, str(tmp_path / "s.toml"), tmp_path), sinks_override=[ListSink()])


def test_every_numeric_key_is_driven():
    keys = {(s, k) for s, k, _ in CASES}
    assert {("driver", "seconds"), ("driver", "speed"), ("buffer", "seconds"), ("features", "window"),
            ("bank", "mean_B"), ("decision", "n")} <= keys
    others = {(w, k) for w, k in _load_only_cases()}
    assert {(("driver", "serial"), "baudrate"), (("driver", "lsl"), "max_gap"), (("driver", "twosense"), "offset"),
            (("sink", "lsl-signal"), "wait_for_consumer"), (("fusion", None), "max_wait"),
            (("stream", None), "mapping")} <= others


@pytest.mark.slow
@pytest.mark.parametrize("section, key, label", CASES)
def test_a_bad_number_is_refused_naming_the_key_or_runs_within_bounds(tmp_path, section, key, label):
    value = BAD[label]
    d = _scene(section, key, value)
    try:
        scene = scene_from_dict(d, str(tmp_path / "s.toml"), tmp_path)
    except SceneError as exc:
        assert f"{key}" in str(exc), str(exc)
        return
    # Accepted by the schema: the node must refuse it naming the key before it starts, or run.
    (tmp_path / "s.toml").write_text(scene_to_toml(scene))
    before = set(tmp_path.iterdir())
    try:
        done = subprocess.run([sys.executable, "-m", "supramodal", "run", str(tmp_path / "s.toml"), "--quiet",
                               "--speed", "max", "--seconds", "5"], capture_output=True, text=True,
                              timeout=TIME_BOUND, cwd=tmp_path)
    except subprocess.TimeoutExpired:
        pytest.fail(f"[{section}] {key} = {value!r}: still running after {TIME_BOUND:g} s")
    assert done.returncode in (0, 2), (done.returncode, done.stderr[-2000:])
    assert "Traceback" not in done.stderr, done.stderr[-2000:]
    if done.returncode == 2:
        assert key in done.stderr, done.stderr
    else:
        assert "nan" not in done.stdout.lower(), done.stdout[-500:]
    assert set(tmp_path.iterdir()) == before
