"""Sensors: what the IMU, magnetometer, barometer and GPS read for a quadrotor's true state.

Every exchange step (250 Hz) gives a SensorFrame. The IMU is new every step; the other sensors sample on
their own schedules, counted in exchange steps k = time_usec // 4000 since reset:

    mag  every 4th step  (62.5 Hz), on k % 4 == 0
    baro every 5th step  (50 Hz),   on k % 5 == 0
    GPS  every 25th step (10 Hz),   on k % 25 == 0

A frame always holds the latest value of every sensor (held between samples) plus flags saying which are new
this step, so a HIL_SENSOR can be filled every step and HIL_GPS sent on GPS steps. Noise is white Gaussian
(std per sample) plus a constant bias, from the vehicle file; preset 'ideal' makes both zero (for an
autopilot, never_repeat keeps a floor of noise on the magnetometer and barometer: NEVER_REPEAT_*). Values are
not clamped here (the HIL encoder clamps to PX4's +-16 g and +-2000 deg/s).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from bridge.geodesy import LocalFrame
from bridge.vehicle import HomeConfig, SensorsConfig
from sitl.dynamics import EXCHANGE_STEP_USEC, Quadrotor

MAG_EVERY_STEPS = 4  # 62.5 Hz
BARO_EVERY_STEPS = 5  # 50 Hz
GPS_EVERY_STEPS = 25  # 10 Hz

# HIL_SENSOR fields_updated bits, as PX4's simulator_mavlink reads them.
FIELDS_ACCEL = 0x7
FIELDS_GYRO = 0x38
FIELDS_MAG = 0x1C0
FIELDS_BARO = 0x1A00  # abs_pressure 0x200 | pressure_alt 0x800 | temperature 0x1000

# International Standard Atmosphere, troposphere.
ISA_T0 = 288.15  # K at sea level
ISA_P0 = 101325.0  # Pa at sea level
ISA_LAPSE = 0.0065  # K/m
ISA_EXPONENT = 5.255877  # g M / (R L)

_NOISE_BLOCK = 4096

# An autopilot fails a sensor whose readings repeat exactly (PX4's DataValidator: more than about 100 equal
# samples in a row, "MAG #0 failed: STALE!"), and noise-free readings repeat while the vehicle is at rest or
# in a steady hover. For an autopilot the magnetometer and barometer carry at least this noise: far below a
# real sensor's, yet enough to change every single-precision sample.
NEVER_REPEAT_MAG = 1e-4  # gauss std per axis (0.02 % of the earth's field; PX4 compares to 1e-6)
NEVER_REPEAT_BARO = 0.05  # Pa std (about 4 mm of altitude; a float32 pressure resolves 0.008 Pa at sea level)


class GpsFix(NamedTuple):
    """One GPS solution: position WGS84 (deg, m AMSL), velocity NED (m/s), accuracy (m), fix type 3 = 3D."""

    time_usec: int
    lat: float  # deg
    lon: float  # deg
    alt: float  # m AMSL
    vel: tuple[float, float, float]  # m/s NED
    eph: float  # m
    epv: float  # m
    fix_type: int
    satellites: int


class SensorFrame(NamedTuple):
    """All sensor readings at one exchange step (latest values held; new_* flags mark fresh samples)."""

    time_usec: int
    accel: tuple[float, float, float]  # specific force, m/s^2, body FRD
    gyro: tuple[float, float, float]  # rad/s, body FRD
    mag: tuple[float, float, float]  # gauss, body FRD
    abs_pressure: float  # hPa
    pressure_alt: float  # m (ISA altitude of the measured pressure)
    temperature: float  # degC
    gps: GpsFix
    new_mag: bool
    new_baro: bool
    new_gps: bool

    @property
    def fields_updated(self) -> int:
        """HIL_SENSOR fields_updated bitmask for this step (accel and gyro always; mag, baro when new)."""
        bits = FIELDS_ACCEL | FIELDS_GYRO
        if self.new_mag:
            bits |= FIELDS_MAG
        if self.new_baro:
            bits |= FIELDS_BARO
        return bits


def isa_pressure(altitude: float) -> float:
    """ISA static pressure (Pa) at an altitude (m AMSL)."""
    return ISA_P0 * (1.0 - ISA_LAPSE * altitude / ISA_T0) ** ISA_EXPONENT


def isa_altitude(pressure: float) -> float:
    """ISA altitude (m AMSL) of a static pressure (Pa)."""
    return ISA_T0 / ISA_LAPSE * (1.0 - (pressure / ISA_P0) ** (1.0 / ISA_EXPONENT))


def isa_temperature(altitude: float) -> float:
    """ISA temperature (degC) at an altitude (m AMSL)."""
    return ISA_T0 - ISA_LAPSE * altitude - 273.15


class SensorModel:
    """Noisy, biased sensor readings of a Quadrotor, deterministic for a seed."""

    def __init__(self, config: SensorsConfig, home: HomeConfig, seed: int = 0, never_repeat: bool = False):
        """never_repeat: magnetometer and barometer noise at least NEVER_REPEAT_* (for an autopilot)."""
        config = config.effective()
        if never_repeat:
            mag_noise = tuple(max(n, NEVER_REPEAT_MAG) for n in config.mag.noise)
            config = dataclasses.replace(
                config, mag=dataclasses.replace(config.mag, noise=mag_noise),
                baro=dataclasses.replace(config.baro, noise=max(config.baro.noise, NEVER_REPEAT_BARO)))
        self.config = config
        self.home = home
        self.seed = seed
        self.frame = LocalFrame.at(home)
        self.reset()

    def reset(self) -> None:
        """Restart the noise stream from the seed and forget held samples (call after Quadrotor.reset)."""
        self._rng = np.random.default_rng(self.seed)
        self._normals: list[float] = []
        self._next = 0
        self._last: SensorFrame | None = None

    def _gauss3(self, std: tuple[float, float, float]) -> tuple[float, float, float]:
        i = self._next
        if i + 3 > len(self._normals):
            self._normals = self._rng.standard_normal(_NOISE_BLOCK).tolist()
            i = 0
        n = self._normals
        self._next = i + 3
        return n[i] * std[0], n[i + 1] * std[1], n[i + 2] * std[2]

    def sample(self, quad: Quadrotor) -> SensorFrame:
        """The sensor frame for the quadrotor's current state (the same frame again if time has not moved)."""
        t = quad.time_usec
        last = self._last
        if last is not None and last.time_usec == t:
            return last
        k = t // EXCHANGE_STEP_USEC
        accel, gyro = self.imu(quad)
        new_mag = last is None or k % MAG_EVERY_STEPS == 0
        mag = self._mag(quad) if new_mag else last.mag  # type: ignore[union-attr]
        new_baro = last is None or k % BARO_EVERY_STEPS == 0
        if new_baro:
            abs_pressure, pressure_alt, temperature = self._baro(quad)
        else:
            abs_pressure, pressure_alt, temperature = last.abs_pressure, last.pressure_alt, last.temperature
        new_gps = last is None or k % GPS_EVERY_STEPS == 0
        gps = self._gps(quad) if new_gps else last.gps  # type: ignore[union-attr]

        out = SensorFrame(t, accel, gyro, mag, abs_pressure, pressure_alt, temperature, gps,
                          new_mag, new_baro, new_gps)
        self._last = out
        return out

    def imu(self, quad: Quadrotor) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(specific force m/s^2, angular rate rad/s), both body FRD, biased and noisy (a new draw each call):
        the IMU part of `sample`, alone for a simulator that needs only the IMU between sample steps."""
        cfg = self.config
        f = quad.specific_force_body()
        b = cfg.accel.bias
        n = self._gauss3(cfg.accel.noise)
        accel = (f[0] + b[0] + n[0], f[1] + b[1] + n[1], f[2] + b[2] + n[2])
        w = quad.rates
        b = cfg.gyro.bias
        n = self._gauss3(cfg.gyro.noise)
        return accel, (w[0] + b[0] + n[0], w[1] + b[1] + n[1], w[2] + b[2] + n[2])

    def _mag(self, quad: Quadrotor) -> tuple[float, float, float]:
        """Earth field rotated into the body (R^T m_NED), plus bias and noise; gauss FRD."""
        qw, qx, qy, qz = quad.quaternion
        mx, my, mz = self.config.mag.earth_field
        xx, yy, zz = qx * qx, qy * qy, qz * qz
        xy, xz, yz = qx * qy, qx * qz, qy * qz
        wx, wy, wz = qw * qx, qw * qy, qw * qz
        bx = (1.0 - 2.0 * (yy + zz)) * mx + 2.0 * (xy + wz) * my + 2.0 * (xz - wy) * mz
        by = 2.0 * (xy - wz) * mx + (1.0 - 2.0 * (xx + zz)) * my + 2.0 * (yz + wx) * mz
        bz = 2.0 * (xz + wy) * mx + 2.0 * (yz - wx) * my + (1.0 - 2.0 * (xx + yy)) * mz
        b = self.config.mag.bias
        n = self._gauss3(self.config.mag.noise)
        return bx + b[0] + n[0], by + b[1] + n[1], bz + b[2] + n[2]

    def _baro(self, quad: Quadrotor) -> tuple[float, float, float]:
        """(abs pressure hPa, pressure altitude m, temperature degC): ISA at home.alt - z, noisy pressure."""
        altitude = self.home.alt - quad.position[2]
        baro = self.config.baro
        noise = self._gauss3((baro.noise, 0.0, 0.0))[0]
        pressure = isa_pressure(altitude) + baro.bias + noise
        return pressure * 0.01, isa_altitude(pressure), isa_temperature(altitude)

    def _gps(self, quad: Quadrotor) -> GpsFix:
        """GPS position (WGS84) and velocity (NED) of the true state plus bias and noise."""
        g = self.config.gps
        x, y, z = quad.position
        n = self._gauss3((g.horizontal_noise, g.horizontal_noise, g.vertical_noise))
        b = g.bias
        lat, lon, alt = self.frame.to_geodetic(x + b[0] + n[0], y + b[1] + n[1], z + b[2] + n[2])
        v = quad.velocity
        nv = self._gauss3((g.velocity_noise, g.velocity_noise, g.velocity_noise))
        vel = (v[0] + nv[0], v[1] + nv[1], v[2] + nv[2])
        return GpsFix(quad.time_usec, lat, lon, alt, vel, g.eph, g.epv, 3, g.satellites)
