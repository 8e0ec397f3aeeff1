"""Three-peak textures: determinism, spectrum, random sets, texture-set files."""

import dataclasses
import json

import numpy as np
import pytest
from scipy.signal import welch

from supramodal.textures import (
    FLOOR_RMS,
    PEAK_RANGES,
    Texture,
    TextureSet,
    gain_db,
    load_texture_set,
    random_texture_set,
    reference_texture_set,
    synthesize,
    texture_set_from_dict,
)

PEAKS = (100.0, 250.0, 600.0)


def test_synthesis_is_deterministic_for_a_seed():
    a = synthesize(PEAKS, 5000.0, 2.0, seed=11)
    b = synthesize(PEAKS, 5000.0, 2.0, seed=11)
    c = synthesize(PEAKS, 5000.0, 2.0, seed=12)
    assert a.shape == (10000,) and a.dtype == np.float64
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_texture_set_synthesis_is_deterministic_per_texture():
    ts = dataclasses.replace(reference_texture_set("whisker"), duration=1.0)
    np.testing.assert_array_equal(ts.synthesize(3), ts.synthesize(3))
    assert not np.allclose(ts.synthesize(3), ts.synthesize(4))
    np.testing.assert_array_equal(ts.synthesize(2, duration=0.5), synthesize(
        ts.textures[2].peaks, 5000.0, 0.5, width=0.2, seed=np.random.SeedSequence([ts.seed, 2])))
    assert ts.synthesize(0).shape == (5000,)
    other_seed = dataclasses.replace(ts, seed=ts.seed + 1)
    assert not np.allclose(ts.synthesize(0), other_seed.synthesize(0))


def test_gain_curve_values():
    g = gain_db(np.array([100.0, 250.0, 600.0, 1500.0, 2400.0, 0.0]), PEAKS)
    np.testing.assert_allclose(g, [6.0, 3.0, 3.0, -3.0, -3.0, -3.0], atol=1e-12)
    # half height (in dB above the floor) at f_k (1 +- width/2): the full width at half height is 0.2 f_k
    half = gain_db(np.array([90.0, 110.0, 540.0, 660.0]), PEAKS)
    np.testing.assert_allclose(half, [-3 + 4.5, -3 + 4.5, -3 + 3.0, -3 + 3.0], atol=1e-12)


def test_welch_spectrum_shows_the_three_peaks_over_the_floor():
    """40 s at 5 kHz, Welch with 8192-sample Hann segments (0.61 Hz bins, ~47 segments).

    The level of each peak over the floor is estimated from the mean PSD over f_k +- 5 % (17..97 bins),
    corrected by the designed bump's known loss over that band (0.5 dB); the floor from 1500..2400 Hz.
    Over 40 noise seeds these estimates scatter with sd 0.25 / 0.13 / 0.10 dB (max |dev| 0.72 / 0.32 /
    0.21); the tolerances are 4 sd: 1.0 dB for the narrow lowest peak, 0.5 dB for the other two.
    The floor's absolute level (RMS 0.1, i.e. PSD 0.01 / (fs/2)) is estimated from ~1500 bins: 3 %.
    """
    fs = 5000.0
    x = synthesize(PEAKS, fs, 40.0, seed=2010)
    f, psd = welch(x, fs, nperseg=8192)
    floor = psd[(f > 1500) & (f < 2400)].mean()
    assert floor * fs / 2 == pytest.approx(FLOOR_RMS**2, rel=0.03)

    def design_db(freq, fk, gain):           # written out: Gaussian bump in dB, FWHM 0.2 fk, floor -3 dB
        sigma = 0.2 * fk / (2 * np.sqrt(2 * np.log(2)))
        return -3.0 + (gain + 3.0) * np.exp(-0.5 * ((freq - fk) / sigma) ** 2)

    heights = []
    for fk, gain in zip(PEAKS, (6.0, 3.0, 3.0)):
        band = np.abs(f - fk) <= 0.05 * fk
        measured = 10 * np.log10(psd[band].mean() / floor)
        loss = (gain + 3.0) - 10 * np.log10(np.mean(10 ** ((design_db(f[band], fk, gain) + 3.0) / 10)))
        heights.append(measured + loss)
    assert heights[0] == pytest.approx(9.0, abs=1.0)
    assert heights[1] == pytest.approx(6.0, abs=0.5)
    assert heights[2] == pytest.approx(6.0, abs=0.5)
    # and nothing else sticks out: between the peaks the spectrum is back on the floor
    between = (f > 800) & (f < 1400)
    assert 10 * np.log10(psd[between].mean() / floor) == pytest.approx(0.0, abs=0.2)


def test_synthesize_refusals():
    with pytest.raises(ValueError, match="exactly 3"):
        synthesize((100.0, 200.0), 5000.0, 1.0)
    with pytest.raises(ValueError, match="ascending"):
        synthesize((300.0, 200.0, 400.0), 5000.0, 1.0)
    with pytest.raises(ValueError, match="ascending"):
        synthesize((200.0, 200.0, 400.0), 5000.0, 1.0)
    with pytest.raises(ValueError, match=r"\(0, fs/2\)"):
        synthesize((100.0, 200.0, 2500.0), 5000.0, 1.0)
    with pytest.raises(ValueError, match=r"\(0, fs/2\)"):
        synthesize((float("nan"), 200.0, 300.0), 5000.0, 1.0)
    with pytest.raises(ValueError, match="no sample"):
        synthesize(PEAKS, 5000.0, 0.0)


# -- random sets -------------------------------------------------------------------------------

@pytest.mark.parametrize("bank, seeds, min_ratio", [
    ("whisker", range(2000), 1.2),
    ("cochlea", range(300), 1.2),
    ("whisker", range(300), 1.5),
])
def test_random_texture_sets_respect_range_and_min_ratio(bank, seeds, min_ratio):
    lo, hi = PEAK_RANGES[bank]
    for seed in seeds:
        ts = random_texture_set(bank, 8, seed=seed, min_ratio=min_ratio)
        assert len(ts.textures) == 8 and len(set(ts.names)) == 8
        for t in ts.textures:
            p = np.array(t.peaks)
            assert np.all((p >= lo) & (p <= hi)), (seed, t)
            assert np.all(p[1:] / p[:-1] >= min_ratio), (seed, t, p[1:] / p[:-1])


def test_random_texture_set_is_deterministic_and_well_formed():
    a = random_texture_set("whisker", 5, seed=4, duration=12.0)
    assert a == random_texture_set("whisker", 5, seed=4, duration=12.0)
    assert a != random_texture_set("whisker", 5, seed=5, duration=12.0)
    assert a.fs == 5000.0 and a.duration == 12.0 and a.bank == "whisker" and a.seed == 4
    assert random_texture_set("cochlea", 2, seed=0).fs == 44100.0
    again = texture_set_from_dict(json.loads(json.dumps(a.to_dict())))
    assert again == a
    with pytest.raises(ValueError, match="unknown bank"):
        random_texture_set("nose")


# -- shipped reference sets and files ----------------------------------------------------------

@pytest.mark.parametrize("bank, fs", [("whisker", 5000.0), ("cochlea", 44100.0)])
def test_reference_sets_load(bank, fs):
    ts = reference_texture_set(bank)
    assert ts.bank == bank and ts.fs == fs and ts.duration == 40.0
    assert len(ts.textures) == 8 and len(set(ts.names)) == 8
    lo, hi = PEAK_RANGES[bank]
    for t in ts.textures:
        assert len(t.peaks) == 3 and list(t.peaks) == sorted(t.peaks)
        assert all(lo <= p <= hi for p in t.peaks)
    assert len({t.peaks for t in ts.textures}) == 8


def test_reference_set_refuses_unknown_bank():
    with pytest.raises(ValueError, match="unknown bank"):
        reference_texture_set("ear")


def test_texture_set_file_round_trip(tmp_path):
    ts = reference_texture_set("whisker")
    ts.save(tmp_path / "set.json")
    assert load_texture_set(tmp_path / "set.json") == ts


def good_dict():
    return {"format": "supramodal-textures", "version": 1, "name": "t", "bank": "whisker", "fs": 5000,
            "duration": 1.0, "width": 0.2, "seed": 3,
            "textures": [{"name": "a", "peaks": [100, 200, 300]}, {"name": "b", "peaks": [110, 220, 330]}]}


@pytest.mark.parametrize("change, match", [
    ({"format": "wav"}, "'format' must be 'supramodal-textures'"),
    ({"version": 2}, "'version' 2 is not supported"),
    ({"colour": "red"}, r"unknown key\(s\) \['colour'\]"),
    ({"bank": "ear"}, "'bank' must be"),
    ({"fs": 0}, "'fs' must be a positive number"),
    ({"fs": "5000"}, "'fs' must be a positive number"),
    ({"duration": -1.0}, "'duration' must be a positive number"),
    ({"width": True}, "'width' must be a positive number"),
    ({"seed": -1}, "'seed' must be a non-negative integer"),
    ({"seed": 1.5}, "'seed' must be a non-negative integer"),
    ({"textures": [{"name": "a", "peaks": [100, 200, 300]}]}, "at least 2 textures"),
    ({"textures": "abc"}, "at least 2 textures"),
    ({"textures": [{"name": "a", "peaks": [300, 200, 400]}, {"name": "b", "peaks": [1, 2, 3]}]},
     r"texture 'a'.*ascending"),
    ({"textures": [{"name": "a", "peaks": [100, 200, 2600]}, {"name": "b", "peaks": [1, 2, 3]}]},
     r"texture 'a'.*\(0, fs/2\)"),
    ({"textures": [{"name": "a", "peaks": [-100, 200, 300]}, {"name": "b", "peaks": [1, 2, 3]}]},
     r"texture 'a'.*\(0, fs/2\)"),
    ({"textures": [{"name": "a", "peaks": [100, 200]}, {"name": "b", "peaks": [1, 2, 3]}]}, "exactly 3"),
    ({"textures": [{"name": "a", "peaks": [100, "x", 300]}, {"name": "b", "peaks": [1, 2, 3]}]},
     "list of 3 numbers"),
    ({"textures": [{"name": "a", "peaks": [1, 2, 3], "gain": 6}, {"name": "b", "peaks": [1, 2, 3]}]},
     "exactly 'name'"),
    ({"textures": [{"name": "a", "peaks": [1, 2, 3]}, {"name": "a", "peaks": [4, 5, 6]}]}, "distinct"),
])
def test_bad_texture_sets_are_refused(change, match):
    d = good_dict()
    d.update(change)
    with pytest.raises(ValueError, match=match):
        texture_set_from_dict(d)


def test_good_dict_is_accepted():
    ts = texture_set_from_dict(good_dict())
    assert isinstance(ts, TextureSet) and ts.textures[1] == Texture("b", (110.0, 220.0, 330.0))


def test_bad_texture_files(tmp_path):
    with pytest.raises(ValueError, match="no texture-set file"):
        load_texture_set(tmp_path / "missing.json")
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_texture_set(p)
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_texture_set(p)
    p.write_text("[1, 2, 3]")
    with pytest.raises(ValueError, match="JSON object"):
        load_texture_set(p)
    d = good_dict()
    d["version"] = 7
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=f"{p.name}.*'version' 7"):
        load_texture_set(p)


@pytest.mark.parametrize("name", ["fingertip_textures.json", "fingertip_heldout_textures.json"])
def test_the_own_sensor_guides_texture_sets_load_and_differ_only_in_seed(name):
    """docs/own-sensor.md synthesises its worked example from these files."""
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / "examples"
    ts, ref = load_texture_set(folder / name), load_texture_set(folder / "fingertip_textures.json")
    assert ts.fs == 2200.0 and len(ts.names) == 5
    assert max(max(t.peaks) for t in ts.textures) < 1000.0             # content below 1 kHz
    assert [t.peaks for t in ts.textures] == [t.peaks for t in ref.textures]
    assert (ts.seed == ref.seed) == (name == "fingertip_textures.json")
