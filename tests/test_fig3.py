"""A quick Fig. 3: 8 s per texture instead of 40, in process and through the CLI."""

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from supramodal.experiments.fig3 import fig3
from supramodal.features import FEATURES
from supramodal.textures import reference_texture_set

ROOT = Path(__file__).resolve().parents[1]
CHANCE = 1 / 8


def short_whisker_set(duration=8.0):
    return dataclasses.replace(reference_texture_set("whisker"), duration=duration)


def check_structure(result, names):
    assert result["bank"] == "whisker"
    assert set(result["features"]) == set(FEATURES)                   # by default every feature of the table
    for feature, r in result["features"].items():
        assert set(r) == {"mean_rate", "per_texture"}
        assert list(r["per_texture"]) == list(names)
        rates = list(r["per_texture"].values())
        assert all(0.0 <= v <= 1.0 for v in rates), feature
        assert 0.0 <= r["mean_rate"] <= 1.0
        # 80 windows per texture -> 20 test windows each: the mean is the mean of the per-texture rates
        assert r["mean_rate"] == pytest.approx(sum(rates) / len(rates), abs=1e-12)
        assert all(abs(v * 20 - round(v * 20)) < 1e-9 for v in rates), "rates are counts out of 20"


@pytest.fixture(scope="module")
def result():
    return fig3(short_whisker_set())


def test_fig3_structure_and_rates(result):
    ts = short_whisker_set()
    check_structure(result, ts.names)
    assert result["texture_set"] == "whisker-reference"
    assert result["textures"] == {t.name: list(t.peaks) for t in ts.textures}
    assert result["timing"]["signal_seconds"] == 64.0


def test_fig3_amplitude_features_are_well_above_chance(result):
    # measured with 8 s per texture: Af 0.73, A 0.77, f 0.31 (chance 0.125); 40 s does better
    assert result["features"]["Af"]["mean_rate"] >= 4 * CHANCE
    assert result["features"]["A"]["mean_rate"] >= 4 * CHANCE
    assert result["features"]["f"]["mean_rate"] > CHANCE


def test_fig3_is_deterministic(result):
    again = fig3(short_whisker_set(), features=("A",))
    assert again["features"]["A"] == result["features"]["A"]


def run_cli(*args, timeout=300):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "supramodal.node.cli", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow   # a long run: Fig. 3 in quick mode in its own process
def test_cli_fig3_json(tmp_path):
    textures = tmp_path / "short.json"
    short_whisker_set().save(textures)
    out = tmp_path / "out"
    proc = run_cli("experiment", "fig3", "--bank", "whisker", "--json", "--quiet", "--out", str(out),
                   "--textures", str(textures))
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""                              # --quiet: no progress
    result = json.loads(proc.stdout)                      # one JSON object, nothing else on stdout
    check_structure(result, short_whisker_set().names)
    assert result["features"]["Af"]["mean_rate"] >= 4 * CHANCE
    assert result["features"]["A"]["mean_rate"] >= 4 * CHANCE
    assert (out / "fig3_whisker.csv").is_file()


def test_cli_refuses_a_texture_set_for_the_other_bank(tmp_path):
    textures = tmp_path / "short.json"
    short_whisker_set().save(textures)
    proc = run_cli("experiment", "fig3", "--bank", "cochlea", "--json", "--quiet", "--out",
                   str(tmp_path / "o"), "--textures", str(textures))
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert "supramodal: error:" in proc.stderr and "--bank whisker" in proc.stderr


def test_cli_refuses_a_bad_texture_file(tmp_path):
    textures = tmp_path / "bad.json"
    textures.write_text(json.dumps({"format": "supramodal-textures", "version": 9}))
    proc = run_cli("experiment", "fig3", "--json", "--quiet", "--out", str(tmp_path / "o"),
                   "--textures", str(textures))
    assert proc.returncode == 2
    assert "'version' 9 is not supported" in proc.stderr
    assert "Traceback" not in proc.stderr
