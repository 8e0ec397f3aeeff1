"""A source's clock model against simulated sources whose truth is known: rate error, offset,
arrival delays that are never negative, outliers, gaps with bursts, restarts, huge indices."""

from __future__ import annotations

import math

import numpy as np
import pytest

from supramodal.node.runtime.clock import ClockError, ClockModel


def simulate(nominal, ppm, t0, seconds, block, jitter, rng, outlier_rate=0.0, gap=None, first_index=0):
    """Blocks of a source whose crystal runs ``ppm`` fast, written independently of the model.

    Sample n is taken at ``t0 + (n - first_index) / (nominal (1 + ppm 1e-6))``. A block arrives after
    its last sample, late by an exponential delay of mean ``jitter`` seconds, plus 50 ms with
    probability ``outlier_rate``; during ``gap = (a, b)`` (seconds) nothing arrives and the held-up
    blocks all come at ``b``. Arrivals are stamped in order. Returns (index of each block's last
    sample, arrival, true time of that sample), arrays.
    """
    true_rate = nominal * (1 + ppm * 1e-6)
    n_blocks = int(seconds * nominal / block)
    last = first_index + (np.arange(n_blocks) + 1) * block - 1
    truth = t0 + (last - first_index) / true_rate
    delay = rng.exponential(jitter, n_blocks) + 0.05 * (rng.random(n_blocks) < outlier_rate)
    arrival = truth + delay
    if gap is not None:
        held = (truth >= t0 + gap[0]) & (truth < t0 + gap[1])
        arrival[held] = np.maximum(arrival[held], t0 + gap[1])
    arrival = np.maximum.accumulate(arrival)
    return last, arrival, truth


def feed(clock, last, arrival):
    for n, t in zip(last.tolist(), arrival.tolist()):
        clock.update(n, t)


def true_time(nominal, ppm, t0, index, first_index=0):
    return t0 + (np.asarray(index, dtype=np.float64) - first_index) / (nominal * (1 + ppm * 1e-6))


@pytest.mark.parametrize("ppm", [-100.0, -70.0, 0.0, 40.0, 100.0])
def test_rate_and_times_match_the_truth(ppm):
    rng = np.random.default_rng(int(ppm) + 1000)
    clock = ClockModel(5000.0)
    last, arrival, truth = simulate(5000.0, ppm, 12.345, 300.0, 50, 2e-3, rng)
    feed(clock, last, arrival)
    est = clock.estimate()
    assert est.fitted and abs(est.ppm - ppm) < 1.0, est
    tail = last[-1000:]                                   # the last 10 s
    err = np.abs(clock.time_of(tail) - true_time(5000.0, ppm, 12.345, tail))
    assert err.max() < 2e-4, err.max()                    # 2 ms of jitter, 0.2 ms of error
    assert abs(est.offset - 12.345) < 2e-4
    # the jitter figure describes the delays: 2 ms exponential -> p95 - p5 of about 6 ms
    assert 3e-3 < est.jitter < 9e-3 and 0.5e-3 < est.delay < 3e-3, est


def test_two_sources_on_their_own_clocks_align():
    """Whiskers at 5 kHz, +40 ppm, 50-sample blocks; a microphone at 44.1 kHz, -70 ppm, 441-sample
    blocks, started 37 ms later: the same true instant, mapped through each clock, agrees."""
    rng = np.random.default_rng(7)
    whiskers, mic = ClockModel(5000.0), ClockModel(44100.0)
    feed(whiskers, *simulate(5000.0, 40.0, 100.0, 180.0, 50, 2e-3, rng)[:2])
    feed(mic, *simulate(44100.0, -70.0, 100.037, 180.0, 441, 2e-3, rng)[:2])
    instants = 100.037 + np.linspace(150.0, 179.0, 50)
    n_w = (instants - 100.0) * 5000.0 * (1 + 40e-6)          # each source's index at that instant
    n_m = (instants - 100.037) * 44100.0 * (1 + -70e-6)
    pair = np.abs(whiskers.time_of(n_w) - mic.time_of(n_m))
    assert pair.max() < 2e-4, pair.max()
    # and each stream's index of the other's window end: a window of the whiskers pairs with
    # the microphone samples taken at the same time, to a few samples
    got = mic.index_at(whiskers.time_of(n_w))
    assert np.abs(got - n_m).max() < 0.2e-3 * 44100


def test_outliers_and_a_burst_after_a_gap_leave_the_line_in_place():
    rng = np.random.default_rng(3)
    clock = ClockModel(5000.0)
    last, arrival, truth = simulate(5000.0, -100.0, 0.0, 240.0, 50, 2e-3, rng, outlier_rate=0.01, gap=(100.0, 104.5))
    worst = 0.0
    for n, t, true in zip(last.tolist(), arrival.tolist(), truth.tolist()):
        clock.update(n, t)
        if true > 30.0:             # at every block after the first half minute, the burst included
            worst = max(worst, abs(clock.time_of(n) - true))
    assert worst < 2e-4, worst
    est = clock.estimate()
    assert abs(est.ppm + 100.0) < 1.0, est
    tail = last[-500:]
    assert np.abs(clock.time_of(tail) - true_time(5000.0, -100.0, 0.0, tail)).max() < 2e-4
    # the segments held up by the gap had no quick block: they were left out, and counted
    assert est.outliers >= 4, est


def test_a_rate_that_wanders_is_followed():
    """A crystal warming up: +20 ppm drifting to +60 ppm over 10 minutes (a ramp in rate)."""
    rng = np.random.default_rng(11)
    nominal, block, seconds = 5000.0, 50, 600.0
    n_blocks = int(seconds * nominal / block)
    last = (np.arange(n_blocks) + 1) * block - 1
    ppm_of = lambda n: 20.0 + 40.0 * n / last[-1]            # noqa: E731 - the rate at sample n
    # time of sample n: the integral of 1 / rate, summed exactly per block (rate constant in one)
    dt = block / (nominal * (1 + ppm_of(last) * 1e-6))
    truth = np.cumsum(dt)
    arrival = np.maximum.accumulate(truth + rng.exponential(2e-3, n_blocks))
    clock = ClockModel(nominal)
    feed(clock, last, arrival)
    assert abs(clock.estimate().ppm - ppm_of(last[-1])) < 5.0        # the window's rate lags a little
    tail = slice(-500, None)
    assert np.abs(clock.time_of(last[tail]) - truth[tail]).max() < 3e-4


def test_before_the_first_fit_times_follow_the_earliest_block_at_the_nominal_rate():
    clock = ClockModel(1000.0)
    assert math.isnan(clock.time_of(0)) and not clock.estimate().fitted
    clock.update(99, 5.100)          # 0.1 s of samples, 1 ms late
    clock.update(199, 5.1995)        # 0.5 ms late: the earlier line wins
    assert clock.time_of(0) == pytest.approx(5.0005, abs=1e-12)
    assert clock.index_at(5.0505) == pytest.approx(50.0, abs=1e-9)
    est = clock.estimate()
    assert not est.fitted and est.rate == 1000.0 and est.blocks == 2


def test_reset_starts_over_after_a_restart():
    rng = np.random.default_rng(5)
    clock = ClockModel(5000.0)
    feed(clock, *simulate(5000.0, 50.0, 0.0, 30.0, 50, 1e-3, rng)[:2])
    with pytest.raises(ClockError, match="reset"):
        clock.update(49, 31.0)                                   # the board restarted its count
    clock.reset()
    last, arrival, _ = simulate(5000.0, 50.0, 31.0, 30.0, 50, 1e-3, rng)
    feed(clock, last, arrival)
    assert clock.estimate().blocks == len(last)
    assert abs(clock.time_of(last[-1]) - true_time(5000.0, 50.0, 31.0, last[-1])) < 2e-4


def test_a_source_running_for_years_keeps_its_precision():
    """Indices near 1e12 (six years at 5 kHz): the fit is centred, times stay exact to microseconds."""
    rng = np.random.default_rng(9)
    first = 10**12
    t0 = first / 5000.0
    clock = ClockModel(5000.0)
    last, arrival, truth = simulate(5000.0, 30.0, t0, 120.0, 50, 1e-3, rng, first_index=first)
    feed(clock, last, arrival)
    assert abs(clock.estimate().ppm - 30.0) < 2.0
    assert np.abs(clock.time_of(last[-200:]) - truth[-200:]).max() < 2e-4


def test_a_source_with_no_jitter_is_exact():
    clock = ClockModel(48000.0)
    last = np.arange(1, 2001) * 480 - 1
    arrival = 3.0 + last / (48000.0 * (1 + 25e-6))
    feed(clock, last, arrival)
    assert clock.estimate().ppm == pytest.approx(25.0, abs=1e-3)
    assert abs(clock.time_of(last[-1]) - arrival[-1]) < 1e-9


@pytest.mark.parametrize("kwargs, match", [
    ({"nominal_rate": 0.0}, "nominal rate must be a positive"),
    ({"nominal_rate": float("nan")}, "nominal rate must be a positive"),
    ({"nominal_rate": True}, "nominal rate must be a positive"),
    ({"nominal_rate": 5000.0, "segment_seconds": -1.0}, "segment_seconds"),
    ({"nominal_rate": 5000.0, "window_segments": 1}, "window_segments must be an integer >= 2"),
])
def test_bad_settings_are_refused(kwargs, match):
    with pytest.raises(ClockError, match=match):
        ClockModel(**kwargs)


def test_bad_updates_are_refused_and_change_nothing():
    clock = ClockModel(5000.0)
    clock.update(49, 1.0)
    with pytest.raises(ClockError, match="must be finite"):
        clock.update(99, float("nan"))
    with pytest.raises(ClockError, match="before the previous block"):
        clock.update(99, 0.5)
    with pytest.raises(ClockError, match="does not follow 49"):
        clock.update(49, 1.1)
    assert clock.estimate().blocks == 1


def test_blocks_all_at_one_instant_leave_the_rate_as_it_was():
    """A source far faster than real time delivers every block at one host instant: no rate can be
    fitted, and the model keeps a positive one (its estimate must not divide by zero)."""
    clock = ClockModel(1000.0)
    for k in range(1, 5000):
        clock.update(10 * k - 1, 5.0)
    e = clock.estimate()
    assert e.rate == pytest.approx(1000.0) and clock.time_of(0) <= 5.0
