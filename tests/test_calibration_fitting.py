"""How a calibration is fitted (issue 38, item 1): the analytic gradients of the window map's, the capped
map's and the capped pooling's losses against finite differences and extended precision, the quasi-Newton
fits against a plain Nelder-Mead search of the same loss, what caps still guarantee, and stiff or bad
held-out logits."""

import math
import warnings

import mpmath
import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.special import log_softmax

from supramodal.calibration import (CAP_BOUNDS, CAP_SHARPNESS, FACTOR_BOUNDS, MAP_BOUNDS, Calibration, _capped_loss,
                                    _MapLoss, _pooling_slope, _PoolLoss, _Prefixes, _smoothed_targets, cap_gaps,
                                    confusion_caps, effective_windows, fit_calibration, fit_capped_pooling,
                                    fit_capped_window_calibration, fit_pooling, fit_window_calibration, log_loss,
                                    pool_log_posteriors, winner)
from supramodal.errors import InputError
from test_calibration import _confusable      # held-out logits of a pair the network cannot tell apart

mpmath.mp.dps = 50


def _logits(n=600, k=5, seed=0, spread=30.0):
    """Held-out logits of a network that is right about 70 % of the time, and their labels."""
    rng = np.random.default_rng(seed)
    y = rng.integers(0, k, n)
    z = rng.normal(-spread, spread / 3, (n, k))
    hit = np.where(rng.random(n) < 0.7, y, rng.integers(0, k, n))
    z[np.arange(n), hit] = rng.normal(spread, spread / 3, n)
    return z, y


def _plain_loss(z, y, a, c):
    """The window map's smoothed log loss, as the fit of before computed it (log_softmax of the map)."""
    t = _smoothed_targets(y, z.shape[1])
    return float(-(t * log_softmax(a * np.arcsinh(z / c), axis=1)).sum(axis=1).mean())


def _capped_map_loss(z, y, a, c, caps):
    t = _smoothed_targets(y, z.shape[1])
    return float(-(t * cap_gaps(a * np.arcsinh(z / c), caps)).sum(axis=1).mean())


def _central(f, p, h=1e-6):
    return np.array([(f(p + e)[0] - f(p - e)[0]) / (2 * h) for e in np.eye(len(p)) * h])


# -- the gradients ---------------------------------------------------------------------------------

@pytest.mark.parametrize("p", [(0.0, 0.0, 0.5), (1.2, 2.0, 0.3), (-2.0, 5.0, 2.0), (5.0, -3.0, 0.1), (3.0, 1.0, 4.5)])
def test_the_window_maps_loss_is_the_one_applied_and_its_gradient_the_finite_differences(p):
    z, y = _logits()
    base = confusion_caps(np.argmax(z, axis=1), y, z.shape[1])
    p = np.array(p)
    a, c, f = np.exp(p)
    plain, capped = _MapLoss(z, y), _MapLoss(z, y, base)
    loss, grad = plain(p[:2])
    assert loss == pytest.approx(_plain_loss(z, y, a, c), rel=1e-12, abs=1e-13)
    np.testing.assert_allclose(grad, _central(plain, p[:2]), rtol=1e-5, atol=1e-8)
    caps = np.clip(base * f, *CAP_BOUNDS)
    np.fill_diagonal(caps, 0.0)
    loss, grad = capped(p)
    assert loss == pytest.approx(_capped_map_loss(z, y, a, c, caps), rel=1e-12, abs=1e-13)
    np.testing.assert_allclose(grad, _central(capped, p), rtol=1e-5, atol=1e-8)


def test_a_cap_at_its_bound_does_not_move_with_the_factor():
    z, y = _logits(seed=1)
    base = np.full((5, 5), 5e3)                 # times f >= 2: every cap at CAP_BOUNDS[1]
    np.fill_diagonal(base, 0.0)
    loss, grad = _MapLoss(z, y, base)(np.array([0.5, 1.0, math.log(3.0)]))
    assert grad[2] == 0.0 and np.isfinite(loss)


def _mp_capped_loss(d, log_caps, target):
    """_capped_loss at 50 digits: -sum_ij t_ij log softmax(-h)_ij / n, h = d / (1 + (d / L) ** q) ** (1 / q)."""
    q = mpmath.mpf(CAP_SHARPNESS)
    total = mpmath.mpf(0)
    for col in range(len(d[0])):
        h = [d[j][col] / (1 + (d[j][col] / mpmath.exp(log_caps[j][col])) ** q) ** (1 / q) for j in range(len(d))]
        lse = mpmath.log(mpmath.fsum(mpmath.exp(-v) for v in h))
        total += mpmath.fsum(target[j][col] * (v + lse) for j, v in enumerate(h))
    return total / len(d[0])


def test_the_capped_losss_derivatives_match_extended_precision():
    """by_lead and by_log_cap, the closed forms dh/dd and dh/dlog L, against mpmath's derivative of the loss."""
    d = np.array([[0.0, 3.0], [0.7, 0.0], [12.0, 1e-9], [0.0, 0.0]])        # (classes, decisions); a tie in column 2
    log_caps = np.log(np.array([[1.0, 2.5], [0.5, 1.0], [3.0, 0.05], [1.0, 1e3]]))
    target = np.array([[0.7, 0.1], [0.1, 0.7], [0.1, 0.1], [0.1, 0.1]])
    loss, by_lead, by_log_cap = _capped_loss(d, log_caps, target)
    mp = [[[mpmath.mpf(float(v)) for v in row] for row in a] for a in (d, log_caps, target)]
    assert loss == pytest.approx(float(_mp_capped_loss(*mp)), rel=1e-13)
    for i in range(4):
        for j in range(2):
            if d[i, j] == 0.0:
                continue                        # a lead of 0 is a winner's or a tie's: never moved by the fit

            def at(v, which, i=i, j=j):
                arrays = [[list(row) for row in a] for a in mp]
                arrays[which][i][j] = v
                return _mp_capped_loss(*arrays)

            assert by_lead[i, j] == pytest.approx(float(mpmath.diff(lambda v: at(v, 0), mp[0][i][j])), rel=1e-9,
                                                  abs=1e-15)
            assert by_log_cap[i, j] == pytest.approx(float(mpmath.diff(lambda v: at(v, 1), mp[1][i][j])), rel=1e-9,
                                                     abs=1e-15)


@pytest.mark.parametrize("rho", [0.0, 1e-3, 0.3, 0.9, 0.9995, 1.0])
def test_the_poolings_slope_matches_extended_precision(rho):
    """d g(n) / d rho, g = effective_windows(n, rho) / n, summed as a series, against mpmath's derivative of
    the definition (one-sided at 0 and 1)."""
    def g(n, r):
        return 1 / (1 + 2 * mpmath.fsum((1 - mpmath.mpf(k) / n) * r ** k for k in range(1, n)))

    side = 1 if rho == 0.0 else -1 if rho == 1.0 else 0
    want = [float(mpmath.diff(lambda r, n=n: g(n, r), mpmath.mpf(rho), direction=side)) for n in range(1, 31)]
    np.testing.assert_allclose(_pooling_slope(30, rho), want, rtol=1e-12, atol=1e-15)


def _runs(seed=7, count=40, classes=4):
    rng = np.random.default_rng(seed)
    labels = [int(k) for k in rng.integers(0, classes, size=count)]
    runs = []
    for label in labels:
        z = rng.normal(size=(int(rng.integers(1, 21)), classes)) + np.eye(classes)[label] * 1.2
        z += rng.normal(size=classes) * 0.8                           # windows of one run correlate
        runs.append(log_softmax(z, axis=1))
    return runs, labels


@pytest.mark.parametrize("p", [(0.3, 0.5), (0.05, 1.5), (0.97, 0.2), (0.5, 4.0), (1e-4, 0.0)])
def test_the_capped_poolings_loss_is_the_one_applied_and_its_gradient_the_finite_differences(p):
    runs, labels = _runs()
    prefixes = _Prefixes(runs)
    y = np.concatenate([np.full(len(r), lab) for r, lab in zip(runs, labels)])
    base = confusion_caps(np.argmax(prefixes.sums, axis=1), y, 4)
    loss_of = _PoolLoss(prefixes, y, base)
    p = np.array(p)
    caps = np.clip(base * math.exp(p[1]), *CAP_BOUNDS)
    np.fill_diagonal(caps, 0.0)
    t = _smoothed_targets(y, 4)
    loss, grad = loss_of(p)
    assert loss == pytest.approx(float(-(t * cap_gaps(prefixes.pooled(p[0]), caps)).sum(axis=1).mean()), rel=1e-12)
    np.testing.assert_allclose(grad, _central(loss_of, p, 1e-7), rtol=1e-5, atol=1e-8)


# -- the fits --------------------------------------------------------------------------------------

def _nelder_mead(loss, starts, bounds):
    """A plain search of the same loss: Nelder-Mead from each start, tightly, within the bounds (clipped)."""
    lo, hi = np.array(bounds).T

    def clipped(p):
        return loss(np.clip(p, lo, hi))

    best = min((minimize(clipped, np.array(s), method="Nelder-Mead",
                         options={"xatol": 1e-7, "fatol": 1e-12, "maxiter": 20000}) for s in starts),
               key=lambda r: r.fun)
    return best.fun


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_fits_reach_the_least_loss_a_plain_search_finds(seed):
    z, y = _logits(seed=seed)
    lo, hi = (math.log(v) for v in MAP_BOUNDS)
    flo, fhi = (math.log(v) for v in FACTOR_BOUNDS)
    starts = [(0.0, 0.0), (0.0, 2.3), (1.1, 3.4), (2.0, 0.0), (-1.0, 4.0)]
    a, c = fit_window_calibration(z, y)
    reference = _nelder_mead(lambda p: _plain_loss(z, y, *np.exp(p)), starts, [(lo, hi)] * 2)
    assert _plain_loss(z, y, a, c) <= reference + 1e-9
    base = confusion_caps(np.argmax(z, axis=1), y, z.shape[1])

    def capped(p):
        caps = np.clip(base * math.exp(p[2]), *CAP_BOUNDS)
        np.fill_diagonal(caps, 0.0)
        return _capped_map_loss(z, y, math.exp(p[0]), math.exp(p[1]), caps)

    reference = _nelder_mead(capped, [(*s, f) for s in starts for f in (0.0, 1.0)], [(lo, hi)] * 2 + [(flo, fhi)])
    for got in (fit_capped_window_calibration(z, y), fit_capped_window_calibration(z, y, start=(a, c))):
        assert _capped_map_loss(z, y, *got) <= reference + 1e-9


def test_the_fitted_map_lowers_the_held_out_log_loss_against_the_identity_and_keeps_winners():
    z, y = _logits(seed=3)
    zt, yt = _logits(seed=4)
    for cal in (fit_calibration(z, y, y), fit_calibration(z, y, y, caps=False)):
        lp = cal.log_posteriors(zt)
        assert log_loss(lp, yt) < log_loss(log_softmax(zt, axis=1), yt) - 1.0
        assert log_loss(cal.log_posteriors(z), y) < log_loss(log_softmax(z, axis=1), y) - 1.0
        np.testing.assert_array_equal(winner(lp), winner(zt))


def test_fitted_caps_still_bound_the_odds_between_each_pair():
    """The odds of a window's winner k against j never exceed exp(caps[k][j]), nor those of a contact its
    contact caps', and the factor stays within its bounds; the pair the network cannot tell apart stays near
    even odds (as test_calibration's caps test asks of it, with the fit of before)."""
    z, y, groups, folds = _confusable()
    cal = fit_calibration(z, y, groups, folds=folds)
    assert cal.caps is not None
    caps = np.array(cal.caps)
    lp = cal.log_posteriors(z)
    k = winner(lp)
    assert np.all(k >= 0)
    lead = lp[np.arange(len(lp)), k][:, None] - lp
    assert np.all(lead <= caps[k] + 1e-9)
    assert np.exp(lp[y < 2].max(axis=1)).mean() < 0.55
    base = confusion_caps(np.argmax(z, axis=1), y, 4)
    off = ~np.eye(4, dtype=bool)
    factor = caps[off] / base[off]
    assert np.all(factor >= FACTOR_BOUNDS[0] * (1 - 1e-9)) and np.all(factor <= FACTOR_BOUNDS[1] * (1 + 1e-9))
    assert np.ptp(factor) < 1e-9 * factor.max()                         # one factor for all
    runs, labels = _runs(seed=3)
    rho, contact_caps = fit_capped_pooling(runs, labels)
    for run in runs:
        for m in range(1, len(run) + 1):
            pooled = pool_log_posteriors(run[:m], rho, contact_caps)
            top = int(np.argmax(pooled))
            assert np.all(pooled[top] - pooled <= contact_caps[top] + 1e-9)


def test_the_capped_poolings_fit_is_the_least_loss_a_plain_search_finds():
    runs, labels = _runs(seed=11)
    rho0 = fit_pooling(runs, labels)
    rho, caps = fit_capped_pooling(runs, labels, plain_correlation=rho0)
    prefixes = _Prefixes(runs)
    y = np.concatenate([np.full(len(r), lab) for r, lab in zip(runs, labels)])
    base = confusion_caps(np.argmax(prefixes.pooled(rho0)[prefixes.lengths >= 2], axis=1),
                          y[prefixes.lengths >= 2], 4)
    loss_of = _PoolLoss(prefixes, y, base)
    flo, fhi = (math.log(v) for v in FACTOR_BOUNDS)
    off = ~np.eye(4, dtype=bool)
    got = loss_of(np.array([rho, math.log(float(np.median(caps[off] / base[off])))]))[0]
    reference = _nelder_mead(lambda p: loss_of(p)[0], [(rho0, 0.5), (0.5, 0.0), (0.9, 2.0)], [(0.0, 1.0), (flo, fhi)])
    assert got <= reference + 1e-9
    assert 0.0 <= rho <= 1.0


# -- stiff and bad held-out logits -----------------------------------------------------------------

def _stiff_cases():
    rng = np.random.default_rng(5)
    y = rng.integers(0, 4, 400)
    huge = rng.choice([-1e3, 1e3], size=(400, 4))
    huge[np.arange(400), y] = 1e3                                     # +-1e3, ties of the top too
    separable = rng.normal(0, 1, (400, 4))
    separable[np.arange(400), y] += 50.0
    return {
        "logits of +-1e3": (huge, y),
        "one class": (rng.normal(0, 5, (400, 4)) + np.eye(4)[0] * 20, np.zeros(400, dtype=int)),
        "all-equal logits": (np.full((400, 4), 3.0), y),
        "perfectly separable": (separable, y),
        "logits of 1e300": (np.where(np.eye(4, dtype=bool)[y], 1e300, -1e300), y),
    }


@pytest.mark.parametrize("case", sorted(_stiff_cases()))
def test_stiff_held_out_logits_give_a_finite_calibration_without_warnings(case):
    z, y = _stiff_cases()[case]
    groups = np.repeat(np.arange(20), 20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                               # no overflow, no NaN on the way
        for caps in (True, False):
            cal = fit_calibration(z, y, groups, caps=caps)
            lp = cal.log_posteriors(z)
            assert np.isfinite(lp).all() and np.isfinite(cal.pool(lp[:10])).all()
            assert MAP_BOUNDS[0] <= cal.temperature <= MAP_BOUNDS[1] * (1 + 1e-12)
            assert MAP_BOUNDS[0] <= cal.scale <= MAP_BOUNDS[1] * (1 + 1e-12)
            np.testing.assert_array_equal(winner(lp), winner(z))
            t = _smoothed_targets(y, z.shape[1])                       # the fit's loss: no worse than its first start
            start = Calibration(1.0, 1.0, 0.0).log_posteriors(z)
            assert -(t * lp).sum(axis=1).mean() <= -(t * start).sum(axis=1).mean() + 1e-12
            assert Calibration.from_dict(cal.to_dict(), InputError, z.shape[1]) == cal


@pytest.mark.parametrize("z, message", [
    (np.array([[1e306, 0.0], [0.0, 1.0]]), "cannot be calibrated"),
    (np.array([[np.nan, 0.0], [0.0, 1.0]]), "NaN or Inf"),
    (np.array([[np.inf, 0.0], [0.0, 1.0]]), "NaN or Inf"),
])
def test_logits_no_fit_can_take_are_refused_by_name(z, message):
    for fit in (fit_window_calibration, fit_capped_window_calibration):
        with pytest.raises(InputError, match=message):
            fit(z, np.array([0, 1]))
    with pytest.raises(InputError, match=message):
        fit_calibration(z, np.array([0, 1]), [0, 0])


def test_the_fit_is_the_same_for_the_same_windows():
    z, y = _logits(seed=8)
    assert fit_calibration(z, y, y) == fit_calibration(z.copy(), y.copy(), y)


def test_effective_windows_and_its_slope_agree():
    """The series' slope is that of effective_windows itself, the g the fit and a node use (away from rho = 1,
    where its closed form cancels and finite differences of it say nothing: the test above covers there)."""
    n = np.arange(1, 21, dtype=np.float64)
    for rho in (0.2, 0.8, 0.99):
        h = 1e-6
        numeric = (effective_windows(n, rho + h) / n - effective_windows(n, rho - h) / n) / (2 * h)
        np.testing.assert_allclose(_pooling_slope(20, rho), numeric, rtol=1e-5, atol=1e-7)
