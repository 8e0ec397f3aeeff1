"""The paper's figures in --quick mode: structure of every result, determinism across --jobs, the CLI.

Quick runs use 4 s textures and small grids; they check shapes and invariants, never the paper's numbers.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.experiments import report
from supramodal.experiments.common import QUICK_DURATION, Plan, Run
from supramodal.experiments.fig1 import transfer_function
from supramodal.experiments.fig4 import sharpness
from supramodal.experiments.fig6 import WHISKER_GROUPS, first_at_or_above
from supramodal.experiments.runner import run_all, run_plans, run_seed
from supramodal.experiments.suite import FIGURES, plans
from supramodal.features import FEATURES
from supramodal.gammatone import GammatoneFilterbank

from results import strip_timing

ROOT = Path(__file__).resolve().parents[1]


def is_rate(v) -> bool:
    return isinstance(v, float) and 0.0 <= v <= 1.0


@pytest.fixture(scope="module")
def quick(once):
    """Every figure in quick mode, in one pool of two workers; run once per test run, whichever xdist
    worker gets here first (tests/harness/run_once.py)."""
    return once("test_experiments.quick all jobs=2 seed=0", lambda: run_plans(plans("all", quick=True), jobs=2, seed=0))


# -- runner ---------------------------------------------------------------------------------------

def test_run_seed_depends_on_seed_and_key_only():
    s = run_seed(0, ("fig5", 145.0))
    assert s == run_seed(0, ("fig5", 145.0)) and 0 <= s < 2**32
    assert len({s, run_seed(1, ("fig5", 145.0)), run_seed(0, ("fig5", 200.0)), run_seed(0, ("fig5", 145))}) == 4
    with pytest.raises(ValueError):
        run_seed(-1, ("x",))


def _echo(value, seed, progress=None):
    return {"value": value, "seed": seed}


def test_runner_returns_results_in_plan_order_whatever_the_schedule():
    runs = [Run(("r", i), _echo, {"value": i}, cost=float(i % 3)) for i in range(7)]
    out = run_all(runs, jobs=2, seed=3)
    assert list(out) == [("r", i) for i in range(7)]
    assert [out[("r", i)] for i in range(7)] == [{"value": i, "seed": run_seed(3, ("r", i))} for i in range(7)]
    with pytest.raises(ValueError, match="unique"):
        run_all(runs + runs[:1], jobs=1)
    with pytest.raises(ValueError, match="jobs"):
        run_all(runs, jobs=0)


@pytest.mark.slow   # a long run: every figure in quick mode (once per run)
def test_quick_results_do_not_depend_on_jobs(quick):
    one = run_plans({"fig5": plans("fig5", quick=True)["fig5"], "fig6": plans("fig6", quick=True)["fig6"]},
                    jobs=1, seed=0)
    assert strip_timing(one["fig5"]) == strip_timing(quick["fig5"])
    assert strip_timing(one["fig6"]) == strip_timing(quick["fig6"])


# -- each figure ----------------------------------------------------------------------------------

@pytest.mark.slow   # every figure in quick mode, as above
def test_all_runs_every_figure(quick):
    assert list(quick) == list(FIGURES)


@pytest.mark.slow   # every figure in quick mode, as above
def test_fig1_structure(quick):
    r = quick["fig1"]
    assert set(r["banks"]) == {"cochlea", "whisker"}
    for bank, channels in (("cochlea", 50), ("whisker", 20)):
        b = r["banks"][bank]
        freqs = np.array(b["freqs"])
        assert np.all(np.diff(freqs) > 0) and freqs[-1] < b["fs"] / 2
        gain = np.array(b["gain_db"])
        assert gain.shape == (channels, freqs.size) and np.isfinite(gain).all()
        assert len(b["channels"]) == channels
        for c in b["channels"]:
            assert -1e-9 < c["max_gain_db"] < 0.5       # unit gain at cf, peak at most slightly above
            assert abs(c["peak_hz"] - c["cf"]) < c["b"]
            if c["width_3db"] is not None:
                assert c["width_3db"] == pytest.approx(c["width_3db_formula"], rel=0.1)
    whisker_B = [c["B"] for c in r["banks"]["whisker"]["channels"]]
    assert min(whisker_B) == pytest.approx(111, abs=0.5) and max(whisker_B) == pytest.approx(233, abs=0.5)
    assert np.mean(whisker_B) == pytest.approx(145, abs=1)


@pytest.mark.parametrize("bank", [whisker_bank(), cochlea_bank(12)])
def test_fig1_closed_form_is_the_filters_own_response(bank):
    n = 1 << 16
    h = GammatoneFilterbank(bank).impulse_response(n)      # decayed to < 1e-12 well before n samples
    freqs = np.fft.rfftfreq(n, 1 / bank.fs)[1:]
    fft = np.fft.rfft(h, axis=1)[:, 1:]
    closed = transfer_function(bank, freqs)
    assert np.max(np.abs(fft - closed)) < 1e-9 * np.max(np.abs(closed))


@pytest.mark.slow   # every figure in quick mode, as above
def test_fig3_quick_structure(quick):
    r = quick["fig3"]
    assert set(r["banks"]) == {"whisker", "cochlea"} and "random_sets" not in r
    for bank, res in r["banks"].items():
        assert res["bank"] == bank and set(res["features"]) == set(FEATURES)
        assert res["timing"]["signal_seconds"] == 8 * QUICK_DURATION
        for f in res["features"].values():
            assert set(f) == {"mean_rate", "per_texture"} and len(f["per_texture"]) == 8
            assert is_rate(f["mean_rate"]) and all(is_rate(v) for v in f["per_texture"].values())


@pytest.mark.slow   # every figure in quick mode, as above
def test_fig4_quick_structure(quick):
    r = quick["fig4"]
    freqs = np.array(r["freqs"])
    assert r["channel"] == "A4" and r["cf"] == 630.0
    assert np.all(np.diff(freqs) > 0) and freqs[0] < 630 < freqs[-1]
    for f in FEATURES:
        d = r["features"][f]
        assert len(d["mean"]) == len(d["sd"]) == len(d["normalised"]) == freqs.size
        assert max(d["normalised"]) == 1.0 and min(d["normalised"]) > 0
        assert set(d["sharpness"]) == {"peak_hz", "low_hz", "high_hz", "width_3db", "q", "closed", "range_db"}
    a = r["features"]["A"]["sharpness"]
    assert a["closed"] and a["low_hz"] < 630 < a["high_hz"]
    assert r["features"]["f"]["sharpness"]["range_db"] < a["range_db"]


def test_sharpness_of_a_known_curve():
    freqs = np.linspace(0, 100, 1001)
    s = sharpness(freqs, 1 / np.sqrt(1 + ((freqs - 50) / 5) ** 2))   # half power at 45 and 55
    assert s["closed"] and s["peak_hz"] == 50
    assert s["width_3db"] == pytest.approx(10, abs=0.05) and s["q"] == pytest.approx(5, rel=0.01)
    rising = sharpness(freqs[1:], freqs[1:])
    assert not rising["closed"] and rising["width_3db"] is None and rising["high_hz"] is None


@pytest.mark.slow   # every figure in quick mode, as above
def test_fig5_quick_structure(quick):
    r = quick["fig5"]
    B = r["mean_B"]
    assert B == sorted(B) and B[0] == 5 and B[-1] == 500
    assert len(r["mean_width_3db"]) == len(B) and np.all(np.diff(r["mean_width_3db"]) > 0)
    for lo_hi, b in zip(r["B_range"], B):
        assert lo_hi[0] < b < lo_hi[1]
    assert set(r["features"]) == set(FEATURES)
    for f in r["features"].values():
        assert len(f["mean_rate"]) == len(B) and all(is_rate(v) for v in f["mean_rate"])
        assert len(f["per_texture"]) == 8 and all(len(v) == len(B) for v in f["per_texture"].values())


@pytest.mark.slow   # every figure in quick mode, as above
def test_fig6_quick_structure(quick):
    r = quick["fig6"]
    assert r["feature"] == "Af"
    c, w = r["cochlea"], r["whisker"]
    assert c["channels"] == sorted(c["channels"]) and c["channels"][0] == 1
    assert len(c["mean_rate"]) == len(c["channels"]) and all(is_rate(v) for v in c["mean_rate"])
    assert w["rows"] == list(WHISKER_GROUPS) == ["A", "AB", "ABC", "ABCD", "ABCDE"]
    assert w["channels"] == [4, 8, 12, 16, 20] and w["groups"] == [1, 2, 3, 4, 5]
    assert all(is_rate(v) for v in w["mean_rate"])


def test_first_at_or_above():
    assert first_at_or_above([1, 2, 3, 4], [0.5, 0.9, 0.7, 0.85]) == 4
    assert first_at_or_above([1, 2, 3], [0.9, 0.95, 0.99]) == 1
    assert first_at_or_above([1, 2], [0.9, 0.5]) is None


# -- files ----------------------------------------------------------------------------------------

EXPECTED_FILES = {
    "fig1": ["fig1_cochlea.csv", "fig1_whisker.csv", "fig1_channels.csv"],
    "fig3": ["fig3_whisker.csv", "fig3_cochlea.csv"],
    "fig4": ["fig4.csv", "fig4_sharpness.csv"],
    "fig5": ["fig5.csv"],
    "fig6": ["fig6_cochlea.csv", "fig6_whisker.csv"],
}


@pytest.mark.slow   # every figure in quick mode, as above
def test_write_figure_csv_always_png_with_matplotlib(quick, tmp_path, monkeypatch):
    monkeypatch.setattr(report, "have_matplotlib", lambda: False)
    for name, result in quick.items():
        written = report.write_figure(name, result, tmp_path / "bare")
        assert sorted(p.name for p in written) == sorted(EXPECTED_FILES[name])
        assert report.figure_table(name, result)
    monkeypatch.undo()
    if not report.have_matplotlib():
        pytest.skip("matplotlib not installed")
    for name, result in quick.items():
        pngs = [p for p in report.write_figure(name, result, tmp_path / "png") if p.suffix == ".png"]
        assert pngs and all(p.stat().st_size > 1000 for p in pngs)


@pytest.mark.slow   # every figure in quick mode, as above
def test_fig5_csv_rows(quick, tmp_path):
    report.write_figure("fig5", quick["fig5"], tmp_path)
    lines = (tmp_path / "fig5.csv").read_text().splitlines()
    assert lines[0] == "mean_B,mean_width_3db_hz,B_min,B_max,Af,A,f"
    assert len(lines) == 1 + len(quick["fig5"]["mean_B"])


# -- CLI ------------------------------------------------------------------------------------------

def run_cli(*args, timeout=300):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "supramodal.node.cli", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow   # every figure in quick mode, as above
def test_cli_fig4_json_quiet(tmp_path, quick):
    proc = run_cli("experiment", "fig4", "--quick", "--json", "--quiet", "--jobs", "1", "--out", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert strip_timing(json.loads(proc.stdout)) == strip_timing(quick["fig4"])
    assert (tmp_path / "fig4.csv").is_file()


@pytest.mark.slow   # a long run: Fig. 6 in quick mode in its own process
def test_cli_fig6_progress_and_table(tmp_path):
    proc = run_cli("experiment", "fig6", "--quick", "--jobs", "2", "--out", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    assert "runs over 2 worker process(es)" in proc.stderr and "[8/8]" in proc.stderr
    assert "whisker rows:" in proc.stdout and "wrote " in proc.stdout


@pytest.mark.slow   # a long run: Fig. 3 in quick mode in its own process
def test_cli_fig3_one_bank_keeps_its_shape(tmp_path):
    proc = run_cli("experiment", "fig3", "--bank", "whisker", "--quick", "--json", "--quiet", "--out", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r["bank"] == "whisker" and set(r["features"]) == set(FEATURES)
    assert all(set(v) == {"mean_rate", "per_texture"} for v in r["features"].values())
    assert (tmp_path / "fig3_whisker.csv").is_file() and not (tmp_path / "fig3_cochlea.csv").exists()


@pytest.mark.parametrize("args, message", [
    (["fig5", "--bank", "whisker"], "apply to fig3"),
    (["fig1", "--jobs", "0"], "argument --jobs: expected a whole number >= 1"),
    (["fig3", "--seed", "-2"], "argument --seed: expected a whole number from 0 to 4294967295"),
    (["all", "--bank", "cochlea"], "not to all"),
])
def test_cli_refuses_bad_options(tmp_path, args, message):
    proc = run_cli("experiment", *args, "--quick", "--quiet", "--out", str(tmp_path))
    assert proc.returncode == 2 and proc.stdout == ""
    assert message in proc.stderr and "Traceback" not in proc.stderr


def test_plans_have_unique_keys_prefixed_by_figure():
    for quick_mode in (True, False):
        ps = plans("all", quick=quick_mode)
        keys = [r.key for p in ps.values() for r in p.runs]
        assert len(keys) == len(set(keys))
        assert all(r.key[0] == name for name, p in ps.items() for r in p.runs)
    full = plans("all")
    assert [r.key[1] for r in full["fig5"].runs] == [5.0, 10.0, 20.0, 30.0, 50.0, 75.0, 100.0, 145.0, 200.0,
                                                     300.0, 400.0, 500.0]
    coch = [r.key[2] for r in full["fig6"].runs if r.key[1] == "cochlea"]
    assert coch[:10] == list(range(1, 11)) and {15, 20, 25, 30, 40, 50, 60} <= set(coch) and max(coch) == 60
    assert sum(r.key[2] == "random" for r in full["fig3"].runs) == 10


def test_plan_is_plain_data():
    p = plans("fig5", quick=True)["fig5"]
    assert isinstance(p, Plan) and all(isinstance(r, Run) for r in p.runs)


# -- ablations ------------------------------------------------------------------------------------

def test_features_from_rest_equal_one_fresh_pipeline_per_window():
    import dataclasses

    from supramodal.experiments.ablations import features_from_rest
    from supramodal.pipeline import extract_features
    from supramodal.textures import reference_texture_set

    ts = dataclasses.replace(reference_texture_set("whisker"), duration=0.5)
    ts = dataclasses.replace(ts, textures=ts.textures[:2])
    bank = whisker_bank(rows="AB")
    values = features_from_rest(ts, bank)
    assert values.shape == (2, 5, 3, 8)
    x = ts.synthesize(1)
    for w in range(5):
        alone = extract_features(x[w * 500 : (w + 1) * 500], bank).values[0]
        np.testing.assert_allclose(values[1, w], alone, rtol=1e-12, atol=1e-12)


def test_features_from_rest_of_more_windows_than_one_bank_may_hold_channels_are_each_windows_own():
    """A texture whose windows times the bank's channels pass the bank's limit (MAX_CHANNELS: 40 s of the
    whole whisker array is 400 windows x 20 channels) goes through in parts, and each part's windows are
    the windows a fresh pipeline gives, the parts' boundary too (it was refused: 'at most 1024 channels')."""
    import dataclasses

    from supramodal.banks import MAX_CHANNELS
    from supramodal.experiments.ablations import features_from_rest
    from supramodal.pipeline import extract_features
    from supramodal.textures import reference_texture_set

    bank = whisker_bank()
    per_call = MAX_CHANNELS // bank.channels
    n = per_call + 3
    ts = dataclasses.replace(reference_texture_set("whisker"), duration=n * 0.1)
    ts = dataclasses.replace(ts, textures=ts.textures[:1])
    values = features_from_rest(ts, bank)
    assert values.shape == (1, n, 3, bank.channels)
    x = ts.synthesize(0)
    for w in (0, per_call - 1, per_call, n - 1):
        alone = extract_features(x[w * 500 : (w + 1) * 500], bank).values[0]
        np.testing.assert_allclose(values[0, w], alone, rtol=1e-12, atol=1e-12)


def test_unscaled_rates_use_raw_inputs():
    from supramodal.experiments.common import classification_rates

    rng = np.random.default_rng(0)
    values = rng.standard_normal((3, 40, 1, 4)) + np.arange(3)[:, None, None, None]
    bank = whisker_bank(rows="A")
    scaled = classification_rates(values, ("a", "b", "c"), bank, ("A",), 500, epochs=50)
    raw = classification_rates(values, ("a", "b", "c"), bank, ("A",), 500, epochs=50, standardise=False)
    assert set(raw) == set(scaled) == {"mean_rate", "per_texture"} and is_rate(raw["mean_rate"])
    assert raw["mean_rate"] > 1 / 3


def test_ablation_plans_have_unique_keys():
    from supramodal.experiments.ablations import plans as ablation_plans

    for quick_mode in (True, False):
        keys = [r.key for p in ablation_plans(quick=quick_mode).values() for r in p.runs]
        assert len(keys) == len(set(keys)) and all(k[0] == "ablation" for k in keys)
