"""The streaming gammatone filterbank against the analytic gammatone, its unit gain at fc,
block-partition invariance and its refusals.

Error figure everywhere: max |y - y_ref| / max |y_ref|, per channel, over the compared span.

The tests' own reference is computed here, independently of the module: the sampled analytic
impulse response ``n**3 exp(-2 pi b n/fs) cos(2 pi fc n/fs)`` evaluated in extended precision
(numpy.longdouble, 64-bit mantissa on x86-64) so that its phase does not drift by n * 1e-16 rad,
normalised by its DTFT at fc summed directly (not by the module's closed form).
"""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from supramodal.banks import Bank, cochlea_bank, whisker_bank
from supramodal.gammatone import (
    GammatoneFilterbank,
    gain_at_cf,
    reference_impulse_response,
    relative_error,
)

from blocks import feed_blocks
from fastform_plain import PlainGammatone

LD = np.longdouble
TWO_PI = 2 * np.arccos(LD(-1))            # pi to long-double precision (np.pi is only a double)
EXTENDED = np.finfo(LD).eps < 1e-18       # x86-64 80-bit or quad; else the reference is only float64


def analytic_ir(cf, b, fs, n):
    """Un-normalised sampled gammatone in long double, shape (n,)."""
    k = np.arange(n, dtype=LD)
    return k**3 * np.exp(-TWO_PI * LD(b) * k / LD(fs)) * np.cos(TWO_PI * LD(cf) * k / LD(fs))


def analytic_gain(cf, b, fs):
    """|DTFT| of the sampled gammatone at fc, by direct summation over 60 time constants."""
    n = int(60 * fs / (2 * np.pi * b)) + 200
    h = analytic_ir(cf, b, fs, n)
    w = TWO_PI * LD(cf) / LD(fs) * np.arange(n, dtype=LD)
    return np.hypot(np.sum(h * np.cos(w)), np.sum(h * np.sin(w)))


def independent_reference(bank, n):
    """Reference impulse responses, shape (channels, n), float64 (rounded once at the end)."""
    return np.stack([
        (analytic_ir(cf, b, bank.fs, n) / analytic_gain(cf, b, bank.fs)).astype(np.float64)
        for cf, b in zip(bank.cf, bank.b)
    ])


BANKS = {
    # name: (bank, impulse-response span in samples: tens of time constants of the narrowest channel)
    "cochlea": (cochlea_bank(), 8192),
    "whisker": (whisker_bank(), 5000),
    "whisker-B5": (whisker_bank(mean_B=5.0), 44100),      # Fig. 5's narrowest: b ~ 0.6..1.3 Hz at 5 kHz
    "whisker-B500": (whisker_bank(mean_B=500.0), 2000),
}


@pytest.fixture(scope="module", params=list(BANKS))
def bank_case(request):
    bank, n = BANKS[request.param]
    return request.param, bank, n, independent_reference(bank, n)


# -- impulse response --------------------------------------------------------------------------

def test_module_reference_is_the_analytic_gammatone(bank_case):
    name, bank, n, ref = bank_case
    err = relative_error(reference_impulse_response(bank, n), ref, axis=-1)
    assert err.max() <= 1e-12, f"{name}: reference_impulse_response off by {err.max():.2e}"


def test_float64_impulse_response_matches_the_reference(bank_case):
    name, bank, n, ref = bank_case
    y = GammatoneFilterbank(bank).impulse_response(n)
    assert y.dtype == np.float64 and y.shape == (bank.channels, n)
    err_module = relative_error(y, reference_impulse_response(bank, n), axis=-1)
    err_indep = relative_error(y, ref, axis=-1)
    assert err_module.max() <= 1e-12, f"{name}: {err_module.max():.2e} vs reference_impulse_response"
    assert err_indep.max() <= 1e-12, f"{name}: {err_indep.max():.2e} vs the long-double analytic gammatone"


# float32: measured (x86-64, numpy 2.4) per-channel worst case 8.3e-7 (cochlea), 2.4e-7 (whisker),
# 4.3e-6 (whisker at mean B = 5 Hz, poles within 1e-3 of the unit circle), 1.6e-7 (mean B = 500).
FLOAT32_BOUND = {"cochlea": 2e-6, "whisker": 2e-6, "whisker-B5": 1e-5, "whisker-B500": 2e-6}


def test_float32_impulse_response_matches_the_reference(bank_case):
    name, bank, n, ref = bank_case
    y = GammatoneFilterbank(bank, dtype=np.float32).impulse_response(n)
    assert y.dtype == np.float32
    err = relative_error(y, ref, axis=-1)
    assert np.isfinite(y).all()
    assert err.max() <= FLOAT32_BOUND[name], f"{name}: float32 error {err.max():.2e}"


def test_gain_at_cf_matches_direct_summation(bank_case):
    name, bank, n, ref = bank_case
    direct = np.array([float(analytic_gain(cf, b, bank.fs)) for cf, b in zip(bank.cf, bank.b)])
    np.testing.assert_allclose(gain_at_cf(bank), direct, rtol=1e-12)


@pytest.mark.parametrize("name, settle, span", [
    ("cochlea", 0.3, 0.1), ("whisker", 0.5, 0.2), ("whisker-B5", 12.0, 1.0), ("whisker-B500", 0.5, 0.2),
])
def test_unit_gain_at_cf_measured_on_a_long_sine(name, settle, span):
    """Independent of any impulse response: each channel gets a unit sine at its own cf, (C, L) input;
    after the transient (tens of time constants) the least-squares amplitude of the output is 1."""
    bank = BANKS[name][0]
    n = np.arange(int(round((settle + span) * bank.fs)))
    x = np.sin(2 * np.pi * bank.cf[:, None] * n / bank.fs)
    y = GammatoneFilterbank(bank).process(x)
    tail = n[int(settle * bank.fs):]
    for c in range(bank.channels):
        w = 2 * np.pi * bank.cf[c] / bank.fs
        basis = np.stack([np.sin(w * tail), np.cos(w * tail)], axis=1)
        coef, *_ = np.linalg.lstsq(basis, y[c, tail], rcond=None)
        # measured: |amplitude - 1| <= 6e-14 (default banks), 6e-13 (mean B = 5 Hz)
        assert abs(np.hypot(*coef) - 1.0) <= 5e-12, f"{name} {bank.names[c]}: gain {np.hypot(*coef)!r}"
        # and the output is that sine: nothing else left once settled
        assert np.max(np.abs(y[c, tail] - basis @ coef)) <= 1e-9


def test_off_cf_sine_is_attenuated_like_a_gammatone():
    """A sine one b away from fc comes out at (1 + 1)**-2 = 1/4 of the gain at fc (order 4), to the
    approximation error of the analytic magnitude near fc (small for b << fc)."""
    bank = Bank("custom", 44100.0, [4000.0], [40.0], ("c",))
    n = np.arange(int(0.5 * bank.fs))
    y = GammatoneFilterbank(bank).process(np.sin(2 * np.pi * (4000.0 + 40.0) * n / bank.fs))
    amp = np.max(np.abs(y[0, int(0.3 * bank.fs):]))
    assert amp == pytest.approx(0.25, rel=2e-2)


# -- any centre frequency, narrow and wide bandwidths -----------------------------------------

@pytest.mark.skipif(not EXTENDED, reason="needs an extended-precision numpy.longdouble for the reference")
@settings(max_examples=60)
@given(
    fs=st.sampled_from([5000.0, 44100.0]),
    cf_pos=st.floats(0.0, 1.0),
    b_pos=st.floats(0.0, 1.0),
)
@example(fs=5000.0, cf_pos=0.0, b_pos=0.0)      # 20 Hz, narrowest
@example(fs=5000.0, cf_pos=1.0, b_pos=0.0)      # 0.45 fs, narrowest
@example(fs=44100.0, cf_pos=1.0, b_pos=0.0)
@example(fs=44100.0, cf_pos=0.0, b_pos=1.0)     # 20 Hz, widest: the negative-frequency image matters
@example(fs=5000.0, cf_pos=1.0, b_pos=1.0)
def test_any_cf_and_bandwidth_float64(fs, cf_pos, b_pos):
    """cf log-uniform over [20 Hz, 0.45 fs]; b log-uniform over [2e-4, 0.1] * fs, i.e. 1..500 Hz at 5 kHz
    (Fig. 5's B = 2 pi b from 6 to 3000) and 8.8..4410 Hz at 44.1 kHz. Span: 40 time constants.

    Below b = 2e-4 fs the float64 rounding of the pole itself (|p| and its angle, 1e-16 each) times the
    response length exceeds 1e-12: measured 1.4e-12 at b = 0.5 Hz, cf = 0.45 fs, 5 kHz. That is a limit
    of any float64 realisation, not of this design, and is left out of the property.
    """
    cf = float(np.exp(np.log(20.0) + cf_pos * np.log(0.45 * fs / 20.0)))
    b = float(fs * np.exp(np.log(2e-4) + b_pos * np.log(0.1 / 2e-4)))
    bank = Bank("custom", fs, [cf], [b], ("c",))
    n = int(max(40 * fs / (2 * np.pi * b), 64))
    y = GammatoneFilterbank(bank).impulse_response(n)
    ref = independent_reference(bank, n)
    assert relative_error(y, ref) <= 1e-12
    assert relative_error(reference_impulse_response(bank, n), ref) <= 1e-12
    # float32 over the same domain: measured worst 3.0e-6 on 600 random draws
    y32 = GammatoneFilterbank(bank, dtype=np.float32).impulse_response(n)
    assert relative_error(y32, ref) <= 1e-5


# -- streaming ---------------------------------------------------------------------------------

PARTITION_BANK = Bank(
    "custom", 5000.0, [30.0, 630.0, 2200.0], [0.9, 33.6, 400.0], ("narrow-low", "A4", "wide-high"))


def feed(fb, x, sizes):
    """Feed x in blocks of the given sizes (the rest in a last block); return the concatenated output."""
    y = np.concatenate(feed_blocks(fb.process, x, sizes), axis=1)
    assert y.shape == (fb.channels, x.shape[-1])
    return y


@settings(max_examples=60)
@given(
    seed=st.integers(0, 2**32 - 1),
    length=st.integers(0, 1500),
    sizes=st.lists(st.one_of(st.just(0), st.just(1), st.integers(0, 200)), max_size=30),
    per_channel=st.booleans(),
    subblock=st.sampled_from([1, 2, 5, 32, 64, 257]),
)
def test_block_partition_invariance(seed, length, sizes, per_channel, subblock):
    rng = np.random.default_rng(seed)
    shape = (PARTITION_BANK.channels, length) if per_channel else (length,)
    x = rng.standard_normal(shape)
    whole = GammatoneFilterbank(PARTITION_BANK, subblock=subblock).process(x)
    fb = GammatoneFilterbank(PARTITION_BANK, subblock=subblock)
    parts = feed(fb, x, sizes)
    assert fb.samples_processed == length
    if length:
        assert relative_error(parts, whole, axis=-1).max() <= 1e-12
    # and the sub-block length changes nothing beyond rounding either
    other = GammatoneFilterbank(PARTITION_BANK, subblock=32).process(x)
    if length:
        assert relative_error(other, whole, axis=-1).max() <= 1e-12


MIXED_BANK = Bank("custom", 5000.0, [30.0, 2000.0, 700.0], [0.9, 49500.0, 3.0], ("narrow", "widest", "mid"))


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    length=st.integers(1, 700),
    sizes=st.lists(st.integers(0, 200), max_size=12),
    plain_m=st.integers(1, 40),
    subblock=st.sampled_from([None, 1, 3, 21, 257]),
    per_channel=st.booleans(),
    mixed=st.booleans(),
)
def test_fast_form_equals_the_plain_loop(seed, length, sizes, plain_m, subblock, per_channel, mixed):
    """The same algorithm written as loops (tests/fastform_plain.py: per channel, per sub-block, no
    rescaling, no products over sub-blocks) at random block sizes, partitions and sub-block lengths,
    after a loud start (an impulse) so the state carries weight: equal to rounding."""
    bank = MIXED_BANK if mixed else PARTITION_BANK
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((bank.channels, length) if per_channel else length)
    x[..., 0] += 50.0
    plain = PlainGammatone(bank, plain_m)
    expected = np.concatenate([plain.process(x[..., i : i + 97]) for i in range(0, length, 97)], axis=1)
    y = feed(GammatoneFilterbank(bank, subblock=subblock), x, sizes)
    scale = np.max(np.abs(expected), axis=1)
    assert (np.max(np.abs(y - expected), axis=1) <= 1e-13 * scale).all()


def test_the_plain_loop_is_the_gammatone():
    """The plain loop itself against the independent long-double reference: it is what the fast form is compared to."""
    ref = independent_reference(PARTITION_BANK, 3000)
    x = np.zeros(3000)
    x[0] = 1.0
    y = PlainGammatone(PARTITION_BANK, 25).process(x)
    assert relative_error(y, ref, axis=-1).max() <= 1e-13


def test_mono_input_equals_the_same_signal_per_channel():
    x = np.random.default_rng(1).standard_normal(3000)
    mono = GammatoneFilterbank(PARTITION_BANK).process(x)
    tiled = GammatoneFilterbank(PARTITION_BANK).process(np.tile(x, (3, 1)))
    assert relative_error(mono, tiled, axis=-1).max() <= 1e-15


def test_per_channel_input_keeps_channels_apart():
    """Channel c sees only row c: an impulse in row 1 leaves rows 0 and 2 at exactly 0."""
    x = np.zeros((3, 2000))
    x[1, 10] = 1.0
    y = GammatoneFilterbank(PARTITION_BANK).process(x)
    assert not y[0].any() and not y[2].any()
    ref = reference_impulse_response(PARTITION_BANK, 1990)
    assert relative_error(y[1, 10:], ref[1]) <= 1e-12


def test_no_drift_after_a_minute_of_stream():
    """Superposition after 60 s of noise: (noise + impulse) - noise is the impulse response."""
    bank = whisker_bank()
    n0, tail = 300_000, 5000
    x = 0.1 * np.random.default_rng(2).standard_normal(n0 + tail)
    y1 = GammatoneFilterbank(bank).process(x)
    x2 = x.copy()
    x2[n0] += 1.0
    fb = GammatoneFilterbank(bank)
    y2 = np.concatenate([fb.process(x2[:n0]), fb.process(x2[n0:])], axis=1)
    err = relative_error((y2 - y1)[:, n0:], reference_impulse_response(bank, tail), axis=-1)
    assert err.max() <= 1e-11     # measured 2e-14


def test_reset_returns_to_rest_and_empty_blocks_change_nothing():
    x = np.random.default_rng(3).standard_normal(700)
    fb = GammatoneFilterbank(PARTITION_BANK)
    first = fb.process(x)
    empty = fb.process(np.zeros(0))
    assert empty.shape == (3, 0)
    fb.reset()
    np.testing.assert_array_equal(fb.process(x), first)
    assert fb.samples_processed == 1400


def test_integer_input_is_filtered_as_float():
    x = np.random.default_rng(4).integers(-1000, 1000, 500)
    a = GammatoneFilterbank(PARTITION_BANK).process(x)
    b = GammatoneFilterbank(PARTITION_BANK).process(x.astype(np.float64))
    np.testing.assert_array_equal(a, b)


# -- non-finite samples ------------------------------------------------------------------------

def test_nan_input_is_refused_by_default():
    x = np.zeros(100)
    x[37] = np.nan
    fb = GammatoneFilterbank(PARTITION_BANK)
    with pytest.raises(ValueError, match=r"1 NaN or Inf sample.*index \[37\].*nonfinite='zero'"):
        fb.process(x)
    x[37] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        fb.process(x)


def test_nonfinite_zero_replaces_and_counts():
    rng = np.random.default_rng(5)
    x = rng.standard_normal((3, 400))
    bad = [(0, 5), (1, 200), (2, 399), (2, 0)]
    dirty = x.copy()
    clean = x.copy()
    for (c, k), v in zip(bad, [np.nan, np.inf, -np.inf, np.nan]):
        dirty[c, k] = v
        clean[c, k] = 0.0
    fb = GammatoneFilterbank(PARTITION_BANK, nonfinite="zero")
    y = fb.process(dirty)
    assert fb.nonfinite_count == 4
    assert np.isfinite(y).all()
    np.testing.assert_array_equal(y, GammatoneFilterbank(PARTITION_BANK).process(clean))
    # the state is not poisoned: the next block is filtered normally
    more = rng.standard_normal((3, 100))
    ref = GammatoneFilterbank(PARTITION_BANK)
    ref.process(clean)
    np.testing.assert_array_equal(fb.process(more), ref.process(more))
    assert fb.nonfinite_count == 4


# -- refusals ----------------------------------------------------------------------------------

@pytest.mark.parametrize("x, match", [
    (np.zeros(10, dtype=complex), "real numbers.*complex"),
    (np.array(["1.0", "2.0"]), "real numbers"),
    (np.array([b"1", b"2"]), "real numbers"),
    (np.array([1.0, None], dtype=object), "real numbers"),
    (np.zeros(10, dtype=bool), "real numbers"),
    (np.zeros((3, 2, 10)), r"shape \(L,\).*\(3, L\).*got shape \(3, 2, 10\)"),
    (np.zeros((2, 10)), r"got shape \(2, 10\)"),
    (np.zeros((10, 3)), r"got shape \(10, 3\)"),
    (np.float64(1.0), r"got shape \(\)"),
])
def test_bad_input_blocks_are_refused(x, match):
    fb = GammatoneFilterbank(PARTITION_BANK)
    with pytest.raises(ValueError, match=match):
        fb.process(x)
    assert fb.samples_processed == 0


@pytest.mark.parametrize("kwargs, match", [
    ({"dtype": np.float16}, "float64 or float32"),
    ({"dtype": np.int32}, "float64 or float32"),
    ({"dtype": np.complex128}, "float64 or float32"),
    ({"subblock": 0}, "subblock"),
    ({"subblock": 5000}, "subblock"),
    ({"subblock": 2.5}, "subblock"),
    ({"nonfinite": "ignore"}, "nonfinite"),
])
def test_bad_filterbank_parameters_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GammatoneFilterbank(PARTITION_BANK, **kwargs)


def test_relative_error_is_the_projects_figure():
    assert relative_error([1.0, 2.0, 3.5], [1.0, 2.0, 4.0]) == pytest.approx(0.125)
    assert relative_error([0.0, 0.0], [0.0, 0.0]) == 0.0
    # one figure per channel (the samples' axis), a zero reference giving the absolute error
    per_channel = relative_error([[1.0, 2.0], [0.0, 3.0], [1.0, np.nan]], [[1.0, 4.0], [0.0, 0.0], [1.0, 1.0]], axis=-1)
    assert per_channel[:2].tolist() == [0.5, 3.0] and np.isnan(per_channel[2])
    # per feature over windows and channels; a floor on the divisor
    values = np.ones((2, 3, 4))
    assert relative_error(values * np.array([1.0, 1.5, 1.0])[None, :, None], values, axis=(0, 2)).tolist() == [0.0, 0.5, 0.0]
    assert relative_error([0.25, 0.0], [0.0, 0.5], floor=1.0) == 0.5
