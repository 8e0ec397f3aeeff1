"""The speed benchmarks of issue 38 (benchmarks/pipeline_speed.py, benchmarks/training_speed.py): what
they report, on short runs; their figures come from running them, not from here."""

import json
import subprocess
import sys

import pytest

from supramodal.benchmarks import pipeline_speed, training_speed


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
