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
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from bridge.errors import UserError
from bridge.vehicle import EXCHANGE_STEP, VehicleConfig
from controller.plugin import Command, Reference, VehicleState

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
        """Gains from a mapping of PX4 parameter names (e.g. the `pid:` section of a gains YAML)."""
        if not data:
            return cls()
        if not isinstance(data, dict):
            raise UserError(f"{where}: expected a mapping of PX4 parameter names to numbers")
        names = {f.name for f in fields(cls)}
        values: dict[str, float] = {}
        for key, value in data.items():
            if key not in names:
                raise UserError(f"{where}: unknown parameter {key!r}",
                                hint=f"known: {', '.join(sorted(names))}")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value < 0:
                raise UserError(f"{where}: parameter {key!r} must be a number >= 0, got {value!r}")
            values[key] = float(value)
        return cls(**values)


# ---- quaternion helpers on plain floats (w, x, y, z), body -> earth ------------------------------------
def _qmul(a: tuple, b: tuple) -> tuple:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def _qinv(q: tuple) -> tuple:
    return q[0], -q[1], -q[2], -q[3]


def _qcanonical(q: tuple) -> tuple:
    return q if q[0] >= 0.0 else (-q[0], -q[1], -q[2], -q[3])


def _qdcm_z(q: tuple) -> tuple:
    """Third column of the rotation matrix (body z axis in earth coordinates)."""
    w, x, y, z = q
    return 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)


def _qrotate_inv(q: tuple, v: tuple) -> tuple:
    """R^T v: an earth vector in body coordinates."""
    w, x, y, z = q
    vx, vy, vz = v
    return ((1 - 2 * (y * y + z * z)) * vx + 2 * (x * y + w * z) * vy + 2 * (x * z - w * y) * vz,
            2 * (x * y - w * z) * vx + (1 - 2 * (x * x + z * z)) * vy + 2 * (y * z + w * x) * vz,
            2 * (x * z + w * y) * vx + 2 * (y * z - w * x) * vy + (1 - 2 * (x * x + y * y)) * vz)


def _q_from_two_vectors(src: tuple, dst: tuple) -> tuple:
    """Shortest rotation taking unit vector src to unit vector dst (PX4's Quatf(src, dst))."""
    cx = src[1] * dst[2] - src[2] * dst[1]
    cy = src[2] * dst[0] - src[0] * dst[2]
    cz = src[0] * dst[1] - src[1] * dst[0]
    d = src[0] * dst[0] + src[1] * dst[1] + src[2] * dst[2]
    if d < -1.0 + 1e-6:  # opposite: rotate pi about any axis orthogonal to src
        if abs(src[0]) > abs(src[2]):
            q = (0.0, src[1], -src[0], 0.0)
        else:
            q = (0.0, 0.0, src[2], -src[1])
    else:
        q = (d + math.sqrt(d * d + cx * cx + cy * cy + cz * cz), cx, cy, cz)
    n = math.sqrt(sum(c * c for c in q))
    return q[0] / n, q[1] / n, q[2] / n, q[3] / n


def _q_from_dcm(r: tuple) -> tuple:
    """Unit quaternion of a rotation matrix given as rows ((r00, r01, r02), ...)."""
    (a, b, c), (d, e, f), (g, h, i) = r
    tr = a + e + i
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = (0.25 * s, (h - f) / s, (c - g) / s, (d - b) / s)
    elif a > e and a > i:
        s = math.sqrt(1.0 + a - e - i) * 2.0
        q = ((h - f) / s, 0.25 * s, (b + d) / s, (c + g) / s)
    elif e > i:
        s = math.sqrt(1.0 + e - a - i) * 2.0
        q = ((c - g) / s, (b + d) / s, 0.25 * s, (f + h) / s)
    else:
        s = math.sqrt(1.0 + i - a - e) * 2.0
        q = ((d - b) / s, (c + g) / s, (f + h) / s, 0.25 * s)
    n = math.sqrt(sum(x * x for x in q))
    return q[0] / n, q[1] / n, q[2] / n, q[3] / n


def _q_from_euler(phi: float, theta: float, psi: float) -> tuple:
    cr, sr = math.cos(0.5 * phi), math.sin(0.5 * phi)
    cp, sp = math.cos(0.5 * theta), math.sin(0.5 * theta)
    cy, sy = math.cos(0.5 * psi), math.sin(0.5 * psi)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


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
    return _q_from_dcm(((bx0, by0, bz0), (bx1, by1, bz1), (bx2, by2, bz2)))


def _lowpass_alpha(cutoff_hz: float, dt: float) -> float:
    if cutoff_hz <= 0.0:
        return 1.0
    rc = 1.0 / (2.0 * math.pi * cutoff_hz)
    return dt / (dt + rc)


class Px4Mixer:
    """PX4's normalised Quad-X allocation with sequential desaturation (airmode off), in per-motor thrust."""

    # columns roll, pitch, yaw of the normalised pseudo-inverse, motors in PX4 order (1 FR, 2 RL, 3 FL, 4 RR)
    ROLL = np.array((-SQRT1_2, SQRT1_2, SQRT1_2, -SQRT1_2))
    PITCH = np.array((SQRT1_2, -SQRT1_2, SQRT1_2, -SQRT1_2))
    YAW = np.array((1.0, 1.0, -1.0, -1.0))
    THRUST = np.ones(4)

    def __init__(self, vehicle: VehicleConfig):
        self.w_max = vehicle.motor_curve.max_speed
        w2 = self.w_max ** 2
        self.thrust_max = 4.0 * vehicle.thrust_coefficient * w2  # N at normalised thrust 1
        self.torque_max = np.array((2.0 * math.sqrt(2.0) * vehicle.mixer_gain * w2,
                                    2.0 * math.sqrt(2.0) * vehicle.mixer_gain * w2,
                                    4.0 * vehicle.moment_coefficient * w2))  # N m at normalised torque 1

    @staticmethod
    def _gain(vec: np.ndarray, sp: np.ndarray) -> float:
        """PX4's computeDesaturationGain: how far along vec to move sp to reduce saturation in [0, 1]."""
        k_min = 0.0
        k_max = 0.0
        for i in range(4):
            d = vec[i]
            if abs(d) < 1e-7:
                continue
            if sp[i] < 0.0:
                k = -sp[i] / d
                k_min = min(k_min, k)
                k_max = max(k_max, k)
            if sp[i] > 1.0:
                k = (1.0 - sp[i]) / d
                k_min = min(k_min, k)
                k_max = max(k_max, k)
        return k_min + k_max

    def _desaturate(self, sp: np.ndarray, vec: np.ndarray, increase_only: bool = False) -> np.ndarray:
        gain = self._gain(vec, sp)
        if increase_only and gain < 0.0:
            return sp
        sp = sp + gain * vec
        gain = 0.5 * self._gain(vec, sp)  # halved second pass balances min and max saturation
        if increase_only and gain < 0.0:
            return sp
        return sp + gain * vec

    def mix(self, thrust: float, torque: np.ndarray) -> tuple[np.ndarray, bool]:
        """Per-motor normalised thrust in [0, 1] for normalised thrust and torque; True if clipped."""
        sp = thrust * self.THRUST + torque[0] * self.ROLL + torque[1] * self.PITCH
        sp = self._desaturate(sp, -self.THRUST, increase_only=True)  # only ever reduce thrust
        sp = self._desaturate(sp, self.ROLL)
        sp = self._desaturate(sp, self.PITCH)
        # yaw mixed separately: its authority is reduced to unsaturate, then thrust may be lowered
        sp = sp + torque[2] * self.YAW
        sp = self._desaturate(sp, self.YAW)
        sp = self._desaturate(sp, -self.THRUST, increase_only=True)
        clipped = bool(np.any(sp < -1e-9) or np.any(sp > 1.0 + 1e-9))
        return np.clip(sp, 0.0, 1.0), clipped

    def speeds(self, normalised: np.ndarray) -> np.ndarray:
        """Rotor speeds (rad/s) of per-motor normalised thrust (thrust ~ w^2)."""
        return self.w_max * np.sqrt(normalised)


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
        self.pos_p = np.array((g.MPC_XY_P, g.MPC_XY_P, g.MPC_Z_P))
        self.vel_p = np.array((g.MPC_XY_VEL_P_ACC, g.MPC_XY_VEL_P_ACC, g.MPC_Z_VEL_P_ACC))
        self.vel_i = np.array((g.MPC_XY_VEL_I_ACC, g.MPC_XY_VEL_I_ACC, g.MPC_Z_VEL_I_ACC))
        self.vel_d = np.array((g.MPC_XY_VEL_D_ACC, g.MPC_XY_VEL_D_ACC, g.MPC_Z_VEL_D_ACC))
        self.tilt_max = math.radians(g.MPC_TILTMAX_AIR)
        yaw_w = min(max(g.MC_YAW_WEIGHT, 0.0), 1.0)
        self.yaw_w = yaw_w
        self.att_p = np.array((g.MC_ROLL_P, g.MC_PITCH_P, g.MC_YAW_P / yaw_w if yaw_w > 1e-4 else g.MC_YAW_P))
        self.rate_max = np.radians((g.MC_ROLLRATE_MAX, g.MC_PITCHRATE_MAX, g.MC_YAWRATE_MAX))
        self.rate_p = np.array((g.MC_ROLLRATE_P, g.MC_PITCHRATE_P, g.MC_YAWRATE_P))
        self.rate_i = np.array((g.MC_ROLLRATE_I, g.MC_PITCHRATE_I, g.MC_YAWRATE_I))
        self.rate_d = np.array((g.MC_ROLLRATE_D, g.MC_PITCHRATE_D, g.MC_YAWRATE_D))
        self.rate_int_lim = np.array((g.MC_RR_INT_LIM, g.MC_PR_INT_LIM, g.MC_YR_INT_LIM))
        self.a_veld = _lowpass_alpha(g.MPC_VELD_LP, dt)
        self.a_dgyro = _lowpass_alpha(g.IMU_DGYRO_CUTOFF, dt)
        self.a_yaw_tq = _lowpass_alpha(g.MC_YAW_TQ_CUTOFF, dt)
        self.reset()

    def reset(self) -> None:
        """Clear integrators, derivative filters and the last mixer saturation."""
        self.vel_int = np.zeros(3)
        self.rate_int = np.zeros(3)
        self.vel_dot = np.zeros(3)
        self.ang_acc = np.zeros(3)
        self.prev_vel: np.ndarray | None = None
        self.prev_rate: np.ndarray | None = None
        self.yaw_torque = 0.0
        self.saturated = False

    # --- position and velocity (mc_pos_control) -------------------------------------------------------
    def _thrust_setpoint(self, p: np.ndarray, v: np.ndarray, ref: Reference) -> np.ndarray:
        g = self.gains
        dt = self.dt
        vel_sp = ref.velocity + self.pos_p * (ref.position - p)
        xy = math.hypot(vel_sp[0], vel_sp[1])
        if xy > g.MPC_XY_VEL_MAX:
            vel_sp[0:2] *= g.MPC_XY_VEL_MAX / xy
        vel_sp[2] = min(max(vel_sp[2], -g.MPC_Z_VEL_MAX_UP), g.MPC_Z_VEL_MAX_DN)
        if self.prev_vel is not None:
            self.vel_dot += self.a_veld * ((v - self.prev_vel) / dt - self.vel_dot)
        self.prev_vel = v.copy()
        self.vel_int[2] = min(max(self.vel_int[2], -self.g), self.g)
        vel_err = vel_sp - v
        acc_sp = ref.acceleration + self.vel_p * vel_err + self.vel_int - self.vel_d * self.vel_dot
        # accelerationControl: tilt from horizontal acceleration, collective thrust from vertical
        body_z = np.array((-acc_sp[0], -acc_sp[1], self.g))
        body_z /= math.sqrt(float(body_z @ body_z))
        angle = math.acos(min(max(body_z[2], -1.0), 1.0))
        if angle > self.tilt_max:
            h = math.hypot(body_z[0], body_z[1])
            s = math.sin(self.tilt_max) / h
            body_z = np.array((body_z[0] * s, body_z[1] * s, math.cos(self.tilt_max)))
        thrust_ned_z = acc_sp[2] * (self.hover_thrust / self.g) - self.hover_thrust
        collective = min(thrust_ned_z / body_z[2], -g.MPC_THR_MIN)
        thr_sp = body_z * collective
        # vertical anti-windup
        if (thr_sp[2] >= -g.MPC_THR_MIN and vel_err[2] >= 0.0) or \
                (thr_sp[2] <= -g.MPC_THR_MAX and vel_err[2] <= 0.0):
            vel_err[2] = 0.0
        # vertical priority with a horizontal margin
        xy_norm = math.hypot(thr_sp[0], thr_sp[1])
        allocated = min(xy_norm, g.MPC_THR_XY_MARG)
        thr_sp[2] = max(thr_sp[2], -math.sqrt(max(g.MPC_THR_MAX ** 2 - allocated ** 2, 0.0)))
        xy_max_sq = g.MPC_THR_MAX ** 2 - thr_sp[2] ** 2
        xy_max = math.sqrt(xy_max_sq) if xy_max_sq > 0.0 else 0.0
        if xy_norm > xy_max:
            thr_sp[0:2] *= xy_max / xy_norm
        # tracking anti-windup (horizontal)
        produced = thr_sp[0:2] * (self.g / self.hover_thrust)
        acc_xy = acc_sp[0:2]
        limited = produced if float(acc_xy @ acc_xy) > float(produced @ produced) else acc_xy
        vel_err[0:2] -= (2.0 / self.vel_p[0]) * (acc_xy - limited)
        self.vel_int += vel_err * self.vel_i * dt
        return thr_sp

    # --- attitude (mc_att_control) --------------------------------------------------------------------
    def _rate_setpoint(self, q: tuple, qd: tuple, yaw_rate: float) -> np.ndarray:
        e_z = _qdcm_z(q)
        e_z_d = _qdcm_z(qd)
        qd_red = _q_from_two_vectors(e_z, e_z_d)
        if abs(qd_red[1]) > 1.0 - 1e-5 or abs(qd_red[2]) > 1.0 - 1e-5:
            qd_red = qd
        else:
            qd_red = _qmul(qd_red, q)
        q_mix = _qcanonical(_qmul(_qinv(qd_red), qd))
        w0 = min(max(q_mix[0], -1.0), 1.0)
        w3 = min(max(q_mix[3], -1.0), 1.0)
        yaw_part = (math.cos(self.yaw_w * math.acos(w0)), 0.0, 0.0, math.sin(self.yaw_w * math.asin(w3)))
        qd = _qmul(qd_red, yaw_part)
        qe = _qcanonical(_qmul(_qinv(q), qd))
        rate_sp = 2.0 * np.array(qe[1:]) * self.att_p
        rate_sp += np.array(_qrotate_inv(q, (0.0, 0.0, yaw_rate)))
        return np.clip(rate_sp, -self.rate_max, self.rate_max)

    # --- rates (mc_rate_control) ----------------------------------------------------------------------
    def _torque(self, rate: np.ndarray, rate_sp: np.ndarray) -> np.ndarray:
        dt = self.dt
        if self.prev_rate is not None:
            self.ang_acc += self.a_dgyro * ((rate - self.prev_rate) / dt - self.ang_acc)
        self.prev_rate = rate.copy()
        err = rate_sp - rate
        torque = self.rate_p * err + self.rate_int - self.rate_d * self.ang_acc
        if not self.saturated:
            i_factor = np.maximum(0.0, 1.0 - (err / math.radians(400.0)) ** 2)
            self.rate_int = np.clip(self.rate_int + i_factor * self.rate_i * err * dt, -self.rate_int_lim,
                                    self.rate_int_lim)
        self.yaw_torque += self.a_yaw_tq * (torque[2] - self.yaw_torque)
        torque[2] = self.yaw_torque
        return torque

    def update(self, t: float, state: VehicleState, reference: Reference) -> Command:
        """Motor speeds [rad/s] from the cascade for the state and reference at time t [s]."""
        xi = state.xi
        if state.quaternion is not None:
            q = tuple(float(c) for c in state.quaternion)
        else:
            q = _q_from_euler(*xi[6:9])
        thr_sp = self._thrust_setpoint(xi[0:3].astype(float), xi[3:6].astype(float), reference)
        collective = math.sqrt(float(thr_sp @ thr_sp))
        qd = body_z_to_attitude((-thr_sp[0], -thr_sp[1], -thr_sp[2]), reference.yaw)
        rate_sp = self._rate_setpoint(q, qd, reference.yaw_rate)
        torque = self._torque(xi[9:12].astype(float), rate_sp)
        normalised, clipped = self.mixer.mix(collective, torque)
        self.saturated = clipped
        speeds = self.mixer.speeds(normalised)
        return Command(speeds, clipped, {"thrust_normalised": collective, "torque_normalised": torque,
                                         "rate_sp": rate_sp})
