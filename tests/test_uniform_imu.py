"""IMU samples with skipped samples and jittering times go onto one uniform grid before differentiation."""

from __future__ import annotations

import numpy as np

from identification.readers import uniform_imu
from identification.targets import contiguous_runs, nominal_step


def test_skipped_samples_and_mid_interval_jitter_give_one_uniform_run():
    # PX4 at a high speed-up: 250 Hz samples, about 2 % skipped; each stamped at the middle of its
    # integration interval, so a skipped sample shifts the next one by half a step
    rng = np.random.default_rng(3)
    ends = np.arange(1, 5001) * 0.004
    keep = rng.random(len(ends)) > 0.02
    keep[:2] = True
    ends = ends[keep]
    t = ends - 0.5 * np.diff(np.concatenate(([0.0], ends)))
    values = np.column_stack([np.sin(2.0 * t), np.cos(3.0 * t)])
    assert len(contiguous_runs(t, nominal_step(t))) > 20  # as logged: no differentiator spans it
    notes: list[str] = []
    grid, out = uniform_imu(t, values, notes)
    assert len(contiguous_runs(grid, nominal_step(grid))) == 1
    assert np.allclose(np.diff(grid), np.diff(grid)[0])
    ok = np.isfinite(out).all(axis=1)
    assert ok.mean() > 0.99
    assert np.abs(out[ok, 0] - np.sin(2.0 * grid[ok])).max() < 1e-3  # linear interpolation of a smooth signal
    assert notes and "resampled to a uniform" in notes[0]


def test_uniform_samples_are_left_as_they_are():
    t = np.arange(1000) * 0.004
    values = np.sin(t)[:, None]
    notes: list[str] = []
    grid, out = uniform_imu(t, values, notes)
    assert grid is t and out is values and not notes


def test_one_nan_angle_is_a_local_gap_not_the_rest_of_the_log():
    # np.unwrap sums its corrections: one NaN sample made every later angle NaN
    from identification.readers import Stream

    t = np.arange(0.0, 10.0, 0.1)
    yaw = np.where(t < 5.0, 3.0, -3.0)  # wraps through +-pi at 5 s
    yaw[20] = np.nan
    values, _ = Stream("ATT", t, yaw, kind="angle").resample(np.arange(0.0, 9.9, 0.02))
    lost = ~np.isfinite(values[:, 0])
    assert 0 < lost.sum() <= 10  # the intervals on either side of t = 2.0 s only
    assert np.abs(values[-10:, 0] + 3.0).max() < 1e-9
