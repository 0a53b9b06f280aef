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
from dataclasses import dataclass
from typing import Any

import numpy as np

from bridge.rotations import rotation_from_euler as rotation_from_euler_rows
from bridge.rotations import rotation_from_quaternion as rotation_from_quaternion_rows
from bridge.vehicle import VehicleConfig
from bridge.yaml_file import Section, read_dataclass
from controller.allocation import allocate
from controller.plugin import Command, Reference, VehicleState, as_floats


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
        """Gains from a mapping of positive numbers (e.g. the `se3:` section of a gains YAML)."""
        return read_dataclass(Section(where, data or {}, noun="gain"), cls, positive=True)


def hat(v: np.ndarray) -> np.ndarray:
    """The skew-symmetric matrix of a 3-vector (hat(a) b = a x b)."""
    return np.array(((0.0, -v[2], v[1]), (v[2], 0.0, -v[0]), (-v[1], v[0], 0.0)))


def vee(m: np.ndarray) -> np.ndarray:
    """The 3-vector of a skew-symmetric matrix (inverse of hat)."""
    return np.array((m[2, 1], m[0, 2], m[1, 0]))


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation matrix body->earth of a scalar-first unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array(rotation_from_quaternion_rows(w, x, y, z)).reshape(3, 3)


def rotation_from_euler(phi: float, theta: float, psi: float) -> np.ndarray:
    """R = Rz(psi) Ry(theta) Rx(phi), body->earth, of ZYX Euler angles (rad)."""
    return np.array(rotation_from_euler_rows(phi, theta, psi)).reshape(3, 3)


def _state_rotation(state: VehicleState, xi: list[float]) -> tuple[float, ...]:
    """Body->earth rotation of a VehicleState (xi as floats), 9 floats row by row."""
    if state.quaternion is not None:
        w, x, y, z = as_floats(state.quaternion)
        return rotation_from_quaternion_rows(w, x, y, z)
    return rotation_from_euler_rows(xi[6], xi[7], xi[8])


def state_rotation(state: VehicleState) -> np.ndarray:
    """Body->earth rotation of a VehicleState: from its quaternion when given, else from its Euler angles."""
    return np.array(_state_rotation(state, as_floats(state.xi))).reshape(3, 3)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of two 3-vectors (np.cross costs ~15 us on 3-vectors; this ~1 us)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))


def _attitude_from_axis(z0: float, z1: float, z2: float, yaw: float) -> tuple[float, ...]:
    """attitude_from_axis on floats: the rotation (b1, b2, b3 as columns) as 9 floats row by row."""
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
    return x0, y0, z0, x1, y1, z1, x2, y2, z2


def attitude_from_axis(b3: np.ndarray, yaw: float) -> np.ndarray:
    """Lee's desired attitude: body z = b3 (unit, NED), body x the projection of the heading (cos, sin, 0)."""
    z0, z1, z2 = (float(c) for c in b3)
    return np.array(_attitude_from_axis(z0, z1, z2, yaw)).reshape(3, 3)


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
        self.sin_tilt = math.sin(g.max_tilt)
        # the same constants as plain floats for the per-step law (numpy costs ~1 us per 3-vector operation)
        self._j = tuple(self.J.ravel().tolist())
        self._kr = tuple(self.kR.tolist())
        self._kw = tuple(self.kW.tolist())
        self._cd = tuple(self.cd.tolist())
        self._fs = tuple(self._f_scale.tolist())

    def reset(self) -> None:
        """Nothing to clear: the law has no integrator or filter state."""

    def _ff_attitude(self, a0: float, a1: float, a2: float, yaw: float) -> tuple[float, ...]:
        """_feedforward_attitude on floats: 9 floats row by row."""
        f0, f1, f2 = a0, a1, a2 - self.g
        n = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
        return _attitude_from_axis(-f0 / n, -f1 / n, -f2 / n, yaw)

    def _feedforward_attitude(self, a: np.ndarray, yaw: float) -> np.ndarray:
        """Attitude whose thrust axis gives the acceleration a [m/s^2, NED] at heading yaw [rad]."""
        return np.array(self._ff_attitude(a[0], a[1], a[2], yaw)).reshape(3, 3)

    def _ff_rates(self, ref: Reference) -> tuple[float, ...]:
        """_feedforward_rates on floats: Wc [rad/s] then Wc' [rad/s^2], 6 floats."""
        h = self.gains.derivative_step
        a0, a1, a2 = as_floats(ref.acceleration)
        j0, j1, j2 = as_floats(ref.jerk)
        s0, s1, s2 = as_floats(ref.snap)
        hh = 0.5 * h * h
        y, yd, ydd = ref.yaw, ref.yaw_rate, ref.yaw_acceleration
        m00, m01, m02, m10, m11, m12, m20, m21, m22 = self._ff_attitude(
            a0 - j0 * h + s0 * hh, a1 - j1 * h + s1 * hh, a2 - j2 * h + s2 * hh, y - yd * h + ydd * hh)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = self._ff_attitude(a0, a1, a2, y)
        p00, p01, p02, p10, p11, p12, p20, p21, p22 = self._ff_attitude(
            a0 + j0 * h + s0 * hh, a1 + j1 * h + s1 * hh, a2 + j2 * h + s2 * hh, y + yd * h + ydd * hh)
        # R' and R'' by central differences
        h2 = 2.0 * h
        d00, d01, d02 = (p00 - m00) / h2, (p01 - m01) / h2, (p02 - m02) / h2
        d10, d11, d12 = (p10 - m10) / h2, (p11 - m11) / h2, (p12 - m12) / h2
        d20, d21, d22 = (p20 - m20) / h2, (p21 - m21) / h2, (p22 - m22) / h2
        hsq = h * h
        e00 = (p00 - 2.0 * r00 + m00) / hsq
        e01 = (p01 - 2.0 * r01 + m01) / hsq
        e02 = (p02 - 2.0 * r02 + m02) / hsq
        e10 = (p10 - 2.0 * r10 + m10) / hsq
        e11 = (p11 - 2.0 * r11 + m11) / hsq
        e12 = (p12 - 2.0 * r12 + m12) / hsq
        e20 = (p20 - 2.0 * r20 + m20) / hsq
        e21 = (p21 - 2.0 * r21 + m21) / hsq
        e22 = (p22 - 2.0 * r22 + m22) / hsq
        # hat(W) = R0^T R' (A_ij = sum_k r0_ki R'_kj), W = vee of its skew part
        a21, a12 = r02 * d01 + r12 * d11 + r22 * d21, r01 * d02 + r11 * d12 + r21 * d22
        a02, a20 = r00 * d02 + r10 * d12 + r20 * d22, r02 * d00 + r12 * d10 + r22 * d20
        a10, a01 = r01 * d00 + r11 * d10 + r21 * d20, r00 * d01 + r10 * d11 + r20 * d21
        w0, w1, w2 = 0.5 * (a21 - a12), 0.5 * (a02 - a20), 0.5 * (a10 - a01)
        # R'' = R (hat(W)^2 + hat(W')) => hat(W') = R^T R'' - hat(W)^2; hat(W)^2 = W W^T - |W|^2 I
        s12, s02, s01 = w1 * w2, w0 * w2, w0 * w1
        a21, a12 = r02 * e01 + r12 * e11 + r22 * e21, r01 * e02 + r11 * e12 + r21 * e22
        a02, a20 = r00 * e02 + r10 * e12 + r20 * e22, r02 * e00 + r12 * e10 + r22 * e20
        a10, a01 = r01 * e00 + r11 * e10 + r21 * e20, r00 * e01 + r10 * e11 + r20 * e21
        wd0 = 0.5 * ((a21 - s12) - (a12 - s12))
        wd1 = 0.5 * ((a02 - s02) - (a20 - s02))
        wd2 = 0.5 * ((a10 - s01) - (a01 - s01))
        return w0, w1, w2, wd0, wd1, wd2

    def _feedforward_rates(self, ref: Reference) -> tuple[np.ndarray, np.ndarray]:
        """Wc and Wc' (body FRD, rad/s and rad/s^2) of the feedforward attitude along the reference."""
        w0, w1, w2, wd0, wd1, wd2 = self._ff_rates(ref)
        return np.array((w0, w1, w2)), np.array((wd0, wd1, wd2))

    def update(self, t: float, state: VehicleState, reference: Reference) -> Command:
        """Motor speeds [rad/s] tracking the reference position NED and yaw (see the module doc)."""
        g = self.gains
        xi = as_floats(state.xi)
        R00, R01, R02, R10, R11, R12, R20, R21, R22 = _state_rotation(state, xi)
        px, py, pz, vx, vy, vz = xi[0:6]
        W0, W1, W2 = xi[9:12]
        rpx, rpy, rpz = as_floats(reference.position)
        rvx, rvy, rvz = as_floats(reference.velocity)
        rax, ray, raz = as_floats(reference.acceleration)
        ex, ey, ez = px - rpx, py - rpy, pz - rpz
        ne = math.sqrt(ex * ex + ey * ey + ez * ez)
        if ne > g.max_position_error:  # keep the direction: a straight path to a far reference
            c = g.max_position_error / ne
            ex, ey, ez = ex * c, ey * c, ez * c
        m, kx, kv = self.m, self.kx, self.kv
        a0 = -(kx * ex + kv * (vx - rvx)) / m
        a1 = -(kx * ey + kv * (vy - rvy)) / m
        a2 = -(kx * ez + kv * (vz - rvz)) / m
        n = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        if n > g.max_acceleration:
            c = g.max_acceleration / n
            a0, a1, a2 = a0 * c, a1 * c, a2 * c
        F0, F1, F2 = m * (a0 + rax), m * (a1 + ray), m * (a2 + raz - self.g)
        if g.drag_feedforward:  # F_b = -Cd v_b |v_b| with v_b = R^T v, back to NED
            cd0, cd1, cd2 = self._cd
            b0 = R00 * vx + R10 * vy + R20 * vz
            b1 = R01 * vx + R11 * vy + R21 * vz
            b2 = R02 * vx + R12 * vy + R22 * vz
            b0, b1, b2 = -cd0 * b0 * abs(b0), -cd1 * b1 * abs(b1), -cd2 * b2 * abs(b2)
            F0 -= R00 * b0 + R01 * b1 + R02 * b2
            F1 -= R10 * b0 + R11 * b1 + R12 * b2
            F2 -= R20 * b0 + R21 * b1 + R22 * b2
        # thrust axis b3c = -F/|F|, its angle from e3 limited (the vertical component of F keeps its value)
        n = math.sqrt(F0 * F0 + F1 * F1 + F2 * F2)
        z0, z1, z2 = -F0 / n, -F1 / n, -F2 / n
        if z2 < self.cos_tilt:
            horiz = float(np.hypot(z0, z1))  # libm hypot, as before (math.hypot can differ by 1 ulp)
            s = self.sin_tilt / horiz if horiz > 1e-12 else 0.0
            z0, z1, z2 = z0 * s, z1 * s, self.cos_tilt
        thrust = max(-F0 * R02 - F1 * R12 - F2 * R22, 0.0)
        C00, C01, C02, C10, C11, C12, C20, C21, C22 = _attitude_from_axis(z0, z1, z2, reference.yaw)
        wc0, wc1, wc2, wcd0, wcd1, wcd2 = self._ff_rates(reference)
        # P = R^T Rc; e_R = vee(Rc^T R - R^T Rc) / 2 = (P12 - P21, P20 - P02, P01 - P10) / 2
        P00 = R00 * C00 + R10 * C10 + R20 * C20
        P01 = R00 * C01 + R10 * C11 + R20 * C21
        P02 = R00 * C02 + R10 * C12 + R20 * C22
        P10 = R01 * C00 + R11 * C10 + R21 * C20
        P11 = R01 * C01 + R11 * C11 + R21 * C21
        P12 = R01 * C02 + R11 * C12 + R21 * C22
        P20 = R02 * C00 + R12 * C10 + R22 * C20
        P21 = R02 * C01 + R12 * C11 + R22 * C21
        P22 = R02 * C02 + R12 * C12 + R22 * C22
        eR0, eR1, eR2 = 0.5 * (P12 - P21), 0.5 * (P20 - P02), 0.5 * (P01 - P10)
        # wr = P Wc, e_W = W - wr; pd = P Wc'
        wr0 = P00 * wc0 + P01 * wc1 + P02 * wc2
        wr1 = P10 * wc0 + P11 * wc1 + P12 * wc2
        wr2 = P20 * wc0 + P21 * wc1 + P22 * wc2
        pd0 = P00 * wcd0 + P01 * wcd1 + P02 * wcd2
        pd1 = P10 * wcd0 + P11 * wcd1 + P12 * wcd2
        pd2 = P20 * wcd0 + P21 * wcd1 + P22 * wcd2
        J00, J01, J02, J10, J11, J12, J20, J21, J22 = self._j
        jw0 = J00 * W0 + J01 * W1 + J02 * W2
        jw1 = J10 * W0 + J11 * W1 + J12 * W2
        jw2 = J20 * W0 + J21 * W1 + J22 * W2
        # u = W x wr - P Wc'; M = -k_R e_R - k_W e_W + W x J W - J u
        u0 = W1 * wr2 - W2 * wr1 - pd0
        u1 = W2 * wr0 - W0 * wr2 - pd1
        u2 = W0 * wr1 - W1 * wr0 - pd2
        kr0, kr1, kr2 = self._kr
        kw0, kw1, kw2 = self._kw
        M0 = -kr0 * eR0 - kw0 * (W0 - wr0) + (W1 * jw2 - W2 * jw1) - (J00 * u0 + J01 * u1 + J02 * u2)
        M1 = -kr1 * eR1 - kw1 * (W1 - wr1) + (W2 * jw0 - W0 * jw2) - (J10 * u0 + J11 * u1 + J12 * u2)
        M2 = -kr2 * eR2 - kw2 * (W2 - wr2) + (W0 * jw1 - W1 * jw0) - (J20 * u0 + J21 * u1 + J22 * u2)
        fs0, fs1, fs2, fs3 = self._fs
        f = [fs0 * thrust, fs1 * M0, fs2 * M1, fs3 * M2]
        alloc = allocate(f, self.w_max)
        return Command(alloc.speeds, alloc.saturated,
                       {"thrust": thrust, "torque": np.array((M0, M1, M2)), "f": np.array(f)})
