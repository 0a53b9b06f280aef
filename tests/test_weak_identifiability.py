"""t ratios on weak-form rows: their residuals are averages over overlapping test-function windows, correlated
up to the windows' overlap (weak_form.overlap_lag) and not beyond, and the effective sample size sums the
residual's autocorrelations up to it (collinearity.effective_rows). AR(1) extrapolated from the lag-1
correlation (0.97-0.98 on 0.4 s windows every 0.02 s) counted ~8x too few independent rows, so a null term's
t came out ~3x too small and a true term 9 standard errors away from zero was called not identifiable."""

from __future__ import annotations

import numpy as np

from identification.collinearity import effective_rows, term_t_ratios
from identification.weak_form import WeakSettings, overlap_lag, weak_operator

RATE = 250.0  # Hz, the IMU's


def _weak_flight(seed: int, seconds: float = 60.0, coef: float = 0.0, noise: float = 0.1):
    """Weak rows (columns [1, x], y) of y = coef x + white noise (noise std), x a smooth excitation."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / RATE)
    phases = rng.uniform(0, 2 * np.pi, 3)
    x = sum(np.sin(2 * np.pi * f * t + p) for f, p in zip((0.13, 0.41, 0.97), phases, strict=True))
    y = coef * x + noise * rng.standard_normal(len(t))
    op = weak_operator(t, WeakSettings())
    cols = np.asarray(op @ np.column_stack([np.ones_like(x), x]))
    return cols, op @ y, overlap_lag(op)


def test_overlap_lag_is_the_window_over_the_stride():
    t = np.arange(0.0, 20.0, 1.0 / RATE)
    assert overlap_lag(weak_operator(t, WeakSettings())) == 20  # 2 x 50 samples / 5 per stride
    assert overlap_lag(weak_operator(t, WeakSettings(half_window_s=0.1))) == 10
    assert overlap_lag(weak_operator(t, WeakSettings(stride_s=0.4))) == 1  # 0.4 s apart: the ends touch
    assert overlap_lag(weak_operator(t, WeakSettings(stride_s=0.5))) == 0  # no shared sample


def test_a_null_term_on_weak_rows_has_a_standard_t_with_the_overlap_and_a_shrunken_one_with_ar1():
    by_overlap, by_ar1 = [], []
    for seed in range(120):
        cols, y, lag = _weak_flight(seed)
        by_overlap.append(term_t_ratios(cols, y, lag)[0][1])
        by_ar1.append(term_t_ratios(cols, y)[0][1])
    # the t of a term whose true coefficient is 0 is |N(0, 1)|: RMS 1
    rms_overlap = float(np.sqrt(np.mean(np.square(by_overlap))))
    rms_ar1 = float(np.sqrt(np.mean(np.square(by_ar1))))
    assert 0.75 < rms_overlap < 1.35
    assert rms_ar1 < 0.5  # AR(1) overstates the correlation length: every t ~3x too small
    assert max(by_overlap) < 5.0  # the pick's min_t still rejects noise


def test_a_term_nine_standard_errors_from_zero_is_identified_only_with_the_overlap():
    # coefficient 0.006 of the excitation under 0.1 white noise, 60 s at 250 Hz: ~9 standard errors (the
    # weak rows' residual ~0.013, ~270 independent windows of 2980)
    cols, y, lag = _weak_flight(7, coef=0.006)
    t_overlap = term_t_ratios(cols, y, lag)[0][1]
    t_ar1 = term_t_ratios(cols, y)[0][1]
    assert t_overlap > 5.0 > t_ar1


def test_effective_rows_stay_between_one_and_n():
    rng = np.random.default_rng(3)
    white = rng.standard_normal(1000)
    assert 850 < effective_rows(white, 20) <= 1000
    assert effective_rows(np.diff(white), 20) == 999  # anti-correlated: capped at N
    assert effective_rows(np.ones(50), 20) == 50.0
    assert effective_rows(np.cumsum(white), 20) < 1000 / 20  # a random walk: far fewer
