"""`supramodal experiment calibration` (issue 23's measurements) in quick mode, and its pieces.

These check behaviour and structure (rows, files, ranges, determinism, held-out windows), never
the figures themselves: quick runs use 4 s textures and few epochs.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math

import numpy as np
import pytest

from supramodal.calibration import calibration_report
from supramodal.errors import InputError
from supramodal.experiments import plotting, report
from supramodal.evaluation import ANYTIME_THRESHOLDS as THRESHOLDS
from supramodal.experiments.calibration import (ANYTIME_CONFIDENCE, anytime_sweep, auroc,
                                                calibration_table, done_when, merge_sweeps)
from supramodal.experiments.fusion import METHODS, merge_reports
from supramodal.experiments.suite import plans

EPOCHS = 60
FILES = ["calibration.csv", "reliability.csv", "unknown.csv", "anytime.csv"]


def numbers(x):
    """Every number in a nested result."""
    if isinstance(x, dict):
        return [n for v in x.values() for n in numbers(v)]
    if isinstance(x, list):
        return [n for v in x for n in numbers(v)]
    return [x] if isinstance(x, (int, float)) and not isinstance(x, bool) else []


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory, once):
    """The experiment in quick mode through the command line: (result, stdout, stderr, out folder);
    run once per test run, whichever xdist worker gets here first (tests/harness/run_once.py)."""
    from supramodal.node.cli import main

    def run():
        out = tmp_path_factory.mktemp("calibration")
        stdout, stderr = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            code = main(["experiment", "calibration", "--quick", "--sets", "1", "--epochs", str(EPOCHS), "--jobs",
                         "2", "--json", "--quiet", "--out", str(out)])
        assert code == 0, stderr.getvalue()
        return json.loads(stdout.getvalue()), stdout.getvalue(), stderr.getvalue(), out

    return once(f"test_calibration_experiment.cli_run epochs={EPOCHS}", run)


@pytest.fixture(scope="module")
def quick(cli_run):
    return cli_run[0]


# -- pieces ------------------------------------------------------------------------------------------

def test_auroc_is_the_chance_an_unknown_scores_above_a_known():
    assert auroc([3, 4], [1, 2]) == 1.0
    assert auroc([1, 2], [3, 4]) == 0.0
    assert auroc([1, 1], [1, 1]) == 0.5                      # ties count half
    assert auroc([2, 0], [1]) == 0.5
    with pytest.raises(InputError, match="unknown and known"):
        auroc([], [1.0])


def _constant_contacts(confidences, right, windows=20):
    """Contacts of ``windows`` identical windows of 3 classes: the top class (0 if right, else 1)
    has posterior ``c``."""
    lp, labels, runs = [], [], []
    for c, ok in zip(confidences, right):
        top = 0 if ok else 1
        p = np.full(3, (1 - c) / 2)
        p[top] = c
        start = len(lp)
        lp += [np.log(p)] * windows
        labels += [0] * windows
        runs.append(np.arange(start, start + windows))
    return np.array(lp), np.array(labels), runs


def test_anytime_decides_at_the_first_window_sure_enough_and_counts_right_and_undecided():
    lp, y, runs = _constant_contacts([0.995, 0.6, 0.9], [True, False, True])
    sweep = anytime_sweep(lp, y, runs, correlation=0.0, thresholds=(0.5, 0.99))
    low, high = sweep
    assert low["decided"] == 3 and low["right"] == 2 and low["windows"] == [1, 1, 1]
    assert high["decided"] == 3 and high["right"] == 2             # naive pooling: evidence grows
    assert high["windows"][0] == 1 and high["windows"][2] > 1 and high["median_windows"] >= 1
    # windows as sure as one (correlation 1): only the contact sure from its first window decides
    one = anytime_sweep(lp, y, runs, correlation=1.0, thresholds=(0.99,))[0]
    assert (one["decided"], one["right"], one["windows"], one["end_right"]) == (1, 1, [1], 2)
    merged = merge_sweeps([sweep, sweep])
    assert merged[1]["contacts"] == 6 and merged[1]["windows"] == high["windows"] * 2


def test_contacts_side_by_side_or_starting_at_every_window_stay_within_one_texture():
    from supramodal.experiments.fusion import contact_runs

    y = np.repeat(np.arange(3), 7)                      # 3 textures, 7 test windows each
    side = contact_runs(y, 7, 3)
    assert [list(r) for r in side] == [[0, 1, 2], [3, 4, 5], [7, 8, 9], [10, 11, 12], [14, 15, 16], [17, 18, 19]]
    every = contact_runs(y, 7, 3, step=1)
    assert [list(r) for r in every] == [list(range(t * 7 + s, t * 7 + s + 3)) for t in range(3) for s in range(5)]
    assert all(len(set(y[r])) == 1 for r in every)


def test_merged_reports_equal_one_report_of_all_decisions():
    rng = np.random.default_rng(1)
    parts = []
    for n in (40, 7, 90):
        lp = np.log(rng.dirichlet(np.ones(4) * 0.5, size=n))
        parts.append((lp, rng.integers(0, 4, n)))
    merged = merge_reports([calibration_report(lp, y) for lp, y in parts])
    whole = calibration_report(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]))
    for k in ("n", "accuracy", "log_loss", "brier", "ece", "sure_count"):
        assert merged[k] == pytest.approx(whole[k], rel=1e-12, abs=1e-12)
    assert merged["reliability"]["count"] == whole["reliability"]["count"]


@pytest.mark.slow   # a long run: two senses' networks trained fold by fold
def test_late_fusion_learns_from_windows_no_sense_network_trained_on(monkeypatch):
    """The weight and sharpness are learned on out-of-fold log-posteriors, not on the sense models'
    own training windows (this fails if run_set passes those)."""
    from supramodal.experiments import fusion

    seen = {}
    real_out_of_fold, real_learn = fusion.senses_out_of_fold, fusion.learn_late_fusion

    def out_of_fold(models, values, *args, **kwargs):
        seen["own"] = [m.log_posteriors(v) for m, v in zip(models, values)]
        return real_out_of_fold(models, values, *args, **kwargs)

    def learn(a, b, labels):
        seen["learned_on"] = (a, b, labels)
        return real_learn(a, b, labels)

    monkeypatch.setattr(fusion, "senses_out_of_fold", out_of_fold)
    monkeypatch.setattr(fusion, "learn_late_fusion", learn)
    r = fusion.run_set(2, seconds=6.0, epochs=100, seed=0)
    a, b, y = seen["learned_on"]
    own_a, own_b = seen["own"]
    assert a.shape == own_a.shape and not np.allclose(a, own_a) and not np.allclose(b, own_b)
    assert r["held_out"]["whiskers"] == pytest.approx(np.mean(np.argmax(a, axis=1) == y))
    assert np.isfinite(a).all() and np.allclose(np.exp(b).sum(axis=1), 1.0)
    assert 0.0 <= r["late_weight"] <= 1.0 and r["late_sharpness"] > 0


# -- the experiment -----------------------------------------------------------------------------------

@pytest.mark.slow   # a long run: the calibration experiment in quick mode (once per run)
def test_quick_result_has_every_part_and_no_nan(quick):
    assert set(quick["reference"]) == set(quick["random_sets"]) == set(quick["leave_out"]) == {"whisker", "cochlea"}
    assert all(not (isinstance(v, float) and math.isnan(v)) for v in numbers(quick))
    for bank in ("whisker", "cochlea"):
        ref = quick["reference"][bank]
        assert set(ref["window"]) == {"calibrated", "uncalibrated"}
        assert set(ref["contact"]) == {"calibrated", "uncalibrated", "summed"}
        for scope in ("window", "contact"):
            for rep in ref[scope].values():
                assert all(0.0 <= rep[k] <= 1.0 for k in ("accuracy", "ece")) and 0.0 <= rep["brier"] <= 2.0
                assert rep["log_loss"] >= 0.0
        assert [r["confidence"] for r in ref["anytime"]] == list(THRESHOLDS)
        for r in ref["anytime"] + ref["anytime_every_start"]:
            assert 0 <= r["right"] <= r["decided"] <= r["contacts"] and len(r["windows"]) == r["decided"]
            assert all(1 <= w <= quick["anytime_windows"] for w in r["windows"])
        per, length = ref["test_windows_per_texture"], min(quick["anytime_windows"], ref["test_windows_per_texture"])
        assert ref["anytime"][0]["contacts"] == 8 * (per // length)                 # side by side
        assert ref["anytime_every_start"][0]["contacts"] == 8 * (per - length + 1)  # one at every window
        folds = quick["leave_out"][bank]["folds"]
        assert [f["left_out"] for f in folds] == [["T1", "T2"], ["T3", "T4"], ["T5", "T6"], ["T7", "T8"]]
        for f in folds:
            for scope in ("window", "contact"):
                assert all(0.0 <= f[scope][k] <= 1.0 for k in ("auroc_novelty", "auroc_mean_novelty", "auroc_doubt",
                                                                "auroc_supervised", "false_unknown", "unknown_caught"))
                assert f[scope]["accuracy_with_rejection"] <= f[scope]["accuracy"]
                assert f[scope]["n_known"] == 3 * f[scope]["n_unknown"]          # 6 known textures, 2 left out
            assert f["window"]["auroc_mean_novelty"] == f["window"]["auroc_novelty"]
    two = quick["two_sense"]
    assert len(two["sets"]) == 1 and list(two["summary"]) == list(METHODS)
    assert 0.0 <= two["late_fusion"]["late_weight"]["mean"] <= 1.0


@pytest.mark.slow   # the calibration experiment in quick mode, as above
def test_quick_table_names_every_part_and_every_done_when_line(quick):
    table = calibration_table(quick)
    for row in ("| whisker reference |", "| cochlea reference |", "| whisker, 1 random sets |",
                "| two senses: late |", "| two senses: early |", "| whisker | T1, T2 |", "| cochlea | T7, T8 |",
                f"| {ANYTIME_CONFIDENCE:g} |", "| early |"):
        assert row in table, row
    lines = done_when(quick)
    assert len(lines) == 13 and all(isinstance(miss, list) for _, _, miss in lines)
    assert all(f"| {what} |" in table for what, _, _ in lines)


@pytest.mark.slow   # the calibration experiment in quick mode, as above
def test_csv_files_parse_with_rates_in_range(quick, tmp_path, monkeypatch):
    monkeypatch.setattr(plotting, "have_matplotlib", lambda: False)      # what the experiments ask
    monkeypatch.setattr(report, "have_matplotlib", lambda: False)
    written = report.write_figure("calibration", quick, tmp_path)
    assert sorted(p.name for p in written) == sorted(FILES)
    rows = list(csv.DictReader(open(tmp_path / "calibration.csv")))
    assert {(r["set"], r["scope"], r["posteriors"]) for r in rows if r["kind"] == "reference"} >= {
        ("whisker reference", "window", "calibrated"), ("cochlea reference", "contact", "uncalibrated")}
    assert {r["method"] for r in rows if r["kind"] == "two-sense"} == set(METHODS)
    for r in rows:
        assert 0.0 <= float(r["accuracy"]) <= 1.0 and 0.0 <= float(r["ece"]) <= 1.0
        assert r["sure_wrong"] == "" or 0.0 <= float(r["sure_wrong"]) <= 1.0
    unknown = list(csv.DictReader(open(tmp_path / "unknown.csv")))
    assert len(unknown) == 2 * 4 * 2 and all(0.0 <= float(r["auroc_novelty"]) <= 1.0 for r in unknown)
    anytime = list(csv.DictReader(open(tmp_path / "anytime.csv")))
    assert len(anytime) == 8 * len(THRESHOLDS)          # 4 groups, contacts side by side and at every start
    assert all(r["right_of_decided"] == "" or 0.0 <= float(r["right_of_decided"]) <= 1.0 for r in anytime)
    bins = list(csv.DictReader(open(tmp_path / "reliability.csv")))
    assert all(int(b["count"]) >= 0 for b in bins)


@pytest.mark.slow   # the calibration experiment in quick mode, as above
def test_no_png_without_matplotlib_says_so(quick, tmp_path, monkeypatch):
    from supramodal.experiments.calibration import write_calibration

    monkeypatch.setattr(plotting, "have_matplotlib", lambda: False)      # what the experiments ask
    monkeypatch.setattr(report, "have_matplotlib", lambda: False)
    said = []
    write_calibration(quick, tmp_path, notice=said.append)
    assert len(said) == 1 and "matplotlib" in said[0] and not list(tmp_path.glob("*.png"))
    monkeypatch.undo()
    if not report.have_matplotlib():
        pytest.skip("matplotlib not installed")
    pngs = [p for p in write_calibration(quick, tmp_path / "png") if p.suffix == ".png"]
    assert sorted(p.name for p in pngs) == ["anytime.png", "calibration.png"]
    assert all(p.stat().st_size > 1000 for p in pngs)


@pytest.mark.slow   # the calibration experiment in quick mode, as above
def test_cli_writes_json_and_files_quietly(cli_run):
    result, _, err, out = cli_run
    assert err == "" and result["figure"] == "calibration" and result["quick"] is True
    assert all((out / name).is_file() for name in FILES)


def test_the_plan_is_plain_data_with_unique_keys():
    from supramodal.experiments.common import Plan, Run

    for quick_mode, sets in ((True, None), (False, None), (False, 2)):
        p = plans("calibration", quick=quick_mode, sets=sets)["calibration"]
        assert isinstance(p, Plan) and all(isinstance(r, Run) for r in p.runs)
        keys = [r.key for r in p.runs]
        assert len(keys) == len(set(keys)) and all(k[0] == "calibration" for k in keys)
        n = (1 if quick_mode else 5) if sets is None else sets
        assert sum(k[1] == "two-sense" for k in keys) == n and sum(k[2:3] == ("random",) for k in keys) == 2 * n
        assert sum(k[2:3] == ("leave-out",) for k in keys) == 8


@pytest.mark.parametrize("args, message", [
    (["--sets", "0"], "--sets must be >= 1"),
    (["--bank", "whisker"], "not to calibration"),
])
def test_cli_refuses_bad_options(tmp_path, capsys, args, message):
    from supramodal.node.cli import main

    assert main(["experiment", "calibration", "--quick", "--quiet", "--out", str(tmp_path), *args]) == 2
    assert message in capsys.readouterr().err
