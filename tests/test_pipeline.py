"""The whole pipeline: features of a pure sine, silence, block-partition invariance, refusals."""

import math
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import supramodal.pipeline
from supramodal.banks import Bank, bank_by_name, whisker_bank
from supramodal.features import FEATURES, concat_windows
from supramodal.gammatone import GammatoneFilterbank, relative_error
from supramodal.pipeline import FeaturePipeline, extract_features, window_length

from blocks import feed_blocks


#: The documented floor a peak must exceed (supramodal.peaks.PEAK_FLOOR), written out here.
FLOOR = 1e-250


def plain_features(y, fs, length):
    """The paper's definitions for one channel, written as a plain loop (independent of the module):
    positive local maxima (x[n-1] < x[n] >= x[n+1], x[n] > FLOOR, rest before the stream), then per
    window the sums of A_k, f_k = fs / (n_k - n_(k-1)) and A_k f_k. Returns (counts, A, f, Af)."""
    n_win = len(y) // length
    count, A, f, Af = (np.zeros(n_win) for _ in range(4))
    prev = None
    for n in range(len(y) - 1):
        left = y[n - 1] if n > 0 else 0.0
        if left < y[n] >= y[n + 1] and y[n] > FLOOR:
            w = n // length
            if w < n_win:
                count[w] += 1
                A[w] += y[n]
                if prev is not None:
                    f[w] += fs / (n - prev)
                    Af[w] += y[n] * (fs / (n - prev))
            prev = n
    return count, A, f, Af


# -- a pure sine at A4's resonance --------------------------------------------------------------

@pytest.fixture(scope="module")
def sine_case():
    bank = whisker_bank()
    fs, f_sine, amp = bank.fs, 630.0, 0.5
    x = amp * np.sin(2 * np.pi * f_sine * np.arange(int(1.0 * fs)) / fs)     # 1 s: 10 windows
    w = FeaturePipeline(bank).run(x)
    c = bank.names.index("A4")
    y = GammatoneFilterbank(bank).process(x)[c]
    return bank, f_sine, amp, w, c, y


def test_sine_pipeline_equals_the_plain_definitions(sine_case):
    bank, f_sine, amp, w, c, y = sine_case
    assert len(w) == 10
    count, A, f, Af = plain_features(y, bank.fs, 500)
    for name, ref in (("A", A), ("f", f), ("Af", Af)):
        np.testing.assert_allclose(w.feature(name)[:, c], ref, rtol=1e-13, atol=0)


def test_sine_at_A4_gives_the_expected_counts_and_values(sine_case):
    """Windows 5..9 (after 0.5 s, > 100 time constants of A4: the output is the unit-gain sine).

    Period P = fs / f_sine = 7.94 samples, a = floor(P). Each peak is the sample nearest a true
    maximum (|offset| <= 0.5), so: intervals are a or a + 1; amplitudes lie in [amp cos(pi/P), amp];
    with D = sum of the count intervals in [count P - 1, count P + 1], the f sum is exactly
    fs (count (2a+1) - D) / (a (a+1)), i.e. f / count = f_sine + fs a'(1-a') / (a (a+1) P) +- fs / (count a (a+1))
    with a' = P - a (the first term is the harmonic-mean bias of the sample grid, 0.66 Hz here).
    """
    bank, f_sine, amp, w, c, y = sine_case
    fs = bank.fs
    P = fs / f_sine
    a = math.floor(P)
    frac = P - a
    count = plain_features(y, fs, 500)[0]
    for k in range(5, 10):
        n = count[k]
        assert abs(n - f_sine * 0.1) <= 1, f"window {k}: {n} peaks"
        A, f, Af = (w.feature(name)[k, c] for name in ("A", "f", "Af"))
        assert amp * math.cos(math.pi / P) * n * (1 - 1e-9) <= A <= amp * n * (1 + 1e-9)
        bias = fs * frac * (1 - frac) / (a * (a + 1) * P)
        assert abs(f / n - f_sine - bias) <= fs / (n * a * (a + 1)) + 1e-9, f"window {k}: f/count = {f / n}"
        assert abs(f / n - f_sine) <= 2.5                         # the same, as a number: within 0.4 %
        assert A * fs / (a + 1) <= Af <= A * fs / a                # each A_k f_k with f_k = fs/a or fs/(a+1)
        assert Af == pytest.approx(A * f_sine, rel=0.02)


def test_sine_resonance_shows_in_A_far_more_than_in_f(sine_case):
    """Fig. 4's point: A of the resonant channel dwarfs a distant channel's; f hardly differs, since
    off resonance the channel still follows the sine (measured: A ratio 7e5, f ratio 1.000)."""
    bank, f_sine, amp, w, c, y = sine_case
    far = bank.names.index("C1")                                   # cf 82 Hz
    A, f = w.feature("A")[5:], w.feature("f")[5:]
    assert A[:, c].mean() > 1000 * A[:, far].mean()
    assert f[:, c].mean() == pytest.approx(f[:, far].mean(), rel=0.05)


def test_extrema_mode_counts_minima_too(sine_case):
    bank, f_sine, amp, w, c, y = sine_case
    x = amp * np.sin(2 * np.pi * f_sine * np.arange(int(1.0 * bank.fs)) / bank.fs)
    we = FeaturePipeline(bank, features=("A",), peak_mode="extrema").run(x)
    ratio = we.feature("A")[5:, c] / w.feature("A")[5:, c]
    np.testing.assert_allclose(ratio, 2.0, rtol=0.05)


def test_silence_gives_exactly_zero_windows():
    w = FeaturePipeline(whisker_bank()).run(np.zeros(2000))
    assert len(w) == 4
    assert not np.isnan(w.values).any()
    np.testing.assert_array_equal(w.values, 0.0)


def test_a_silent_window_between_sounds_is_zero_and_the_next_f_reaches_back():
    """A burst, 0.8 s of silence, a second burst. The filter rings down through ever smaller peaks,
    which count (the model has no threshold) down to the floor of 1e-250; the windows after that are
    exactly 0, and the first peak of the second burst takes its f from the last ring-down peak above
    the floor, several windows back."""
    bank = Bank("custom", 5000.0, [630.0], [300.0], ("c",))        # wide: rings down fast
    n = np.arange(500)
    burst = np.sin(2 * np.pi * 630.0 * n / 5000.0)
    x = np.concatenate([burst, np.zeros(4000), burst])
    w = FeaturePipeline(bank, window=0.1).run(x)
    y = GammatoneFilterbank(bank).process(x)[0]
    assert not y[3000:4500].any(), "the ring-down reaches exact zero before window 6"
    count, A, f, Af = plain_features(y, 5000.0, 500)
    assert len(w) == 10 and count[9] > 0 and count[6:9].sum() == 0
    np.testing.assert_array_equal(w.values[6:9], 0.0)
    last_ring = max(k for k in range(1, 3000) if y[k - 1] < y[k] >= y[k + 1] and y[k] > FLOOR)
    first_new = min(k for k in range(4500, 4999) if y[k - 1] < y[k] >= y[k + 1] and y[k] > 0)
    assert f[9] < (count[9] - 1) * 5000.0 / 7 + 5000.0 / (first_new - last_ring) + 1e-9
    np.testing.assert_allclose(w.feature("f")[:, 0], f, rtol=1e-13, atol=0)
    np.testing.assert_allclose(w.feature("Af")[:, 0], Af, rtol=1e-13, atol=0)


# -- block partitions ---------------------------------------------------------------------------

SMALL = Bank("custom", 5000.0, [40.0, 630.0, 1800.0], [2.0, 33.6, 300.0], ("lo", "A4", "hi"))


def feed(pipe, x, sizes):
    """Feed x in blocks of the given sizes, then finish; return every call's windows."""
    return feed_blocks(pipe.process, x, sizes) + [pipe.finish()]


@settings(max_examples=50)
@given(
    seed=st.integers(0, 2**32 - 1),
    length=st.integers(0, 2500),
    sizes=st.lists(st.one_of(st.just(0), st.just(1), st.integers(0, 400)), max_size=25),
    per_channel=st.booleans(),
    subblock=st.sampled_from([1, 7, 32, 100]),
    peak_mode=st.sampled_from(["maxima", "extrema"]),
)
def test_pipeline_block_partition_invariance(seed, length, sizes, per_channel, subblock, peak_mode):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((3, length) if per_channel else length)
    kw = dict(window=0.01, subblock=subblock, peak_mode=peak_mode)          # 50-sample windows
    whole = FeaturePipeline(SMALL, **kw).run(x)
    pipe = FeaturePipeline(SMALL, **kw)
    parts = concat_windows(feed(pipe, x, sizes), FEATURES, 3)
    assert len(parts) == len(whole) == length // 50
    assert pipe.partial_samples == length % 50
    if len(whole):
        assert parts.first == whole.first == 0
        for k, name in enumerate(FEATURES):
            assert relative_error(parts.values[:, k], whole.values[:, k]) <= 1e-12, name


def plain_cut_points(length, window, chunk):
    """Stream indices where a chunked pipeline runs its stages, written out: every ``chunk``
    samples from each window's start, and every window end."""
    cuts = set()
    for w0 in range(0, length + 1, window):
        cuts.update(i for i in range(w0 + chunk, w0 + window, chunk) if i <= length)
        if w0 + window <= length:
            cuts.add(w0 + window)
    return sorted(cuts)


def plain_stage_ends(cuts, window, channels, cells):
    """Where a chunked pipeline runs its peaks and windows, written out: from each window's start,
    at the first cut with at least ``cells`` channel-samples since the last stage, and at every
    window end."""
    ends, begun = [], 0
    for c in cuts:
        if c % window == 0 or (c - begun) * channels >= cells:
            ends.append(c)
            begun = c
    return ends


@settings(max_examples=40)
@given(
    seed=st.integers(0, 2**32 - 1),
    length=st.integers(0, 1200),
    sizes=st.lists(st.integers(0, 300), max_size=25),
    chunk_samples=st.sampled_from([1, 7, 13, 25, 49]),
    per_channel=st.booleans(),
    stage_cells=st.sampled_from([1, 20, 60, 16384]),
)
def test_a_chunked_pipeline_runs_exactly_its_chunks_whatever_the_blocks(seed, length, sizes, chunk_samples,
                                                                         per_channel, stage_cells):
    """With ``chunk``, the filterbank runs on the segments between fixed cut points and the peaks
    and windows on stages of them, whatever the blocks: bit for bit the stages fed exactly that,
    written out; and within rounding of running every stage on every segment."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((3, length) if per_channel else length)
    chunk = chunk_samples / SMALL.fs
    with mock.patch.object(supramodal.pipeline, "STAGE_CELLS", stage_cells):
        pipe = FeaturePipeline(SMALL, window=0.01, chunk=chunk)            # 50-sample windows
        assert pipe.chunk_samples == chunk_samples
        got = concat_windows(feed(pipe, x, sizes), FEATURES, 3)
    cuts = plain_cut_points(length, 50, chunk_samples)
    segments = [x[..., a:b] for a, b in zip([0] + cuts, cuts + [length])]
    stages = FeaturePipeline(SMALL, window=0.01, gather=False)
    filtered = np.concatenate([stages.filterbank.process(s) for s in segments], axis=1)
    ends = plain_stage_ends(cuts, 50, 3, stage_cells)
    by_stage = [filtered[:, a:b] for a, b in zip([0] + ends, ends + [length])]
    want = concat_windows([stages.windows.process(stages.peaks.process(y)) for y in by_stage]
                          + [stages.windows.process(stages.peaks.finish())], FEATURES, 3)
    assert len(got) == len(want) == length // 50
    np.testing.assert_array_equal(got.values, want.values)
    assert pipe.partial_samples == length % 50
    every_stage = FeaturePipeline(SMALL, window=0.01, gather=False)
    per_segment = concat_windows([every_stage.process(s) for s in segments] + [every_stage.finish()], FEATURES, 3)
    for k, name in enumerate(FEATURES):
        assert relative_error(got.values[:, k], per_segment.values[:, k]) <= 1e-12, name


def test_a_stage_is_three_chunks_for_the_cochlea_and_a_window_for_the_whiskers():
    """The stage rule on the two banks at the scene's 10 ms chunks."""
    cochlea = FeaturePipeline(bank_by_name("cochlea"), chunk=0.01)          # 441-sample chunks, 50 channels
    assert [cochlea._stage_end(s) for s in (0, 1323, 2646, 3969, 4410)] == [1323, 2646, 3969, 4410, 5733]
    whisker = FeaturePipeline(bank_by_name("whisker"), chunk=0.01)          # 50-sample chunks, 20 channels
    assert [whisker._stage_end(s) for s in (0, 500, 950)] == [500, 1000, 1000]


def test_chunks_change_the_features_only_by_rounding_and_a_chunk_of_a_window_or_more_is_whole():
    x = np.random.default_rng(12).standard_normal(7 * 500 + 55)
    whole = FeaturePipeline(SMALL).run(x, block=500)
    chunked = FeaturePipeline(SMALL, chunk=0.01).run(x, block=4096)
    assert len(chunked) == len(whole) == 7
    for k in range(len(FEATURES)):
        assert relative_error(chunked.values[:, k], whole.values[:, k]) <= 1e-12
    for chunk in (0.1, 0.5, 0, None):
        pipe = FeaturePipeline(SMALL, chunk=chunk)
        assert pipe.chunk_samples == 0
        np.testing.assert_array_equal(pipe.run(x, block=500).values, whole.values)


def test_run_in_blocks_equals_one_call_and_extract_features():
    x = np.random.default_rng(7).standard_normal(5 * 500 + 123)
    one = FeaturePipeline(SMALL).run(x)
    blocks = FeaturePipeline(SMALL).run(x, block=333)
    assert len(one) == 5
    np.testing.assert_allclose(blocks.values, one.values, rtol=1e-12, atol=0)
    np.testing.assert_allclose(extract_features(x, SMALL).values, one.values, rtol=1e-12, atol=0)


def test_float32_pipeline_stays_close_to_float64():
    x = np.random.default_rng(8).standard_normal(5000)
    w64 = FeaturePipeline(SMALL, features=("A",)).run(x)
    w32 = FeaturePipeline(SMALL, features=("A",), dtype=np.float32).run(x)
    np.testing.assert_allclose(w32.values, w64.values, rtol=1e-3)


def test_pipeline_nonfinite_policy():
    x = np.random.default_rng(9).standard_normal(1000)
    x[100] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        FeaturePipeline(SMALL).run(x)
    pipe = FeaturePipeline(SMALL, nonfinite="zero")
    w = pipe.run(x)
    assert pipe.filterbank.nonfinite_count == 1
    x[100] = 0.0
    np.testing.assert_array_equal(w.values, FeaturePipeline(SMALL).run(x).values)


@pytest.mark.parametrize("kwargs, match", [
    ({"window": 0.0}, "window must be a positive"),
    ({"window": -0.1}, "window must be a positive"),
    ({"window": float("nan")}, "window must be a positive"),
    ({"window": 0.0002}, "at least 2"),
    ({"features": ("A", "X")}, "unknown feature"),
    ({"features": ()}, "at least one feature"),
    ({"peak_mode": "minima"}, "peak mode"),
    ({"nonfinite": "drop"}, "nonfinite"),
    ({"dtype": np.float16}, "float64 or float32"),
    ({"chunk": -0.01}, "chunk must be a positive number of seconds"),
    ({"chunk": float("inf")}, "chunk must be a positive number of seconds"),
    ({"chunk": "10 ms"}, "chunk must be a positive number of seconds"),
    ({"chunk": 1e-5}, "less than one sample at 5000 Hz"),
])
def test_pipeline_refuses_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FeaturePipeline(SMALL, **kwargs)


def test_pipeline_refuses_bad_blocks():
    pipe = FeaturePipeline(SMALL)
    for x in (np.zeros((2, 10)), np.zeros((3, 4, 10)), np.zeros(10, complex), np.array(["a", "b"])):
        with pytest.raises(ValueError):
            pipe.process(x)


def test_window_length():
    assert window_length(0.1, 5000.0) == 500
    assert window_length(0.1, 44100.0) == 4410
    assert window_length(0.1, 22050.0) == 2205


# -- repeatable features after long silence ----------------------------------------------------

def _sound_silence_sound(bank, seconds_silent, seed):
    """Texture, then exact zeros, then texture again: the filterbank rings down through ~1e-300
    during the silence, where the state's flush to zero runs at block-dependent times."""
    rng = np.random.default_rng(seed)
    n_sound, n_zero = int(0.5 * bank.fs), int(seconds_silent * bank.fs)
    burst = lambda: 0.3 * rng.standard_normal(n_sound)     # noqa: E731 - two fresh bursts
    return np.concatenate([burst(), np.zeros(n_zero), burst()])


@pytest.mark.slow   # a long stream: 7 s of signal fed 8 times, in blocks as short as 1 sample
@pytest.mark.parametrize("bank_name", ["whisker", "cochlea"])
@pytest.mark.parametrize("gather", [True, False])
def test_features_after_long_silence_are_the_same_for_every_chunking(bank_name, gather):
    """A replay gives the same features whatever its block sizes, also in the first window after
    seconds of exact zeros (where ring-down residue of ~1e-300 once made up to 2.7e-3 of Af)."""
    from supramodal.banks import cochlea_bank
    bank = whisker_bank() if bank_name == "whisker" else cochlea_bank()
    x = _sound_silence_sound(bank, 6.0, seed=3)
    reference = FeaturePipeline(bank, gather=gather).run(x)
    rng = np.random.default_rng(11)
    worst = 0.0
    # Every regime of block size once (1 to 7 samples, ..., up to 5000), then three more drawn: 8 chunkings
    # (there were 20 drawn, which took a minute of CPU on the cochlea and could leave a regime out).
    regimes = [7, 64, 441, 2000, 5000]
    for top in regimes + [int(t) for t in rng.choice(regimes, size=3)]:
        sizes = rng.integers(1, top + 1, size=x.size // max(1, top // 2) + 2).tolist()
        pipe = FeaturePipeline(bank, gather=gather)
        got = concat_windows(feed(pipe, x, sizes), FEATURES, bank.channels)
        assert len(got) == len(reference)
        worst = max(worst, max(relative_error(got.values[:, k], reference.values[:, k]) for k in range(3)))
    assert worst <= 1e-12, worst
