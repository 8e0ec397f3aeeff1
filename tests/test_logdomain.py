"""supramodal.logdomain: logsumexp and log_softmax against 50-digit arithmetic (mpmath) and against scipy's."""

from __future__ import annotations

import mpmath
import numpy as np
import pytest
from scipy import special

from supramodal.logdomain import log_softmax, logsumexp


def _rows(rng) -> list[np.ndarray]:
    """Rows a decision meets and rows that break a naive exp: huge, tiny, wide, tied, with -inf terms."""
    rows = [rng.normal(size=k) * s for k in (1, 2, 8, 50) for s in (1e-3, 1.0, 30.0, 700.0)]
    rows += [np.array([1000.0, 1.0]), np.array([-1000.0, -1001.0, -1e4]), np.array([3.0, 3.0, 3.0]),
             np.array([1e308, 1e308]), np.array([-745.0, 0.0]), np.array([-np.inf, 0.5, 2.0]),
             np.array([5e-324, 0.0, -5e-324])]
    return rows


def _exact_logsumexp(row) -> mpmath.mpf:
    with mpmath.workdps(50):
        return mpmath.log(mpmath.fsum(mpmath.exp(mpmath.mpf(float(v))) for v in row if v != -np.inf))


def test_logsumexp_and_log_softmax_against_fifty_digits():
    rng = np.random.default_rng(11)
    for row in _rows(rng):
        exact = _exact_logsumexp(row)
        got = logsumexp(row)
        assert abs(mpmath.mpf(float(got)) - exact) <= 4e-16 * max(1.0, abs(exact)), (row, got, exact)
        for v, g in zip(row, log_softmax(row)):
            if v == -np.inf:
                assert g == -np.inf
                continue
            want = mpmath.mpf(float(v)) - exact
            assert abs(mpmath.mpf(float(g)) - want) <= 4e-16 * max(1.0, abs(want), abs(v)), (row, g, want)


def test_as_scipy_along_any_axis_with_and_without_kept_axes():
    rng = np.random.default_rng(12)
    x = rng.normal(size=(4, 5, 6)) * 40.0
    x[1, 2, :] = -np.inf                          # a row of no terms: -inf, as scipy gives it
    x[2, :, 3] = np.inf
    with np.errstate(invalid="ignore"):
        for axis in (0, 1, 2, -1):
            for keep in (False, True):
                np.testing.assert_allclose(logsumexp(x, axis=axis, keepdims=keep),
                                           special.logsumexp(x, axis=axis, keepdims=keep), rtol=1e-14, atol=0)
            np.testing.assert_allclose(log_softmax(x, axis=axis), special.log_softmax(x, axis=axis), rtol=1e-14,
                                       atol=1e-300)
    assert logsumexp(np.full(3, -np.inf)) == -np.inf


@pytest.mark.parametrize("n", [1, 7, 64])
def test_a_log_softmax_row_sums_to_one_and_keeps_its_order(n):
    rng = np.random.default_rng(n)
    x = rng.normal(size=(10, n)) * 100.0
    lp = log_softmax(x, axis=1)
    assert np.all(lp <= 0.0)
    np.testing.assert_allclose(np.exp(lp).sum(axis=1), 1.0, rtol=1e-13)
    assert np.array_equal(np.argsort(lp, axis=1, kind="stable"), np.argsort(x, axis=1, kind="stable"))
