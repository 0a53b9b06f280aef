"""Wind: Dryden turbulence against MIL-F-8785C (variance, mean, power spectral density), the 1-cosine gust's
shape, determinism with a seed, the drift it gives, the true wind in telemetry (WIND_COV) over real UDP."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.signal import welch

from bridge.airframe import FOOT, KNOT, GustConfig, WindConfig, dryden_parameters, wind_config
from bridge.lockstep import LockstepClient
from bridge.tlog import read_tlog
from bridge.vehicle import load_vehicle
from sitl.dryden import dryden_psd
from sitl.dynamics import Quadrotor
from sitl.wind import Wind

DT = 0.05  # s: the generator's step for the long statistical runs (the SITL uses 0.004)
STEADY = (6.0, 8.0, 0.0)  # m/s NED: 10 m/s, blowing toward 53 deg east of north
GUST = GustConfig(0.2, 0.4, (0.0, 3.0, 0.0))  # s, s, m/s NED
ALTITUDE = 5.0  # m


@pytest.fixture(scope="module")
def turbulence_run() -> np.ndarray:
    """A long seeded run (8000 s at 20 Hz) of moderate turbulence, (N, 3) NED m/s."""
    wind = Wind(WindConfig(steady=STEADY, turbulence="moderate", reference_altitude=ALTITUDE, seed=3), DT)
    return np.array([wind.sample(k * DT) for k in range(160_000)])


def wind_axes(ned: np.ndarray) -> np.ndarray:
    """NED wind minus the steady part, in the mean-wind axes (u along the wind, v to its right, w down)."""
    d = ned - np.array(STEADY)
    heading = math.atan2(STEADY[1], STEADY[0])
    c, s = math.cos(heading), math.sin(heading)
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])


def test_dryden_parameters_follow_mil_f_8785c():
    sigma, length = dryden_parameters("severe", 20.0 * FOOT)
    w20 = 45.0 * KNOT
    assert sigma[2] == pytest.approx(0.1 * w20)
    assert sigma[0] == pytest.approx(0.1 * w20 / (0.177 + 0.000823 * 20.0) ** 0.4)
    assert length[2] == pytest.approx(20.0 * FOOT)
    assert length[0] == pytest.approx(20.0 / (0.177 + 0.000823 * 20.0) ** 1.2 * FOOT)


def test_dryden_mean_and_variance_match_the_preset(turbulence_run):
    sigma, _ = dryden_parameters("moderate", ALTITUDE)
    mean = turbulence_run.mean(axis=0)
    assert np.linalg.norm(mean - STEADY) < 0.1 * np.linalg.norm(STEADY)
    uvw = wind_axes(turbulence_run)
    np.testing.assert_allclose(uvw.var(axis=0), np.square(sigma), rtol=0.10)


@pytest.mark.parametrize("axis,component", [(0, "u"), (1, "v"), (2, "w")])
def test_dryden_spectrum_matches_the_analytic_one_over_a_decade(turbulence_run, axis, component):
    sigma, length = dryden_parameters("moderate", ALTITUDE)
    speed = float(np.linalg.norm(STEADY))
    corner = speed / (2.0 * math.pi * length[axis])  # Hz
    f, psd = welch(wind_axes(turbulence_run)[:, axis], fs=1.0 / DT, nperseg=8192)
    bands = np.geomspace(corner / 2.0, corner * 5.0, 6)  # a decade around the corner, 5 bands
    for lo, hi in zip(bands[:-1], bands[1:], strict=True):
        sel = (f >= lo) & (f < hi)
        assert sel.sum() >= 2
        omega = 2.0 * math.pi * f[sel]
        analytic = 2.0 * math.pi * dryden_psd(component, omega, sigma[axis], length[axis], speed)
        ratio = psd[sel].mean() / analytic.mean()  # one-sided per Hz vs per rad/s * 2 pi
        assert abs(ratio - 1.0) < 0.2, f"{component} {lo:.3f}-{hi:.3f} Hz: estimate/analytic {ratio:.3f}"


def test_a_gust_is_one_minus_cosine():
    gust = GustConfig(start=1.0, duration=2.0, amplitude=(0.0, 4.0, -1.0))
    wind = Wind(WindConfig(gusts=(gust,)), 0.004)
    t = np.arange(0, 1000) * 0.004
    w = np.array([wind.sample(tk) for tk in t])
    x = np.clip((t - 1.0) / 2.0, 0.0, 1.0)
    expected = 0.5 * (1.0 - np.cos(2.0 * math.pi * x))
    np.testing.assert_allclose(w[:, 1], 4.0 * expected, atol=1e-12)
    np.testing.assert_allclose(w[:, 2], -1.0 * expected, atol=1e-12)
    assert np.all(w[:, 0] == 0.0) and np.all(w[t < 1.0] == 0.0) and np.all(w[t > 3.0] == 0.0)
    assert w[:, 1].max() == pytest.approx(4.0, abs=1e-3) and t[np.argmax(w[:, 1])] == pytest.approx(2.0)


def flight(seed: int, steps: int = 300) -> np.ndarray:
    cfg = wind_config("test", (5.0, 0.0, 0.0), "light", 10.0, (GUST,), seed)
    v = load_vehicle("fang-chen-aero").with_overrides(ground="none", initial_position=(0, 0, -20.0), wind=cfg)
    quad = Quadrotor(v)
    quad.reset(position=(0, 0, -20.0), rotor_speeds=[v.hover_speed] * 4)
    throttle = v.motor_curve.throttle_for_speed(v.hover_speed)
    out = []
    for _ in range(steps):
        quad.step([throttle] * 4)
        out.append(quad.state + quad.wind)
    return np.array(out)


def test_the_same_seed_flies_the_same_wind_and_another_seed_does_not():
    a, b, c = flight(4), flight(4), flight(5)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a[:, -3:] - c[:, -3:]).max() > 0.05


def test_wind_pushes_the_vehicle_downwind_through_the_airspeed():
    base = load_vehicle("fang-chen-aero").with_overrides(ground="none", initial_position=(0, 0, -20.0))
    results = {}
    for name, steady in (("calm", (0.0, 0.0, 0.0)), ("north", (5.0, 0.0, 0.0))):
        v = dataclasses.replace(base, wind=wind_config("test", steady))
        quad = Quadrotor(v)
        quad.reset(position=(0, 0, -20.0), rotor_speeds=[v.hover_speed] * 4)
        results[name] = np.array(quad.acceleration_earth())
    assert results["north"][0] - results["calm"][0] > 0.05  # m/s^2 toward north, the way the air moves


def test_the_sitl_reports_the_true_wind_in_wind_cov_and_its_log(start_sitl, tmp_path):
    log = tmp_path / "wind.tlog"
    sitl = start_sitl("--vehicle", "fang-chen-aero", "--ground", "none", "--initial-position", "0,0,-20",
                      "--sensors", "ideal", "--wind", "5,0,0", "--turbulence", "light",
                      "--gust", "0.2,0.4,0,3,0", "--wind-seed", "4", "--log", str(log))
    expected = flight(4, steps=150)[:, -3:]  # the same wind, computed in this process
    reported = []
    with LockstepClient(sitl.hil, timeout=5.0) as client:
        v = load_vehicle("fang-chen-aero")
        throttle = v.motor_curve.throttle_for_speed(v.hover_speed)
        client.connect(10.0)
        for _ in range(150):
            obs = client.step([throttle] * 4)
            assert obs.wind is not None  # the step's WIND_COV, matched by time_usec
            assert not [m for m in obs.extras if m.get_type() == "WIND_COV"]
            reported.append(tuple(obs.wind))
    reported = np.array(reported)
    np.testing.assert_allclose(reported, expected.astype(np.float32), rtol=1e-6, atol=1e-6)
    assert reported[:, 1].max() > 2.0  # the gust went by
    sitl.stop()
    logged = [m for _, m in read_tlog(log) if m.get_type() == "WIND_COV"]
    assert len(logged) >= 150 and all(m.var_horiz > 0 for m in logged)
