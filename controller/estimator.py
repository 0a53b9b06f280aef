"""State estimation from sensors alone (`quadsr fly --state sensors`), as a companion without ground truth.

Two small filters run at the IMU rate on HIL_SENSOR and HIL_GPS:

Attitude: a Mahony complementary filter on the unit quaternion (body FRD -> earth NED). The gyro [rad/s]
propagates it; the accelerometer corrects roll and pitch, the magnetometer corrects yaw only (its horizontal
component in the earth frame against the vehicle file's earth field), and an integral term estimates the gyro
bias. A quadrotor's accelerometer does not sense gravity's direction while the vehicle accelerates (it reads
mostly thrust), so the accelerometer's reference is aided: the expected specific force is R^T (a - g e3)
with a the position filter's acceleration estimate, not R^T (-g e3).

Position and velocity: a linear Kalman filter per step, state (p [m NED], v [m/s NED], b [m/s^2 NED], c [m]):
    p' = v,  v' = R f + g e3 - b,  b and c random walks
with f the accelerometer's specific force [m/s^2 FRD] rotated to NED by the attitude filter. b absorbs the
accelerometer bias and the attitude filter's error as seen in NED; c is the barometer's offset. Measurements:
GPS position (WGS84 -> NED about the vehicle file's home, as PX4's map projection) and velocity at 10 Hz,
barometric altitude (z = home.alt - pressure altitude + c) at 50 Hz.

Seeded by nothing: the first sample levels the attitude from the accelerometer and the magnetometer (the
vehicle starts at rest), the first GPS fix sets the position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from bridge.geodesy import LocalFrame
from bridge.messages import GpsSample, ImuSample
from bridge.rotations import (
    euler_from_quaternion,
    quaternion_from_euler,
    rotation_from_euler,
    rotation_from_quaternion,
)
from bridge.vehicle import EXCHANGE_STEP, VehicleConfig
from bridge.yaml_file import Section, read_dataclass


@dataclass(frozen=True)
class EstimatorSettings:
    """Filter gains and noise levels (SI). Defaults suit the vehicle file's 'realistic' sensors."""

    attitude_kp: float = 1.0  # rad/s per unit of accelerometer direction error
    attitude_ki: float = 0.05  # rad/s^2 per unit error (gyro bias estimation)
    heading_kp: float = 0.5  # rad/s per rad of magnetometer heading error
    acceleration_aiding: bool = True  # accelerometer reference from the position filter's acceleration
    accel_noise: float = 0.5  # m/s^2 / sqrt(Hz), process noise on the velocity
    accel_offset_walk: float = 0.5  # m/s^2 / sqrt(s), random walk of b
    baro_offset_walk: float = 0.05  # m / sqrt(s), random walk of the barometer offset c
    gps_horizontal_noise: float = 0.05  # m (std of one fix)
    gps_vertical_noise: float = 0.08  # m
    gps_velocity_noise: float = 0.05  # m/s
    baro_noise: float = 0.15  # m

    @classmethod
    def from_mapping(cls, data: dict[str, Any] | None, where: str = "estimator") -> EstimatorSettings:
        """Settings from a mapping of positive numbers (unknown keys are a UserError)."""
        return read_dataclass(Section(where, data or {}), cls, positive=True)


@dataclass(frozen=True)
class Estimate:
    """An estimated state: xi (12, as docs/design.md), quaternion (w, x, y, z) body->NED, time [s]."""

    t: float
    xi: np.ndarray
    quaternion: np.ndarray
    accel_offset: np.ndarray  # m/s^2 NED, the position filter's b
    gyro_bias: np.ndarray  # rad/s FRD


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array((aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array((a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]))


class StateEstimator:
    """Mahony attitude filter + linear Kalman position filter on HIL_SENSOR / HIL_GPS (see module doc)."""

    def __init__(self, vehicle: VehicleConfig, settings: EstimatorSettings | None = None):
        self.vehicle = vehicle
        self.settings = settings or EstimatorSettings()
        self.g = vehicle.gravity
        self.frame = LocalFrame(vehicle.home.lat, vehicle.home.lon, vehicle.home.alt)
        field_ned = np.array(vehicle.sensors.mag.earth_field, dtype=float)
        self.mag_heading_ref = math.atan2(field_ned[1], field_ned[0])
        s = self.settings
        h, v, vel = s.gps_horizontal_noise ** 2, s.gps_vertical_noise ** 2, s.gps_velocity_noise ** 2
        self._r_gps = np.diag((h, h, v, vel, vel, vel))
        self._h_gps = np.zeros((6, 10))
        self._h_gps[0:6, 0:6] = np.eye(6)
        self._h_baro = np.zeros(10)
        self._h_baro[2] = 1.0
        self._h_baro[9] = 1.0
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next sample initialises the filters."""
        self.q: np.ndarray | None = None
        self.gyro_bias = np.zeros(3)
        self.x = np.zeros(10)
        self.P = np.diag([100.0] * 3 + [1.0] * 3 + [0.5] * 3 + [100.0])
        self.position_initialised = False
        self.baro_initialised = False
        self.last_time_usec: int | None = None
        self.first_time_usec = 0
        self.rates = np.zeros(3)
        self.accel_ned = np.zeros(3)
        self.heading_error = 0.0

    # --- attitude ------------------------------------------------------------------------------------------
    def _initial_attitude(self, imu: ImuSample) -> np.ndarray:
        f = np.asarray(imu.accel, dtype=float)
        phi = math.atan2(-f[1], -f[2])
        theta = math.atan2(f[0], math.hypot(f[1], f[2]))
        psi = 0.0
        if imu.mag is not None:
            tilt = np.array(rotation_from_euler(phi, theta, 0.0)).reshape(3, 3)
            m = tilt @ np.asarray(imu.mag, dtype=float)
            psi = self.mag_heading_ref - math.atan2(m[1], m[0])
        return np.array(quaternion_from_euler(phi, theta, psi))

    def _attitude_step(self, imu: ImuSample, dt: float) -> None:
        s = self.settings
        q = self.q
        R = np.array(rotation_from_quaternion(*q)).reshape(3, 3)
        f = np.asarray(imu.accel, dtype=float)
        correction = np.zeros(3)
        nf = math.sqrt(float(f @ f))
        if 0.3 * self.g < nf < 3.0 * self.g:
            if s.acceleration_aiding and self.position_initialised:
                expected = f - R.T @ self.x[6:9]  # R^T (a_hat - g e3), a_hat = R f + g e3 - b
            else:
                expected = R.T @ np.array((0.0, 0.0, -self.g))
            ne = math.sqrt(float(expected @ expected))
            if ne > 1e-6:
                err = _cross(f / nf, expected / ne)
                correction += s.attitude_kp * err
                self.gyro_bias -= s.attitude_ki * err * dt
        if imu.mag is not None:  # heading error from each new mag sample, held until the next one
            m_e = R @ np.asarray(imu.mag, dtype=float)
            if math.hypot(m_e[0], m_e[1]) > 1e-6:
                err = math.atan2(m_e[1], m_e[0]) - self.mag_heading_ref
                self.heading_error = (err + math.pi) % (2.0 * math.pi) - math.pi
        # heading gain 1/t at first (a running mean of the first mag samples), then heading_kp; the held
        # error shrinks by what was applied, so several IMU steps per mag sample do not overshoot
        elapsed = (imu.time_usec - self.first_time_usec) * 1e-6
        kh = min(max(s.heading_kp, 1.0 / max(elapsed, dt)), 1.0 / dt)
        correction += R.T @ np.array((0.0, 0.0, -kh * self.heading_error))
        self.heading_error -= kh * dt * self.heading_error
        w = np.asarray(imu.gyro, dtype=float) - self.gyro_bias
        self.rates = w
        omega = w + correction
        angle = math.sqrt(float(omega @ omega)) * dt
        if angle > 1e-12:
            axis = omega * (dt / angle)
            dq = np.concatenate(((math.cos(0.5 * angle),), math.sin(0.5 * angle) * axis))
            q = _qmul(q, dq)
        self.q = q / math.sqrt(float(q @ q))

    # --- position and velocity -----------------------------------------------------------------------------
    def _predict(self, imu: ImuSample, dt: float) -> None:
        s = self.settings
        R = np.array(rotation_from_quaternion(*self.q)).reshape(3, 3)
        u = R @ np.asarray(imu.accel, dtype=float) + np.array((0.0, 0.0, self.g))
        x = self.x
        a = u - x[6:9]
        self.accel_ned = a
        x[0:3] += x[3:6] * dt + 0.5 * a * dt * dt
        x[3:6] += a * dt
        F = np.eye(10)
        idx = np.arange(3)
        F[idx, idx + 3] = dt
        F[idx, idx + 6] = -0.5 * dt * dt
        F[idx + 3, idx + 6] = -dt
        Q = np.zeros((10, 10))
        qa = s.accel_noise ** 2
        Q[idx, idx] = qa * dt ** 3 / 3.0
        Q[idx, idx + 3] = Q[idx + 3, idx] = qa * dt * dt / 2.0
        Q[idx + 3, idx + 3] = qa * dt
        Q[idx + 6, idx + 6] = s.accel_offset_walk ** 2 * dt
        Q[9, 9] = s.baro_offset_walk ** 2 * dt
        self.P = F @ self.P @ F.T + Q

    def _correct(self, H: np.ndarray, z: np.ndarray, R: np.ndarray) -> None:
        y = z - H @ self.x
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T
        self.x = self.x + K @ y
        ikh = np.eye(10) - K @ H
        self.P = ikh @ self.P @ ikh.T + K @ R @ K.T

    def _gps(self, gps: GpsSample) -> None:
        p = np.array(self.frame.to_ned(gps.lat, gps.lon, gps.alt))
        z = np.concatenate((p, np.asarray(gps.vel, dtype=float)))
        if not self.position_initialised:
            self.x[0:6] = z
            self.P[0:6, 0:6] = self._r_gps
            self.position_initialised = True
            return
        self._correct(self._h_gps, z, self._r_gps)

    def _baro(self, pressure_alt: float) -> None:
        z_baro = self.vehicle.home.alt - pressure_alt
        if not self.position_initialised:
            return
        if not self.baro_initialised:
            self.x[9] = z_baro - self.x[2]
            self.P[9, 9] = self.P[2, 2] + self.settings.baro_noise ** 2
            self.baro_initialised = True
            return
        H = self._h_baro[None, :]
        self._correct(H, np.array((z_baro,)), np.array(((self.settings.baro_noise ** 2,),)))

    # --- one sample ----------------------------------------------------------------------------------------
    def update(self, imu: ImuSample, gps: GpsSample | None = None) -> Estimate:
        """Take one HIL_SENSOR sample (and the step's HIL_GPS fix, if any); return the new estimate."""
        if self.q is None:
            self.q = self._initial_attitude(imu)
            self.first_time_usec = imu.time_usec
            dt = 0.0
        else:
            dt = (imu.time_usec - (self.last_time_usec or 0)) * 1e-6
            if not 0.0 < dt < 1.0:
                dt = EXCHANGE_STEP
        self.last_time_usec = imu.time_usec
        if dt > 0.0:
            self._attitude_step(imu, dt)
            if self.position_initialised:
                self._predict(imu, dt)
        else:
            self.rates = np.asarray(imu.gyro, dtype=float) - self.gyro_bias
        if gps is not None and gps.fix_type >= 3:
            self._gps(gps)
        if imu.pressure_alt is not None:
            self._baro(float(imu.pressure_alt))
        return self.estimate()

    def estimate(self) -> Estimate:
        """The current estimate (position NED m, velocity NED m/s, Euler ZYX rad, rates FRD rad/s)."""
        q = self.q if self.q is not None else np.array((1.0, 0.0, 0.0, 0.0))
        xi = np.concatenate((self.x[0:6], euler_from_quaternion(q), self.rates))
        t = (self.last_time_usec or 0) * 1e-6
        return Estimate(t, xi, q.copy(), self.x[6:9].copy(), self.gyro_bias.copy())
