"""The speed benchmarks of issue 38 (benchmarks/pipeline_speed.py, benchmarks/training_speed.py,
benchmarks/fit_speed.py): what they report, on short runs; their figures come from running them, not
from here."""

import json
import subprocess
import sys

import pytest

from supramodal.benchmarks import fit_speed, pipeline_speed, training_speed
from supramodal.node.workflows.fit_search import DEFAULT_PATIENCE


def test_pipeline_speed_reports_each_bank_against_its_own_filterbank():
    said = []
    result = pipeline_speed.run(0.3, 1, said.append)
    rows = {(r["bank"], r["block"], r["what"]): r for r in result["rows"]}
    assert set(rows) == {(bank, block, what) for bank, block in pipeline_speed.CASES
                         for what in ("filterbank", "pipeline", "pipeline, whole windows")}
    for bank, block in pipeline_speed.CASES:
        assert rows[(bank, block, "filterbank")]["ratio"] == 1.0
        pipe = rows[(bank, block, "pipeline")]
        assert pipe["cpu_s"] > 0 and pipe["ratio"] == pytest.approx(
            pipe["cpu_s"] / rows[(bank, block, "filterbank")]["cpu_s"], rel=0.02, abs=0.01)   # both rounded
    assert len(said) == len(pipeline_speed.CASES)
    table = pipeline_speed.report(result)
    assert table.count("\n| cochlea (50 ch) | 441 |") == 3 and table.count("\n| whisker (20 ch) | 50 |") == 3


def test_the_first_decision_is_the_first_line_that_is_one():
    assert training_speed.FIRST_DECISION.match("    0.100 s  T3           conf 0.54  truth T1           --")
    assert not training_speed.FIRST_DECISION.match("       time  decision     confidence  (time: each window's end")
    assert not training_speed.FIRST_DECISION.match("supramodal: the whisker bank's model: 4 s so far")


@pytest.mark.slow   # re-executes itself with one BLAS thread, then a second or two of noise per bank
def test_pipeline_speed_runs_as_documented(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "supramodal.benchmarks.pipeline_speed", "--seconds", "0.3",
                           "--rounds", "1", "--out", str(tmp_path), "--json"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == json.loads((tmp_path / "pipeline_speed.json").read_text())


@pytest.fixture(scope="module")
def quick_fit_speed(tmp_path_factory):
    """benchmarks/fit_speed.py on 32 recordings of 1 s (two of each label), 3 trials of 8 epochs, in this
    process."""
    pytest.importorskip("optuna", reason="the fit extra (optuna) is not installed")
    out = tmp_path_factory.mktemp("fit_speed")
    said: list[str] = []
    return fit_speed.run(32, 1.0, 1, 3, None, 8, out, said.append), said, out


def test_fit_speed_times_the_quick_fit_and_says_where_its_cpu_went(quick_fit_speed):
    result, said, out = quick_fit_speed
    assert (result["recordings"], result["rate"], result["max_window"], result["jobs"]) == (32, 2200, 0.1, 1)
    assert result["trials"] == 3 == result["complete"] + result["pruned"] + result["empty band"]
    assert result["patience"] == DEFAULT_PATIENCE and not result["stopped_early"] and result["stopped"] is None
    assert 0 < result["cpu_s"] and 0 < result["wall_s"]
    assert result["trials_per_cpu_minute"] == pytest.approx(3 / (result["cpu_s"] / 60), rel=0.01)
    # In one process the features and networks are this process's CPU: their sum is within its total.
    assert 0 < result["features_cpu_s"] and 0 < result["networks_cpu_s"]
    assert result["features_cpu_s"] + result["networks_cpu_s"] <= result["cpu_s"] + 0.2      # each rounded
    # Every distinct bank of the trials, and the paper's two, once per recording.
    assert result["filterbank_runs"] % 32 == 0 and result["filterbank_runs"] >= 3 * 32
    assert result["met"] == (result["wall_s"] <= fit_speed.TARGET_SECONDS)
    assert result["verdict"].startswith("The best beats" if result["beats_paper"] else "The best does NOT beat")
    assert any("fit: trial 3 of 3;" in line for line in said)
    assert (out / "bank.json").is_file() and not list((out / "cache").glob("*.npy"))
    text = fit_speed.report(result)
    assert f"| {result['wall_s']:.1f} | {result['cpu_s']:.1f} | 3 (" in text
    assert "The search ran all its 3 trials." in text and result["verdict"] in text
    assert f"Where the CPU went: {result['features_cpu_s']:.1f} s features" in text


def test_fit_speed_says_when_the_early_stop_ended_the_search():
    result = {"recordings": 700, "seconds_each": 5.0, "rate": 2200, "labels": 16, "folds": 5, "max_window": 0.1,
              "jobs": 2, "cores": 2, "cpu": "a CPU", "trials_asked": 16, "patience": 8, "trials": 12, "complete": 7,
              "pruned": 5, "empty band": 0, "stopped_early": True,
              "stopped": "stopped after 12 trials: the best has not moved by more than the fold spread (0.007) for 8 "
                         "trials", "wall_s": 200.0, "cpu_s": 380.0, "synth_s": 1.0, "features_cpu_s": 330.0,
              "networks_cpu_s": 20.0, "trials_per_cpu_minute": 1.89, "filterbank_runs": 7000, "best": 0.377,
              "best_sd": 0.007, "verdict": "The best does NOT beat the paper's banks.", "beats_paper": False,
              "target_s": 600.0, "met": True, "load_before": [0.1, 0.2, 0.3], "load_after": [2.0, 1.5, 1.0],
              "date": "2026-11-30"}
    text = fit_speed.report(result)
    assert "| 200.0 | 380.0 | 12 (7, 5, 0) | 1.89 | yes | yes (<= 600 s) |" in text
    assert "The search stopped after 12 trials: the best has not moved" in text
    assert "30.0 s the rest" in text and "2026-11-30, 2 cores, a CPU; load 0.10, 0.20, 0.30 before" in text
