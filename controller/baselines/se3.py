"""Geometric tracking controller on SE(3) (Lee, Leok, McClamroch, CDC 2010), in NED/FRD.

With e3 = (0, 0, 1) pointing down, the paper's equations hold as written: m x'' = m g e3 - f R e3,
J W' + W x J W = M. Per step:

    e_x = x - x_d, e_v = v - v_d
    F   = -k_x sat(e_x) - k_v e_v + m x_d'' - m g e3 - F_drag(v)      (force the rotors must supply, NED)
    b3c = -F / |F| (tilt-limited), f = -F . R e3                      (collective thrust, N)
    b1d = (cos psi_d, sin psi_d, 0);  b2c = b3c x b1d / |.|;  Rc = [b2c x b3c, b2c, b3c]
    e_R = vee(Rc^T R - R^T Rc) / 2,  e_W = W - R^T Rc Wc
    M   = -k_R e_R - k_W e_W + W x J W - J (hat(W) R^T Rc Wc - R^T Rc Wc')

Feedforward Wc, Wc' come from the reference's derivatives (acceleration, jerk, snap, yaw and its two
derivatives): the feedforward attitude Rff(t) is built from the flat outputs alone and differentiated by
central differences over a Taylor expansion of the reference (exact to O(h^2) with snap as the highest
derivative; odd terms cancel in the second difference). The drag term uses the vehicle file's body drag
(F_b = -Cd v_b |v_b|), so the controller knows the vehicle the way its mass and inertia are known.

Motor speeds: f1 = f/Ct, f2 = M1/k, f3 = M2/k, f4 = M3/Cm (k = d Ct sqrt(2)/2), then the rotor speeds from
controller.allocation (squared speeds within [0, w_max^2]; yaw, then collective, then roll/pitch give way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from bridge.errors import UserError
from bridge.vehicle import VehicleConfig
from controller.allocation import allocate
from controller.plugin import Command, Reference, VehicleState

E3 = np.array((0.0, 0.0, 1.0))


@dataclass(frozen=True)
class Se3Gains:
    """Gains as bandwidths: k_x = m wn^2, k_v = 2 zeta wn m; k_R = J wn_R^2, k_W = 2 zeta_R wn_R J (per axis).

    Position error saturation and acceleration/tilt limits keep a far-away start (Case I: 3.7 m) gentle.
    """

    position_wn: float = 4.0  # rad/s
    position_zeta: float = 1.0
    attitude_wn: float = 22.0  # rad/s, roll and pitch
    attitude_zeta: float = 0.8
    yaw_wn: float = 8.0  # rad/s
    yaw_zeta: float = 0.9
    max_position_error: float = 1.0  # m, length limit of e_x in the proportional term
    max_acceleration: float = 6.0  # m/s^2, norm limit of the feedback acceleration
    max_tilt: float = math.radians(45.0)  # rad, limit of the commanded thrust axis from vertical
    drag_feedforward: bool = True  # cancel the vehicle file's body drag
    derivative_step: float = 2e-3  # s, step of the central differences for Wc, Wc'

    @classmethod
    def from_mapping(cls, data: dict[str, Any] | None, where: str = "se3 gains") -> Se3Gains:
        """Gains from a mapping (e.g. the `se3:` section of a gains YAML); unknown keys are a UserError."""
        if not data:
            return cls()
        if not isinstance(data, dict):
            raise UserError(f"{where}: expected a mapping of gain names to numbers, "
                            f"got {type(data).__name__}")
        names = {f.name: f for f in fields(cls)}
        values: dict[str, Any] = {}
        for key, value in data.items():
            if key not in names:
                raise UserError(f"{where}: unknown gain {key!r}", hint=f"known gains: {', '.join(names)}")
            if names[key].type in ("bool", bool):
                if not isinstance(value, bool):
                    raise UserError(f"{where}: gain {key!r} must be true or false, got {value!r}")
                values[key] = value
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value <= 0:
                raise UserError(f"{where}: gain {key!r} must be a positive number, got {value!r}")
            values[key] = float(value)
        return cls(**values)


def hat(v: np.ndarray) -> np.ndarray:
    """The skew-symmetric matrix of a 3-vector (hat(a) b = a x b)."""
    return np.array(((0.0, -v[2], v[1]), (v[2], 0.0, -v[0]), (-v[1], v[0], 0.0)))


def vee(m: np.ndarray) -> np.ndarray:
    """The 3-vector of a skew-symmetric matrix (inverse of hat)."""
    return np.array((m[2, 1], m[0, 2], m[1, 0]))


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation matrix body->earth of a scalar-first unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array((
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    ))


def rotation_from_euler(phi: float, theta: float, psi: float) -> np.ndarray:
    """R = Rz(psi) Ry(theta) Rx(phi), body->earth, of ZYX Euler angles (rad)."""
    cf, sf = math.cos(phi), math.sin(phi)
    ct, st = math.cos(theta), math.sin(theta)
    cp, sp = math.cos(psi), math.sin(psi)
    return np.array((
        (ct * cp, sf * st * cp - cf * sp, cf * st * cp + sf * sp),
        (ct * sp, sf * st * sp + cf * cp, cf * st * sp - sf * cp),
        (-st, sf * ct, cf * ct),
    ))


def state_rotation(state: VehicleState) -> np.ndarray:
    """Body->earth rotation of a VehicleState: from its quaternion when given, else from its Euler angles."""
    if state.quaternion is not None:
        return rotation_from_quaternion(np.asarray(state.quaternion, dtype=float))
    return rotation_from_euler(*state.xi[6:9])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of two 3-vectors (np.cross costs ~15 us on 3-vectors; this ~1 us)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))


def attitude_from_axis(b3: np.ndarray, yaw: float) -> np.ndarray:
    """Lee's desired attitude: body z = b3 (unit, NED), body x the projection of the heading (cos, sin, 0)."""
    z0, z1, z2 = (float(c) for c in b3)
    c, s = math.cos(yaw), math.sin(yaw)
    # b2 = b3 x (c, s, 0)
    y0, y1, y2 = -z2 * s, z2 * c, z0 * s - z1 * c
    n = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    if n < 1e-9:  # heading along the thrust axis: use east as the reference instead
        y0, y1, y2 = -z2, 0.0, z0
        n = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    y0, y1, y2 = y0 / n, y1 / n, y2 / n
    # b1 = b2 x b3
    x0, x1, x2 = y1 * z2 - y2 * z1, y2 * z0 - y0 * z2, y0 * z1 - y1 * z0
    return np.array(((x0, y0, z0), (x1, y1, z1), (x2, y2, z2)))


class Se3Controller:
    """Lee-Leok-McClamroch geometric tracking on SE(3) for a vehicle file's mass, inertia and rotors."""

    name = "se3"

    def __init__(self, vehicle: VehicleConfig, gains: Se3Gains | None = None):
        self.vehicle = vehicle
        self.gains = gains or Se3Gains()
        g = self.gains
        self.m = vehicle.mass
        self.g = vehicle.gravity
        self.J = np.array(vehicle.inertia, dtype=float)
        self.kx = self.m * g.position_wn ** 2
        self.kv = 2.0 * g.position_zeta * g.position_wn * self.m
        jd = np.diag(self.J)
        self.kR = jd * np.array((g.attitude_wn ** 2, g.attitude_wn ** 2, g.yaw_wn ** 2))
        self.kW = jd * 2.0 * np.array((g.attitude_zeta * g.attitude_wn, g.attitude_zeta * g.attitude_wn,
                                       g.yaw_zeta * g.yaw_wn))
        self.cd = np.array(vehicle.drag.body_quadratic, dtype=float)
        self.w_max = vehicle.motor_curve.max_speed
        k = vehicle.mixer_gain
        self._f_scale = np.array((1.0 / vehicle.thrust_coefficient, 1.0 / k, 1.0 / k,
                                  1.0 / vehicle.moment_coefficient))
        self.cos_tilt = math.cos(g.max_tilt)

    def reset(self) -> None:
        """Nothing to clear: the law has no integrator or filter state."""

    def _drag(self, R: np.ndarray, v: np.ndarray) -> np.ndarray:
        vb = R.T @ v
        return R @ (-self.cd * vb * np.abs(vb))

    def _feedforward_attitude(self, a: np.ndarray, yaw: float) -> np.ndarray:
        f0, f1, f2 = a[0], a[1], a[2] - self.g
        n = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
        return attitude_from_axis((-f0 / n, -f1 / n, -f2 / n), yaw)

    def _feedforward_rates(self, ref: Reference) -> tuple[np.ndarray, np.ndarray]:
        """Wc and Wc' (body FRD, rad/s and rad/s^2) of the feedforward attitude along the reference."""
        h = self.gains.derivative_step
        a, j, s = ref.acceleration, ref.jerk, ref.snap
        hh = 0.5 * h * h
        y, yd, ydd = ref.yaw, ref.yaw_rate, ref.yaw_acceleration
        r_minus = self._feedforward_attitude(a - j * h + s * hh, y - yd * h + ydd * hh)
        r0 = self._feedforward_attitude(a, y)
        r_plus = self._feedforward_attitude(a + j * h + s * hh, y + yd * h + ydd * hh)
        rdot = (r_plus - r_minus) / (2.0 * h)
        rddot = (r_plus - 2.0 * r0 + r_minus) / (h * h)
        w_hat = r0.T @ rdot
        w = vee(0.5 * (w_hat - w_hat.T))
        # R'' = R (hat(W)^2 + hat(W')) => hat(W') = R^T R'' - hat(W)^2
        wd_hat = r0.T @ rddot - hat(w) @ hat(w)
        wd = vee(0.5 * (wd_hat - wd_hat.T))
        return w, wd

    def update(self, t: float, state: VehicleState, reference: Reference) -> Command:
        """Motor speeds [rad/s] tracking the reference position NED and yaw (see the module doc)."""
        g = self.gains
        xi = state.xi
        R = state_rotation(state)
        W = xi[9:12]
        ex = xi[0:3] - reference.position
        ev = xi[3:6] - reference.velocity
        ne = math.sqrt(float(ex @ ex))
        if ne > g.max_position_error:  # keep the direction: a straight path to a far reference
            ex = ex * (g.max_position_error / ne)
        a_fb = -(self.kx * ex + self.kv * ev) / self.m
        n = math.sqrt(float(a_fb @ a_fb))
        if n > g.max_acceleration:
            a_fb *= g.max_acceleration / n
        F = self.m * (a_fb + reference.acceleration - self.g * E3)
        if g.drag_feedforward:
            F = F - self._drag(R, xi[3:6])
        # thrust axis b3c = -F/|F|, its angle from e3 limited (the vertical component of F keeps its value)
        b3c = -F / math.sqrt(float(F @ F))
        if b3c[2] < self.cos_tilt:
            horiz = np.hypot(b3c[0], b3c[1])
            s = math.sin(g.max_tilt) / horiz if horiz > 1e-12 else 0.0
            b3c = np.array((b3c[0] * s, b3c[1] * s, self.cos_tilt))
        thrust = max(float(-F @ R[:, 2]), 0.0)
        Rc = attitude_from_axis(b3c, reference.yaw)
        Wc, Wc_dot = self._feedforward_rates(reference)
        RtRc = R.T @ Rc
        eR_hat = 0.5 * (Rc.T @ R - R.T @ Rc)
        eR = vee(eR_hat)
        wr = RtRc @ Wc
        eW = W - wr
        JW = self.J @ W
        M = -self.kR * eR - self.kW * eW + cross(W, JW) - self.J @ (cross(W, wr) - RtRc @ Wc_dot)
        f = self._f_scale * np.array((thrust, M[0], M[1], M[2]))
        alloc = allocate(f, self.w_max)
        return Command(alloc.speeds, alloc.saturated, {"thrust": thrust, "torque": M, "f": f})
