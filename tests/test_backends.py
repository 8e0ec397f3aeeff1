"""Filterbank backends behind one interface, and the pipeline's gathering of blocks.

Error figure: max |y - y_ref| / max |y_ref| per channel, over the compared span.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supramodal.backends import BACKENDS, ReferenceFilterbank, make_filterbank
from supramodal.banks import Bank, cochlea_bank, whisker_bank
from supramodal.features import concat_windows
from supramodal.gammatone import GammatoneFilterbank, auto_subblock, reference_impulse_response, relative_error
from supramodal.peaks import PeakExtractor
from supramodal.pipeline import FeaturePipeline

BANKS = {"cochlea": cochlea_bank(), "whisker": whisker_bank(), "whisker-B5": whisker_bank(mean_B=5.0)}
SMALL = Bank("custom", 5000.0, [30.0, 630.0, 2200.0], [0.9, 33.6, 400.0], ("narrow-low", "A4", "wide-high"))


def feed(fb, x, sizes):
    out, i = [], 0
    for s in sizes:
        out.append(fb.process(x[..., i : i + s]))
        i += s
    out.append(fb.process(x[..., i:]))
    return np.concatenate(out, axis=1)


@pytest.mark.parametrize("name", list(BANKS))
def test_reference_backend_is_the_sampled_gammatone(name):
    bank = BANKS[name]
    n = 8192 if bank.fs > 10000 else 20000
    y = make_filterbank(bank, "reference").impulse_response(n)
    # measured: 4e-14 (cochlea), 8e-15 (whisker), 2.5e-13 (whisker at mean B = 5 Hz)
    assert relative_error(y, reference_impulse_response(bank, n), axis=-1).max() <= 1e-12


@pytest.mark.parametrize("name", list(BANKS))
def test_fast_backend_matches_the_reference_on_a_stream(name):
    bank = BANKS[name]
    x = np.random.default_rng(0).standard_normal(int(0.5 * bank.fs))
    sizes = [1, 63, 441, 7, 4410, 50, 2]
    ref = feed(make_filterbank(bank, "reference"), x, sizes)
    fast = feed(make_filterbank(bank, "fast"), x, sizes[::-1])
    assert relative_error(fast, ref, axis=-1).max() <= 1e-12
    fast32 = feed(make_filterbank(bank, "fast", dtype=np.float32), x, sizes)
    assert fast32.dtype == np.float32
    assert relative_error(fast32, ref, axis=-1).max() <= 2e-6


def test_backends_share_the_interface():
    for backend in BACKENDS:
        fb = make_filterbank(SMALL, backend, nonfinite="zero")
        x = np.ones(10)
        x[3] = np.nan
        y = fb.process(x)
        assert y.shape == (3, 10) and np.isfinite(y).all()
        assert fb.nonfinite_count == 1 and fb.samples_processed == 10
        fb.reset()
        assert fb.process(np.zeros((3, 0))).shape == (3, 0)
        assert fb.backend == backend


@pytest.mark.parametrize("kwargs, match", [
    ({"backend": "slaney"}, "unknown filterbank backend"),
    ({"backend": "reference", "dtype": np.float32}, "float64 only"),
    ({"backend": "reference", "subblock": 32}, "no options"),
])
def test_make_filterbank_refusals(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_filterbank(SMALL, **kwargs)


def test_out_argument_is_written_and_checked():
    x = np.random.default_rng(1).standard_normal(500)
    expected = GammatoneFilterbank(SMALL).process(x)
    for L in (500, 441):                                   # exact sub-block division and a remainder
        out = np.full((3, L), np.nan)
        got = GammatoneFilterbank(SMALL).process(x[:L], out=out)
        assert got is out
        np.testing.assert_allclose(out, expected[:, :L], rtol=0, atol=1e-15)
    wide = np.zeros((3, 502))                              # rows not contiguous, as the pipeline's are
    GammatoneFilterbank(SMALL).process(x, out=wide[:, 2:])
    np.testing.assert_allclose(wide[:, 2:], expected, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="out must be"):
        GammatoneFilterbank(SMALL).process(x, out=np.zeros((3, 499)))
    with pytest.raises(ValueError, match="out must be"):
        GammatoneFilterbank(SMALL).process(x, out=np.zeros((3, 500), np.float32))


def test_automatic_subblock_prefers_exact_divisions():
    assert auto_subblock(1) == 1 and auto_subblock(32) == 32
    assert auto_subblock(50) == 25 and auto_subblock(64) == 16
    assert auto_subblock(441) == 21 and auto_subblock(500) == 20 and auto_subblock(4410) == 21
    for L in (41, 97, 443, 1000, 65536):
        m = auto_subblock(L)
        assert 16 <= m <= 32
        assert L % m == 0 or m == 21            # no exact division: 21 and a pass for the rest


def test_long_and_uneven_blocks_go_in_passes():
    cochlea = GammatoneFilterbank(cochlea_bank())
    assert cochlea._layout(441) == [(21, 21)]
    assert cochlea._layout(443) == [(21, 21), (2, 1)]
    passes = cochlea._layout(4410)
    assert sum(m * K for m, K in passes) == 4410 and max(K for _, K in passes) <= 24
    # a pass never spans more than exp(200) of decay of the widest channel
    fb = GammatoneFilterbank(SMALL)
    beta = 2 * np.pi * SMALL.b.max() / SMALL.fs
    assert all(beta * m * K <= 200 for m, K in fb._layout(4410))
    x = np.random.default_rng(1).standard_normal(4410 + 443)
    y = np.concatenate([fb.process(x[:4410]), fb.process(x[4410:])], axis=1)
    assert relative_error(y, GammatoneFilterbank(SMALL, subblock=7).process(x), axis=-1).max() <= 1e-13


def test_variable_block_lengths_stop_adapting_the_subblock():
    fb = GammatoneFilterbank(SMALL)
    x = np.random.default_rng(2).standard_normal(20000)
    sizes = list(range(100, 140))
    y = feed(fb, x, sizes)
    assert len(fb._matrices) <= 16 and len(fb._plans) <= 16
    assert relative_error(y, GammatoneFilterbank(SMALL).process(x), axis=-1).max() <= 1e-13


def test_too_narrow_bandwidth_is_refused():
    bank = Bank("custom", 192000.0, [1000.0], [1e-3], ("c",))
    with pytest.raises(ValueError, match="below 1e-07 \\* fs"):
        GammatoneFilterbank(bank)
    with pytest.raises(ValueError, match="below"):
        ReferenceFilterbank(bank)


# -- peak extractor: the staging array ----------------------------------------------------------

def test_staged_blocks_give_the_same_peaks():
    y = np.random.default_rng(3).standard_normal((3, 1000))
    plain, staged = PeakExtractor(3), PeakExtractor(3)
    for a, b in ((0, 300), (300, 301), (301, 700), (700, 1000)):
        p = plain.process(y[:, a:b])
        buf = staged.staging(b - a)
        buf[...] = y[:, a:b]
        q = staged.process(buf)
        for f in ("channel", "index", "amplitude"):
            np.testing.assert_array_equal(getattr(p, f), getattr(q, f))
        assert p.decided == q.decided


# -- pipeline: gathering to window ends -------------------------------------------------------

def run_calls(pipe, x, sizes):
    """Per-call window counts and all windows (finished)."""
    counts, parts, i = [], [], 0
    for s in sizes:
        w = pipe.process(x[..., i : i + s])
        counts.append((w.first, len(w)))
        parts.append(w)
        i += s
    parts.append(pipe.finish())
    return counts, concat_windows(parts, pipe.features, pipe.bank.channels)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), sizes=st.lists(st.integers(0, 700), min_size=1, max_size=25),
       per_channel=st.booleans(), mode=st.sampled_from(["maxima", "extrema"]))
def test_gathering_changes_nothing_but_the_cost(seed, sizes, per_channel, mode):
    """Same windows, returned by the same calls, with and without gathering (50-sample windows)."""
    rng = np.random.default_rng(seed)
    n = sum(sizes)
    x = rng.standard_normal((SMALL.channels, n) if per_channel else n)
    kw = dict(window=0.01, peak_mode=mode)
    c1, w1 = run_calls(FeaturePipeline(SMALL, gather=True, **kw), x, sizes)
    c2, w2 = run_calls(FeaturePipeline(SMALL, gather=False, **kw), x, sizes)
    assert c1 == c2
    assert w1.first == w2.first and w1.values.shape == w2.values.shape
    # Rounding is relative to the signal, not to each value: a quiet channel's small features
    # (the narrow 30 Hz channel's A is ~1e-4 here) differ by ~1e-16 in absolute terms.
    scale = np.abs(w2.values).max(axis=(0, 1), initial=0.0)          # per feature, over channels
    assert np.all(np.abs(w1.values - w2.values) <= 1e-12 * np.abs(w2.values) + 1e-13 * scale)


def test_gathering_holds_samples_until_a_window_ends():
    pipe = FeaturePipeline(SMALL, window=0.01)                 # 50-sample windows
    x = np.random.default_rng(4).standard_normal(200)
    assert len(pipe.process(x[:30])) == 0
    assert pipe.peaks.samples_seen == 0 and pipe.partial_samples == 30
    w = pipe.process(x[30:120])                                # completes window 0 and 1
    assert (w.first, len(w)) == (0, 2)
    assert pipe.peaks.samples_seen == 100 and pipe.partial_samples == 20
    pipe.process(np.tile(x[120:140], (3, 1)))                  # per-channel after mono: released first
    assert pipe.partial_samples == 40
    assert len(pipe.finish()) == 0 and pipe.partial_samples == 40
    with pytest.raises(RuntimeError, match="finish"):
        pipe.process(x[:10])


def test_reference_backend_pipeline_gives_the_same_windows():
    bank = whisker_bank()
    x = np.random.default_rng(5).standard_normal(int(0.6 * bank.fs))
    fast = FeaturePipeline(bank).run(x, block=50)
    ref = FeaturePipeline(bank, backend="reference").run(x, block=50)
    np.testing.assert_allclose(fast.values, ref.values, rtol=1e-10, atol=0)


def test_nonfinite_samples_are_refused_in_the_call_that_brings_them():
    pipe = FeaturePipeline(SMALL, window=0.01)
    pipe.process(np.zeros(10))
    with pytest.raises(ValueError, match="NaN or Inf"):
        pipe.process(np.array([0.0, np.inf]))
    counted = FeaturePipeline(SMALL, window=0.01, nonfinite="zero")
    counted.process(np.array([np.nan, 1.0, -np.inf]))
    assert counted.filterbank.nonfinite_count == 2
