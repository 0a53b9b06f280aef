"""The quadrotor's rigid-body dynamics: read motors, compute forces and moments, integrate (fixed-step RK4).

State (17 floats): position NED (m), velocity NED (m/s), unit quaternion body->earth (w, x, y, z),
body rates FRD (rad/s), rotor speeds (rad/s, PX4 order).

    m dv/dt  = m g e3 + R (0, 0, -T) + R F_drag,b          F_drag,b,i = -Cd_i v_b,i |v_b,i|,  v_b = R^T v
    J dw/dt  = -w x (J w) - w x (0, 0, h_z) + tau - D w    (tau, h_z from sitl.mixer)
    dq/dt    = q (x) (0, w) / 2
    dW_i/dt  = (W_cmd,i - W_i) / Tm                        (sitl.motors)

One exchange step (4 ms) holds the commanded speeds and takes 4 ms / physics_step RK4 substeps; after each
the quaternion is renormalised and the ground contact (sitl.ground) resolved. Under a held command the motor
lag has a closed form, W_i(t) = W_cmd,i + (W_i(0) - W_cmd,i) exp(-t/Tm), so the substeps take the rotor
speeds from it (bridge.integration.rk4_step's `known`) rather than from RK4's estimates: with one 4 ms
substep on a 20 ms lag those are 0.5 % of the change off at the half step, and the step's mean angular
acceleration was 2.2e-4 rad/s^2 RMS off the equations above in a PRBS transient (a dense replay, 64 substeps:
1.0e-5 with the closed form; specific force along z 2.0e-5 -> 9.5e-7 m/s^2), more than the small terms a
model identified from the flight has to resolve.

The derivative is written with plain floats: the step runs 250 times per simulated second inside a lockstep
loop that must reach thousands of steps per wall second, and numpy is slower than floats for 3-vectors.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from bridge.integration import Derivative, rk4_step
from bridge.vehicle import EXCHANGE_STEP, VehicleConfig
from sitl import compiled_physics
from sitl.airframe_dynamics import airframe_wrench, inverse3
from sitl.fused_wrench import fused_airframe_wrench
from sitl.ground import make_ground
from sitl.mixer import QuadXMixer
from sitl.motors import Motors
from sitl.wind import Wind

EXCHANGE_STEP_USEC = 4000


def make_derivative(vehicle: VehicleConfig, motors: Motors, mixer: QuadXMixer,
                    wind: list[float] | None = None, *, reference: bool = False,
                    compiled: bool | None = None) -> Derivative:
    """The state derivative f(state, cmd) -> 17 floats, constants bound once.

    The paper's physics (VehicleConfig.paper_physics) take the closed form of the module docstring; any other
    vehicle (its own rotor geometry, effects, wind) its body wrench from sitl.fused_wrench (every effect in
    one pass), or with reference=True from sitl.airframe_dynamics (the per-effect functions it must equal).
    Both read `wind` (NED m/s) at every call. The rigid body (translation, attitude, rotation, motor lag) is
    shared. compiled (default: when built, sitl.compiled_physics.available()): the same derivative in C,
    bit-identical and about 10x faster; never with reference=True.
    """
    wind = wind if wind is not None else [0.0, 0.0, 0.0]
    if compiled is None:
        compiled = not reference and compiled_physics.available()
    if compiled:
        if reference:
            raise ValueError("the compiled derivative is the fused one, not the reference")
        return compiled_physics.compiled_derivative(
            vehicle, motors.inv_time_constant, {"ct": mixer.ct, "k": mixer.k, "cm": mixer.cm, "jm": mixer.jm},
            wind)
    paper = vehicle.paper_physics
    wrench_of = airframe_wrench if reference else fused_airframe_wrench
    body_wrench = None if paper else wrench_of(vehicle, wind)
    itm = motors.inv_time_constant
    ct, k, cm, jm = mixer.ct, mixer.k, mixer.cm, mixer.jm
    g = vehicle.gravity
    im = 1.0 / vehicle.mass
    j00, j01, j02, j10, j11, j12, j20, j21, j22 = (x for row in vehicle.inertia for x in row)
    i00, i01, i02, i10, i11, i12, i20, i21, i22 = inverse3(vehicle.inertia)
    cdx, cdy, cdz = vehicle.drag.body_quadratic
    has_drag = cdx != 0.0 or cdy != 0.0 or cdz != 0.0
    d0, d1, d2 = vehicle.drag.angular_damping

    def derivative(s: Sequence[float], cmd: Sequence[float]) -> tuple[float, ...]:
        _, _, z, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz, w1, w2, w3, w4 = s
        # motors: first-order lag toward the commanded speeds
        c1, c2, c3, c4 = cmd
        dw1 = (c1 - w1) * itm
        dw2 = (c2 - w2) * itm
        dw3 = (c3 - w3) * itm
        dw4 = (c4 - w4) * itm
        # rotation body -> earth
        xx, yy, zz = qx * qx, qy * qy, qz * qz
        xy, xz, yz = qx * qy, qx * qz, qy * qz
        wxq, wyq, wzq = qw * qx, qw * qy, qw * qz
        r00 = 1.0 - 2.0 * (yy + zz)
        r01 = 2.0 * (xy - wzq)
        r02 = 2.0 * (xz + wyq)
        r10 = 2.0 * (xy + wzq)
        r11 = 1.0 - 2.0 * (xx + zz)
        r12 = 2.0 * (yz - wxq)
        r20 = 2.0 * (xz - wyq)
        r21 = 2.0 * (yz + wxq)
        r22 = 1.0 - 2.0 * (xx + yy)
        if not paper:  # every effect's force and moment, body FRD about the CG
            fbx, fby, fbz, tx, ty, tz, hz = body_wrench(z, vx, vy, vz, wx, wy, wz, w1, w2, w3, w4,
                                                        r00, r01, r02, r10, r11, r12, r20, r21, r22)
        else:
            # forces and moments of the rotors (body FRD): QuadXMixer.wrench, inlined as this is the hot path
            s1, s2, s3, s4 = w1 * w1, w2 * w2, w3 * w3, w4 * w4
            thrust = ct * (s1 + s2 + s3 + s4)
            tx = k * (-s1 + s2 + s3 - s4)
            ty = k * (s1 - s2 + s3 - s4)
            tz = cm * (s1 + s2 - s3 - s4)
            hz = jm * (-w1 - w2 + w3 + w4)
            # body-frame force: thrust and quadratic drag on the body-frame velocity R^T v
            fbz = -thrust
            if has_drag:
                ubx = r00 * vx + r10 * vy + r20 * vz
                uby = r01 * vx + r11 * vy + r21 * vz
                ubz = r02 * vx + r12 * vy + r22 * vz
                fbx = -cdx * ubx * abs(ubx)
                fby = -cdy * uby * abs(uby)
                fbz -= cdz * ubz * abs(ubz)
            else:
                fbx = fby = 0.0
        # translational: a = g e3 + R F_b / m
        ax = (r00 * fbx + r01 * fby + r02 * fbz) * im
        ay = (r10 * fbx + r11 * fby + r12 * fbz) * im
        az = (r20 * fbx + r21 * fby + r22 * fbz) * im + g
        # attitude kinematics: dq = q (x) (0, w) / 2
        dqw = 0.5 * (-qx * wx - qy * wy - qz * wz)
        dqx = 0.5 * (qw * wx + qy * wz - qz * wy)
        dqy = 0.5 * (qw * wy - qx * wz + qz * wx)
        dqz = 0.5 * (qw * wz + qx * wy - qy * wx)
        # rotational: J dw = -w x (J w + (0, 0, hz)) + tau - D w
        hx = j00 * wx + j01 * wy + j02 * wz
        hy = j10 * wx + j11 * wy + j12 * wz
        hzb = j20 * wx + j21 * wy + j22 * wz + hz
        mx = tx - (wy * hzb - wz * hy) - d0 * wx
        my = ty - (wz * hx - wx * hzb) - d1 * wy
        mz = tz - (wx * hy - wy * hx) - d2 * wz
        return (
            vx, vy, vz, ax, ay, az, dqw, dqx, dqy, dqz,
            i00 * mx + i01 * my + i02 * mz,
            i10 * mx + i11 * my + i12 * mz,
            i20 * mx + i21 * my + i22 * mz,
            dw1, dw2, dw3, dw4,
        )

    return derivative


# s: the accelerometer feels a touchdown as a constant deceleration over this long (the velocity the rigid
# plane takes away within a substep, spread as landing gear and frame compliance spread it on a vehicle):
# 1.5 m/s down reads 3.8 g for 40 ms, inside the IMU's 16 g, where one substep's impulse would read 150 g
TOUCHDOWN_S = 0.04

class Quadrotor:
    """A simulated quadrotor: reset it, then step(throttles) advances one exchange step (4 ms by default;
    step_usec, a divisor of 4000 us, for a simulator that steps faster, as ArduPilot's JSON one does)."""

    def __init__(self, vehicle: VehicleConfig, step_usec: int = EXCHANGE_STEP_USEC):
        if step_usec <= 0 or EXCHANGE_STEP_USEC % step_usec:
            raise ValueError(f"step_usec must divide {EXCHANGE_STEP_USEC} us, got {step_usec}")
        self.step_usec = step_usec
        self.vehicle = vehicle
        self.motors = Motors(vehicle)
        self.mixer = QuadXMixer(vehicle)
        self.ground = make_ground(vehicle.ground)
        self.substeps = vehicle.simulation.substeps
        self.h = EXCHANGE_STEP / self.substeps * (step_usec / EXCHANGE_STEP_USEC)
        # the motor lag's decay over half a substep and over a substep (the closed form of the lag)
        self._lag_half = math.exp(-0.5 * self.h * self.motors.inv_time_constant)
        self._lag_full = self._lag_half * self._lag_half
        self._g = vehicle.gravity
        self._inv_m = 1.0 / vehicle.mass
        self._cd = vehicle.drag.body_quadratic
        self._paper = vehicle.paper_physics
        self._wind = [0.0, 0.0, 0.0]  # NED m/s, held over each exchange step
        self._wind_model: Wind | None = None
        self._specific_force: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._specific_force_at: tuple[int, int] = (-1, 0)  # (time_usec, id of the state list) it is for
        self._slope: tuple[float, ...] | None = None  # f(s, cmd) at the current state (_current_slope)
        self._slope_at: tuple[int, int] = (-1, 0)  # (time_usec, id of the state list) _slope is for
        self._f = make_derivative(vehicle, self.motors, self.mixer, self._wind)
        self._cmd = (0.0, 0.0, 0.0, 0.0)
        self._s: list[float] = [0.0] * 17
        self._time_usec = 0
        self._on_ground = False
        self._touchdown = (0.0, 0.0, 0.0)  # NED m/s^2 the accelerometer feels of the last touchdown
        self._touchdown_left_usec = 0
        pos = vehicle.initial.position
        self.reset(position=pos, yaw=vehicle.initial.yaw)

    # ------------------------------------------------------------------------------------------------------
    # Setting the state

    def reset(
        self,
        position: Sequence[float] = (0.0, 0.0, 0.0),
        yaw: float = 0.0,
        rotor_speeds: Sequence[float] | None = None,
        *,
        velocity: Sequence[float] = (0.0, 0.0, 0.0),
        rates: Sequence[float] = (0.0, 0.0, 0.0),
        roll: float = 0.0,
        pitch: float = 0.0,
    ) -> None:
        """Put the vehicle at position NED (m) with attitude ZYX (rad), velocity NED (m/s), rates FRD (rad/s).

        Rotor speeds (rad/s) default to 0; the held command is set to them, so a step with the matching
        throttles keeps them. Time restarts at 0. With a ground plane a start below z = 0 is lifted to it.
        """
        speeds = (0.0, 0.0, 0.0, 0.0) if rotor_speeds is None else tuple(float(w) for w in rotor_speeds)
        if len(speeds) != 4:
            raise ValueError(f"expected 4 rotor speeds, got {len(speeds)}")
        cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
        cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
        cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
        q = (
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        )
        self._s = [
            *(float(p) for p in position), *(float(v) for v in velocity), *q,
            *(float(w) for w in rates), *speeds,
        ]
        if len(self._s) != 17:
            raise ValueError("position, velocity and rates must have 3 components each")
        self._cmd = speeds
        self._time_usec = 0
        self._on_ground = False
        self._touchdown_left_usec = 0
        self._specific_force_at = self._slope_at = (-1, 0)
        if self.vehicle.wind.active:  # the wind restarts with time (same seed: same wind)
            self._wind_model = Wind(self.vehicle.wind, EXCHANGE_STEP)
            self._wind[:] = self._wind_model.sample(0.0)
        if self.vehicle.ground == "plane" and self._s[2] >= 0.0:
            self._s[2] = 0.0
            self._on_ground = self.ground.apply(self._s)

    # ------------------------------------------------------------------------------------------------------
    # Stepping

    def step(self, throttles: Sequence[float]) -> None:
        """Advance one exchange step (4 ms unless step_usec) holding four throttles in [0, 1] (PX4 order)."""
        cmd = self.motors.commanded_speeds(throttles)
        self._cmd = cmd
        h = self.h
        f = self._f
        apply_ground = self.ground.apply
        s = self._s
        c1, c2, c3, c4 = cmd
        e_half, e_full = self._lag_half, self._lag_full
        self._touchdown_left_usec = max(self._touchdown_left_usec - self.step_usec, 0)
        for _ in range(self.substeps):
            flying = not self._on_ground
            v = s[3], s[4], s[5]
            # bridge.integration.lag_path written out: this runs every step
            d1, d2, d3, d4 = s[13] - c1, s[14] - c2, s[15] - c3, s[16] - c4
            rotors = ((c1 + d1 * e_half, c2 + d2 * e_half, c3 + d3 * e_half, c4 + d4 * e_half),
                      (c1 + d1 * e_full, c2 + d2 * e_full, c3 + d3 * e_full, c4 + d4 * e_full))
            s = rk4_step(f, s, cmd, h, self._first_slope(s, cmd), rotors)
            qw, qx, qy, qz = s[6], s[7], s[8], s[9]
            n = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            s[6] = qw * n
            s[7] = qx * n
            s[8] = qy * n
            s[9] = qz * n
            self._on_ground = apply_ground(s)
            if flying and self._on_ground:  # a touchdown: the plane took v away
                self._touchdown = (-v[0] / TOUCHDOWN_S, -v[1] / TOUCHDOWN_S, -v[2] / TOUCHDOWN_S)
                self._touchdown_left_usec = round(TOUCHDOWN_S * 1e6)
        self._s = s
        self._time_usec += self.step_usec
        if self._wind_model is not None:  # the wind over the next step, reported with this step's telemetry
            self._wind[:] = self._wind_model.sample(self._time_usec * 1e-6)

    def _first_slope(self, s: list[float], cmd: Sequence[float]) -> list[float] | None:
        """f(s, cmd) from the derivative already computed at s this step (None if there is none).

        Only the motor-lag rates depend on the command, so the cached derivative's first 13 entries hold; the
        SITL reads the specific force and the true accelerations every step, which saves one of five
        derivative calls.
        """
        if self._slope is None or self._slope_at != (self._time_usec, id(s)):
            return None
        d = self._slope
        itm = self.motors.inv_time_constant
        return [*d[:13], (cmd[0] - s[13]) * itm, (cmd[1] - s[14]) * itm, (cmd[2] - s[15]) * itm,
                (cmd[3] - s[16]) * itm]

    def _current_slope(self) -> tuple[float, ...]:
        """f(s, cmd) at the current state, computed once per step and kept (the specific force, the true
        accelerations and the next step's first RK4 stage read it)."""
        key = (self._time_usec, id(self._s))
        if self._slope is None or self._slope_at != key:
            self._slope = self._derivative(self._s, self._cmd)
            self._slope_at = key
        return self._slope

    def _derivative(self, s: Sequence[float], cmd: Sequence[float]) -> tuple[float, ...]:
        """d(state)/dt for the 17-float state under commanded rotor speeds cmd (rad/s)."""
        return self._f(s, cmd)

    # ------------------------------------------------------------------------------------------------------
    # Reading the state

    @property
    def time_usec(self) -> int:
        """Simulated time since reset, integer microseconds (a multiple of step_usec, 4000 by default)."""
        return self._time_usec

    @property
    def position(self) -> tuple[float, float, float]:
        """Position NED, m."""
        return self._s[0], self._s[1], self._s[2]

    @property
    def velocity(self) -> tuple[float, float, float]:
        """Velocity NED, m/s."""
        return self._s[3], self._s[4], self._s[5]

    @property
    def quaternion(self) -> tuple[float, float, float, float]:
        """Attitude as a unit quaternion (w, x, y, z), body FRD -> earth NED."""
        return self._s[6], self._s[7], self._s[8], self._s[9]

    @property
    def euler(self) -> tuple[float, float, float]:
        """Attitude as ZYX Euler angles (phi roll, theta pitch, psi yaw), rad."""
        qw, qx, qy, qz = self._s[6], self._s[7], self._s[8], self._s[9]
        phi = math.atan2(2.0 * (qw * qx + qy * qz), 1.0 - 2.0 * (qx * qx + qy * qy))
        sin_theta = 2.0 * (qw * qy - qz * qx)
        theta = math.asin(max(-1.0, min(1.0, sin_theta)))
        psi = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        return phi, theta, psi

    @property
    def rates(self) -> tuple[float, float, float]:
        """Body angular rates FRD (p, q, r), rad/s."""
        return self._s[10], self._s[11], self._s[12]

    @property
    def rotor_speeds(self) -> tuple[float, float, float, float]:
        """True rotor speeds after the motor lag, rad/s, PX4 order."""
        return self._s[13], self._s[14], self._s[15], self._s[16]

    @property
    def commanded_speeds(self) -> tuple[float, float, float, float]:
        """Rotor speeds the motors are lagging toward (from the last throttles), rad/s."""
        return self._cmd

    @property
    def wind(self) -> tuple[float, float, float]:
        """The wind over the current exchange step, NED m/s (0 without wind)."""
        return self._wind[0], self._wind[1], self._wind[2]

    @property
    def wind_model(self) -> Wind | None:
        """The wind field being flown (None without wind)."""
        return self._wind_model

    @property
    def on_ground(self) -> bool:
        """True while the vehicle rests on the ground plane."""
        return self._on_ground

    @property
    def state(self) -> tuple[float, ...]:
        """The full 17-float state (see the module docstring)."""
        return tuple(self._s)

    def acceleration_earth(self) -> tuple[float, float, float]:
        """Linear acceleration NED, m/s^2, at the current state (0 while resting on the ground)."""
        a = self.accelerations()
        return a[0], a[1], a[2]

    def angular_acceleration(self) -> tuple[float, float, float]:
        """Body angular acceleration FRD, rad/s^2, at the current state (0 while resting on the ground)."""
        a = self.accelerations()
        return a[3], a[4], a[5]

    def accelerations(self) -> tuple[float, float, float, float, float, float]:
        """(acceleration NED m/s^2, body angular acceleration FRD rad/s^2) at the current state, 6 floats.

        Zeros while resting on the ground.
        """
        if self._on_ground:
            return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        d = self._current_slope()
        return d[3], d[4], d[5], d[10], d[11], d[12]

    def specific_force_body(self) -> tuple[float, float, float]:
        """What an ideal accelerometer measures, FRD m/s^2: R^T (a - g e3); (0, 0, -g) at rest, level.

        In flight that is the non-gravitational force over the mass, thrust and drag, already in body axes.
        """
        s = self._s
        qw, qx, qy, qz = s[6], s[7], s[8], s[9]
        if self._on_ground:
            # a = 0 at rest: R^T (0, 0, -g); after a touchdown its deceleration over TOUCHDOWN_S (the rigid
            # plane stops the vehicle within a substep; an IMU that never felt it left an autopilot's
            # estimator moving on into the ground, and ArduCopter's EKF flew the next flight 0.2-0.5 m low)
            if self._touchdown_left_usec > 0:
                ax, ay, az = self._touchdown
                return _to_body(qw, qx, qy, qz, ax, ay, az - self._g)
            return _to_body(qw, qx, qy, qz, 0.0, 0.0, -self._g)
        if not self._paper:  # R^T (a - g e3) from the derivative: every effect's force, already summed
            if self._specific_force_at == (self._time_usec, id(s)):
                return self._specific_force
            d = self._current_slope()
            self._specific_force = _to_body(qw, qx, qy, qz, d[3], d[4], d[5] - self._g)
            self._specific_force_at = (self._time_usec, id(s))
            return self._specific_force
        mixer = self.mixer
        w1, w2, w3, w4 = s[13], s[14], s[15], s[16]
        fbz = -mixer.ct * (w1 * w1 + w2 * w2 + w3 * w3 + w4 * w4)
        fbx = fby = 0.0
        cdx, cdy, cdz = self._cd
        if cdx != 0.0 or cdy != 0.0 or cdz != 0.0:
            vx, vy, vz = s[3], s[4], s[5]
            ubx = (1.0 - 2.0 * (qy * qy + qz * qz)) * vx + 2.0 * (qx * qy + qw * qz) * vy \
                + 2.0 * (qx * qz - qw * qy) * vz
            uby = 2.0 * (qx * qy - qw * qz) * vx + (1.0 - 2.0 * (qx * qx + qz * qz)) * vy \
                + 2.0 * (qy * qz + qw * qx) * vz
            ubz = 2.0 * (qx * qz + qw * qy) * vx + 2.0 * (qy * qz - qw * qx) * vy \
                + (1.0 - 2.0 * (qx * qx + qy * qy)) * vz
            fbx = -cdx * ubx * abs(ubx)
            fby = -cdy * uby * abs(uby)
            fbz -= cdz * ubz * abs(ubz)
        im = self._inv_m
        return fbx * im, fby * im, fbz * im


def _to_body(qw: float, qx: float, qy: float, qz: float, ax: float, ay: float, az: float
             ) -> tuple[float, float, float]:
    """R(q)^T a: an NED vector in FRD body axes (q body->earth, unit), written out for the hot path."""
    return (
        (1.0 - 2.0 * (qy * qy + qz * qz)) * ax + 2.0 * (qx * qy + qw * qz) * ay
        + 2.0 * (qx * qz - qw * qy) * az,
        2.0 * (qx * qy - qw * qz) * ax + (1.0 - 2.0 * (qx * qx + qz * qz)) * ay
        + 2.0 * (qy * qz + qw * qx) * az,
        2.0 * (qx * qz + qw * qy) * ax + 2.0 * (qy * qz - qw * qx) * ay
        + (1.0 - 2.0 * (qx * qx + qy * qy)) * az)
