"""Banks as data: Slaney's ERB spacing for the cochlea, the reconstructed whisker table, refusals."""

import math

import numpy as np
import pytest

from supramodal.banks import (
    WHISKER_TABLE,
    Bank,
    bank_by_name,
    cochlea_bank,
    erb_space,
    half_power_width,
    slaney_bandwidth,
    whisker_bank,
)


# -- cochlea -----------------------------------------------------------------------------------

def slaney_erbspace(f_low, f_high, n, q_ear=9.26449, b_min=24.7):
    """Slaney's ERBSpace written out term by term, in plain Python floats (independent of the module)."""
    c = q_ear * b_min
    return [
        -c + math.exp(k / n * (math.log(f_low + c) - math.log(f_high + c))) * (f_high + c)
        for k in range(1, n + 1)
    ]


def test_erb_space_is_slaneys_formula_descending_with_f_high_excluded():
    cf = erb_space(20.0, 20000.0, 50)
    ref = slaney_erbspace(20.0, 20000.0, 50)
    assert cf.shape == (50,)
    np.testing.assert_allclose(cf, ref, rtol=1e-13, atol=0)
    assert np.all(np.diff(cf) < 0), "ERBSpace is descending"
    assert cf[0] < 20000.0, "f_high itself is excluded"
    assert cf[-1] == pytest.approx(20.0, rel=1e-12), "k = N lands on f_low"
    # Equal steps on the ERB-rate scale ln(f + c): that is what 'ERB spacing' means.
    c = 9.26449 * 24.7
    steps = np.diff(np.log(cf + c))
    np.testing.assert_allclose(steps, steps[0], rtol=1e-9)


def test_erb_space_other_parameters_follow_the_formula():
    cf = erb_space(100.0, 8000.0, 7, q_ear=35.0, b_min=15.0)
    np.testing.assert_allclose(cf, slaney_erbspace(100.0, 8000.0, 7, 35.0, 15.0), rtol=1e-13)


@pytest.mark.parametrize("args, match", [
    ((20.0, 20000.0, 0), "number of channels"),
    ((0.0, 20000.0, 50), "f_low"),
    ((500.0, 100.0, 50), "f_low"),
])
def test_erb_space_refuses_bad_arguments(args, match):
    with pytest.raises(ValueError, match=match):
        erb_space(*args)


def test_cochlea_bank_is_the_papers_50_channels_with_glasberg_moore_b():
    bank = cochlea_bank()
    assert bank.kind == "cochlea"
    assert bank.fs == 44100.0
    assert bank.channels == 50
    np.testing.assert_allclose(bank.cf, sorted(slaney_erbspace(20.0, 20000.0, 50)), rtol=1e-13)
    assert np.all(np.diff(bank.cf) > 0), "channels ascend, ch00 lowest"
    expected_b = [1.019 * (f / 9.26449 + 24.7) for f in bank.cf]
    np.testing.assert_allclose(bank.b, expected_b, rtol=1e-14)
    assert bank.names[0] == "ch00" and bank.names[-1] == "ch49"
    assert len(set(bank.names)) == 50


def test_cochlea_bank_custom_size_and_rate():
    bank = cochlea_bank(n=20, f_low=50.0, f_high=8000.0, fs=16000.0)
    assert bank.channels == 20 and bank.fs == 16000.0
    np.testing.assert_allclose(bank.cf, sorted(slaney_erbspace(50.0, 8000.0, 20)), rtol=1e-13)


# -- whiskers ----------------------------------------------------------------------------------

def slaney_B(cf, q_ear=35.0, b_min=15.0):
    return 2 * math.pi * 1.019 * (cf / q_ear + b_min)


def test_whisker_table_meets_every_figure_the_paper_states():
    bank = whisker_bank()
    assert bank.kind == "whisker" and bank.fs == 5000.0
    assert bank.channels == 20
    assert bank.names == tuple(f"{r}{a}" for r in "ABCDE" for a in range(1, 5))
    cf = dict(zip(bank.names, bank.cf))
    assert cf["A4"] == 630.0
    assert bank.cf.min() == 82.0 and bank.cf.max() == 749.0
    # The paper's figures are integers: the notes' reconstruction meets them to the unit.
    assert round(slaney_B(82.0)) == 111
    assert round(slaney_B(749.0)) == 233
    assert round(float(np.mean(bank.cf))) == 270
    B = slaney_bandwidth(bank.b)
    assert round(float(B.min())) == 111 and round(float(B.max())) == 233
    assert round(float(B.mean())) == 145
    # b = 1.019 * (cf / 35 + 15), per channel, written out here.
    np.testing.assert_allclose(bank.b, [1.019 * (f / 35.0 + 15.0) for f in bank.cf], rtol=1e-14)


def test_whisker_table_is_the_notes_reconstruction():
    notes = {
        "A": (105, 158, 340, 630),
        "B": (85, 146, 251, 749),
        "C": (82, 136, 240, 560),
        "D": (86, 130, 222, 420),
        "E": (99, 147, 255, 560),
    }
    assert {r: tuple(int(v) for v in vals) for r, vals in WHISKER_TABLE.items()} == notes


def test_whisker_rows_are_subsets_in_the_order_given():
    bank = whisker_bank(rows="CA")
    assert bank.channels == 8
    assert bank.names == ("C1", "C2", "C3", "C4", "A1", "A2", "A3", "A4")
    np.testing.assert_array_equal(bank.cf, [82, 136, 240, 560, 105, 158, 340, 630])
    full = whisker_bank()
    for name, cf, b in zip(bank.names, bank.cf, bank.b):
        k = full.names.index(name)
        assert cf == full.cf[k] and b == full.b[k]
    assert whisker_bank(rows=["E"]).names == ("E1", "E2", "E3", "E4")


@pytest.mark.parametrize("target", [5.0, 145.0, 200.0, 500.0])
def test_whisker_mean_B_scaling_hits_the_target(target):
    base = whisker_bank()
    bank = whisker_bank(mean_B=target)
    assert float(np.mean(slaney_bandwidth(bank.b))) == pytest.approx(target, rel=1e-14)
    ratio = bank.b / base.b
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-14)     # one factor for every channel
    np.testing.assert_array_equal(bank.cf, base.cf)


def test_whisker_mean_B_on_a_subset_scales_that_subset():
    bank = whisker_bank(rows="AB", mean_B=200.0)
    assert float(np.mean(slaney_bandwidth(bank.b))) == pytest.approx(200.0, rel=1e-14)


@pytest.mark.parametrize("kwargs, match", [
    ({"rows": ""}, "at least one whisker row"),
    ({"rows": "AF"}, r"unknown whisker row.*F"),
    ({"rows": ["A", "a"]}, "unknown whisker row"),
    ({"rows": "AA"}, "repeat"),
    ({"mean_B": 0.0}, "mean_B"),
    ({"mean_B": -5.0}, "mean_B"),
    ({"mean_B": float("nan")}, "mean_B"),
])
def test_whisker_bank_refuses_bad_rows_and_bandwidths(kwargs, match):
    with pytest.raises(ValueError, match=match):
        whisker_bank(**kwargs)


def test_bank_by_name():
    assert bank_by_name("whisker").matches(whisker_bank())
    assert bank_by_name("cochlea", n=10).matches(cochlea_bank(n=10))
    with pytest.raises(ValueError, match="unknown bank 'ear'"):
        bank_by_name("ear")


# -- Bank itself -------------------------------------------------------------------------------

def test_half_power_width_is_the_minus_3_db_point_of_the_order_4_magnitude():
    b = 30.0
    w = float(half_power_width(b))
    # |H| near fc ~ (1 + (df/b)^2)^(-2): at df = w/2 the power is exactly one half.
    assert (1 + (w / 2 / b) ** 2) ** -4 == pytest.approx(0.5, rel=1e-12)
    assert w == pytest.approx(0.87 * b, rel=2e-3)


def test_bank_round_trips_through_its_dict():
    bank = whisker_bank(rows="BD", mean_B=77.0)
    again = Bank.from_dict(bank.to_dict())
    assert again.matches(bank)
    np.testing.assert_array_equal(again.b, bank.b)      # floats survive exactly


def test_bank_arrays_are_read_only():
    bank = whisker_bank()
    with pytest.raises(ValueError):
        bank.cf[0] = 1.0


def test_bank_matches_detects_differences():
    a = whisker_bank()
    assert not a.matches(whisker_bank(mean_B=100.0))
    assert not a.matches(whisker_bank(fs=8000.0))
    assert not a.matches(whisker_bank(rows="ABCD"))
    assert not a.matches(cochlea_bank(n=20))


@pytest.mark.parametrize("kwargs, match", [
    ({"cf": [2500.0], "b": [10.0]}, r"outside \(0, fs/2\)"),       # cf == fs/2
    ({"cf": [3000.0], "b": [10.0]}, r"outside \(0, fs/2\)"),
    ({"cf": [0.0], "b": [10.0]}, r"outside \(0, fs/2\)"),
    ({"cf": [-5.0], "b": [10.0]}, r"outside \(0, fs/2\)"),
    ({"cf": [100.0], "b": [0.0]}, "must be > 0"),
    ({"cf": [100.0], "b": [-1.0]}, "must be > 0"),
    ({"fs": 0.0}, "sample rate fs must be a positive"),
    ({"fs": -5000.0}, "sample rate fs must be a positive"),
    ({"fs": float("inf")}, "sample rate fs must be a positive"),
    ({"cf": [], "b": [], "names": ()}, "at least one channel"),
    ({"cf": [100.0, 200.0], "b": [10.0]}, "one entry per channel"),
    ({"cf": [float("nan")], "b": [10.0]}, "finite"),
    ({"cf": [100.0], "b": [float("inf")]}, "finite"),
    ({"cf": [100.0, 200.0], "b": [10.0, 10.0], "names": ("x", "x")}, "unique"),
])
def test_bank_refuses_bad_parameters(kwargs, match):
    args = {"kind": "custom", "fs": 5000.0, "cf": [100.0], "b": [10.0]}
    args.update(kwargs)
    args.setdefault("names", tuple(f"c{k}" for k in range(len(args["cf"]))))
    with pytest.raises(ValueError, match=match):
        Bank(**args)


def test_bank_error_names_the_channel():
    with pytest.raises(ValueError, match="channel hi"):
        Bank("custom", 5000.0, [100.0, 2600.0], [10.0, 10.0], ("lo", "hi"))


def test_bank_from_dict_refuses_malformed_descriptions():
    with pytest.raises(ValueError, match="malformed bank description"):
        Bank.from_dict({"kind": "x", "fs": 5000.0})
    with pytest.raises(ValueError):
        Bank.from_dict("whisker")
