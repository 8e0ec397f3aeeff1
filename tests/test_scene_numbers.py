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

from supramodal.node.registry import driver_spec, source_keys
from supramodal.node.scene import SECTIONS, SceneError, scene_from_dict, scene_to_toml

BAD = {"zero": 0, "negative": -1.5, "huge": 1e300, "nan": math.nan, "inf": math.inf, "huge-int": 10**30}
#: A run that is accepted must end within this (wall seconds, on a loaded CI machine).
TIME_BOUND = 90.0
BASE = {"driver": {"type": "synth", "seconds": 0.5, "order": ["T1", "T2"], "speed": "max"},
        "features": {"names": ["Af"]}}


def _numeric(key) -> bool:
    """Whether a key takes numbers: its check accepts one of a few ordinary ones."""
    return any(key.check(v) for v in (1, 2, 10, 0.5, 1.0, 100.0, 0.01))


def _cases():
    for name, key in source_keys(driver_spec("synth")).items():
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
    if section == "decision" and key in ("confidence",):
        d["decision"]["scope"] = "contact"
    return d


def test_every_numeric_key_is_driven():
    keys = {(s, k) for s, k, _ in CASES}
    assert {("driver", "seconds"), ("driver", "speed"), ("buffer", "seconds"), ("features", "window"),
            ("bank", "mean_B"), ("decision", "n")} <= keys


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
