"""Peak extractor and feature windows: hand-made signals, block boundaries, exact sums."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supramodal.features import FEATURE_TABLE, FEATURES, FeatureWindows, Windows, check_features, concat_windows
from supramodal.peaks import PeakExtractor, Peaks

# One channel, indices 0..13:
#   0  1  2  3  4  5  6  7   8  9 10 11 12 13
SIGNAL = np.array([0, 1, 3, 2, 2, 5, 1, 0, -1, 4, 4, 4, 1, 7], dtype=float)
# maxima: 2 (3.0), 5 (5.0), 9 (4.0: first sample of the plateau 9..11); 13 is the last sample: never a peak
MAXIMA = {2: 3.0, 5: 5.0, 9: 4.0}
# extrema adds the minimum at 8 (|-1|); 3..4 is a dip but positive, so not a minimum
EXTREMA = {2: 3.0, 5: 5.0, 8: 1.0, 9: 4.0}


def run_blocks(extractor, y, cuts):
    """Feed y (channels, L) cut at the given stream indices; return ({(ch, idx): amp}, [Peaks...])."""
    bounds = [0, *sorted(cuts), y.shape[1]]
    found, calls = {}, []
    for a, b in zip(bounds, bounds[1:]):
        p = extractor.process(y[:, a:b])
        calls.append(p)
        for c, i, v in zip(p.channel, p.index, p.amplitude):
            assert (int(c), int(i)) not in found, "a peak reported twice"
            found[(int(c), int(i))] = float(v)
    calls.append(extractor.finish())
    return found, calls


def test_maxima_of_a_hand_made_signal():
    found, calls = run_blocks(PeakExtractor(1), SIGNAL[None], [])
    assert found == {(0, k): v for k, v in MAXIMA.items()}
    assert calls[0].decided == 13                   # the last sample waits for a successor ...
    assert len(calls[-1]) == 0 and calls[-1].decided == 14   # ... and finish() says it is no peak


def test_extrema_mode_keeps_minima_with_their_magnitude():
    found, _ = run_blocks(PeakExtractor(1, mode="extrema"), SIGNAL[None], [])
    assert found == {(0, k): v for k, v in EXTREMA.items()}


def test_peak_at_the_last_sample_of_a_block_is_decided_by_the_next_block():
    ex = PeakExtractor(1)
    first = ex.process(SIGNAL[None, :6])            # index 5 (value 5) is this block's last sample
    assert first.index.tolist() == [2] and first.decided == 5
    second = ex.process(SIGNAL[None, 6:7])          # one sample is enough to decide it
    assert second.index.tolist() == [5] and second.amplitude.tolist() == [5.0]
    assert second.decided == 6


def test_peak_at_the_first_sample_of_a_block():
    ex = PeakExtractor(1)
    ex.process(SIGNAL[None, :9])
    p = ex.process(SIGNAL[None, 9:])                # the plateau's first sample opens this block
    assert p.index.tolist() == [9] and p.amplitude.tolist() == [4.0]


def test_plateau_split_across_blocks_gives_one_peak_at_its_first_sample():
    y = np.array([[0.0, 4.0, 4.0, 4.0, 1.0]])
    for cuts in ([], [1], [2], [3], [4], [1, 2, 3, 4]):
        found, _ = run_blocks(PeakExtractor(1), y, cuts)
        assert found == {(0, 1): 4.0}, cuts


def test_peak_at_the_very_first_sample_and_a_rising_end():
    """The stream starts at rest (0 before it): a first sample above its successor is a peak.
    A signal still rising at its end has no peak at its last sample."""
    found, _ = run_blocks(PeakExtractor(1), np.array([[2.0, 1.0, 3.0, 4.0]]), [1])
    assert found == {(0, 0): 2.0}


def test_non_positive_maxima_are_not_peaks_in_maxima_mode():
    y = np.array([[-3.0, -1.0, -2.0, 0.0, 0.0, -1.0]])
    assert run_blocks(PeakExtractor(1), y, [])[0] == {}
    # extrema: -3 at index 0 is a minimum (rest before it), -2 at 2; -1 at 1 is a negative maximum: no
    assert run_blocks(PeakExtractor(1, mode="extrema"), y, [])[0] == {(0, 0): 3.0, (0, 2): 2.0}


@settings(max_examples=100)
@given(cuts=st.lists(st.integers(0, len(SIGNAL)), max_size=20),
       mode=st.sampled_from(["maxima", "extrema"]))
def test_any_partition_of_the_hand_made_signal_gives_the_same_peaks(cuts, mode):
    """Includes 0- and 1-sample blocks (repeated or adjacent cuts) and cuts at every peak."""
    y = np.stack([SIGNAL, -SIGNAL, np.roll(SIGNAL, 3)])
    whole, _ = run_blocks(PeakExtractor(3, mode), y, [])
    parts, calls = run_blocks(PeakExtractor(3, mode), y, cuts)
    assert parts == whole
    decided = [c.decided for c in calls]
    assert decided == sorted(decided) and decided[-1] == len(SIGNAL)
    for c in calls:                                  # sorted by channel, then stream index
        order = np.lexsort((c.index, c.channel))
        assert np.array_equal(order, np.arange(len(c)))


def test_peak_extractor_refusals():
    with pytest.raises(ValueError, match="peak mode"):
        PeakExtractor(2, mode="minima")
    with pytest.raises(ValueError, match="channels must be >= 1"):
        PeakExtractor(0)
    ex = PeakExtractor(2)
    with pytest.raises(ValueError, match=r"shape \(2, L\)"):
        ex.process(np.zeros(10))
    with pytest.raises(ValueError, match=r"shape \(2, L\)"):
        ex.process(np.zeros((3, 10)))
    ex.finish()
    with pytest.raises(RuntimeError, match="finish"):
        ex.process(np.zeros((2, 10)))


# -- feature windows ---------------------------------------------------------------------------

def peaks(entries, decided):
    """Peaks from [(channel, index, amplitude), ...] (sorted here as the extractor sorts them)."""
    entries = sorted(entries)
    return Peaks(np.array([e[0] for e in entries], dtype=np.intp),
                 np.array([e[1] for e in entries], dtype=np.int64),
                 np.array([e[2] for e in entries], dtype=float), decided)


FS = 1000.0
# window length 10 samples; channel 0: peaks at 3, 7, 12, 25 (window 0, 0, 1, 2), channel 1: one at 5.
P = [(0, 3, 1.0), (0, 7, 2.0), (0, 12, 3.0), (0, 25, 4.0), (1, 5, 10.0)]


#: The paper's three features, in the order of the values written out by hand below (the table may hold more).
PAPER = ("Af", "A", "f")


def expected_values():
    """(windows 0..3, features Af, A, f, channels 2) by hand."""
    v = np.zeros((4, 3, 2))
    # window 0, channel 0: peak 3 is the channel's first ever: A only; peak 7: f = 1000/4
    v[0, 1, 0] = 1.0 + 2.0
    v[0, 2, 0] = 1000 / 4
    v[0, 0, 0] = 2.0 * (1000 / 4)     # written amp * (fs / interval), as summed
    # window 1: peak 12, predecessor 7 in the previous window
    v[1, 1, 0], v[1, 2, 0], v[1, 0, 0] = 3.0, 1000 / 5, 3.0 * (1000 / 5)
    # window 2: peak 25, predecessor 12 two windows back
    v[2, 1, 0], v[2, 2, 0], v[2, 0, 0] = 4.0, 1000 / 13, 4.0 * (1000 / 13)
    # channel 1: its first ever peak: A only
    v[0, 1, 1] = 10.0
    # window 3 (30..39) has no peak: exactly 0
    return v


def test_exact_sums_from_a_synthetic_peaks_object():
    fw = FeatureWindows(2, FS, 10, PAPER)
    out = fw.process(peaks(P, decided=40))
    assert isinstance(out, Windows) and out.first == 0 and len(out) == 4
    assert out.features == PAPER
    # by default every feature of the table, in its order
    assert FeatureWindows(2, FS, 10).features == FEATURES == tuple(FEATURE_TABLE) and set(PAPER) <= set(FEATURES)
    np.testing.assert_array_equal(out.values, expected_values())
    np.testing.assert_array_equal(out.feature("A"), expected_values()[:, 1, :])
    assert out.numbers.tolist() == [0, 1, 2, 3]
    assert not np.isnan(out.values).any()
    assert fw.windows_emitted == 4


def test_same_sums_when_peaks_arrive_in_several_calls():
    """The f of a peak whose predecessor arrived in an earlier call (and earlier window)."""
    fw = FeatureWindows(2, FS, 10, PAPER)
    chunks = [
        peaks([e for e in P if e[1] < 8], decided=8),        # sample 8 undecided: window 0 not complete yet
        peaks([], decided=9),                                # its peaks are all known now (detections up to 9)
        peaks([e for e in P if 8 <= e[1] < 20], decided=21),
        peaks([e for e in P if e[1] >= 20], decided=40),
    ]
    outs = [fw.process(c) for c in chunks]
    assert [len(o) for o in outs] == [0, 1, 1, 2]
    assert [o.first for o in outs if len(o)] == [0, 1, 2]
    np.testing.assert_array_equal(concat_windows(outs, PAPER, 2).values, expected_values())


def test_a_window_closes_when_its_last_sample_has_arrived():
    """A peak counts in the window of its detection (the sample after it): window w holds the peaks at
    samples [10w - 1, 10w + 9) and closes once samples up to 10w + 8 are decided, i.e. when the
    extractor has seen sample 10w + 9, the window's own last sample."""
    fw = FeatureWindows(1, FS, 10)
    assert len(fw.process(peaks([(0, 7, 1.0)], decided=8))) == 0
    out = fw.process(peaks([(0, 8, 2.0)], decided=9))           # peak at 8, detected at 9: window 0
    assert out.first == 0 and out.feature("A")[:, 0].tolist() == [3.0]
    assert len(fw.process(peaks([(0, 9, 4.0)], decided=18))) == 0  # peak at 9, detected at 10: window 1
    out = fw.process(peaks([], decided=19))
    assert out.first == 1 and out.feature("A")[:, 0].tolist() == [4.0]
    out = fw.process(peaks([], decided=35))
    assert out.first == 2 and len(out) == 1
    np.testing.assert_array_equal(out.values, 0.0)


def test_feature_subset_is_computed_in_the_given_order():
    fw = FeatureWindows(2, FS, 10, features=("f", "A"))
    out = fw.process(peaks(P, decided=40))
    assert out.values.shape == (4, 2, 2) and out.features == ("f", "A")
    np.testing.assert_array_equal(out.feature("f"), expected_values()[:, 2, :])
    np.testing.assert_array_equal(out.feature("A"), expected_values()[:, 1, :])
    only_a = FeatureWindows(2, FS, 10, features="A").process(peaks(P, decided=40))
    np.testing.assert_array_equal(only_a.values[:, 0, :], expected_values()[:, 1, :])


def test_extractor_into_windows_counts_a_first_peak_in_A_only():
    """End to end on a hand-made signal: peaks at 2, 5, 9 with window length 5."""
    ex, fw = PeakExtractor(1), FeatureWindows(1, FS, 5)
    parts = [fw.process(ex.process(SIGNAL[None, a:b])) for a, b in ((0, 5), (5, 6), (6, 11), (11, 14))]
    parts.append(fw.process(ex.finish()))
    w = concat_windows(parts, FEATURES, 1)
    assert len(w) == 2                              # 14 samples: windows [0,5) and [5,10); 10..13 partial
    # The peak at 9 is detected at sample 10: it belongs to the partial window 2, which is dropped.
    np.testing.assert_array_equal(w.feature("A")[:, 0], [3.0, 5.0])
    np.testing.assert_array_equal(w.feature("f")[:, 0], [0.0, FS / 3])
    np.testing.assert_array_equal(w.feature("Af")[:, 0], [0.0, 5.0 * (FS / 3)])


def test_peaks_out_of_order_are_refused():
    fw = FeatureWindows(1, FS, 10)
    fw.process(peaks([], decided=25))
    with pytest.raises(ValueError, match="already emitted"):
        fw.process(peaks([(0, 5, 1.0)], decided=30))


@pytest.mark.parametrize("kwargs, match", [
    ({"length": 0}, "window length"),
    ({"length": 2.5}, "window length"),
    ({"fs": 0.0}, "sample rate"),
    ({"fs": float("nan")}, "sample rate"),
    ({"features": ()}, "at least one feature"),
    ({"features": ("A", "B")}, r"unknown feature.*'B'"),
    ({"features": ("A", "A")}, "repeat"),
])
def test_feature_windows_refusals(kwargs, match):
    args = {"channels": 2, "fs": FS, "length": 10}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        FeatureWindows(**args)


def test_check_features():
    assert check_features("Af") == ("Af",)
    assert check_features(["f", "Af"]) == ("f", "Af")
    with pytest.raises(ValueError, match="unknown feature"):
        check_features("af")


def test_an_unknown_feature_is_refused_everywhere_with_the_known_names():
    """Names come from the one table: no fall-through to a computation for a name it lacks."""
    from supramodal.node.cli import build_parser
    from supramodal.node.scene.schema import SceneError, scene_from_dict
    from supramodal.errors import InputError

    with pytest.raises(InputError, match=r"unknown feature\(s\) \['Amp'\]; the features are Af: .*; A: .*; f: "):
        FeatureWindows(2, FS, 10, ("Af", "Amp"))
    with pytest.raises(SceneError, match=r"\[features\] names: expected a list of distinct names drawn from Af \("):
        scene_from_dict({"driver": {"type": "synth"}, "features": {"names": ["Amp"]}})
    choices = next(a for a in build_parser()._subparsers._group_actions[0].choices["train"]._actions
                   if a.dest == "features").choices
    assert list(choices) == list(FEATURE_TABLE) == list(FEATURES)


def test_a_feature_is_computed_from_its_table_entry(monkeypatch):
    """A feature added to the table is accepted and computed from its entry alone:
    here the sum of squared amplitudes, against a plain per-peak loop."""
    from supramodal import features

    extra = features.Feature("A2", "sum of squared amplitudes", False, lambda amp, freq: amp ** 2)
    monkeypatch.setitem(features.FEATURE_TABLE, "A2", extra)
    fw = FeatureWindows(2, FS, 10, ("A2", "A"))
    out = fw.process(peaks(P, decided=40))
    want = np.zeros((4, 2))
    for ch, idx, amp in P:
        want[(idx + 1) // 10, ch] += amp * amp
    np.testing.assert_array_equal(out.feature("A2"), want)
    np.testing.assert_array_equal(out.feature("A"), expected_values()[:, 1, :])


def test_concat_windows_refuses_gaps():
    a = Windows(0, np.zeros((2, 1, 1)), ("A",))
    b = Windows(3, np.zeros((1, 1, 1)), ("A",))
    with pytest.raises(ValueError, match="not consecutive"):
        concat_windows([a, b], ("A",), 1)
    assert len(concat_windows([], ("A",), 1)) == 0


# -- against the plain definitions, on random data ----------------------------------------------

def plain_peaks(y, mode):
    """Loop version of the definition (rest = 0 before the stream, last sample never a peak)."""
    out = {}
    for c in range(y.shape[0]):
        for n in range(y.shape[1] - 1):
            left = y[c, n - 1] if n > 0 else 0.0
            mid, right = y[c, n], y[c, n + 1]
            if left < mid >= right and mid > 0:
                out[(c, n)] = float(mid)
            elif mode == "extrema" and left > mid <= right and mid < 0:
                out[(c, n)] = float(-mid)
    return out


@settings(max_examples=100)
@given(seed=st.integers(0, 2**32 - 1), length=st.integers(0, 120),
       cuts=st.lists(st.integers(0, 120), max_size=15), mode=st.sampled_from(["maxima", "extrema"]))
def test_extractor_matches_the_definition_on_plateau_rich_signals(seed, length, cuts, mode):
    """Small integers: plateaus, ties and zeros everywhere, cut anywhere."""
    y = np.random.default_rng(seed).integers(-2, 3, (2, length)).astype(float)
    found, _ = run_blocks(PeakExtractor(2, mode), y, [k for k in cuts if k <= length])
    assert found == plain_peaks(y, mode)


def plain_windows(entries, fs, length, n_windows, channels):
    v = np.zeros((n_windows, 3, channels))
    for c in range(channels):
        prev = None
        for _, n, amp in sorted(e for e in entries if e[0] == c):
            w = (n + 1) // length                    # the window of the peak's detection
            if w >= n_windows:
                continue
            v[w, 1, c] += amp
            if prev is not None:
                v[w, 2, c] += fs / (n - prev)
                v[w, 0, c] += amp * (fs / (n - prev))
            prev = n
    return v


@settings(max_examples=100)
@given(seed=st.integers(0, 2**32 - 1), length=st.integers(1, 40), n_windows=st.integers(1, 8),
       splits=st.lists(st.integers(0, 320), max_size=6))
def test_feature_windows_match_the_definition_for_any_delivery(seed, length, n_windows, splits):
    """Random peaks on 3 channels delivered in calls that end at random 'decided' points."""
    rng = np.random.default_rng(seed)
    total = length * n_windows
    entries = []
    for c in range(3):
        idx = np.flatnonzero(rng.random(total) < 0.3)
        entries += [(c, int(n), float(a)) for n, a in zip(idx, rng.uniform(0.1, 5.0, idx.size))]
    fw = FeatureWindows(3, 4000.0, length, PAPER)
    outs, done = [], 0
    for d in sorted({min(s, total) for s in splits} | {total}):
        outs.append(fw.process(peaks([e for e in entries if done <= e[1] < d], decided=d)))
        done = d
    got = concat_windows(outs, PAPER, 3)
    n_closed = (total + 1) // length                 # detections up to sample `total` are known
    assert got.first == 0 and len(got) == n_closed
    np.testing.assert_allclose(got.values, plain_windows(entries, 4000.0, length, n_closed, 3),
                               rtol=1e-12, atol=0)


def test_peak_threshold_drops_small_peaks_in_both_modes():
    y = np.array([[0.0, 0.5, 0.0, 2.0, 0.0, -0.5, 0.0, -3.0, 0.0, 0.0]])
    maxima = PeakExtractor(1, threshold=1.0).process(y)
    assert maxima.index.tolist() == [3] and maxima.amplitude.tolist() == [2.0]
    extrema = PeakExtractor(1, mode="extrema", threshold=1.0).process(y)
    assert extrema.index.tolist() == [3, 7] and extrema.amplitude.tolist() == [2.0, 3.0]
    assert PeakExtractor(1).process(y).index.tolist() == [1, 3]
    with pytest.raises(ValueError, match="peak threshold"):
        PeakExtractor(1, threshold=-1.0)


@pytest.mark.parametrize("mode", ["maxima", "extrema"])
@pytest.mark.parametrize("threshold", [0.0, 1e-300, 1e-260])
def test_peaks_must_exceed_the_floor_whatever_the_threshold(mode, threshold):
    """Ring-down residue (far below any signal) is no peak, even with no threshold; 1e-249 is."""
    from supramodal.peaks import PEAK_FLOOR
    assert PEAK_FLOOR == 1e-250
    x = np.zeros((1, 12))
    x[0, 2], x[0, 5], x[0, 8] = 1e-300, 1e-250, 1e-249      # at the floor: not above it
    p = PeakExtractor(1, mode=mode, threshold=threshold).process(x)
    assert p.index.tolist() == [8] and p.amplitude.tolist() == [1e-249]
    if mode == "extrema":                                     # minima by their magnitude
        q = PeakExtractor(1, mode=mode, threshold=threshold).process(-x)
        assert q.index.tolist() == [8]


def test_a_block_that_is_part_of_the_staged_work_array_is_read_before_the_array_is_laid_out_anew():
    """A pipeline hands the peak extractor the first part of its staged array at the stream's end (a
    partial stage): the same peaks as that block copied out, though the work array is reused."""
    from supramodal.peaks import PeakExtractor

    rng = np.random.default_rng(5)
    first, rest = rng.standard_normal((4, 30)), rng.standard_normal((4, 40))
    plain = PeakExtractor(4)
    want = [plain.process(first), plain.process(rest[:, :17].copy())]
    pe = PeakExtractor(4)
    got = [pe.process(first)]
    staged = pe.staging(40)
    staged[:] = rest
    got.append(pe.process(staged[:, :17]))
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g.channel, w.channel)
        np.testing.assert_array_equal(g.index, w.index)
        np.testing.assert_array_equal(g.amplitude, w.amplitude)
