"""Control allocation: f <-> rotor speeds, clipping to [0, w_max], saturation priorities."""

from __future__ import annotations

import math

import numpy as np

from controller.allocation import MIX, allocate, f_from_speeds, squared_speeds

W_MAX = 1006.6


def test_mixing_matches_design_contract():
    u = np.array([100.0, 200.0, 300.0, 400.0])
    q = u**2
    f = f_from_speeds(u)
    assert np.allclose(f, [q.sum(), -q[0] + q[1] + q[2] - q[3], q[0] - q[1] + q[2] - q[3],
                           q[0] + q[1] - q[2] - q[3]])
    assert np.allclose(MIX @ MIX.T, 4 * np.eye(4))
    assert np.allclose(squared_speeds(f), q)


def test_round_trip_inside_the_limits():
    rng = np.random.default_rng(0)
    for _ in range(200):
        u = rng.uniform(0.0, W_MAX, 4)
        a = allocate(f_from_speeds(u), W_MAX)
        assert not a.saturated and a.stage == "none"
        assert np.allclose(a.speeds, u, rtol=1e-12, atol=1e-9)
        assert np.allclose(a.applied, f_from_speeds(u))


def test_too_much_thrust_is_clipped_to_w_max():
    a = allocate([4 * W_MAX**2 * 1.5, 0.0, 0.0, 0.0], W_MAX)
    assert a.saturated
    assert np.allclose(a.speeds, W_MAX)


def test_negative_requests_never_give_negative_squares_or_nan():
    a = allocate([-1e5, 3e4, -2e4, 1e3], W_MAX)
    assert a.saturated
    assert np.all(np.isfinite(a.speeds)) and np.all(a.speeds >= 0.0)
    assert np.all(squared_speeds(a.applied) >= -1e-6)


def test_yaw_gives_way_first_and_roll_pitch_are_kept():
    hover = 4 * 557.0**2
    f = [hover, 2e5, -1e5, 1.5e6]  # yaw asks for more than the motors can give with this roll/pitch
    q = squared_speeds(f)
    assert q.min() < 0 or q.max() > W_MAX**2
    a = allocate(f, W_MAX)
    assert a.stage == "yaw"
    assert np.allclose(a.applied[:3], f[:3], rtol=1e-9)  # thrust, roll, pitch exactly
    assert 0.0 <= a.applied[3] < f[3]


def test_thrust_shifts_to_keep_roll_and_pitch():
    f = [4 * W_MAX**2 * 0.98, 3e5, 0.0, 0.0]  # full thrust plus a roll demand
    a = allocate(f, W_MAX)
    assert a.stage == "thrust"
    assert np.isclose(a.applied[1], f[1], rtol=1e-9) and np.isclose(a.applied[2], 0.0, atol=1e-6)
    assert a.applied[0] < f[0]
    assert np.all(a.speeds <= W_MAX + 1e-9)


def test_impossible_attitude_is_scaled_keeping_its_direction():
    f = [1e6, 8e6, -4e6, 0.0]
    a = allocate(f, W_MAX)
    assert a.stage == "attitude"
    assert np.all(a.speeds >= 0) and np.all(a.speeds <= W_MAX + 1e-9)
    assert math.isclose(a.applied[1] / a.applied[2], f[1] / f[2], rel_tol=1e-9)


def test_non_finite_request_gives_finite_speeds():
    a = allocate([math.nan, 0.0, math.inf, 0.0], W_MAX)
    assert a.saturated and np.all(np.isfinite(a.speeds))


def test_random_requests_always_within_limits():
    rng = np.random.default_rng(1)
    for _ in range(2000):
        f = rng.normal(0.0, 2e6, 4) + np.array([2e6, 0, 0, 0])
        a = allocate(f, W_MAX)
        assert np.all(a.speeds >= 0.0) and np.all(a.speeds <= W_MAX + 1e-9)
        if not a.saturated:
            assert np.allclose(a.applied, f, rtol=1e-9, atol=1e-3)
