"""The discovery engine's rules for targets whose errors sit on a few rows, and the replacement screening.

Small seeded synthetic data with a known answer: robust t ratios (least absolute error), Huber row weights,
weighted least squares, and the replacement of a term by a near-collinear truer feature.
"""

from __future__ import annotations

import numpy as np

from identification.collinearity import robust_scale, term_t_ratios
from identification.discovery import _standardized
from identification.replacement import replacements
from identification.robust_weights import HUBER_K, huber_weights
from identification.sparse import LeastSquaresProblem, fitted_identification


def _spiky_rows(seed: int, n: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Columns (1, x1, x2) and y = 2 x1 + 0.002 x2 + 1e-4 noise, with 2 % of rows off by +-0.5 (kinks)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 2))
    y = 2.0 * x[:, 0] + 0.002 * x[:, 1] + 1e-4 * rng.normal(size=n)
    spikes = rng.choice(n, size=n // 50, replace=False)
    y[spikes] += rng.choice([-0.5, 0.5], size=spikes.size)
    return np.hstack([np.ones((n, 1)), x]), y


def test_robust_t_sees_a_small_term_that_a_few_large_errors_hide_from_least_squares():
    cols, y = _spiky_rows(seed=0)
    t_ls, _ = term_t_ratios(cols, y)
    problem = LeastSquaresProblem(cols, y)
    active = np.ones(3, dtype=bool)
    coef = problem.l1_refit(active, problem.solve(active), 30)
    t_rob, _ = term_t_ratios(cols, y, coef, robust=True)
    assert t_ls[2] < 5.0 < 100.0 < t_rob[2]  # x2: hidden by the spikes' RMS, pinned by the typical rows
    assert abs(coef[2] - 0.002) < 0.02 * 0.002  # the absolute-error fit has it within 2 %
    # the engines' helper gives the same weakest t for the absolute loss, least squares' for 'squared'
    assert fitted_identification(cols, y, "absolute", 30)[0] > 100.0
    assert fitted_identification(cols, y, "squared")[0] < 5.0


def test_robust_t_matches_least_squares_for_normal_errors():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(20000, 1))
    y = 0.01 * x[:, 0] + rng.normal(size=20000)
    cols = np.hstack([np.ones((20000, 1)), x])
    t_ls, _ = term_t_ratios(cols, y)
    problem = LeastSquaresProblem(cols, y)
    coef = problem.l1_refit(np.ones(2, bool), problem.solve(np.ones(2, bool)), 30)
    t_rob, _ = term_t_ratios(cols, y, coef, robust=True)
    # LAD's standard error is sqrt(pi/2) x least squares' for normal errors: t about 0.8 x, not larger
    assert 0.6 < t_rob[1] / t_ls[1] < 1.0
    assert abs(robust_scale(rng.normal(size=200000)) - np.sqrt(np.pi / 2)) < 0.02


def test_huber_weights_down_weight_only_the_large_residuals():
    rng = np.random.default_rng(2)
    r = rng.normal(size=5000)
    r[:10] = 40.0
    w = huber_weights(r)
    assert w is not None and np.all((w > 0) & (w <= 1))
    assert np.all(w[:10] < 0.05)  # k s / |r| with s ~ 1
    assert np.isclose(w[:10], HUBER_K * 1.0 / 40.0, rtol=0.1).all()
    assert np.mean(w[10:] == 1.0) > 0.75  # within k s: full weight (82 % of normal rows)
    assert huber_weights(np.zeros(100)) is None  # an exact fit: nothing to weigh


def test_weighted_least_squares_is_the_fit_without_zero_weight_rows():
    cols, y = _spiky_rows(seed=3)
    keep = np.ones(len(y), dtype=bool)
    keep[::7] = False
    active = np.ones(3, dtype=bool)
    weighted = LeastSquaresProblem(cols, y, keep.astype(float)).solve(active)
    plain = LeastSquaresProblem(cols[keep], y[keep]).solve(active)
    assert np.allclose(weighted, plain, rtol=1e-9, atol=1e-12)
    ones = LeastSquaresProblem(cols, y, np.ones(len(y))).solve(active)
    assert np.allclose(ones, LeastSquaresProblem(cols, y).solve(active), rtol=1e-9, atol=1e-12)


def test_replacement_finds_the_rotor_sum_product_a_rate_stands_for():
    # physics: y = 2e-6 w (u1 + u2 + u3 + u4) + 0.3 v, the rotor sum near hover (+-5 %); a model that holds
    # w in place of w * sum is challenged by the feature, and a model with the true terms is left alone
    rng = np.random.default_rng(4)
    n = 3000
    u = 550.0 + 25.0 * rng.normal(size=(n, 4))
    w, v = rng.normal(size=n), rng.normal(size=n)
    total = u.sum(axis=1)
    F = np.column_stack([w, v, w * total, w * u[:, 0] ** 2, v * total, u[:, 0], w * np.abs(v)])
    y = 2e-6 * w * total + 0.3 * v
    Z = _standardized(F)
    assert replacements(F, Z, y, terms=[0, 1], exclude=[0, 1]) == [2]
    assert replacements(F, Z, y, terms=[2, 1], exclude=[0, 1, 2]) == []
