"""Generalised least squares on weak rows (identification.weak_noise): the whitener, its standard errors and
the refit that uses it, on synthetic rows with a known answer (seeded, fast)."""

from __future__ import annotations

import numpy as np
import pytest
import sympy

from identification.candidate import Candidate
from identification.collinearity import term_t_ratios
from identification.refit import refit_rows
from identification.weak_form import WeakSettings, overlap_lag, weak_operator, weak_rows
from identification.weak_noise import (
    STEP_DIFFERENCE,
    STEP_MEAN,
    WHITE,
    raw_noise_operator,
    specification_test,
    weak_whitener,
)

DT = 0.004


def _closed_loop(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A rate under a P controller that reads a noisy gyro: w' = -c w + b u, u = -k (w + n) + r.

    Returns (t s, the true rate w, the input u, the gyro's white noise n (n + 1 samples)). The rows are step
    intervals: the target is the gyro's difference over a step, as on our .tlog; the controller's use of the
    noisy gyro ties u to the rows' noise, as a rate loop does.
    """
    rng = np.random.default_rng(seed)
    c, b, k = 0.05, 40.0, 0.08
    r = np.repeat(rng.choice([-1.0, 1.0], size=n // 50 + 1), 50)[:n] * 0.02  # PRBS reference
    noise = rng.normal(0.0, 0.01, n + 1)
    w = np.zeros(n + 1)
    u = np.zeros(n)
    for i in range(n):
        u[i] = -k * (w[i] + noise[i]) + r[i]
        w[i + 1] = w[i] + DT * (-c * w[i] + b * u[i])
    return np.arange(n) * DT, w, u, noise


def _rows(t, w, u, noise):
    """Regressors (-w at the step's start is the damping's column; u the input's) and the gyro targets."""
    a = np.column_stack((w[:-1], u))
    y = np.diff(w + noise) / DT
    return a, y


def test_raw_noise_operator_shares_samples_within_a_run_only():
    t = np.r_[np.arange(5) * DT, 1.0 + np.arange(3) * DT]  # two runs: a gap after the fifth row
    b = raw_noise_operator(t, None, STEP_DIFFERENCE).toarray()
    assert b.shape == (8, 6 + 4)  # each run has its rows + 1 samples
    assert np.allclose(b[0, :2], [-1, 1]) and np.allclose(b[1, 1:3], [-1, 1])
    assert not np.any((b[:5] != 0) & (b[5:].sum(axis=0, keepdims=True) != 0))  # runs share nothing
    two = raw_noise_operator(np.r_[np.arange(4) * DT, np.arange(4) * DT], np.r_[[0] * 4, [1] * 4], STEP_MEAN)
    assert two.shape == (8, 10)


def test_a_steps_node_rows_share_its_noise():
    """Node rows (two per step, one time: Dataset.at_step_nodes) carry their step's raw target, so its noise:
    the weak rows' covariance and whitener are those of the steps' rows, flight by flight."""
    t = np.r_[np.arange(300) * DT, 2.0 + np.arange(200) * DT]
    flight = np.r_[[0] * 300, [1] * 200]
    b = raw_noise_operator(t, flight, STEP_DIFFERENCE)
    b2 = raw_noise_operator(np.repeat(t, 2), np.repeat(flight, 2), STEP_DIFFERENCE)
    assert np.allclose(b2.toarray()[::2], b.toarray()) and np.allclose(b2.toarray()[1::2], b.toarray())
    v = weak_rows(t, flight, WeakSettings())
    v2 = weak_rows(np.repeat(t, 2), np.repeat(flight, 2), WeakSettings())
    w, w2 = (weak_whitener(v, t, flight, STEP_DIFFERENCE),
             weak_whitener(v2, np.repeat(t, 2), np.repeat(flight, 2), STEP_DIFFERENCE))
    assert w is not None and w2 is not None and np.allclose(w2.factor, w.factor)


@pytest.mark.parametrize("stencil", [STEP_DIFFERENCE, STEP_MEAN, WHITE])
def test_whitened_weak_noise_is_white_with_one_variance(stencil):
    rng = np.random.default_rng(3)
    t = np.arange(4000) * DT
    v = weak_operator(t, WeakSettings())
    b = raw_noise_operator(t, None, stencil)
    white = weak_whitener(v, t, None, stencil)
    assert white is not None and white.rows == v.shape[0]
    draws = np.array([white.apply(v @ (b @ rng.normal(size=b.shape[1]))) for _ in range(40)])
    assert abs(draws.var() - 1.0) < 0.05
    lag1 = np.mean(draws[:, 1:] * draws[:, :-1])
    assert abs(lag1) < 0.05  # before whitening, neighbouring weak rows share most of their samples
    plain = np.array([v @ (b @ rng.normal(size=b.shape[1])) for _ in range(40)])
    assert abs(np.mean(plain[:, 1:] * plain[:, :-1]) / plain.var()) > 0.5


def test_gls_pins_a_closed_loop_damping_that_weak_least_squares_does_not():
    """The damping (-c w) is small beside the input's torque, and the controller ties u to w: over noise
    draws, the generalised fit's spread is well under the ordinary one's, and its standard error matches
    its spread."""
    c_true = 0.05
    ols, gls, ses, passed = [], [], [], []
    for seed in range(12):
        t, w, u, noise = _closed_loop(6000, seed)
        a, y = _rows(t, w, u, noise)
        v = weak_rows(t, None, WeakSettings())
        aw, yw = v @ a, v @ y
        ols.append(-np.linalg.lstsq(aw, yw, rcond=None)[0][0] / c_true - 1)
        test = specification_test([(aw, yw, weak_whitener(v, t, None, STEP_DIFFERENCE))])
        assert np.allclose(test.plain, np.linalg.lstsq(aw, yw, rcond=None)[0])
        gls.append(-test.gls[0] / c_true - 1)
        ses.append((test.se_gls[0] / c_true, test.se_plain[0] / c_true))
        passed.append(test.generalised)
    ses = np.array(ses)
    assert np.std(gls) < 0.5 * np.std(ols)
    assert abs(np.mean(gls)) < 3 * np.std(gls) / np.sqrt(len(gls))  # no bias beyond its spread
    assert 0.6 < np.median(ses[:, 0]) / np.std(gls) < 1.6  # each fit's standard error matches its spread
    assert 0.6 < np.median(ses[:, 1]) / np.std(ols) < 1.6
    assert sum(passed) >= 10  # a right model: Hausman's test at 1 % rejects about one draw in a hundred


def test_the_picks_t_ratios_under_the_stated_noise_match_the_weak_fits_spread():
    """The pick's t ratio of a term on weak rows (collinearity.term_t_ratios) with the rows' whitener: the
    standard error it implies, |c| / t, matches the weak least-squares estimate's spread over noise draws
    (the residual's effective sample size, without the whitener, has no such guarantee under blue noise)."""
    c_true = 0.05
    est, se = [], []
    for seed in range(12):
        t, w, u, noise = _closed_loop(6000, seed)
        a, y = _rows(t, w, u, noise)
        v = weak_rows(t, None, WeakSettings())
        cols, yw = np.column_stack((np.ones(v.shape[0]), v @ a)), v @ y  # the constant, as the pick fits it
        coef = np.linalg.lstsq(cols, yw, rcond=None)[0]
        ratios, vif = term_t_ratios(cols, yw, overlap_lag(v), weak_whitener(v, t, None, STEP_DIFFERENCE))
        assert np.isnan(ratios[0]) and np.isnan(vif[0])  # the constant is fitted, not measured
        est.append(-coef[1] / c_true)
        se.append(abs(coef[1]) / ratios[1] / c_true)
    assert 0.7 < np.median(se) / np.std(est) < 1.4
    t_short = np.arange(3000) * DT  # a whitener of other rows: the effective sample size is used
    short = weak_whitener(weak_rows(t_short, None, WeakSettings()), t_short, None, STEP_DIFFERENCE)
    assert np.allclose(term_t_ratios(cols, yw, overlap_lag(v), short)[0][1:],
                       term_t_ratios(cols, yw, overlap_lag(v))[0][1:])


def test_the_specification_test_rejects_a_systematic_low_frequency_error():
    """A slow drift in the targets that no term holds: the generalised fit, weighing the low frequencies,
    takes it in and moves away from the weak rows' own fit by far more than their covariances allow."""
    t, w, u, noise = _closed_loop(6000, 0)
    a, y = _rows(t, w, u, noise)
    v = weak_rows(t, None, WeakSettings())
    white = weak_whitener(v, t, None, STEP_DIFFERENCE)
    clean = specification_test([(v @ a, v @ y, white)])
    drift = specification_test([(v @ a, v @ (y + 0.05 * np.sin(2 * np.pi * t / 7.0)), white)])
    assert clean.generalised and not drift.generalised
    assert drift.p_value < 1e-6


def test_refit_rows_uses_the_whiteners_and_reports_the_loss_on_the_plain_rows():
    t, w, u, noise = _closed_loop(6000, 0)
    a, y = _rows(t, w, u, noise)
    X = np.zeros((len(y), 16))
    X[:, 9], X[:, 12] = w[:-1], u  # wx and u1 in the 16 variables
    wx, u1 = sympy.symbols("wx u1")
    chosen = Candidate(-0.04 * wx + 39.0 * u1, 3, 0.0, "test")
    half = len(y) // 2
    parts = [(X[:half], y[:half], weak_rows(t[:half], None, WeakSettings())),
             (X[half:], y[half:], weak_rows(t[half:], None, WeakSettings()))]
    whiteners = [weak_whitener(op, tt, None, STEP_DIFFERENCE) for (_, _, op), tt in
                 zip(parts, (t[:half], t[half:]), strict=True)]
    refit = refit_rows(chosen, parts, "squared", 0, 0, whiteners)
    plain = refit_rows(chosen, parts, "squared", 0, 0)
    halves = (slice(0, half), slice(half, None))
    direct = np.concatenate([wh.apply(op @ np.column_stack((-X[s, 9], X[s, 12])))
                             for wh, (_, _, op), s in zip(whiteners, parts, halves, strict=True)])
    target = np.concatenate([wh.apply(op @ y[s])
                             for wh, (_, _, op), s in zip(whiteners, parts, halves, strict=True)])
    expected = np.linalg.lstsq(direct, target, rcond=None)[0]
    got = float(refit.expression.coeff(wx))
    assert got == pytest.approx(-expected[0], rel=1e-6)
    assert got != pytest.approx(float(plain.expression.coeff(wx)), rel=1e-3)
    yw = np.concatenate([op @ y[s] for (_, _, op), s in zip(parts, halves, strict=True)])
    assert refit.train_loss == pytest.approx(np.sqrt(np.mean((yw - np.concatenate(
        [op @ refit.evaluate(xx) for xx, _, op in parts])) ** 2)), rel=1e-6)  # RMSE on the weak rows
    # a part without a whitener: ordinary least squares for all, not a mix of scales
    mixed = refit_rows(chosen, parts, "squared", 0, 0, [whiteners[0], None])
    assert float(mixed.expression.coeff(wx)) == pytest.approx(float(plain.expression.coeff(wx)), rel=1e-9)


def test_a_stacked_whitener_whitens_each_roles_rows_as_its_own_does():
    """Two roles' weak rows one after the other (fit, then pick): their noises are independent, so the
    stacked whitener is block-diagonal and whitens each block as that role's whitener does."""
    from identification.weak_noise import stacked_whitener

    rng = np.random.default_rng(3)
    t1, t2 = np.arange(900) * DT, 10.0 + np.arange(500) * DT
    w1 = weak_whitener(weak_operator(t1, WeakSettings(half_window_s=0.05, stride_s=0.02)), t1, None,
                       STEP_DIFFERENCE)
    w2 = weak_whitener(weak_operator(t2, WeakSettings(half_window_s=0.03, stride_s=0.02)), t2, None,
                       STEP_MEAN)
    both = stacked_whitener([w1, w2])
    assert both.rows == w1.rows + w2.rows and both.bandwidth == max(w1.bandwidth, w2.bandwidth)
    a = rng.standard_normal((both.rows, 2))
    np.testing.assert_allclose(both.apply(a), np.vstack([w1.apply(a[: w1.rows]), w2.apply(a[w1.rows:])]),
                               rtol=1e-10, atol=1e-12)
    lower = both.lower().toarray()
    assert not np.any(lower[w1.rows:, : w1.rows])  # nothing ties the pick rows' noise to the fit rows'
    assert stacked_whitener([w1, None]) is None and stacked_whitener([]) is None
