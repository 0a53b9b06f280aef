"""A small cascaded hover controller on the true state: position -> velocity -> attitude -> rates -> rotors.

It keeps the vehicle flying under the closed-loop excitation (it is not the model-based controller of the
paper): position and velocity P loops give an acceleration command NED (m/s^2), which sets the thrust and the
tilt (limited to max_tilt); an attitude P loop gives body rate commands FRD (rad/s) through the Euler-rate
transform; a rate P loop with the gyroscopic feed-forward w x Jw gives torques (N m); the Quad-X allocation
of the vehicle file (Ct, Cm, arm length, PX4 motor order) turns thrust and torques into rotor speeds (rad/s).
Like an autopilot's tuning, it uses the vehicle file's nominal mass, inertia and rotor coefficients.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bridge.vehicle import VehicleConfig

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class StabilizerGains:
    """Loop gains (1/s) per axis N E D / roll pitch yaw, the tilt limit (deg) and speed limits (m/s)."""

    position_gain: Vec3 = (1.0, 1.0, 1.5)
    velocity_gain: Vec3 = (2.5, 2.5, 3.0)
    attitude_gain: Vec3 = (7.0, 7.0, 4.0)
    rate_gain: Vec3 = (20.0, 20.0, 10.0)
    max_tilt: float = 20.0
    max_speed: Vec3 = (2.0, 2.0, 1.5)


@dataclass(frozen=True)
class Reference:
    """Where to be: position NED (m), velocity NED (m/s, feed-forward), yaw (rad)."""

    position: Vec3
    velocity: Vec3 = (0.0, 0.0, 0.0)
    yaw: float = 0.0


def _clip(v: float, lim: float) -> float:
    return lim if v > lim else (-lim if v < -lim else v)


class HoverStabilizer:
    """Rotor speed commands (rad/s, PX4 order) that track a Reference from the true state."""

    def __init__(self, vehicle: VehicleConfig, gains: StabilizerGains | None = None):
        self.gains = gains or StabilizerGains()
        self.mass = vehicle.mass
        self.g = vehicle.gravity
        self.J = np.asarray(vehicle.inertia, dtype=float)
        self.max_speed_sq = vehicle.motor_curve.max_speed**2
        k = vehicle.mixer_gain
        ct, cm = vehicle.thrust_coefficient, vehicle.moment_coefficient
        # [T, tau_x, tau_y, tau_z] = M [w1^2 .. w4^2] (docs/design.md: f1..f4 with PX4 Quad-X order)
        alloc = np.array(
            [
                [ct, ct, ct, ct],
                [-k, k, k, -k],
                [k, -k, k, -k],
                [cm, cm, -cm, -cm],
            ]
        )
        self.inverse_allocation = np.linalg.inv(alloc)

    def command(self, xi: np.ndarray, ref: Reference) -> np.ndarray:
        """Rotor speeds (4,) rad/s for state xi (12: NED m, m/s, ZYX rad, FRD rad/s) and the reference."""
        (pc, qc, rc), thrust = self.rates_and_thrust(xi, ref)
        p, q, r = (float(v) for v in xi[9:12])
        # rates -> torques with gyroscopic feed-forward
        w = np.array((p, q, r))
        kr = self.gains.rate_gain
        alpha = np.array((kr[0] * (pc - p), kr[1] * (qc - q), kr[2] * (rc - r)))
        tau = self.J @ alpha + np.cross(w, self.J @ w)
        return self.allocate(thrust, tau)

    def rates_and_thrust(self, xi: np.ndarray, ref: Reference) -> tuple[tuple[float, float, float], float]:
        """The outer loops alone: body rate commands FRD (rad/s) and the collective thrust (N) for state xi
        (12: NED m, m/s, ZYX rad, FRD rad/s) and the reference (an autopilot's rate loop does the rest)."""
        gn = self.gains
        x, y, z, vx, vy, vz, phi, theta, psi = (float(v) for v in xi[:9])
        # position -> velocity -> acceleration (NED)
        vc = [
            _clip(gn.position_gain[i] * (ref.position[i] - pos) + ref.velocity[i], gn.max_speed[i])
            for i, pos in enumerate((x, y, z))
        ]
        acc = [gn.velocity_gain[i] * (vc[i] - v) for i, v in enumerate((vx, vy, vz))]
        max_tilt = math.radians(gn.max_tilt)
        lift = max(self.g - acc[2], 0.3 * self.g)  # never ask for less than 30% of hover thrust
        horizontal = math.hypot(acc[0], acc[1])
        limit = lift * math.tan(max_tilt)
        if horizontal > limit:
            acc[0] *= limit / horizontal
            acc[1] *= limit / horizontal
        # acceleration -> attitude and thrust (forward accel needs nose down, right accel needs roll right)
        cy, sy = math.cos(ref.yaw), math.sin(ref.yaw)
        a_fwd = cy * acc[0] + sy * acc[1]
        a_right = -sy * acc[0] + cy * acc[1]
        theta_d = math.atan2(-a_fwd, lift)
        phi_d = math.atan2(a_right * math.cos(theta_d), lift)
        thrust = self.mass * lift / max(math.cos(phi) * math.cos(theta), 0.5)
        # attitude -> body rates (Euler-rate transform of the angle errors)
        ka = gn.attitude_gain
        dphi = ka[0] * (phi_d - phi)
        dtheta = ka[1] * (theta_d - theta)
        dpsi = ka[2] * math.remainder(ref.yaw - psi, 2.0 * math.pi)
        sphi, cphi = math.sin(phi), math.cos(phi)
        sth, cth = math.sin(theta), math.cos(theta)
        pc = dphi - sth * dpsi
        qc = cphi * dtheta + sphi * cth * dpsi
        rc = -sphi * dtheta + cphi * cth * dpsi
        return (pc, qc, rc), thrust

    def allocate(self, thrust: float, tau: np.ndarray) -> np.ndarray:
        """Rotor speeds (4,) rad/s for thrust (N) and torques FRD (N m); squares clipped to [0, w_max^2]."""
        sq = self.inverse_allocation @ np.array((thrust, tau[0], tau[1], tau[2]))
        return np.sqrt(np.clip(sq, 0.0, self.max_speed_sq))
