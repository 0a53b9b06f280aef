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
