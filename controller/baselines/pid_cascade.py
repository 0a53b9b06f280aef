"""A PX4-style cascade (mc_pos_control, mc_att_control, mc_rate_control, allocation) with PX4's defaults.

Loops, all at the 250 Hz control rate, NED/FRD:
  position P            v_sp = v_d + P_pos (p_d - p), limited to the velocity limits
  velocity PID          a_sp = a_d + P_vel (v_sp - v) + I_vel int(...) - D_vel dv/dt (dv/dt low-passed, 5 Hz),
                        with PX4's vertical-priority thrust limits and tracking anti-windup
  thrust and attitude   body z from (-a_x, -a_y, g), tilt-limited; collective thrust in PX4's normalised units
                        (hover thrust = m g / T_max); attitude setpoint from body z and yaw (bodyzToAttitude)
  attitude P            PX4's quaternion law, reduced yaw priority (MC_YAW_WEIGHT), rate limits, yaw-rate FF
  rate PID              normalised torque = P e + I int(e) - D dW/dt (dW/dt low-passed at 30 Hz), PX4's
                        integrator limit and i-factor; yaw torque low-passed (MC_YAW_TQ_CUTOFF)
  mixing                PX4's normalised Quad-X pseudo-inverse (roll/pitch column entries +-sqrt(2)/2,
                        yaw +-1, thrust 1) with sequential desaturation as with airmode off, into per-motor
                        normalised thrust n_i in [0, 1], then rotor speed w_i = w_max sqrt(n_i).

Scaling PX4's gains to this vehicle: PX4's rate loop outputs torque normalised so that +-1 is the torque of
its mixer's full differential, i.e. with per-motor thrust T_i = n_i Ct w_max^2:
  roll/pitch: 1 -> 4 (sqrt(2)/2) k w_max^2 = 2 sqrt(2) k w_max^2 (k = d Ct sqrt(2)/2)   (5.04 N m here)
  yaw:        1 -> 4 Cm w_max^2                                                         (0.72 N m here)
  thrust:     1 -> 4 Ct w_max^2                                                         (44.8 N here)
so a gain G keeps its meaning per unit of this vehicle's authority: the angular acceleration it commands per
rad/s of rate error is G tau_max / J (roll: 0.15 * 5.04 / 0.0211 = 36 rad/s^2 per rad/s). The position and
velocity gains are in m/s and m/s^2 already and are used as they are.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from bridge.rotations import quaternion_from_euler, quaternion_from_rotation
from bridge.vehicle import EXCHANGE_STEP, VehicleConfig
from bridge.yaml_file import Section, read_dataclass
from controller.plugin import Command, Reference, VehicleState, as_floats

SQRT1_2 = math.sqrt(0.5)


@dataclass(frozen=True)
class PidCascadeGains:
    """PX4 parameters (defaults of PX4 v1.14+ mc_pos_control, mc_att_control, mc_rate_control), PX4 units."""

    MPC_XY_P: float = 0.95  # 1/s
    MPC_Z_P: float = 1.0  # 1/s
    MPC_XY_VEL_P_ACC: float = 1.8  # 1/s
    MPC_XY_VEL_I_ACC: float = 0.4  # 1/s^2
    MPC_XY_VEL_D_ACC: float = 0.2  # 1
    MPC_Z_VEL_P_ACC: float = 4.0  # 1/s
    MPC_Z_VEL_I_ACC: float = 2.0  # 1/s^2
    MPC_Z_VEL_D_ACC: float = 0.0  # 1
    MPC_XY_VEL_MAX: float = 12.0  # m/s
    MPC_Z_VEL_MAX_UP: float = 3.0  # m/s
    MPC_Z_VEL_MAX_DN: float = 1.5  # m/s
    MPC_TILTMAX_AIR: float = 45.0  # deg
    MPC_THR_MIN: float = 0.12  # normalised
    MPC_THR_MAX: float = 1.0  # normalised
    MPC_THR_XY_MARG: float = 0.3  # normalised
    MPC_VELD_LP: float = 5.0  # Hz
    MC_ROLL_P: float = 6.5  # 1/s
    MC_PITCH_P: float = 6.5  # 1/s
    MC_YAW_P: float = 2.8  # 1/s
    MC_YAW_WEIGHT: float = 0.4
    MC_ROLLRATE_MAX: float = 220.0  # deg/s
    MC_PITCHRATE_MAX: float = 220.0  # deg/s
    MC_YAWRATE_MAX: float = 200.0  # deg/s
    MC_ROLLRATE_P: float = 0.15
    MC_ROLLRATE_I: float = 0.2
    MC_ROLLRATE_D: float = 0.003
    MC_RR_INT_LIM: float = 0.3
    MC_PITCHRATE_P: float = 0.15
    MC_PITCHRATE_I: float = 0.2
    MC_PITCHRATE_D: float = 0.003
    MC_PR_INT_LIM: float = 0.3
    MC_YAWRATE_P: float = 0.2
    MC_YAWRATE_I: float = 0.1
    MC_YAWRATE_D: float = 0.0
    MC_YR_INT_LIM: float = 0.3
    MC_YAW_TQ_CUTOFF: float = 2.0  # Hz (0: off)
    IMU_DGYRO_CUTOFF: float = 30.0  # Hz, low-pass of the rate derivative for the D term

    @classmethod
    def from_mapping(cls, data: dict[str, Any] | None, where: str = "pid gains") -> PidCascadeGains:
        """Gains from a mapping of PX4 parameter names to numbers >= 0 (a gains YAML's `pid:` section)."""
        return read_dataclass(Section(where, data or {}, noun="parameter"), cls)


# ---- quaternion helpers on plain floats (w, x, y, z), body -> earth ------------------------------------
# (products, inverses and axis rotations are written out in PidCascadeController._rate_setpoint: they run
# every control step, and numpy or a helper call per 4-vector costs more than the arithmetic)
def _q_from_two_vectors(src: tuple, dst: tuple) -> tuple:
    """Shortest rotation taking unit vector src to unit vector dst (PX4's Quatf(src, dst))."""
    cx = src[1] * dst[2] - src[2] * dst[1]
    cy = src[2] * dst[0] - src[0] * dst[2]
    cz = src[0] * dst[1] - src[1] * dst[0]
    d = src[0] * dst[0] + src[1] * dst[1] + src[2] * dst[2]
    if d < -1.0 + 1e-6:  # opposite: rotate pi about any axis orthogonal to src
        if abs(src[0]) > abs(src[2]):
            qw, qx, qy, qz = 0.0, src[1], -src[0], 0.0
        else:
            qw, qx, qy, qz = 0.0, 0.0, src[2], -src[1]
    else:
        qw, qx, qy, qz = d + math.sqrt(d * d + cx * cx + cy * cy + cz * cz), cx, cy, cz
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return qw / n, qx / n, qy / n, qz / n


def body_z_to_attitude(body_z: tuple, yaw: float) -> tuple:
    """PX4's ControlMath::bodyzToAttitude: attitude quaternion with body z = body_z (NED) and heading yaw."""
    bz0, bz1, bz2 = body_z
    n = math.sqrt(bz0 * bz0 + bz1 * bz1 + bz2 * bz2)
    if n < 1e-9:
        bz0, bz1, bz2, n = 0.0, 0.0, 1.0, 1.0
    bz0, bz1, bz2 = bz0 / n, bz1 / n, bz2 / n
    yc0, yc1 = -math.sin(yaw), math.cos(yaw)  # desired heading rotated by pi/2, y_C = (yc0, yc1, 0)
    bx0, bx1, bx2 = yc1 * bz2, -yc0 * bz2, yc0 * bz1 - yc1 * bz0  # y_C x body_z
    if bz2 < 0.0:
        bx0, bx1, bx2 = -bx0, -bx1, -bx2
    if abs(bz2) < 1e-6:
        bx0, bx1, bx2 = 0.0, 0.0, 1.0
    n = math.sqrt(bx0 * bx0 + bx1 * bx1 + bx2 * bx2)
    bx0, bx1, bx2 = bx0 / n, bx1 / n, bx2 / n
    by0, by1, by2 = bz1 * bx2 - bz2 * bx1, bz2 * bx0 - bz0 * bx2, bz0 * bx1 - bz1 * bx0
    return quaternion_from_rotation(((bx0, by0, bz0), (bx1, by1, bz1), (bx2, by2, bz2)))


Vec3 = tuple[float, float, float]


def _filtered_derivative(est: list[float], prev: Vec3 | None, now: Vec3, alpha: float, dt: float) -> Vec3:
    """Low-pass (alpha per step) the finite difference (now - prev) / dt into est, in place; returns now."""
    if prev is not None:
        est[0] += alpha * ((now[0] - prev[0]) / dt - est[0])
        est[1] += alpha * ((now[1] - prev[1]) / dt - est[1])
        est[2] += alpha * ((now[2] - prev[2]) / dt - est[2])
    return now


def _lowpass_alpha(cutoff_hz: float, dt: float) -> float:
    if cutoff_hz <= 0.0:
        return 1.0
    rc = 1.0 / (2.0 * math.pi * cutoff_hz)
    return dt / (dt + rc)


# the mixer's columns as plain floats, motors in PX4 order (1 FR, 2 RL, 3 FL, 4 RR)
_ROLL = (-SQRT1_2, SQRT1_2, SQRT1_2, -SQRT1_2)
_PITCH = (SQRT1_2, -SQRT1_2, SQRT1_2, -SQRT1_2)
_YAW = (1.0, 1.0, -1.0, -1.0)
_DOWN = (-1.0, -1.0, -1.0, -1.0)  # -THRUST: the direction that lowers the collective


class Px4Mixer:
    """PX4's normalised Quad-X allocation with sequential desaturation (airmode off), in per-motor thrust."""

    # columns roll, pitch, yaw of the normalised pseudo-inverse, motors in PX4 order (1 FR, 2 RL, 3 FL, 4 RR)
    ROLL = np.array(_ROLL)
    PITCH = np.array(_PITCH)
    YAW = np.array(_YAW)
    THRUST = np.ones(4)

    def __init__(self, vehicle: VehicleConfig):
        self.w_max = vehicle.motor_curve.max_speed
        w2 = self.w_max ** 2
        self.thrust_max = 4.0 * vehicle.thrust_coefficient * w2  # N at normalised thrust 1
        self.torque_max = np.array((2.0 * math.sqrt(2.0) * vehicle.mixer_gain * w2,
                                    2.0 * math.sqrt(2.0) * vehicle.mixer_gain * w2,
                                    4.0 * vehicle.moment_coefficient * w2))  # N m at normalised torque 1

    @staticmethod
    def _gain(vec: Sequence[float], sp: Sequence[float]) -> float:
        """PX4's computeDesaturationGain: how far along vec to move sp to reduce saturation in [0, 1]."""
        k_min = 0.0
        k_max = 0.0
        for d, s in zip(vec, sp, strict=True):
            if abs(d) < 1e-7:
                continue
            if s < 0.0:
                k = -s / d
            elif s > 1.0:
                k = (1.0 - s) / d
            else:
                continue
            if k < k_min:
                k_min = k
            if k > k_max:
                k_max = k
        return k_min + k_max

    def _desaturate(self, sp: list[float], vec: Sequence[float], increase_only: bool = False) -> list[float]:
        gain = self._gain(vec, sp)
        if increase_only and gain < 0.0:
            return sp
        if gain != 0.0:
            sp = [s + gain * d for s, d in zip(sp, vec, strict=True)]
        gain = 0.5 * self._gain(vec, sp)  # halved second pass balances min and max saturation
        if increase_only and gain < 0.0:
            return sp
        if gain != 0.0:
            sp = [s + gain * d for s, d in zip(sp, vec, strict=True)]
        return sp

    def mix_floats(self, thrust: float, roll: float, pitch: float, yaw: float) -> tuple[list[float], bool]:
        """mix() on floats: per-motor normalised thrust in [0, 1] of thrust and torques; True if clipped."""
        s0 = thrust + roll * _ROLL[0] + pitch * _PITCH[0]
        s1 = thrust + roll * _ROLL[1] + pitch * _PITCH[1]
        s2 = thrust + roll * _ROLL[2] + pitch * _PITCH[2]
        s3 = thrust + roll * _ROLL[3] + pitch * _PITCH[3]
        sp = [s0, s1, s2, s3]
        # within [0, 1] every desaturation gain is 0: skip them
        if not (0.0 <= s0 <= 1.0 and 0.0 <= s1 <= 1.0 and 0.0 <= s2 <= 1.0 and 0.0 <= s3 <= 1.0):
            sp = self._desaturate(sp, _DOWN, increase_only=True)  # only ever reduce thrust
            sp = self._desaturate(sp, _ROLL)
            sp = self._desaturate(sp, _PITCH)
        # yaw mixed separately: its authority is reduced to unsaturate, then thrust may be lowered
        s0 = sp[0] + yaw * _YAW[0]
        s1 = sp[1] + yaw * _YAW[1]
        s2 = sp[2] + yaw * _YAW[2]
        s3 = sp[3] + yaw * _YAW[3]
        sp = [s0, s1, s2, s3]
        if not (0.0 <= s0 <= 1.0 and 0.0 <= s1 <= 1.0 and 0.0 <= s2 <= 1.0 and 0.0 <= s3 <= 1.0):
            sp = self._desaturate(sp, _YAW)
            sp = self._desaturate(sp, _DOWN, increase_only=True)
        clipped = False
        for s in sp:
            if s < -1e-9 or s > 1.0 + 1e-9:
                clipped = True
        return [0.0 if s < 0.0 else 1.0 if s > 1.0 else s for s in sp], clipped

    def mix(self, thrust: float, torque: np.ndarray) -> tuple[np.ndarray, bool]:
        """Per-motor normalised thrust in [0, 1] for normalised thrust and torque; True if clipped."""
        out, clipped = self.mix_floats(float(thrust), float(torque[0]), float(torque[1]), float(torque[2]))
        return np.array(out), clipped

    def speeds(self, normalised: np.ndarray) -> np.ndarray:
        """Rotor speeds (rad/s) of per-motor normalised thrust (thrust ~ w^2)."""
        return self.w_max * np.sqrt(normalised)


_RATE_400 = math.radians(400.0)  # rad/s, rate error at which PX4's i-factor stops integrating


class PidCascadeController:
    """PX4's multicopter cascade with default gains, scaled to a vehicle's thrust and torque authority."""

    name = "pid"

    def __init__(self, vehicle: VehicleConfig, gains: PidCascadeGains | None = None,
                 dt: float = EXCHANGE_STEP):
        self.vehicle = vehicle
        self.gains = g = gains or PidCascadeGains()
        self.dt = dt
        self.mixer = Px4Mixer(vehicle)
        self.g = vehicle.gravity
        self.hover_thrust = vehicle.mass * vehicle.gravity / self.mixer.thrust_max
        # per-axis gains as plain float triples (x, y, z) or (roll, pitch, yaw): the step runs on floats
        self.pos_p = (g.MPC_XY_P, g.MPC_XY_P, g.MPC_Z_P)
        self.vel_p = (g.MPC_XY_VEL_P_ACC, g.MPC_XY_VEL_P_ACC, g.MPC_Z_VEL_P_ACC)
        self.vel_i = (g.MPC_XY_VEL_I_ACC, g.MPC_XY_VEL_I_ACC, g.MPC_Z_VEL_I_ACC)
        self.vel_d = (g.MPC_XY_VEL_D_ACC, g.MPC_XY_VEL_D_ACC, g.MPC_Z_VEL_D_ACC)
        self.tilt_max = math.radians(g.MPC_TILTMAX_AIR)
        yaw_w = min(max(g.MC_YAW_WEIGHT, 0.0), 1.0)
        self.yaw_w = yaw_w
        self.att_p = (g.MC_ROLL_P, g.MC_PITCH_P, g.MC_YAW_P / yaw_w if yaw_w > 1e-4 else g.MC_YAW_P)
        self.rate_max = (math.radians(g.MC_ROLLRATE_MAX), math.radians(g.MC_PITCHRATE_MAX),
                         math.radians(g.MC_YAWRATE_MAX))
        self.rate_p = (g.MC_ROLLRATE_P, g.MC_PITCHRATE_P, g.MC_YAWRATE_P)
        self.rate_i = (g.MC_ROLLRATE_I, g.MC_PITCHRATE_I, g.MC_YAWRATE_I)
        self.rate_d = (g.MC_ROLLRATE_D, g.MC_PITCHRATE_D, g.MC_YAWRATE_D)
        self.rate_int_lim = (g.MC_RR_INT_LIM, g.MC_PR_INT_LIM, g.MC_YR_INT_LIM)
        self.a_veld = _lowpass_alpha(g.MPC_VELD_LP, dt)
        self.a_dgyro = _lowpass_alpha(g.IMU_DGYRO_CUTOFF, dt)
        self.a_yaw_tq = _lowpass_alpha(g.MC_YAW_TQ_CUTOFF, dt)
        self._sin_tilt_max = math.sin(self.tilt_max)
        self._cos_tilt_max = math.cos(self.tilt_max)
        self._hover_per_g = self.hover_thrust / self.g  # normalised thrust per m/s^2
        self._g_per_hover = self.g / self.hover_thrust  # m/s^2 per normalised thrust
        self.reset()

    def reset(self) -> None:
        """Clear integrators, derivative filters and the last mixer saturation."""
        self.vel_int = [0.0, 0.0, 0.0]
        self.rate_int = [0.0, 0.0, 0.0]
        self.vel_dot = [0.0, 0.0, 0.0]
        self.ang_acc = [0.0, 0.0, 0.0]
        self.prev_vel: tuple[float, float, float] | None = None
        self.prev_rate: tuple[float, float, float] | None = None
        self.yaw_torque = 0.0
        self.saturated = False

    # --- position and velocity (mc_pos_control) -------------------------------------------------------
    def _thrust_setpoint(self, p: Sequence[float], v: Sequence[float], ref: Reference) -> tuple[float, ...]:
        """Normalised thrust setpoint (NED, hover = hover_thrust) for position p [m] and velocity v [m/s]."""
        g = self.gains
        dt = self.dt
        px, py, pz = p
        vx, vy, vz = v
        rpx, rpy, rpz = as_floats(ref.position)
        rvx, rvy, rvz = as_floats(ref.velocity)
        rax, ray, raz = as_floats(ref.acceleration)
        kp0, kp1, kp2 = self.pos_p
        sx = rvx + kp0 * (rpx - px)
        sy = rvy + kp1 * (rpy - py)
        sz = rvz + kp2 * (rpz - pz)
        xy = math.hypot(sx, sy)
        if xy > g.MPC_XY_VEL_MAX:
            c = g.MPC_XY_VEL_MAX / xy
            sx *= c
            sy *= c
        sz = min(max(sz, -g.MPC_Z_VEL_MAX_UP), g.MPC_Z_VEL_MAX_DN)
        vel_dot = self.vel_dot
        self.prev_vel = _filtered_derivative(vel_dot, self.prev_vel, (vx, vy, vz), self.a_veld, dt)
        vel_int = self.vel_int
        vel_int[2] = min(max(vel_int[2], -self.g), self.g)
        ex, ey, ez = sx - vx, sy - vy, sz - vz
        kv0, kv1, kv2 = self.vel_p
        kd0, kd1, kd2 = self.vel_d
        ax = rax + kv0 * ex + vel_int[0] - kd0 * vel_dot[0]
        ay = ray + kv1 * ey + vel_int[1] - kd1 * vel_dot[1]
        az = raz + kv2 * ez + vel_int[2] - kd2 * vel_dot[2]
        # accelerationControl: tilt from horizontal acceleration, collective thrust from vertical
        bx, by, bz = -ax, -ay, self.g
        n = math.sqrt(bx * bx + by * by + bz * bz)
        bx, by, bz = bx / n, by / n, bz / n
        if math.acos(min(max(bz, -1.0), 1.0)) > self.tilt_max:
            s = self._sin_tilt_max / math.hypot(bx, by)
            bx, by, bz = bx * s, by * s, self._cos_tilt_max
        thrust_ned_z = az * self._hover_per_g - self.hover_thrust
        collective = min(thrust_ned_z / bz, -g.MPC_THR_MIN)
        tx, ty, tz = bx * collective, by * collective, bz * collective
        # vertical anti-windup
        if (tz >= -g.MPC_THR_MIN and ez >= 0.0) or (tz <= -g.MPC_THR_MAX and ez <= 0.0):
            ez = 0.0
        # vertical priority with a horizontal margin
        xy_norm = math.hypot(tx, ty)
        allocated = min(xy_norm, g.MPC_THR_XY_MARG)
        tz = max(tz, -math.sqrt(max(g.MPC_THR_MAX ** 2 - allocated ** 2, 0.0)))
        xy_max_sq = g.MPC_THR_MAX ** 2 - tz ** 2
        xy_max = math.sqrt(xy_max_sq) if xy_max_sq > 0.0 else 0.0
        if xy_norm > xy_max:
            c = xy_max / xy_norm
            tx *= c
            ty *= c
        # tracking anti-windup (horizontal): the acceleration the limited thrust produces
        ux, uy = tx * self._g_per_hover, ty * self._g_per_hover
        if ax * ax + ay * ay > ux * ux + uy * uy:
            c = 2.0 / kv0
            ex -= c * (ax - ux)
            ey -= c * (ay - uy)
        ki0, ki1, ki2 = self.vel_i
        vel_int[0] += ex * ki0 * dt
        vel_int[1] += ey * ki1 * dt
        vel_int[2] += ez * ki2 * dt
        return tx, ty, tz

    # --- attitude (mc_att_control) --------------------------------------------------------------------
    def _rate_setpoint(self, q: Sequence[float], qd: Sequence[float], yaw_rate: float) -> tuple[float, ...]:
        """Body rate setpoint [rad/s, FRD] taking attitude q to qd (w, x, y, z) with yaw-rate FF [rad/s]."""
        w, x, y, z = q
        dw, dx, dy, dz = qd
        # body z axes (third DCM columns) of q and qd; the reduced attitude tilts the one onto the other
        e_z = (2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y))
        e_z_d = (2.0 * (dx * dz + dw * dy), 2.0 * (dy * dz - dw * dx), 1.0 - 2.0 * (dx * dx + dy * dy))
        aw, ax, ay, az = _q_from_two_vectors(e_z, e_z_d)
        if abs(ax) > 1.0 - 1e-5 or abs(ay) > 1.0 - 1e-5:
            rw, rx, ry, rz = dw, dx, dy, dz
        else:  # qd_red = q_from_two_vectors * q
            rw = aw * w - ax * x - ay * y - az * z
            rx = aw * x + ax * w + ay * z - az * y
            ry = aw * y - ax * z + ay * w + az * x
            rz = aw * z + ax * y - ay * x + az * w
        # q_mix = qd_red^-1 * qd, canonical (w >= 0); only its w and z parts are used
        ax, ay, az = -rx, -ry, -rz
        mw = rw * dw - ax * dx - ay * dy - az * dz
        mz = rw * dz + ax * dy - ay * dx + az * dw
        if mw < 0.0:
            mw, mz = -mw, -mz
        w0 = min(max(mw, -1.0), 1.0)
        w3 = min(max(mz, -1.0), 1.0)
        # qd = qd_red * (cos(yw acos w0), 0, 0, sin(yw asin w3)): yaw reached with reduced priority
        cw = math.cos(self.yaw_w * math.acos(w0))
        sz = math.sin(self.yaw_w * math.asin(w3))
        nw = rw * cw - rz * sz
        nx = rx * cw + ry * sz
        ny = -rx * sz + ry * cw
        nz = rw * sz + rz * cw
        # qe = q^-1 * qd, canonical; rate setpoint 2 qe_vec P
        ax, ay, az = -x, -y, -z
        ew = w * nw - ax * nx - ay * ny - az * nz
        ex = w * nx + ax * nw + ay * nz - az * ny
        ey = w * ny - ax * nz + ay * nw + az * nx
        ez = w * nz + ax * ny - ay * nx + az * nw
        if ew < 0.0:
            ex, ey, ez = -ex, -ey, -ez
        p0, p1, p2 = self.att_p
        m0, m1, m2 = self.rate_max
        # plus the yaw-rate feedforward (0, 0, yaw_rate) in body coordinates: R^T e3 yaw_rate
        r0 = 2.0 * ex * p0 + 2 * (x * z - w * y) * yaw_rate
        r1 = 2.0 * ey * p1 + 2 * (y * z + w * x) * yaw_rate
        r2 = 2.0 * ez * p2 + (1 - 2 * (x * x + y * y)) * yaw_rate
        return (-m0 if r0 < -m0 else m0 if r0 > m0 else r0,
                -m1 if r1 < -m1 else m1 if r1 > m1 else r1,
                -m2 if r2 < -m2 else m2 if r2 > m2 else r2)

    # --- rates (mc_rate_control) ----------------------------------------------------------------------
    def _torque(self, rate: Sequence[float], rate_sp: Sequence[float]) -> list[float]:
        """Normalised torque (roll, pitch, yaw) for body rates and their setpoint [rad/s, FRD]."""
        dt = self.dt
        wx, wy, wz = rate
        acc = self.ang_acc
        self.prev_rate = _filtered_derivative(acc, self.prev_rate, (wx, wy, wz), self.a_dgyro, dt)
        err = (rate_sp[0] - wx, rate_sp[1] - wy, rate_sp[2] - wz)
        kp, ki, kd = self.rate_p, self.rate_i, self.rate_d
        rate_int = self.rate_int
        torque = [kp[0] * err[0] + rate_int[0] - kd[0] * acc[0],
                  kp[1] * err[1] + rate_int[1] - kd[1] * acc[1],
                  kp[2] * err[2] + rate_int[2] - kd[2] * acc[2]]
        if not self.saturated:
            lim = self.rate_int_lim
            for i in range(3):
                e = err[i]
                i_factor = 1.0 - (e / _RATE_400) ** 2
                if i_factor < 0.0:
                    i_factor = 0.0
                v = rate_int[i] + i_factor * ki[i] * e * dt
                rate_int[i] = -lim[i] if v < -lim[i] else lim[i] if v > lim[i] else v
        self.yaw_torque += self.a_yaw_tq * (torque[2] - self.yaw_torque)
        torque[2] = self.yaw_torque
        return torque

    def update(self, t: float, state: VehicleState, reference: Reference) -> Command:
        """Motor speeds [rad/s] from the cascade for the state and reference at time t [s]."""
        xi = as_floats(state.xi)
        if state.quaternion is not None:
            q = as_floats(state.quaternion)
        else:
            q = quaternion_from_euler(xi[6], xi[7], xi[8])
        tx, ty, tz = self._thrust_setpoint(xi[0:3], xi[3:6], reference)
        collective = math.sqrt(tx * tx + ty * ty + tz * tz)
        qd = body_z_to_attitude((-tx, -ty, -tz), reference.yaw)
        rate_sp = self._rate_setpoint(q, qd, reference.yaw_rate)
        torque = self._torque(xi[9:12], rate_sp)
        mixer = self.mixer
        normalised, clipped = mixer.mix_floats(collective, torque[0], torque[1], torque[2])
        self.saturated = clipped
        w_max = mixer.w_max
        speeds = np.array([w_max * math.sqrt(n) for n in normalised])
        return Command(speeds, clipped, {"thrust_normalised": collective,
                                         "torque_normalised": np.array(torque), "rate_sp": np.array(rate_sp)})
