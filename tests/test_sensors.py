"""Sensor model and geodesy, in process: ideal readings, noise statistics, seeds, rates and flags."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from bridge.geodesy import EARTH_RADIUS, LocalFrame, geodetic_to_ned, ned_to_geodetic
from bridge.vehicle import HomeConfig, ImuNoiseConfig, VehicleConfig, load_vehicle
from sitl.dynamics import Quadrotor
from sitl.sensors import (
    BARO_EVERY_STEPS,
    FIELDS_BARO,
    FIELDS_MAG,
    GPS_EVERY_STEPS,
    MAG_EVERY_STEPS,
    SensorModel,
    isa_altitude,
    isa_pressure,
)


@pytest.fixture(scope="module")
def realistic() -> VehicleConfig:
    return load_vehicle("fang-chen-buaa")


@pytest.fixture(scope="module")
def ideal(realistic) -> VehicleConfig:
    return realistic.with_overrides(sensors="ideal")


def collect(vehicle: VehicleConfig, steps: int, seed: int = 1, throttles=(0.0,) * 4, quad=None):
    quad = quad or Quadrotor(vehicle)
    model = SensorModel(vehicle.sensors, vehicle.home, seed)
    frames = [model.sample(quad)]
    for _ in range(steps - 1):
        quad.step(throttles)
        frames.append(model.sample(quad))
    return frames


def test_ideal_at_rest_on_the_ground(ideal):
    quad = Quadrotor(ideal)
    frame = SensorModel(ideal.sensors, ideal.home, 0).sample(quad)
    assert frame.time_usec == 0
    assert frame.accel == (0.0, 0.0, -9.8)
    assert frame.gyro == (0.0, 0.0, 0.0)
    assert frame.mag == pytest.approx(ideal.sensors.mag.earth_field, abs=1e-15)  # yaw 0: body = NED
    assert frame.pressure_alt == pytest.approx(488.0, abs=1e-6)
    assert frame.abs_pressure == pytest.approx(955.98, abs=0.01)  # ISA at 488 m
    assert frame.temperature == pytest.approx(15.0 - 0.0065 * 488.0, abs=1e-9)
    gps = frame.gps
    assert (gps.lat, gps.lon, gps.alt) == (47.397742, 8.545594, 488.0)
    assert gps.vel == (0.0, 0.0, 0.0) and gps.fix_type == 3 and gps.satellites == 10
    assert frame.new_mag and frame.new_baro and frame.new_gps


def test_ideal_readings_follow_the_state(ideal):
    v = ideal.with_overrides(ground="none")
    quad = Quadrotor(v)
    quad.reset(position=(30.0, -40.0, -100.0), yaw=math.pi / 2, velocity=(1.0, 2.0, -3.0),
               rates=(0.1, 0.2, 0.3), rotor_speeds=(v.hover_speed,) * 4)
    frame = SensorModel(v.sensors, v.home, 0).sample(quad)
    assert frame.gyro == (0.1, 0.2, 0.3)
    assert frame.accel == quad.specific_force_body()
    m_n, m_e, m_d = v.sensors.mag.earth_field
    assert frame.mag == pytest.approx((m_e, -m_n, m_d), abs=1e-12)  # nose east: body x sees the east field
    assert frame.pressure_alt == pytest.approx(588.0, abs=1e-6)
    assert frame.gps.alt == pytest.approx(588.0, abs=1e-9)
    assert frame.gps.vel == (1.0, 2.0, -3.0)
    north, east, down = geodetic_to_ned(frame.gps.lat, frame.gps.lon, frame.gps.alt, v.home)
    assert (north, east, down) == pytest.approx((30.0, -40.0, -100.0), abs=1e-6)


def test_noise_statistics_match_the_configured_std(realistic):
    sensors = dataclasses.replace(
        realistic.sensors,
        accel=ImuNoiseConfig(noise=(0.5, 1.7, 1.4), bias=(0.2, -0.3, 0.1)),
    )
    v = dataclasses.replace(realistic, sensors=sensors)
    frames = collect(v, 5000)
    accel = np.array([f.accel for f in frames])
    gyro = np.array([f.gyro for f in frames])
    mags = np.array([f.mag for f in frames if f.new_mag])
    baro = np.array([f.abs_pressure for f in frames if f.new_baro]) * 100.0
    gps = [f.gps for f in frames if f.new_gps]
    n = len(frames)
    truth = np.array([0.0, 0.0, -9.8])
    np.testing.assert_allclose(accel.std(axis=0), (0.5, 1.7, 1.4), rtol=0.06)
    np.testing.assert_allclose(accel.mean(axis=0) - truth, (0.2, -0.3, 0.1), atol=4 * 1.7 / math.sqrt(n))
    g = v.sensors.gyro
    np.testing.assert_allclose(gyro.std(axis=0), g.noise, rtol=0.06)
    np.testing.assert_allclose(gyro.mean(axis=0), g.bias, atol=4 * g.noise[0] / math.sqrt(n))
    m = v.sensors.mag
    assert len(mags) == 1250
    np.testing.assert_allclose(mags.std(axis=0), m.noise, rtol=0.12)
    np.testing.assert_allclose(mags.mean(axis=0), np.array(m.earth_field) + m.bias,
                               atol=4 * 0.03 / math.sqrt(1250))
    assert len(baro) == 1000
    assert baro.std() == pytest.approx(v.sensors.baro.noise, rel=0.12)
    expected = isa_pressure(488.0) + v.sensors.baro.bias
    assert baro.mean() == pytest.approx(expected, abs=4 * v.sensors.baro.noise / math.sqrt(1000))
    assert len(gps) == 200
    frame = LocalFrame.at(v.home)
    ned = np.array([frame.to_ned(p.lat, p.lon, p.alt) for p in gps])
    gc = v.sensors.gps
    np.testing.assert_allclose(ned.std(axis=0), (gc.horizontal_noise, gc.horizontal_noise, gc.vertical_noise),
                               rtol=0.25)
    vel = np.array([p.vel for p in gps])
    np.testing.assert_allclose(vel.std(axis=0), (gc.velocity_noise,) * 3, rtol=0.25)


def test_same_seed_same_samples_other_seed_other_samples(realistic):
    a = collect(realistic, 200, seed=5)
    b = collect(realistic, 200, seed=5)
    c = collect(realistic, 200, seed=6)
    assert a == b
    assert [f.accel for f in a] != [f.accel for f in c]


def test_sample_twice_at_one_time_gives_the_same_frame(realistic):
    quad = Quadrotor(realistic)
    model = SensorModel(realistic.sensors, realistic.home, 3)
    first = model.sample(quad)
    assert model.sample(quad) is first
    quad.step([0.0] * 4)
    assert model.sample(quad).time_usec == 4000
    model.reset()
    quad.reset()
    assert model.sample(quad) == first


def test_rates_and_flags(ideal):
    frames = collect(ideal, 101)
    for k, f in enumerate(frames):
        assert f.time_usec == 4000 * k
        assert f.new_mag == (k % MAG_EVERY_STEPS == 0)
        assert f.new_baro == (k % BARO_EVERY_STEPS == 0)
        assert f.new_gps == (k % GPS_EVERY_STEPS == 0)
        expected = 0x3F | (FIELDS_MAG if f.new_mag else 0) | (FIELDS_BARO if f.new_baro else 0)
        assert f.fields_updated == expected
    assert (MAG_EVERY_STEPS, BARO_EVERY_STEPS, GPS_EVERY_STEPS) == (4, 5, 25)  # 62.5, 50, 10 Hz
    assert frames[5].fields_updated == 0x1A3F and frames[4].fields_updated == 0x1FF
    assert frames[20].fields_updated == 0x1BFF


def test_held_values_between_samples(realistic):
    v = realistic.with_overrides(ground="none", initial_position=(0.0, 0.0, -100.0))
    frames = collect(v, 30)  # falling: the true state changes every step
    assert frames[1].mag == frames[0].mag and frames[1].gps == frames[0].gps
    assert frames[1].pressure_alt == frames[0].pressure_alt
    assert frames[4].mag != frames[3].mag
    assert frames[5].pressure_alt != frames[4].pressure_alt
    assert frames[25].gps != frames[24].gps and frames[25].gps.time_usec == 100_000


def test_baro_follows_altitude(ideal):
    v = ideal.with_overrides(ground="none")
    quad = Quadrotor(v)
    model = SensorModel(v.sensors, v.home, 0)
    quad.reset(position=(0.0, 0.0, -10.0))
    high = model.sample(quad)
    assert high.pressure_alt == pytest.approx(498.0, abs=1e-6)
    # dp = rho g dh with rho about 1.16 kg/m^3 at 490 m
    assert isa_pressure(488.0) - high.abs_pressure * 100 == pytest.approx(10 * 1.16 * 9.8, rel=0.03)
    assert isa_altitude(isa_pressure(1234.5)) == pytest.approx(1234.5, abs=1e-6)
    assert isa_pressure(0.0) == 101325.0


@pytest.mark.parametrize(
    "ned",
    [(0.0, 0.0, 0.0), (0.3, -0.2, 0.1), (123.4, -567.8, -90.0), (1e4, 1e4, -500.0), (-2e5, 3e5, 20.0)],
)
def test_geodesy_round_trip_below_a_millimetre(ned):
    home = HomeConfig(47.397742, 8.545594, 488.0)
    lat, lon, alt = ned_to_geodetic(*ned, home)
    back = geodetic_to_ned(lat, lon, alt, home)
    assert max(abs(a - b) for a, b in zip(back, ned, strict=True)) < 1e-3


def test_geodesy_scale_and_direction():
    home = HomeConfig(47.397742, 8.545594, 488.0)
    metres_per_degree = EARTH_RADIUS * math.pi / 180.0
    lat, lon, alt = ned_to_geodetic(metres_per_degree, 0.0, -12.0, home)
    assert lat == pytest.approx(48.397742, abs=1e-9) and lon == pytest.approx(8.545594, abs=1e-9)
    assert alt == 500.0
    lat, lon, _ = ned_to_geodetic(0.0, 1000.0, 0.0, home)
    assert lon > 8.545594 and lat == pytest.approx(47.397742, abs=1e-5)
    east = (lon - 8.545594) * metres_per_degree * math.cos(math.radians(47.397742))
    assert east == pytest.approx(1000.0, rel=1e-4)


def test_ideal_readings_repeat_at_rest_unless_never_repeat(ideal, realistic):
    """Noise-free readings of a vehicle at rest repeat exactly (PX4 fails a sensor as stuck after about 100
    equal samples in a row); for an autopilot (never_repeat) new magnetometer and barometer samples differ
    from the last as PX4 reads them (float32, compared to 1e-6), never more than 3 in a row equal, while
    staying within a few centimetres of altitude / 0.6 mgauss of the truth."""

    def longest_repeat(changed: np.ndarray) -> int:
        run = best = 0
        for c in changed:
            run = 0 if c else run + 1
            best = max(best, run)
        return best

    def samples(vehicle, never_repeat):
        quad = Quadrotor(vehicle)
        model = SensorModel(vehicle.sensors, vehicle.home, 0, never_repeat=never_repeat)
        mags, baros = [], []
        for _ in range(600):
            f = model.sample(quad)
            if f.new_mag:
                mags.append(np.float32(f.mag))
            if f.new_baro:
                baros.append(np.float32(f.abs_pressure * 100.0))  # Pa, as PX4's sensor_baro
            quad.step((0.0,) * 4)
        return np.array(mags), np.array(baros)

    mags, baros = samples(ideal, False)
    assert np.all(mags == mags[0]) and np.all(baros == baros[0])
    mags, baros = samples(ideal, True)
    assert len(mags) >= 150 and len(baros) >= 120
    assert longest_repeat(np.abs(np.diff(mags, axis=0)).max(axis=1) > 1e-6) <= 3
    assert longest_repeat(np.diff(baros) != 0.0) <= 3
    truth_mag = np.array(ideal.sensors.mag.earth_field)
    assert np.abs(mags - truth_mag).max() < 6e-4  # gauss
    assert np.abs(baros - isa_pressure(ideal.home.alt)).max() < 0.3  # Pa: about 2.5 cm of altitude
    # realistic noise is larger than the floor: the same readings either way
    quad_a, quad_b = Quadrotor(realistic), Quadrotor(realistic)
    a = SensorModel(realistic.sensors, realistic.home, 4).sample(quad_a)
    b = SensorModel(realistic.sensors, realistic.home, 4, never_repeat=True).sample(quad_b)
    assert a == b
