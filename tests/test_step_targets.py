"""Truth targets over step intervals (identification.step_targets): the motor lag ratio found from speeds and
throttles alone, the RMS speed over a lagged step against quadrature, and a rigid body under held commands
whose interval targets match its derivative at the interval rows where point stencils cannot."""

from __future__ import annotations

import numpy as np

from identification.step_targets import lagged_rms_speed, motor_lag_ratio, step_interval_rows
from identification.targets import kink_aware_derivative

DT = 0.004
TM = 0.02  # s, motor time constant


def lagged_speeds(throttles: np.ndarray, curve, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Rotor speeds (N,4) rad/s at the samples of a first-order lag toward curve(throttle) held per step."""
    rng = np.random.default_rng(seed)
    r = np.exp(-DT / TM)
    u = np.empty_like(throttles)
    u[0] = curve(throttles[0])
    for k in range(len(u) - 1):
        c = curve(throttles[k]) + noise * rng.standard_normal(4)
        u[k + 1] = c + (u[k] - c) * r
    return u


def px4_like_curve(s: np.ndarray) -> np.ndarray:
    """A nonlinear throttle -> speed map (rad/s), PX4's thrust model with factor 0.3 and 1000 rad/s."""
    return 1000.0 * np.sqrt(0.7 * s + 0.3 * s * s)


def test_lag_ratio_from_speeds_and_throttles_alone():
    rng = np.random.default_rng(1)
    drift = 0.5 + 0.005 * np.cumsum(rng.standard_normal((3000, 4)), axis=0)
    # a controller: a new command every step
    throttles = np.clip(drift + 0.02 * rng.standard_normal(drift.shape), 0.05, 0.95)
    for noise in (0.0, 5.0):  # white noise on the commanded speed (rad/s), as the SITL's speed_noise
        u = lagged_speeds(throttles, px4_like_curve, noise=noise)
        r = motor_lag_ratio(u, throttles, np.ones(len(u), bool))
        assert r is not None and abs(r - np.exp(-DT / TM)) < 2e-3, r
    # speeds that do not follow their commands at all: no lag to estimate, or a ratio outside (0, 1)
    assert motor_lag_ratio(np.zeros((3000, 4)), throttles, np.ones(3000, bool)) is None


def test_rms_speed_over_a_lagged_step_matches_quadrature():
    r = np.exp(-DT / TM)
    u0 = np.array([300.0, 550.0, 800.0, 0.0])
    c = np.array([700.0, 520.0, 100.0, 400.0])
    s = np.linspace(0.0, DT, 20001)
    path = c + (u0 - c) * np.exp(-s[:, None] / TM)
    exact = np.sqrt(np.trapezoid(path**2, s, axis=0) / DT)
    got = lagged_rms_speed(u0, path[-1], r)
    assert np.allclose(got, exact, rtol=1e-9), (got, exact)
    assert np.abs(got - 0.5 * (u0 + path[-1])).max() > 1.0  # the mean of the ends would be wrong


def test_a_body_under_held_commands_gets_exact_interval_targets():
    """w' = k (u1^2 - u2^2) about one axis with lagged rotors and a new command every step."""
    rng = np.random.default_rng(2)
    n = 400
    throttles = np.clip(0.5 + 0.1 * rng.standard_normal((n, 4)), 0.0, 1.0)
    k = 1e-4
    r = np.exp(-DT / TM)
    # integrate finely within each step: rotor speeds and the rate w (rad/s)
    fine = 200
    h = DT / fine
    u = np.empty((n, 4))
    w = np.zeros(n)
    u[0] = px4_like_curve(throttles[0])
    for i in range(n - 1):
        c = px4_like_curve(throttles[i])
        s = (np.arange(fine) + 0.5) * h
        path = c + (u[i] - c) * np.exp(-s[:, None] / TM)
        w[i + 1] = w[i] + h * np.sum(k * (path[:, 0] ** 2 - path[:, 1] ** 2))
        u[i + 1] = c + (u[i] - c) * r
    t = np.arange(n) * DT
    zeros = np.zeros((n, 3))
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    rates = np.column_stack((w, np.zeros(n), np.zeros(n)))
    ratio = motor_lag_ratio(u, throttles, np.ones(n, bool))
    t_mid, xi, u_mid, targets = step_interval_rows(t, zeros, zeros, quat, rates, u, ratio)
    assert np.allclose(t_mid, t[:-1] + DT / 2)
    model = k * (u_mid[:, 0] ** 2 - u_mid[:, 1] ** 2)
    err_interval = np.abs(targets[:, 3] - model).max()
    # point derivatives at the samples (every sample a kink) against the model at the samples
    point = kink_aware_derivative(rates, DT, np.ones(n, bool))[:, 0]
    at_samples = k * (u[:, 0] ** 2 - u[:, 1] ** 2)
    err_point = np.nanmax(np.abs(point - at_samples))
    assert err_interval < 1e-3 * err_point, (err_interval, err_point)
    assert np.allclose(xi[:, 6:9], 0.0) and np.allclose(xi[:, 9], 0.5 * (w[:-1] + w[1:]))


def test_a_spinning_body_gets_its_midpoint_acceleration():
    """Body rates of 30 rad/s and a held specific force: the step mean of R f_b goes back to R_mid f_b."""
    from scipy.spatial.transform import Rotation

    from bridge.rotations import quaternion_from_euler, rotation_matrix

    g = 9.80665
    rates = np.array([20.0, -15.0, 17.0])  # rad/s FRD, |w| = 30
    f_b = np.array([0.3, -0.2, -9.0])  # m/s^2 FRD
    n, fine = 6, 4000
    t = np.arange(n) * DT
    rot0 = Rotation.from_euler("ZYX", [0.3, 0.2, 0.1])
    rot = [rot0 * Rotation.from_rotvec(rates * tk) for tk in t]  # body rates: R(t) = R0 exp([w] t)
    vel = np.zeros((n, 3))
    for k in range(n - 1):  # v integrated finely: dv/dt = R(t) f_b + g e3
        s = (np.arange(fine) + 0.5) * DT / fine
        acc = (rot[k] * Rotation.from_rotvec(np.outer(s, rates))).apply(f_b) + [0.0, 0.0, g]
        vel[k + 1] = vel[k] + acc.mean(axis=0) * DT
    euler = np.array([r.as_euler("ZYX")[::-1] for r in rot])
    quat = np.array([quaternion_from_euler(*e) for e in euler])
    u = np.full((n, 4), 500.0)
    _, xi, _, with_g = step_interval_rows(t, np.zeros((n, 3)), vel, quat, np.tile(rates, (n, 1)), u, 0.8, g)
    _, _, _, plain = step_interval_rows(t, np.zeros((n, 3)), vel, quat, np.tile(rates, (n, 1)), u, 0.8)
    expected = np.einsum("nij,j->ni", rotation_matrix(xi[:, 6], xi[:, 7], xi[:, 8]), f_b) + [0.0, 0.0, g]
    assert np.abs(with_g[:, :3] - expected).max() < 1e-6
    assert np.abs(plain[:, :3] - expected).max() > 1e-3  # the plain step mean is off by ~|w|^2 dt^2/24 |f|


def test_an_accelerating_spin_gets_its_midpoint_acceleration():
    """Rates changing at 300 rad/s^2 (a motor PRBS step) under a held specific force: the step mean of R f_b
    goes back to f_b within 1e-5 m/s^2 (without the [dw]x dt^2/12 term it is 3e-3 off, along dw x f_b)."""
    from scipy.spatial.transform import Rotation

    from bridge.rotations import quaternion_from_euler, rotation_matrix

    g = 9.80665
    w0, dw = np.array([2.0, -1.5, 1.0]), np.array([300.0, -250.0, 80.0])  # rad/s, rad/s^2 FRD
    f_b = np.array([0.3, -0.2, -9.0])  # m/s^2 FRD
    n, fine = 3, 400
    h = DT / fine
    rot = [Rotation.from_euler("ZYX", [0.3, 0.2, 0.1])]
    vel = np.zeros((n, 3))
    for k in range(n - 1):  # R and v integrated finely with w(t) = w0 + dw t
        acc = np.zeros(3)
        for j in range(fine):
            tm = k * DT + (j + 0.5) * h
            mid = rot[-1] * Rotation.from_rotvec((w0 + dw * tm) * 0.5 * h)
            acc += mid.apply(f_b) / fine
            rot.append(rot[-1] * Rotation.from_rotvec((w0 + dw * tm) * h))
        vel[k + 1] = vel[k] + (acc + [0.0, 0.0, g]) * DT
    t = np.arange(n) * DT
    euler = np.array([rot[k * fine].as_euler("ZYX")[::-1] for k in range(n)])
    quat = np.array([quaternion_from_euler(*e) for e in euler])
    rates = w0 + np.outer(t, dw)
    _, xi, _, tgt = step_interval_rows(t, np.zeros((n, 3)), vel, quat, rates, np.full((n, 4), 500.0), 0.8, g)
    r = rotation_matrix(xi[:, 6], xi[:, 7], xi[:, 8])
    body = np.einsum("nji,nj->ni", r, tgt[:, :3] - [0.0, 0.0, g])
    assert np.abs(body - f_b).max() < 1e-5
    assert np.allclose(tgt[:, 3:], dw)
