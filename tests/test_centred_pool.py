"""collinearity.CentredPool: the t ratios and VIFs of column subsets from one growing QR factorisation."""

import numpy as np
import pytest

from identification.collinearity import CentredPool, term_identification


def _columns(rng: np.random.Generator, n: int, m: int) -> np.ndarray:
    """Columns of very different scales and means, as terms' values are (u^2 ~ 1e6 beside rates ~ 1)."""
    return rng.standard_normal((n, m)) * rng.uniform(0.01, 100, m) + rng.uniform(-50, 50, m)


def test_subsets_measure_as_their_own_columns_do_whatever_order_the_columns_joined_in():
    rng = np.random.default_rng(7)
    x = _columns(rng, 3000, 24)
    # a smooth residual: the effective rows (its autocorrelation) matter too
    y = x[:, :6] @ rng.standard_normal(6) + 0.05 * np.cumsum(rng.standard_normal(3000)) / 30
    pool = CentredPool(y)
    assert list(pool.add(x[:, :10])) == list(range(10))
    assert list(pool.add(x[:, 10:])) == list(range(10, 24))
    for _ in range(60):
        idx = list(rng.choice(24, int(rng.integers(1, 12)), replace=False))
        t, vif = pool.identification(idx)
        t0, vif0 = term_identification(x[:, idx], y)
        assert t == pytest.approx(t0, rel=1e-9) and vif == pytest.approx(vif0, rel=1e-9)


def test_tied_or_constant_columns_are_left_to_the_caller():
    rng = np.random.default_rng(8)
    x = _columns(rng, 2000, 6)
    tied = 2 * x[:, 0] - x[:, 1]  # exactly a combination of two pooled columns
    constant = np.full(2000, 3.0)
    y = x @ rng.standard_normal(6) + rng.standard_normal(2000)
    pool = CentredPool(y)
    pool.add(np.column_stack([x, tied, constant]))
    assert pool.identification([0, 1, 6]) is None  # VIF beyond the centred path's: the general path's call
    assert pool.identification([6, 7]) is None  # a column that does not vary
    t, vif = pool.identification([0, 6])  # the tied column beside only one of its members: measurable
    t0, vif0 = term_identification(np.column_stack([x[:, 0], tied]), y)
    assert abs(t - t0) <= 1e-9 * t0 and abs(vif - vif0) <= 1e-9 * vif0
    assert pool.identification([0, 0]) is None  # a repeated column: tied exactly


def test_an_exact_fit_has_infinite_t_ratios():
    rng = np.random.default_rng(9)
    x = _columns(rng, 500, 3)
    y = x @ np.array([1.0, -2.0, 0.5])
    pool = CentredPool(y)
    pool.add(x)
    t, vif = pool.identification([0, 1, 2])
    assert t > 1e6 and np.isfinite(vif)
