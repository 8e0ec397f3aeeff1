"""`supramodal fit`'s joint search (node/workflows/fit_search.py) and its feature cache (node/workflows/fit_cache.py)."""

from __future__ import annotations

import csv
import sys

import numpy as np
import pytest
from test_fit import SENSOR_RATE as RATE
from test_fit import (
    TEXTURES,
    sensor,  # noqa: F401  (a fixture)
)

from supramodal.banks import whisker_bank
from supramodal.node.cli import main
from supramodal.node.workflows.fit_cache import FeatureCache, base_samples
from supramodal.node.workflows.manifest import read_manifest
from supramodal.node.workflows.training import recording_windows
from supramodal.pipeline import FeaturePipeline
from supramodal.replay.wavio import write_wav
from supramodal.textures import synthesize

pytest.importorskip("optuna", reason="the fit extra (optuna) is not installed: pip install -e '.[fit]'")

from supramodal.node.workflows.fit_search import (  # noqa: E402
    DEFAULT_PATIENCE,
    FitError,
    Setting,
    cpu_per_trial,
    fit_search,
    format_search,
    paper_verdict,
    plateau,
    search_space,
)

#: Small and fast: few trials of few epochs (the search's behaviour, not its accuracy, is tested).
FAST = {"k": 3, "quick": True, "trials": 6, "batch": 3, "max_epochs": 8}


@pytest.fixture(scope="module")
def manifest(sensor):  # noqa: F811  (test_fit's fingertip-like sensor: 2.2 kHz, four textures close together)
    return sensor / "m.csv"


def _settings(rows):
    return [(r["trial"], r["state"], r.get("family"), r.get("channels"), r.get("window"), r.get("features"),
             r.get("hidden"), r.get("epochs"), r.get("window_mean")) for r in rows]


# -- the cache -----------------------------------------------------------------------------------

def test_cached_windows_are_the_pipelines_for_every_window_and_feature_set_from_one_filterbank_run(manifest, tmp_path):
    recs = read_manifest(manifest)
    bank = Setting(RATE, "erb", 12, 40.0, 900.0, 1.0, 0.1, "Af", 8, 10).bank()
    cache = FeatureCache(recs, (0.05, 0.1, 0.2), folder=tmp_path / "cache")
    for window, features in ((0.1, ("Af",)), (0.2, ("A", "f", "Af")), (0.05, ("f", "A")), (0.1, ("A",))):
        got = cache.features(bank, window, features)
        for rec, v in zip(recs, got):
            want = recording_windows(rec, FeaturePipeline(bank, features, window))
            assert v.shape == want.shape
            np.testing.assert_allclose(v, want, rtol=1e-12, atol=1e-12)
    assert cache.filterbank_runs == len(recs)               # once per recording, for four windows x features
    # Another process of the same machine reads the bank from the folder instead of filtering again.
    other = FeatureCache(recs, (0.05, 0.1, 0.2), folder=tmp_path / "cache")
    np.testing.assert_array_equal(other.features(bank, 0.2, ("Af",))[3], cache.features(bank, 0.2, ("Af",))[3])
    assert (other.filterbank_runs, other.disk_reads) == (0, 1)


def test_windows_of_no_useful_common_divisor_take_bases_of_their_own(tmp_path):
    # 0.025 s and 0.05 s at 44.1 kHz are 1102 and 2205 samples (rounded): no common base of 2 or more.
    assert base_samples((0.025, 0.05, 0.1), 44100) == (1102, 2205)
    assert base_samples((0.05, 0.1, 0.2, 0.4), 2000) == (100,)
    write_wav(tmp_path / "a.wav", 0.2 * synthesize((300, 900, 2500), 44100, 0.5, seed=2)[:, None], 44100)
    write_wav(tmp_path / "b.wav", 0.2 * synthesize((400, 1200, 3000), 44100, 0.5, seed=3)[:, None], 44100)
    (tmp_path / "m.csv").write_text("path,label\na.wav,a\nb.wav,b\n")
    recs = read_manifest(tmp_path / "m.csv")
    bank = Setting(44100, "erb", 4, 200.0, 5000.0, 1.0, 0.025, "Af", 8, 10).bank()
    cache = FeatureCache(recs, (0.025, 0.05, 0.1))
    for window in (0.025, 0.05, 0.1):
        for rec, v in zip(recs, cache.features(bank, window, ("A", "Af"))):
            want = recording_windows(rec, FeaturePipeline(bank, ("A", "Af"), window))
            np.testing.assert_allclose(v, want, rtol=1e-12, atol=1e-12)
    assert cache.filterbank_runs == 2 * len(recs)            # one run per base


def test_the_cache_keeps_within_its_memory_bound_and_refilters_only_without_a_folder(manifest, tmp_path):
    recs = read_manifest(manifest)
    a = Setting(RATE, "erb", 8, 40.0, 900.0, 1.0, 0.1, "Af", 8, 10).bank()
    b = Setting(RATE, "whisker", 8, 40.0, 900.0, 1.0, 0.1, "Af", 8, 10).bank()
    bounded = FeatureCache(recs, (0.1,), memory_bytes=1)       # one bank at a time
    bounded.features(a, 0.1, ("Af",))
    bounded.features(b, 0.1, ("Af",))
    bounded.features(a, 0.1, ("Af",))
    assert bounded.filterbank_runs == 3 * len(recs) and len(bounded._held) == 1
    spilled = FeatureCache(recs, (0.1,), memory_bytes=1, folder=tmp_path / "spill")
    for bank in (a, b, a, b):
        spilled.features(bank, 0.1, ("Af",))
    assert (spilled.filterbank_runs, spilled.disk_reads) == (2 * len(recs), 2)


# -- the search ----------------------------------------------------------------------------------

@pytest.mark.slow   # a long run: a fit's search run twice
def test_the_search_is_deterministic_for_a_seed_and_each_fold_is_filtered_once_per_bank(manifest):
    first = fit_search(manifest, seed=3, **FAST)
    again = fit_search(manifest, seed=3, **FAST)
    assert _settings(first["rows"]) == _settings(again["rows"])
    assert _untimed(first["best"]) == _untimed(again["best"]) and _untimed(first["curve"]) == _untimed(again["curve"])
    other = fit_search(manifest, seed=4, **FAST)
    assert _settings(other["rows"]) != _settings(first["rows"])
    # Work done once: every distinct bank (of the trials and the paper's two) ran through the
    # filterbank once per recording, whatever the folds, windows and feature sets that used it.
    banks = {(r["family"], r["channels"], r["f_low"], r["f_high"], r["b_scale"]) for r in first["rows"]
             if r["folds"]}
    assert first["filterbank_runs"] == (len(banks) + 2) * first["recordings"]
    scored = sum(r["folds"] for r in first["rows"])
    assert first["filterbank_runs"] < (scored + 2 * len(first["curve"]) * FAST["k"]) * first["recordings"]


def _untimed(x):
    """``x`` without the CPU seconds the trials took (the only part that is not the seed's)."""
    if isinstance(x, dict):
        return {k: _untimed(v) for k, v in x.items() if k != "cpu_seconds"}
    if isinstance(x, list):
        return [_untimed(v) for v in x]
    return x


def test_the_search_reports_each_fold_and_prunes_hopeless_trials(manifest):
    said = []
    result = fit_search(manifest, seed=0, progress=said.append, patience=0, **{**FAST, "trials": 14})
    states = [r["state"] for r in result["rows"]]
    assert len(states) == 14 and "complete" in states
    pruned = [r for r in result["rows"] if r["state"] == "pruned"]
    assert pruned and all(1 <= r["folds"] < FAST["k"] for r in pruned)
    complete = [r for r in result["rows"] if r["state"] == "complete"]
    assert all(r["folds"] == FAST["k"] for r in complete)
    assert result["best"]["score"] == max(r["score"] for r in complete)
    # Each trial's CPU seconds (issue 38, item 3): its folds' sum, said as the search goes and in the report.
    assert all(r["cpu_seconds"] > 0 for r in complete + pruned)
    assert any("CPU s per complete trial" in line for line in said)
    assert f"({cpu_per_trial(result['rows']):.1f} CPU s per complete trial, median)" in format_search(result)


def _row(trial, state="complete", score=0.5, sd=0.05):
    return {"trial": trial, "state": state, "score": score, "window_mean": score, "window_sd": sd,
            "recording_mean": score, "recording_sd": sd}


def test_a_plateau_is_the_best_not_moving_by_more_than_its_fold_spread_in_the_last_trials():
    rows = [_row(0, score=0.40), _row(1, score=0.50, sd=0.05), _row(2, "pruned"), _row(3, score=0.52, sd=0.04)]
    # Four trials, patience 3: the best (0.52, spread 0.04) moved 0.12 above trial 0's, more than its spread.
    assert plateau(rows, 3, "window") is None
    # Patience 2: above the best of trials 0 and 1 (0.50) by 0.02, within its spread: stopped.
    said = plateau(rows, 2, "window")
    assert said is not None and said["trials"] == 4 and said["spread"] == 0.04
    assert said["moved"] == pytest.approx(0.02)
    assert said["text"] == ("stopped after 4 trials: the best has not moved by more than the fold spread (0.040) "
                            "for 2 trials")
    # Exactly the spread is not more than it; a hair above it is (binary fractions: the sums are exact).
    assert plateau([_row(0, score=0.5), _row(1, score=0.625, sd=0.125)], 1, "window") is not None
    assert plateau([_row(0, score=0.5), _row(1, score=0.625 + 1e-9, sd=0.125)], 1, "window") is None
    # A pruned or empty trial is a trial in which the best did not move.
    assert plateau([_row(0), _row(1, "pruned"), _row(2, "empty band")], 2, "window") is not None
    # Nothing to move from (no trial complete before the last ``patience``), too few trials, or patience 0: none.
    assert plateau([_row(0, "pruned"), _row(1), _row(2)], 2, "window") is None
    assert plateau([_row(0), _row(1)], 2, "window") is None
    assert plateau([_row(i) for i in range(40)], 0, "window") is None
    # The spread is the target's: a recording's sd where the fit maximises recording accuracy.
    rows = [_row(0, score=0.5), {**_row(1, score=0.6, sd=0.01), "recording_sd": 0.2}]
    assert plateau(rows, 1, "window") is None and plateau(rows, 1, "recording") is not None


def test_the_search_stops_on_a_plateau_at_the_first_round_that_ends_on_one_and_patience_0_runs_every_trial(manifest):
    """The stop comes at the first round's end on a plateau, not before; without patience every trial runs.

    The patience is one at which a round's end that may stop the search (past the patience) is off a plateau before
    the stop, on this seed's trials (asserted below): 5 since the trials score the calibrated model `train` makes;
    at 6 the first such end was already on one, so the test could not tell a stop at the first plateau from a
    stop at any round's end."""
    trials, patience, batch = 15, 5, FAST["batch"]
    every = fit_search(manifest, seed=1, patience=0, **{**FAST, "trials": trials})
    assert len(every["rows"]) == trials and every["stopped"] is None and every["patience"] == 0
    said: list[str] = []
    early = fit_search(manifest, seed=1, patience=patience, progress=said.append, **{**FAST, "trials": trials})
    n = len(early["rows"])
    assert n < trials and early["stopped"]["trials"] == n and early["patience"] == patience
    # The stop cuts the search short and changes none of its trials (the seed's, as without it).
    assert _settings(early["rows"]) == _settings(every["rows"][:n])

    def still(k):
        """The best of the first k trials is within its fold spread of the best before the last ``patience``."""
        best = max((r for r in every["rows"][:k] if r["state"] == "complete"),
                   key=lambda r: (r["score"], r["window_mean"], r["recording_mean"], -r["trial"]))
        before = [r["score"] for r in every["rows"][:k - patience] if r["state"] == "complete"]
        return bool(before) and best["score"] - max(before) <= best["window_sd"]

    ends = list(range(batch, trials, batch))                 # the rounds' ends, where the search may stop
    assert any(k > patience and not still(k) for k in ends if k < n)     # the premise: one end did not stop it
    assert n == next(k for k in ends if k > patience and still(k))
    text = (f"stopped after {n} trials: the best has not moved by more than the fold spread "
            f"({early['best']['window_sd']:.3f}) for {patience} trials")
    assert f"fit: {text}; {trials - n} trials not run" in said
    assert f"{text} (--patience {patience}; {trials - n} of the {trials} trials not run)" in format_search(early)
    assert "stopped after" not in format_search(every)


def test_the_report_says_whether_the_best_beats_the_papers_banks_by_more_than_a_folds_spread(manifest):
    def result(best, sd, whisker, cochlea, bank_sd=0.01):
        paper = {name: {"window_mean": mean, "window_sd": bank_sd} for name, mean in (("whisker", whisker),
                                                                                        ("cochlea", cochlea))}
        return {"target": "window", "best": {"window_mean": best, "window_sd": sd}, "paper": paper}

    clear = paper_verdict(result(0.80, 0.02, 0.50, 0.70))
    assert clear["beats"] and clear["cochlea"] == {"ahead": pytest.approx(0.10), "spread": 0.02, "beats": True}
    assert clear["text"].startswith("The best beats the paper's banks by more than a fold's spread (window "
                                    "accuracy): the whisker bank by +0.300, more than a fold's spread (0.020)")
    # Ahead of the cochlea by less than the larger of the two spreads (its own here): not a clear win.
    close = paper_verdict(result(0.80, 0.02, 0.50, 0.75, bank_sd=0.06))
    assert not close["beats"] and close["whisker"]["beats"] and not close["cochlea"]["beats"]
    assert close["text"].startswith("The best does NOT beat the paper's banks by more than a fold's spread")
    assert "the cochlea bank by +0.050, not more than a fold's spread (0.060)" in close["text"]
    # Behind a paper bank: said the same way, with the sign.
    assert "the cochlea bank by -0.050" in paper_verdict(result(0.70, 0.02, 0.50, 0.75))["text"]
    # A search's report says it.
    run = fit_search(manifest, seed=0, **FAST)
    assert paper_verdict(run)["text"] in format_search(run)


def test_a_trials_score_is_the_cross_validation_of_the_model_train_makes_with_its_setting(manifest):
    """Each fold scores the model `train --hidden H` makes of its training recordings (calibrated on folds by
    recording, its fold networks stopped early together and deployed): a complete trial's window and recording
    accuracy are `train --cv`'s (cross_validate_manifest) for its setting, its hidden units included. (They were a
    single uncalibrated network's, trained every epoch, which `train` does not make.)"""
    from supramodal.node.workflows.fit_search import Setting
    from supramodal.node.workflows.training import cross_validate_manifest

    result = fit_search(manifest, seed=1, **{**FAST, "trials": 3})
    rows = [r for r in result["rows"] if r["state"] == "complete"]
    assert len(rows) == 3
    for row in rows:
        setting = Setting(result["fs"], *(row[f] for f in list(Setting.__dataclass_fields__)[1:]))
        features = tuple(setting.features.split("+"))
        assert setting.hidden != len(features) * setting.channels   # the paper's rule would not give the same network
        direct = cross_validate_manifest(manifest, setting.bank(), features, setting.window, FAST["k"],
                                         epochs=setting.epochs, seed=1, hidden=setting.hidden)
        assert row["window_mean"] == pytest.approx(direct["window_accuracy"]["mean"], abs=1e-12)
        assert row["recording_mean"] == pytest.approx(direct["recording_accuracy"]["mean"], abs=1e-12)


def test_a_folds_score_is_train_s_where_its_fold_networks_stop_early(manifest, monkeypatch):
    """At 300 epochs (patience 100) the fold networks stop early together: the fold's score is still the one
    `train --cv` gives (cross_validate_manifest's fold), and its networks did stop before 300 epochs."""
    from supramodal.node.workflows import fit_search as search
    from supramodal.node.workflows.training import cross_validate_manifest

    models = []
    train = search.TextureModel.train

    def spy(*args, **kwargs):
        models.append(train(*args, **kwargs))
        return models[-1]

    monkeypatch.setattr(search.TextureModel, "train", spy)
    setting = search.Setting(RATE, "erb", 8, 60.0, 900.0, 1.0, 0.1, "Af", 6, 300)
    job = {"manifest": str(manifest), "mapping": "auto", "windows": (0.1,), "cache_dir": None,
           "cache_memory": 64 << 20, "k": 3, "seed": 2, "contact": 0.5, "train_windows": None, "augment": None,
           "bank": setting.bank().to_dict(), "window": 0.1, "features": "Af", "hidden": 6, "epochs": 300}
    scores = [search.score_fold({**job, "fold": f})["window"] for f in range(3)]
    direct = cross_validate_manifest(manifest, setting.bank(), ("Af",), 0.1, 3, epochs=300, seed=2, hidden=6)
    assert scores == pytest.approx([f["window_accuracy"] for f in direct["folds"]], abs=1e-12)
    assert all(max(m.training["network_epochs"]) < 300 for m in models), [m.training["network_epochs"] for m in models]


def test_a_folds_model_trains_on_the_windows_the_quick_cap_keeps_each_with_its_recordings_group(manifest,
                                                                                                 monkeypatch):
    """--quick keeps at most so many training windows, evenly spaced: the calibration's groups (each window's
    recording) are kept with them, window for window, as a plain gathering of the fold's recordings gives them."""
    from supramodal.node.workflows import fit_search as search
    from supramodal.node.workflows.training import recording_group
    from supramodal.training import grouped_folds

    seen = {}
    train = search.TextureModel.train

    def spy(values, labels, classes, *args, groups=None, **kwargs):
        seen.update(values=np.array(values), labels=np.array(labels), groups=np.array(groups), kwargs=kwargs)
        return train(values, labels, classes, *args, groups=groups, **kwargs)

    monkeypatch.setattr(search.TextureModel, "train", spy)
    setting = search.Setting(RATE, "erb", 8, 60.0, 900.0, 1.0, 0.1, "Af", 6, 5)
    job = {"manifest": str(manifest), "mapping": "auto", "windows": (0.1,), "cache_dir": None,
           "cache_memory": 64 << 20, "k": 3, "seed": 2, "contact": 0.5, "train_windows": 50, "augment": None,
           "bank": setting.bank().to_dict(), "window": 0.1, "features": "Af", "hidden": 6, "epochs": 5, "fold": 1}
    search.score_fold(job)
    recs = read_manifest(manifest)
    classes = sorted({r.label for r in recs})
    fold = grouped_folds([r.where for r in recs], [r.label for r in recs], 3, 2)
    kept = [i for i in range(len(recs)) if fold[i] != 1]
    counts = [len(recording_windows(recs[i], FeaturePipeline(setting.bank(), ("Af",), 0.1))) for i in kept]
    every_group = np.repeat([recording_group(recs[i]) for i in kept], counts)
    every_label = np.repeat([classes.index(recs[i].label) for i in kept], counts)
    keep = np.round(np.linspace(0, sum(counts) - 1, 50)).astype(int)
    assert sum(counts) > 50 and len(seen["values"]) == 50
    np.testing.assert_array_equal(seen["groups"], every_group[keep])
    np.testing.assert_array_equal(seen["labels"], every_label[keep])
    assert seen["kwargs"]["calibration_folds"] > 0 and seen["kwargs"]["patience"] is not None      # train's model


def test_a_time_budget_stops_new_rounds_after_the_first(manifest):
    result = fit_search(manifest, seed=2, timeout=1e-6, **{**FAST, "trials": 9})
    assert len(result["rows"]) == FAST["batch"]                  # one round of trials, then the budget is spent


@pytest.mark.slow   # a long run: a fit's search on a local Dask cluster and in one process
def test_a_dask_cluster_gives_the_result_of_one_process(manifest, tmp_path):
    distributed = pytest.importorskip("distributed", reason="the fit extra (dask[distributed]) is not installed")
    alone = fit_search(manifest, seed=5, **FAST)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp://",
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        # The workers share a cache folder: each bank's parts are filtered by tasks of their own first.
        spread = fit_search(manifest, seed=5, cluster=cluster.scheduler_address, cache_dir=tmp_path / "cache", **FAST)
    assert spread["where"].startswith("Dask scheduler tcp://127.0.0.1:")
    assert spread["filterbank_runs"] == alone["filterbank_runs"]         # still once per bank and recording
    assert all(_untimed(spread[key]) == _untimed(alone[key]) for key in ("rows", "curve", "best"))


def test_constraints_are_obeyed_and_the_curve_holds_every_window_within_the_budget(manifest):
    result = fit_search(manifest, seed=1, max_window=0.15, max_channels=12, **FAST)
    tried = [r for r in result["rows"] if r["folds"]]
    assert all(r["window"] <= 0.15 and r["channels"] <= 12 for r in tried)
    assert all(r["f_low"] >= 1 / r["window"] - 1e-9 for r in tried)        # one period of the lowest channel
    assert [p["window"] for p in result["curve"]] == [0.05, 0.1, 0.15]       # the budget itself is tried
    for p in result["curve"]:
        assert set(p) == {"window", "fitted", "whisker", "cochlea"} and p["whisker"]["folds"] == FAST["k"]
    assert result["paper"]["whisker"] == next(p["whisker"] for p in result["curve"]
                                              if p["window"] == result["best"]["window"])


@pytest.mark.parametrize(("options", "words"), [
    ({"max_window": 0.0005}, "1 sample(s) at the recordings' 2200 Hz; a window needs at least 2"),
    ({"max_window": 0.002}, "shorter than one period of the lowest band any bank could have"),
    ({"max_channels": 5000}, "--max-channels must be a whole number from 1 to 1024"),
    ({"target": "contact", "contact": 2.0}, "--contact 2 s is longer than"),
    ({"target": "contact", "contact": 0.01}, "shorter than the shortest window"),
    ({"target": "session"}, "--target 'session': choose one of window, recording, contact"),
])
def test_impossible_constraints_are_refused_before_any_work(manifest, options, words):
    with pytest.raises(FitError) as caught:
        search_space(read_manifest(manifest), quick=True, **options)
    assert words in str(caught.value)


def test_trials_shorter_than_every_window_are_refused_naming_the_line(tmp_path):
    rows = ["path,label,start,end"]
    for name, peaks in TEXTURES.items():
        write_wav(tmp_path / f"{name}.wav", 0.2 * synthesize(peaks, RATE, 1.0, seed=1)[:, None], RATE)
        rows += [f"{name}.wav,{name},0,0.5", f"{name}.wav,{name},0.5,0.53"]
    (tmp_path / "m.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(FitError, match=r"line 3: silk.wav holds 0.03 s, shorter than every window"):
        search_space(read_manifest(tmp_path / "m.csv"), quick=True)


def test_whisker_family_spans_the_band_with_the_whisker_layout(manifest):
    s = Setting(RATE, "whisker", 20, 50.0, 900.0, 1.0, 0.1, "Af", 8, 10)
    bank = s.bank()
    assert bank.cf[0] == pytest.approx(50.0) and bank.cf[-1] == pytest.approx(900.0)
    paper = np.sort(whisker_bank().cf)
    # The layout's spacing on a log scale is the whiskers', stretched over the band.
    np.testing.assert_allclose(np.diff(np.log(bank.cf)) / np.log(900 / 50),
                               np.diff(np.log(paper)) / np.log(paper[-1] / paper[0]), atol=1e-12)


# -- the command ---------------------------------------------------------------------------------

def test_fit_command_prints_progress_the_curve_and_writes_its_files(manifest, tmp_path, capsys):
    out = tmp_path / "fit"
    assert main(["fit", str(manifest), "--out", str(out), "--cv", "3", "--quick", "--trials", "4", "--batch", "2",
                 "--epochs", "8", "--max-window", "0.1"]) == 0
    captured = capsys.readouterr()
    assert "fit: trial 2 of 4; best so far" in captured.err and "s left" in captured.err
    assert "fit: trial 4 of 4;" in captured.err
    assert "the paper's whisker bank (same window, features, network)" in captured.out
    assert "best window accuracy per window length" in captured.out and "next: supramodal train --bank" in captured.out
    best = max((r for r in csv.DictReader(open(out / "fit.csv")) if r["state"] == "complete"),
               key=lambda r: (float(r["score"]), float(r["window_mean"]), float(r["recording_mean"]), -int(r["trial"])))
    assert f" --hidden {best['hidden']} --epochs {best['epochs']} " in captured.out   # the network it scored
    curve = list(csv.DictReader(open(out / "fit-curve.csv")))
    assert [float(r["window"]) for r in curve] == [0.05, 0.1]
    assert len(list(csv.DictReader(open(out / "fit.csv")))) == 4
    # Issue 36 item 6: the feature cache's folder went with its files (an empty fit/cache was left behind).
    assert (out / "bank.json").is_file() and not (out / "cache").exists()


def test_the_next_command_the_fit_prints_makes_the_model_it_scored(manifest, tmp_path, capsys):
    """Its `next:` line, run as printed with `--cv` of the fit's folds, cross-validates to the fit's best score:
    the same bank, window, features, hidden units, epochs, seed (the networks' start and the folds) and channel
    mapping. (It left out --seed unless --augment-gains was given.)"""
    import shlex

    out = tmp_path / "fit"
    assert main(["fit", str(manifest), "--out", str(out), "--cv", "3", "--quick", "--trials", "3", "--batch", "3",
                 "--epochs", "8", "--max-window", "0.1", "--seed", "1", "--mapping", "mono", "--quiet"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("next: supramodal train "))
    argv = [str(tmp_path / "model.npz") if a == "MODEL" else a for a in shlex.split(line)[2:]]
    assert argv[argv.index("--seed") + 1] == "1" and argv[argv.index("--mapping") + 1] == "mono"
    best = max((r for r in csv.DictReader(open(out / "fit.csv")) if r["state"] == "complete"),
               key=lambda r: (float(r["score"]), float(r["window_mean"]), float(r["recording_mean"]), -int(r["trial"])))
    assert main([*argv, "--cv", "3", "--quiet"]) == 0
    said = capsys.readouterr().out
    assert f"window accuracy     {float(best['window_mean']):.3f} +- {float(best['window_sd']):.3f}" in said


def test_fit_command_stops_early_as_patience_says_and_patience_0_runs_every_trial(manifest, tmp_path, capsys):
    from supramodal.node.cli import fit as fit_command

    assert fit_command.DEFAULT_PATIENCE == DEFAULT_PATIENCE       # the parser's default is the search's
    common = ["--cv", "3", "--quick", "--trials", "12", "--batch", "3", "--epochs", "8"]
    assert main(["fit", str(manifest), "--out", str(tmp_path / "a"), *common, "--patience", "3"]) == 0
    captured = capsys.readouterr()
    stopped = [line for line in captured.err.splitlines() if "fit: stopped after " in line]
    assert len(stopped) == 1 and stopped[0].endswith("for 3 trials; 6 trials not run"), captured.err
    n = len(list(csv.DictReader(open(tmp_path / "a" / "fit.csv"))))
    assert n == 6 and f"fit: trial {n} of 12;" in captured.err
    assert "(--patience 3; 6 of the 12 trials not run)" in captured.out
    assert "the paper's banks by more than a fold's spread" in captured.out
    assert main(["fit", str(manifest), "--out", str(tmp_path / "b"), *common, "--patience", "0"]) == 0
    assert "stopped after" not in capsys.readouterr().err
    assert len(list(csv.DictReader(open(tmp_path / "b" / "fit.csv")))) == 12
    with pytest.raises(SystemExit) as refused:
        main(["fit", str(manifest), "--out", str(tmp_path / "c"), "--patience", "-1"])
    assert refused.value.code == 2 and "argument --patience: expected a whole number >= 0" in capsys.readouterr().err


def test_fit_command_without_the_extra_says_how_to_install_it(manifest, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "optuna", None)            # import optuna raises ImportError
    assert main(["fit", str(manifest), "--out", str(tmp_path / "fit"), "--quick"]) == 2
    assert "pip install 'supramodal[fit]'" in capsys.readouterr().err


def test_fit_command_refuses_an_impossible_budget_at_once(manifest, tmp_path, capsys):
    assert main(["fit", str(manifest), "--out", str(tmp_path / "fit"), "--max-window", "0.002"]) == 2
    err = capsys.readouterr().err
    assert "supramodal: error:" in err and "raise --max-window" in err and "trial" not in err


def test_a_manifest_of_one_label_is_refused_as_train_refuses_it(tmp_path, capsys):
    """Issue 35, item 22: fit took a manifest of one label and reported "windows 1.000 ± 0.000" with a
    bank.json; train refused it. Both refuse it now, with the same words, before any work."""
    name, peaks = next(iter(TEXTURES.items()))
    write_wav(tmp_path / "a.wav", 0.2 * synthesize(peaks, RATE, 1.0, seed=1)[:, None], RATE)
    (tmp_path / "m.csv").write_text("path,label\na.wav,only\n")
    for argv in (["fit", str(tmp_path / "m.csv"), "--out", str(tmp_path / "fit"), "--quick"],
                 ["train", "--bank", "whisker", "--manifest", str(tmp_path / "m.csv"), "--out", str(tmp_path / "m.npz")]):
        assert main(argv) == 2
        assert "training needs at least two labels, found ['only']" in capsys.readouterr().err
    assert not (tmp_path / "fit" / "bank.json").exists()


def test_a_cluster_address_that_accepts_and_never_answers_is_refused_in_bounded_time(monkeypatch):
    """Issue 35, item 9: ``--cluster`` at an address that accepts TCP and stays silent waited forever (Dask's
    timeout covers only the connection). Refused once its greeting is late, saying so; a server that
    closes at once is refused as no scheduler too."""
    import socket
    import threading
    import time

    from supramodal.node.workflows import fit_search as fs

    pytest.importorskip("distributed")
    monkeypatch.setattr(fs, "SCHEDULER_TIMEOUT", 1.0)
    for behaviour, said in (("silent", "accepts connections but said nothing in 1 s"),
                            ("closes", "closed the connection without a word")):
        server = socket.socket()
        server.bind(("127.0.0.1", 0))
        server.listen(4)
        held = []

        def serve(server=server, behaviour=behaviour, held=held):
            while True:
                try:
                    conn, _ = server.accept()
                except OSError:
                    return
                if behaviour == "closes":
                    conn.close()
                else:
                    held.append(conn)

        threading.Thread(target=serve, daemon=True).start()
        address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        t = time.monotonic()
        try:
            with pytest.raises(FitError, match=rf"--cluster {address}: {said}: no Dask scheduler there"):
                fs.Runner(cluster=address)
            assert time.monotonic() - t < 10.0
        finally:
            server.close()
            for conn in held:
                conn.close()


def test_a_local_cluster_says_nothing_of_a_port_another_one_holds():
    """Issue 35, item 33: ``fit --jobs N`` printed Dask's raw 4-line "Port 8787 is already in use" warning when
    another cluster (or anything) held Dask's default port. The local cluster's HTTP server takes a free
    port on this machine; no warning."""
    import socket
    import warnings

    from supramodal.node.workflows import fit_search as fs

    pytest.importorskip("distributed")
    holder = socket.socket()
    try:
        holder.bind(("127.0.0.1", 8787))
        holder.listen()
    except OSError:
        pass                                            # held already: the case itself
    try:
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            with fs.Runner(jobs=2) as runner:
                assert runner.map([{"x": 1}, {"x": 2}], task=_echo) == [{"x": 1}, {"x": 2}]
        assert not [w for w in said if "already in use" in str(w.message)], [str(w.message) for w in said]
    finally:
        holder.close()


def _echo(job: dict) -> dict:
    return job


#: Seconds a worker process that ran :func:`_slow_to_end` takes to end (as on a busy machine).
SLOW_END = 6.0


def _slow_to_end(job: dict) -> dict:
    import atexit
    import time

    atexit.register(time.sleep, SLOW_END)
    return job


@pytest.mark.slow   # two worker processes, each taking 6 s to end
def test_local_workers_slow_to_end_are_given_time_and_the_fit_ends_without_dasks_kill_warnings():
    """Issue 36 item 6: a fit on local workers ended with Dask's "Worker process still alive after 4.0
    seconds, killing", once a worker: Dask gives a worker 4 s to end, and on a busy machine its exit took
    longer. A fit that ran to its end gives each WORKER_CLOSE_SECONDS; they end on their own, unkilled."""
    import logging

    from supramodal.node.workflows import fit_search as fs

    pytest.importorskip("distributed")
    said: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            said.append(record.getMessage())

    nanny = logging.getLogger("distributed.nanny")       # the workers' nannies log in this process
    keep = Keep(logging.WARNING)
    nanny.addHandler(keep)
    try:
        with fs.Runner(jobs=2) as runner:
            assert runner.map([{"x": 1}, {"x": 2}], task=_slow_to_end) == [{"x": 1}, {"x": 2}]
    finally:
        nanny.removeHandler(keep)
    assert not [m for m in said if "still alive" in m or "killing" in m.lower()], said
    assert SLOW_END < 0.8 * fs.WORKER_CLOSE_SECONDS / 2         # the test's premise: a margin, not a race


def test_a_local_worker_says_nothing_of_a_heartbeat_that_finds_the_scheduler_gone():
    """The workers' preload: the heartbeat's failure as the cluster closes is left out, a worker's other
    errors are not."""
    import subprocess
    import sys

    from supramodal.node.workflows.fit_search import WORKER_IGNORES_SIGINT

    said = subprocess.run([sys.executable, "-c", WORKER_IGNORES_SIGINT + (
        "log = logging.getLogger('distributed.worker')\n"
        "try:\n    raise OSError('Stream is closed')\n"
        "except OSError:\n    log.exception('Failed to communicate with scheduler during heartbeat.')\n"
        "log.error('Unexpected exception during heartbeat. Closing worker.')\n")],
                          capture_output=True, text=True, timeout=60)
    assert said.returncode == 0, said.stderr
    assert "Traceback" not in said.stderr and "Failed to communicate" not in said.stderr
    assert "Unexpected exception during heartbeat" in said.stderr


@pytest.mark.slow   # a fit on a local Dask cluster, interrupted twice
@pytest.mark.parametrize("how", ["SIGINT to the group", "SIGTERM to the fit"])
def test_an_interrupted_fit_on_local_workers_ends_in_one_line(sensor, tmp_path, how):
    """Issue 35, item 19: Ctrl-C on ``fit --jobs 2`` (SIGINT to the whole process group, as a terminal sends it)
    printed a KeyboardInterrupt traceback per worker; SIGTERM ended it on the spot, leaking its workers'
    semaphores. Either ends the fit within seconds, in one line, its workers gone, no traceback."""
    import os
    import signal
    import subprocess
    import time

    pytest.importorskip("distributed")
    # No early stop (--patience 0): the fit is still at work when the signal comes, however fast its trials.
    fit = subprocess.Popen([sys.executable, "-m", "supramodal", "fit", str(sensor / "m.csv"), "--out",
                            str(tmp_path / "out"), "--quick", "--jobs", "2", "--trials", "400", "--patience", "0"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        assert fit.stderr is not None
        lines = []
        while not any("trial 4 of" in line for line in lines):       # the workers are at work
            lines.append(fit.stderr.readline())
            assert lines[-1], "".join(lines)
        t = time.monotonic()
        if how.startswith("SIGINT"):
            os.killpg(fit.pid, signal.SIGINT)
        else:
            fit.send_signal(signal.SIGTERM)
        _, err = fit.communicate(timeout=60)
        took = time.monotonic() - t
        assert took < 30.0, f"the fit ended {took:.1f} s after the signal; its stderr: {err[-2000:]}"
    finally:
        fit.kill()
    signum = signal.SIGINT if how.startswith("SIGINT") else signal.SIGTERM
    assert fit.returncode == 128 + signum, err
    assert f"interrupted by {signal.Signals(signum).name} during the fit's search; no fit file was written" in err
    assert "Traceback" not in err and "leaked" not in err and "KeyboardInterrupt" not in err, err[-2000:]
    assert not (tmp_path / "out" / "bank.json").exists() and not (tmp_path / "out" / "cache").exists()
    deadline = time.monotonic() + 15.0                      # the group empties: no worker left behind (init
    while time.monotonic() < deadline:                       # reaps an ended one within a few seconds)
        try:
            os.killpg(fit.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.2)
    else:
        pytest.fail("a process of the fit's group is still there 15 s after it ended")


# -- scored as the model will be trained: gain augmentation (issue 34) --------------------------------------

def test_every_folds_network_and_the_papers_banks_train_with_the_gain_augmentation_asked(manifest, monkeypatch):
    """`fit --augment-gains`: each fold's network, the paper's banks' too, trains on the copies (gains by the trial's
    bank where left to it); gains of 1 (exact copies, which iRPROP- does not see) score as no augmentation."""
    from supramodal.model import GainAugment, TextureModel
    from supramodal.node.workflows import fit_search as search

    asked = []
    train = TextureModel.train

    def spy(*args, augment=None, **kwargs):
        asked.append(augment)
        return train(*args, augment=augment, **kwargs)

    monkeypatch.setattr(search.TextureModel, "train", spy)
    fast = {**FAST, "trials": 2, "batch": 2}
    plain = fit_search(manifest, seed=1, **fast)
    assert set(asked) == {None} and plain.get("augment") is None
    asked.clear()
    ones = fit_search(manifest, seed=1, augment=GainAugment(1, 0.0, None, 1), **fast)
    assert asked and set(asked) == {GainAugment(1, 0.0, None, 1)}
    assert ones["augment"] == {"copies": 1, "spread": 0.0, "per_channel": None, "seed": 1}
    assert _untimed(ones["rows"]) == _untimed(plain["rows"]) and _untimed(ones["paper"]) == _untimed(plain["paper"])
    assert "trained with gain augmentation: 1 more copies of each window, gains exp(N(0, 0)) by bank" in \
        format_search(ones)
    assert "gain augmentation" not in format_search(plain)


def test_fit_command_with_gain_augmentation_says_so_and_its_next_command_trains_alike(manifest, tmp_path, capsys):
    out = tmp_path / "fit"
    assert main(["fit", str(manifest), "--out", str(out), "--cv", "3", "--quick", "--trials", "2", "--batch", "2",
                 "--epochs", "8", "--max-window", "0.1", "--augment-gains", "2,0.05,shared", "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "trained with gain augmentation: 2 more copies of each window, gains exp(N(0, 0.05)) shared" in said
    assert "--augment-gains 2,0.05,shared --out MODEL" in said
    with pytest.raises(SystemExit) as exit_:
        main(["fit", str(manifest), "--out", str(out), "--augment-gains", "0", "--force"])
    assert exit_.value.code == 2
    assert "COPIES a whole number from 1" in capsys.readouterr().err
