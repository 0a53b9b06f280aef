"""The sensor-only state estimator on synthetic sensor streams from the SITL's own physics and sensor model.

Each step's messages are built as the SITL builds them (sitl.hil.reference_messages: GPS in degE7 and mm,
HIL_SENSOR with its fields_updated bits) and decoded by the companion's ObservationAssembler, so the
estimator sees what it sees over the link. Floors (realistic sensors, Case I, errors from 5 s on, after the
take-off transient): position < 3 cm RMS per axis, velocity < 6 cm/s RMS, roll and pitch < 0.4 deg RMS,
yaw < 1.5 deg RMS.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.errors import UserError
from bridge.messages import ObservationAssembler
from bridge.vehicle import load_vehicle
from controller.baselines.se3 import Se3Controller
from controller.estimator import EstimatorSettings, StateEstimator
from controller.plugin import VehicleState
from controller.trajectories import case1, case2
from sitl.dynamics import Quadrotor
from sitl.hil import reference_messages
from sitl.sensors import SensorModel


def _fly(trajectory, duration, *, closed_loop=False, settings=None, sensors="realistic", seed=3, **overrides):
    """Fly SE(3) on the SITL physics; return t, estimate - truth (12 columns), 3-D tracking error."""
    vehicle = load_vehicle("fang-chen-buaa").with_overrides(sensors=sensors, seed=seed, **overrides)
    quad = Quadrotor(vehicle)
    sensor_model = SensorModel(vehicle.sensors, vehicle.home, seed)
    assembler = ObservationAssembler()
    estimator = StateEstimator(vehicle, settings)
    ctrl = Se3Controller(vehicle)
    curve = vehicle.motor_curve
    ts, errs, track = [], [], []
    for _ in range(int(round(duration / 0.004)) + 1):
        (obs,) = assembler.feed(reference_messages(quad, sensor_model.sample(quad), vehicle.home))
        est = estimator.update(obs.imu, obs.gps)
        truth = obs.truth
        state = VehicleState(est.xi, obs.rotor_speeds, est.quaternion) if closed_loop else \
            VehicleState(truth.xi, obs.rotor_speeds, truth.quaternion)
        ref = trajectory.reference(obs.t)
        cmd = ctrl.update(obs.t, state, ref)
        err = est.xi - truth.xi
        err[6:9] = (err[6:9] + math.pi) % (2 * math.pi) - math.pi
        ts.append(obs.t)
        errs.append(err)
        track.append(np.linalg.norm(truth.position - ref.position))
        quad.step([curve.throttle_for_speed(float(w)) for w in cmd.rotor_speeds])
    return np.array(ts), np.array(errs), np.array(track)


def _rms(x: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(np.square(x), axis=0))


def test_estimate_follows_case1_with_realistic_sensors():
    t, err, _ = _fly(case1(), 10.0)
    late = t >= 5.0
    assert np.all(_rms(err[late, 0:3]) < 0.03)
    assert np.all(_rms(err[late, 3:6]) < 0.06)
    assert np.all(np.degrees(_rms(err[late, 6:8])) < 0.4)
    assert np.degrees(_rms(err[late, 8])) < 1.5


def test_acceleration_aiding_is_what_keeps_the_tilt_right_while_circling():
    """Without aiding, the accelerometer (which reads thrust, not gravity) pulls the tilt toward level."""
    t, err, _ = _fly(case1(), 10.0, settings=EstimatorSettings(acceleration_aiding=False))
    late = t >= 5.0
    assert np.max(np.degrees(_rms(err[late, 6:8]))) > 1.5


def test_estimate_converges_from_a_yawed_start_away_from_home():
    t, err, _ = _fly(case2(), 5.0, initial_position=(1.0, -2.0, 0.0), initial_yaw=1.0)
    assert abs(math.degrees(err[0, 8])) < 10.0  # levelled and headed from the first accel + mag sample
    late = t >= 3.0
    assert np.degrees(np.max(np.abs(err[late, 8]))) < 2.0
    assert np.all(np.abs(err[late, 0:3]) < 0.1)


def test_noise_free_sensors_give_a_near_exact_estimate():
    t, err, _ = _fly(case2(), 6.0, sensors="ideal")
    late = t >= 4.0
    assert np.all(_rms(err[late, 0:3]) < 0.01)  # GPS quantisation (degE7, mm, cm/s) is all that is left
    assert np.degrees(np.max(np.abs(err[late, 6:9]))) < 0.2


def test_closed_loop_on_the_estimate_tracks_case2():
    t, _, track = _fly(case2(), 8.0, closed_loop=True)
    assert np.sqrt(np.mean(track[t >= 5.0] ** 2)) < 0.1


def test_settings_mapping_is_validated():
    assert EstimatorSettings.from_mapping({"attitude_kp": 2}).attitude_kp == 2.0
    with pytest.raises(UserError, match="unknown key 'kp'"):
        EstimatorSettings.from_mapping({"kp": 1.0})
    with pytest.raises(UserError, match="baro_noise. must be > 0"):
        EstimatorSettings.from_mapping({"baro_noise": -1})
