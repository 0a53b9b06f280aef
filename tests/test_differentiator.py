"""The smoothing differentiator on a known signal with 250 Hz white noise: it beats the raw stencil by far,
knows its own error and the noise level, and stays exact when there is no noise."""

from __future__ import annotations

import numpy as np
import pytest

from identification.targets import choose_savgol, finite_runs, five_point_derivative, stream_derivative

DT = 0.004  # s, 250 Hz like the SITL's IMU


def _signal(seconds: float = 20.0):
    """Two sines (rad/s, like a gyro axis) and their exact derivative (rad/s^2) on a 250 Hz grid."""
    t = np.arange(int(seconds / DT)) * DT
    y = np.sin(2 * np.pi * 1.3 * t) + 0.3 * np.sin(2 * np.pi * 4.7 * t + 0.4)
    w1, w2 = 2 * np.pi * 1.3, 2 * np.pi * 4.7
    dy = w1 * np.cos(w1 * t) + 0.3 * w2 * np.cos(w2 * t + 0.4)
    return t, y, dy


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.sqrt(np.mean((a[ok] - b[ok]) ** 2)))


@pytest.mark.parametrize("sigma", [0.003, 0.01, 0.03])
def test_noisy_derivative_is_far_closer_to_the_truth_than_the_stencil(sigma):
    t, y, dy = _signal()
    noisy = y + sigma * np.random.default_rng(int(sigma * 1e4)).standard_normal(len(t))
    raw = _rms(five_point_derivative(noisy, DT), dy)
    smooth = _rms(stream_derivative(t, noisy[:, None])[:, 0], dy)
    assert raw == pytest.approx(sigma / DT * np.sqrt(65 / 72), rel=0.1)  # the stencil's noise gain
    assert smooth < 0.1 * raw, (smooth, raw)
    choice = choose_savgol(t, noisy, DT, deriv=1)
    assert choice.noise == pytest.approx(sigma, rel=0.15)  # the noise floor it estimated
    assert choice.window > 5
    assert 0.5 * smooth < choice.error < 2.0 * smooth  # it knows its own error


def test_without_noise_the_derivative_stays_exact():
    t, y, dy = _signal(8.0)
    choice = choose_savgol(t, y, DT, deriv=1)
    assert choice.noise < 3e-4  # 10x below the smallest noise above (a smooth signal's third differences)
    assert choice.polyorder == 4 and choice.window <= 11  # high order, short: little to smooth
    assert _rms(stream_derivative(t, y[:, None])[:, 0], dy) < 1e-3 * np.sqrt(np.mean(dy**2))


@pytest.mark.parametrize("where", ["last", "middle"])
def test_a_gaps_nan_does_not_blind_the_choice_to_the_signal(where):
    # A resampled IMU stream carries NaN across its gaps. A Welch segment holding one NaN made every bin NaN,
    # the signal's spectrum read as empty and the widest window won: on a real PX4 flight whose length put
    # its one NaN (the last sample) inside the last segment, wx' came out smoothed over 362 ms.
    t, y, _ = _signal(256 * 0.004 + 128 * 0.004 * 30)  # 256 + 128 k: a segment ends on the last
    noisy = y + 0.003 * np.random.default_rng(5).standard_normal(len(t))
    clean = choose_savgol(t, noisy, DT, deriv=1)
    gapped = noisy.copy()
    gapped[-1 if where == "last" else len(t) // 2] = np.nan
    choice = choose_savgol(t, gapped, DT, deriv=1)
    assert (choice.window, choice.polyorder) == (clean.window, clean.polyorder)
    assert choice.error == pytest.approx(clean.error, rel=0.1)


def test_without_a_spectrum_it_does_not_smooth():
    t, y, _ = _signal(0.2)  # 50 samples: too short for a spectrum
    choice = choose_savgol(t, y + 0.01 * np.random.default_rng(1).standard_normal(len(t)), DT, deriv=1)
    assert (choice.window, choice.polyorder) == (5, 4)  # the 5-point stencil, not the widest window


def test_finite_runs_split_at_nan_and_at_time_gaps():
    t = np.concatenate((np.arange(10) * DT, 1.0 + np.arange(5) * DT))
    y = np.ones(len(t))
    y[[0, 4, 5]] = np.nan
    assert [(r.start, r.stop) for r in finite_runs(t, DT, y)] == [(1, 4), (6, 10), (10, 15)]


def test_short_scraps_between_gaps_do_not_outvote_the_noise_estimate():
    # Three logger dropouts 16 samples apart leave two 10-sample scraps between long runs: too short for a
    # noise estimate of their own (0), they halved a median over runs and the shortest window won.
    t, y, _ = _signal(30.0)
    noisy = y + 0.01 * np.random.default_rng(1).standard_normal(len(t))
    gapped = noisy.copy()
    for a in (5000, 5016, 5032):
        gapped[a : a + 6] = np.nan
    clean, choice = choose_savgol(t, noisy, DT, deriv=1), choose_savgol(t, gapped, DT, deriv=1)
    assert choice.noise == pytest.approx(0.01, rel=0.1)
    assert (choice.window, choice.polyorder) == (clean.window, clean.polyorder)


def test_the_derivative_is_not_drawn_across_a_hole():
    # A table's empty cells (a motion-capture dropout) are NaN: the rows beside the hole must get their own
    # window's derivative or none, never a straight line from one side of the hole to the other.
    t = np.arange(0.0, 20.0, 0.01)
    y = np.sin(2 * np.pi * 3.0 * t) + 0.002 * np.random.default_rng(0).standard_normal(len(t))
    dy = 2 * np.pi * 3.0 * np.cos(2 * np.pi * 3.0 * t)
    hole = (t >= 10.0) & (t < 10.05)
    y[hole] = np.nan
    d = stream_derivative(t, y[:, None])[:, 0]
    assert not np.isfinite(d[hole]).any()
    ok = np.isfinite(d)
    assert ok.sum() > 0.95 * len(t)
    far = np.abs(t - 10.025) > 0.5
    assert np.max(np.abs(d - dy)[ok]) < 5.0 * np.max(np.abs(d - dy)[ok & far])
