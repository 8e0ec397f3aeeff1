"""The unit-gain normalisation ``gain_at_cf`` against an independent reference in mpmath.

``gain_at_cf`` is the magnitude at ``fc`` of ``h[n] = n**3 exp(-2 pi b n / fs) cos(2 pi fc n / fs)``.
``reference_impulse_response`` divides by the same gain, so the impulse-response tests cannot see
an error in it: here it is computed at 80 significant digits from the float64 inputs taken exactly,
by the textbook closed form (two geometric-type sums, no argument reduction, no care about
cancellation: 80 digits leave over 50 after the worst, ~27 digits lost at b = 10 fs, fc = fs/4),
which is itself checked against the plain sum of the series at the corners.

The grid holds the corners of the accepted domain (b from 1e-7 fs to 10 fs, fc in (0, fs/2)):
fc near 0, near and at fs/4 (where the two halves of the real sequence's transform cancel for
wide b), near fs/2 (where ``1 - r exp(-2j theta)`` is tiny for narrow b).
"""

import mpmath as mp
import numpy as np
import pytest

from supramodal.banks import Bank
from supramodal.gammatone import MAX_B_OVER_FS, MIN_B_OVER_FS, gain_at_cf

EPS = np.finfo(np.float64).eps
#: "A few units in the last place": measured worst 0.49 eps over the grid and 3000 random points.
GAIN_BOUND = 4 * EPS
DIGITS = 80


def mp_gain_closed(cf: float, b: float, fs: float) -> mp.mpf:
    """``|M(r) + M(r exp(-2j theta))| / 2``, ``M(q) = q (1 + 4q + q^2) / (1 - q)^4``, at DIGITS digits."""
    with mp.workdps(DIGITS):
        cf, b, fs = mp.mpf(cf), mp.mpf(b), mp.mpf(fs)
        r = mp.exp(-2 * mp.pi * b / fs)
        q = r * mp.exp(-4j * mp.pi * cf / fs)

        def moments(z):
            return z * (1 + 4 * z + z * z) / (1 - z) ** 4

        return abs(moments(r) + moments(q)) / 2


def mp_gain_series(cf: float, b: float, fs: float, terms: int) -> mp.mpf:
    """``|sum_n n^3 exp(-2 pi b n/fs) cos(2 pi fc n/fs) exp(-j 2 pi fc n/fs)|`` summed directly."""
    with mp.workdps(DIGITS):
        cf, b, fs = mp.mpf(cf), mp.mpf(b), mp.mpf(fs)
        total = mp.mpc(0)
        for n in range(1, terms + 1):
            total += n**3 * mp.exp(-2 * mp.pi * b * n / fs) * mp.cos(2 * mp.pi * cf * n / fs) \
                * mp.exp(-2j * mp.pi * cf * n / fs)
        return abs(total)


def corner_grid():
    """(cf, b, fs): every corner of the domain at 1 kHz, 44.1 kHz and 192 kHz, and the issue's case."""
    for fs in (1000.0, 44100.0, 192000.0):
        quarter, half = fs / 4, fs / 2
        cfs = [1e-9 * fs, 1e-6 * fs, 1e-3 * fs, 0.1 * fs,
               quarter * (1 - 1e-6), quarter * (1 - 1e-12), np.nextafter(quarter, 0), quarter,
               np.nextafter(quarter, fs), quarter * (1 + 1e-9), 0.3 * fs, 0.45 * fs,
               half * (1 - 1e-6), half * (1 - 1e-12), np.nextafter(half, 0)]
        bs = [MIN_B_OVER_FS * fs, 1.5e-7 * fs, 1e-5 * fs, 1e-3 * fs, 0.05 * fs, 0.2 * fs, 0.47 * fs,
              0.48 * fs, 0.5 * fs, 1.0 * fs, 2.0 * fs, 5.0 * fs, 9.0 * fs, MAX_B_OVER_FS * fs]
        for cf in cfs:
            for b in bs:
                yield float(cf), float(b), fs
    for b in (2000.0, 5000.0, 10000.0):             # issue 10: fs 1 kHz, cf 250.00046 Hz
        yield 250.00046, b, 1000.0


def relative_errors(points) -> np.ndarray:
    cf, b, fs = (np.array(v) for v in zip(*points))
    errors = []
    for f in np.unique(fs):                          # one bank per rate: every channel at once
        at = fs == f
        names = tuple(f"c{i}" for i in range(at.sum()))
        gains = gain_at_cf(Bank("custom", f, cf[at], b[at], names))
        for g, c, w in zip(gains, cf[at], b[at]):
            ref = mp_gain_closed(c, w, f)
            errors.append(float(abs(mp.mpf(float(g)) - ref) / ref))
    return np.array(errors)


def test_the_mpmath_closed_form_equals_the_series_at_the_corners():
    # The reference itself, checked against the plain definition where the series is short
    # enough to sum (b >= 0.05 fs: 4000 terms reach 1e-80 of the first).
    for cf, b, fs in [(250.00046, 10000.0, 1000.0), (250.0, 5000.0, 1000.0), (11025.0, 0.5 * 44100, 44100.0),
                      (1e-6 * 44100, 44100.0, 44100.0), (np.nextafter(96000.0, 0), 9600.0, 192000.0),
                      (300.0, 50.0, 1000.0)]:
        terms = int(200 * fs / b) + 60
        closed, series = mp_gain_closed(cf, b, fs), mp_gain_series(cf, b, fs, terms)
        assert abs(closed - series) / series < mp.mpf(10) ** -40, (cf, b, fs)


def test_gain_at_cf_is_correct_to_a_few_ulp_at_every_corner_of_the_domain():
    points = list(corner_grid())
    err = relative_errors(points)
    worst = int(np.argmax(err))
    assert err[worst] <= GAIN_BOUND, (
        f"gain_at_cf off by {err[worst]:.3g} ({err[worst] / EPS:.3g} eps) at cf, b, fs = {points[worst]}")


@pytest.mark.parametrize("seed", [0, 1])
def test_gain_at_cf_is_correct_to_a_few_ulp_at_random_points(seed):
    rng = np.random.default_rng(seed)
    n = 200
    fs = rng.choice([1000.0, 5000.0, 44100.0, 192000.0], n)
    b = fs * 10 ** rng.uniform(np.log10(MIN_B_OVER_FS), np.log10(MAX_B_OVER_FS), n)
    b[: n // 4] = fs[: n // 4] * rng.uniform(0.4, 0.6, n // 4)      # around the change of form
    near_quarter = rng.uniform(0, 1, n) < 0.3
    cf = fs * np.where(near_quarter, 0.25 + rng.normal(0, 1e-6, n), rng.uniform(1e-9, 0.5, n))
    cf = np.minimum(cf, np.nextafter(fs / 2, 0))
    points = list(zip(cf.tolist(), b.tolist(), fs.tolist()))
    err = relative_errors(points)
    worst = int(np.argmax(err))
    assert err[worst] <= GAIN_BOUND, (
        f"gain_at_cf off by {err[worst]:.3g} ({err[worst] / EPS:.3g} eps) at cf, b, fs = {points[worst]}")


def corner_bank(fs: float) -> Bank:
    """Wide and narrow channels at and near the quarter and half rate, where phases must be exact."""
    quarter = fs / 4
    cf = [quarter, np.nextafter(quarter, fs), quarter * (1 + 1e-9), quarter, 0.3 * fs, np.nextafter(fs / 2, 0),
          1e-6 * fs, quarter]
    b = [MAX_B_OVER_FS * fs, MAX_B_OVER_FS * fs, 2.0 * fs, 0.5 * fs, 1e-3 * fs, 1e-5 * fs, 0.01 * fs, 1e-4 * fs]
    return Bank("custom", fs, cf, b, tuple(f"c{i}" for i in range(len(cf))))


@pytest.mark.parametrize("fs", [1000.0, 44100.0])
def test_reference_impulse_response_matches_mpmath_at_the_corners(fs):
    # The tests' analytic reference, itself checked: n^3 exp(-2 pi b n/fs) cos(2 pi fc n/fs) / gain, at
    # 50 digits. At fc = fs/4, b = 10 fs the normalised n = 1 term is exactly 0 but huge if cos(pi/2)
    # is not (1e-20 * exp(63) / 8: the old reference gave 6e6 there, the peak being 1).
    from supramodal.gammatone import reference_impulse_response

    bank = corner_bank(fs)
    n = 64
    got = reference_impulse_response(bank, n)
    for c in range(bank.channels):
        cf, b = float(bank.cf[c]), float(bank.b[c])
        with mp.workdps(50):
            g = mp_gain_closed(cf, b, fs)
            want = [k**3 * mp.exp(-2 * mp.pi * mp.mpf(b) * k / fs) * mp.cos(2 * mp.pi * mp.mpf(cf) * k / fs) / g
                    for k in range(n)]
            peak = max(abs(v) for v in want)
            err = max(abs(mp.mpf(float(got[c, k])) - want[k]) for k in range(n)) / peak
        assert err <= 4 * EPS, f"channel cf={cf!r} b={b!r}: reference off by {float(err):.3g} of its peak"


@pytest.mark.parametrize("fs", [1000.0, 192000.0])
def test_pole_powers_match_mpmath(fs):
    from supramodal.gammatone import pole_powers

    bank = corner_bank(fs)
    d = np.array([1.0, 2.0, 3.0, 21.0, -21.0, 441.0, -504.0, 4096.0, 1e6])
    with np.errstate(over="ignore", invalid="ignore"):      # p**-504 of a 10 fs channel: beyond float64
        got = pole_powers(bank, d)
    for c in range(bank.channels):
        cf, b = float(bank.cf[c]), float(bank.b[c])
        for i, e in enumerate(d):
            with mp.workdps(50):
                want = mp.exp((-2 * mp.pi * mp.mpf(b) + 2j * mp.pi * mp.mpf(cf)) * mp.mpf(e) / fs)
                if abs(want) < mp.mpf(10) ** -290 or abs(want) > mp.mpf(10) ** 290:
                    continue                             # beyond float64: the fast form never asks
                err = abs(mp.mpc(complex(got[c, i])) - want) / abs(want)
            assert err <= 2 * EPS, f"p**{e} of cf={cf!r} b={b!r} off by {float(err):.3g}"
