"""Typed observations and commands, and their conversion to and from MAVLink (common dialect) messages.

Frames and units: accel (specific force) FRD m/s^2, gyro FRD rad/s, mag FRD gauss, pressure hPa, position
and velocity NED m and m/s, quaternion scalar-first body-to-NED, Euler ZYX rad, rotor speeds rad/s.

Rotor speeds travel as RAW_RPM (id 339), one frame per rotor, index 0..3 = motors 1..4 in PX4 order,
frequency in rpm (float). pymavlink 2.4.50's common dialect has no ESC_STATUS, and RAW_RPM is the common
message for it; it carries no time, so it belongs to the step of the datagram it arrives in.

The SITL's true accelerations at each step's state travel as DEBUG_FLOAT_ARRAY (id 350) named TRUE_ACC:
data[0..2] the linear acceleration NED m/s^2, data[3..5] the body angular acceleration FRD rad/s^2 (common
has no message for an angular acceleration). A log's truth targets are then exact, not differentiated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from bridge.framing import decode_frame, spec_for, unpack_frame
from bridge.rotations import euler_from_quaternion  # noqa: F401 - also used by importers of messages

G0 = 9.80665  # m/s^2, the g PX4 uses to clamp accelerometer readings
ACCEL_LIMIT = 16.0 * G0  # m/s^2
GYRO_LIMIT = math.radians(2000.0)  # rad/s
RAD_S_TO_RPM = 60.0 / (2.0 * math.pi)
RPM_TO_RAD_S = 2.0 * math.pi / 60.0

# HIL_SENSOR fields_updated bits (HIL_SENSOR_UPDATED_FLAGS), as PX4 reads them.
ACCEL_BITS = 0x7
GYRO_BITS = 0x38
MAG_BITS = 0x1C0
ABS_PRESSURE_BIT = 0x200
PRESSURE_ALT_BIT = 0x800
TEMPERATURE_BIT = 0x1000
BARO_BITS = ABS_PRESSURE_BIT | PRESSURE_ALT_BIT | TEMPERATURE_BIT  # 0x1A00

# DEBUG_FLOAT_ARRAY of the SITL's true accelerations (see the module docstring).
TRUE_ACCELERATIONS_NAME = "TRUE_ACC"
TRUE_ACCELERATIONS_WIRE = TRUE_ACCELERATIONS_NAME.encode("ascii")  # as the name field packs it

# HIL_ACTUATOR_CONTROLS as PX4 sends it when armed.
ARMED_MODE = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
LOCKSTEP_FLAG = 0x1

HilSensor = mavlink.MAVLink_hil_sensor_message
HilStateQuaternion = mavlink.MAVLink_hil_state_quaternion_message
LocalPositionNed = mavlink.MAVLink_local_position_ned_message
RawRpm = mavlink.MAVLink_raw_rpm_message
HilGps = mavlink.MAVLink_hil_gps_message
WindCov = mavlink.MAVLink_wind_cov_message
HilActuatorControls = mavlink.MAVLink_hil_actuator_controls_message
DebugFloatArray = mavlink.MAVLink_debug_float_array_message
Heartbeat = mavlink.MAVLink_heartbeat_message

_ZERO3 = (0.0, 0.0, 0.0)
_ZERO16 = [0.0] * 16
# Fast constructors (same objects as the pymavlink classes build; see bridge.framing).
_make_hil_sensor = spec_for(HilSensor).make
_make_hsq = spec_for(HilStateQuaternion).make
_make_lpn = spec_for(LocalPositionNed).make
_make_raw_rpm = spec_for(RawRpm).make
_make_hil_gps = spec_for(HilGps).make
_make_hac = spec_for(HilActuatorControls).make
_ndarray = np.ndarray


def _seq(v: Sequence[float]) -> Sequence[float]:
    """Plain Python numbers of a vector (numpy scalars are slow to convert one by one)."""
    return v.tolist() if type(v) is _ndarray else v


def _vec(values: Sequence[float] | None) -> np.ndarray | None:
    return None if values is None else np.asarray(values, dtype=float)


def _clip(value: float, limit: float) -> float:
    # NaN passes through unchanged (a broken sensor model should be visible, not hidden as a limit)
    return limit if value > limit else (-limit if value < -limit else value)


def _int_clip(value: float, lo: int, hi: int) -> int:
    if value != value:  # NaN
        return 0
    v = round(value)
    return lo if v < lo else (hi if v > hi else int(v))


@dataclass
class ImuSample:
    """One HIL_SENSOR reading: accel FRD m/s^2 (specific force), gyro FRD rad/s, mag FRD gauss, baro.

    mag/abs_pressure (hPa)/pressure_alt (m)/temperature (degC) are None on steps they were not updated.
    fields_updated None: derived from which fields are present.
    """

    time_usec: int
    accel: np.ndarray
    gyro: np.ndarray
    mag: np.ndarray | None = None
    abs_pressure: float | None = None
    pressure_alt: float | None = None
    temperature: float | None = None
    fields_updated: int | None = None

    def updated_bits(self) -> int:
        """fields_updated as sent: the given value, else accel|gyro plus mag/baro bits of present fields."""
        if self.fields_updated is not None:
            return int(self.fields_updated)
        bits = ACCEL_BITS | GYRO_BITS
        if self.mag is not None:
            bits |= MAG_BITS
        if self.abs_pressure is not None:
            bits |= ABS_PRESSURE_BIT
        if self.pressure_alt is not None:
            bits |= PRESSURE_ALT_BIT
        if self.temperature is not None:
            bits |= TEMPERATURE_BIT
        return bits


@dataclass
class TrueState:
    """The simulator's true state: position NED m, velocity NED m/s, quaternion (w,x,y,z) body->NED,
    Euler ZYX rad (phi, theta, psi), body rates FRD rad/s."""

    time_usec: int
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    euler: np.ndarray
    rates: np.ndarray

    @classmethod
    def from_quaternion(
        cls,
        time_usec: int,
        position: Sequence[float],
        velocity: Sequence[float],
        quaternion: Sequence[float],
        rates: Sequence[float],
    ) -> TrueState:
        """A TrueState whose Euler angles are computed from the quaternion."""
        q = np.asarray(quaternion, dtype=float)
        return cls(
            int(time_usec),
            np.asarray(position, dtype=float),
            np.asarray(velocity, dtype=float),
            q,
            euler_from_quaternion(q),
            np.asarray(rates, dtype=float),
        )

    @property
    def xi(self) -> np.ndarray:
        """The 12-vector x y z vx vy vz phi theta psi wx wy wz (NED m, m/s, rad, FRD rad/s)."""
        return np.concatenate((self.position, self.velocity, self.euler, self.rates))


@dataclass
class GpsSample:
    """One HIL_GPS fix: lat/lon deg (WGS84), alt m (MSL, up), velocity NED m/s, accuracies eph/epv m."""

    time_usec: int
    lat: float
    lon: float
    alt: float
    vel: np.ndarray
    fix_type: int = 3
    satellites: int = 10
    eph: float = 0.3
    epv: float = 0.4


@dataclass
class ActuatorCommand:
    """One HIL_ACTUATOR_CONTROLS: time_usec it answers, throttles (4,) as sent (unclamped), mode, flags."""

    time_usec: int
    throttles: np.ndarray
    mode: int
    flags: int

    @property
    def lockstep(self) -> bool:
        """Flags bit 0: the sender runs in lockstep."""
        return bool(self.flags & LOCKSTEP_FLAG)


@dataclass
class Observation:
    """Everything the SITL sent for one step: time (us and s), IMU, true state, true rotor speeds (rad/s),
    GPS on GPS steps. truth/rotor_speeds are None only if those frames were lost."""

    time_usec: int
    t: float
    imu: ImuSample
    truth: TrueState | None
    rotor_speeds: np.ndarray | None
    gps: GpsSample | None = None
    extras: list = field(default_factory=list)  # other messages that came with this step (e.g. STATUSTEXT)
    wind: np.ndarray | None = None  # true wind over the coming step, NED m/s (WIND_COV; None: no wind flown)
    # true accelerations at this step's state (TRUE_ACC): NED m/s^2 (3), then body FRD rad/s^2 (3)
    accelerations: np.ndarray | None = None


# --------------------------------------------------------------------------------------------------------
# Encoders (used by the SITL and the companion). An optional leading pymavlink MAVLink object is accepted
# and ignored: messages are packed by bridge.link, which owns ids, sequence numbers and signing.
# --------------------------------------------------------------------------------------------------------
def _strip_mav(args: tuple) -> tuple:
    if args and isinstance(args[0], mavlink.MAVLink):
        return args[1:]
    return args


def encode_hil_sensor(*args: object) -> HilSensor:
    """HIL_SENSOR (id 0) of an ImuSample; accel clamped to +-16 g, gyro to +-2000 deg/s as PX4 clamps."""
    (imu,) = _strip_mav(args)
    ax, ay, az = _seq(imu.accel)
    gx, gy, gz = _seq(imu.gyro)
    mx, my, mz = _ZERO3 if imu.mag is None else _seq(imu.mag)
    return _make_hil_sensor(
        int(imu.time_usec),
        _clip(ax, ACCEL_LIMIT),
        _clip(ay, ACCEL_LIMIT),
        _clip(az, ACCEL_LIMIT),
        _clip(gx, GYRO_LIMIT),
        _clip(gy, GYRO_LIMIT),
        _clip(gz, GYRO_LIMIT),
        mx,
        my,
        mz,
        0.0 if imu.abs_pressure is None else float(imu.abs_pressure),
        0.0,
        0.0 if imu.pressure_alt is None else float(imu.pressure_alt),
        0.0 if imu.temperature is None else float(imu.temperature),
        imu.updated_bits(),
        0,
    )


def encode_hil_state_quaternion(*args: object, **kwargs: object) -> HilStateQuaternion:
    """HIL_STATE_QUATERNION(state, lat_deg, lon_deg, alt_m, accel_frd=(0,0,0)): float quaternion and rates;
    lat/lon degE7, alt mm, velocity NED cm/s, accel (body FRD, m/s^2) in mG (all ints, clamped to range)."""
    params = _strip_mav(args)
    state, lat_deg, lon_deg, alt_m = params[:4]
    accel_frd = params[4] if len(params) > 4 else kwargs.get("accel_frd", _ZERO3)
    q = list(_seq(state.quaternion))
    p, q_, r = _seq(state.rates)
    vx, vy, vz = _seq(state.velocity)
    ax, ay, az = _seq(accel_frd)
    speed_cm_s = 100.0 * math.sqrt(vx * vx + vy * vy + vz * vz)
    mg = 1000.0 / G0
    return _make_hsq(
        int(state.time_usec),
        q,
        p,
        q_,
        r,
        _int_clip(lat_deg * 1e7, -900000000, 900000000),
        _int_clip(lon_deg * 1e7, -1800000000, 1800000000),
        _int_clip(alt_m * 1000.0, -2147483648, 2147483647),
        _int_clip(vx * 100.0, -32768, 32767),
        _int_clip(vy * 100.0, -32768, 32767),
        _int_clip(vz * 100.0, -32768, 32767),
        _int_clip(speed_cm_s, 0, 65535),
        _int_clip(speed_cm_s, 0, 65535),
        _int_clip(ax * mg, -32768, 32767),
        _int_clip(ay * mg, -32768, 32767),
        _int_clip(az * mg, -32768, 32767),
    )


def encode_local_position_ned(*args: object) -> LocalPositionNed:
    """LOCAL_POSITION_NED of a TrueState: float position NED m, velocity m/s, time_boot_ms (ms)."""
    (state,) = _strip_mav(args)
    x, y, z = _seq(state.position)
    vx, vy, vz = _seq(state.velocity)
    return _make_lpn((int(state.time_usec) // 1000) & 0xFFFFFFFF, x, y, z, vx, vy, vz)


def encode_raw_rpm(*args: object) -> list[RawRpm]:
    """Four RAW_RPM messages (index 0..3 = motors 1..4, PX4 order) of rotor speeds in rad/s, as float rpm."""
    (rotor_speeds_rad_s,) = _strip_mav(args)
    return [_make_raw_rpm(i, w * RAD_S_TO_RPM) for i, w in enumerate(_seq(rotor_speeds_rad_s))]


def encode_esc_status(*args: object) -> list[RawRpm]:
    """Rotor speeds (time_usec, speeds rad/s) as RAW_RPM messages (common has no ESC_STATUS; see module doc).

    Returns a list; UdpLink.send flattens nested lists, so [hsq, lpn, encode_esc_status(...), sensor] works.
    """
    params = _strip_mav(args)
    return encode_raw_rpm(params[-1])


def encode_hil_gps(*args: object) -> HilGps:
    """HIL_GPS of a GpsSample: lat/lon degE7, alt mm, eph/epv cm, speeds cm/s, course over ground cdeg."""
    (gps,) = _strip_mav(args)
    vn, ve, vd = _seq(gps.vel)
    ground = math.hypot(vn, ve)
    cog = 65535 if ground < 0.01 else int(round(math.degrees(math.atan2(ve, vn)) * 100.0)) % 36000
    return _make_hil_gps(
        int(gps.time_usec),
        int(gps.fix_type),
        _int_clip(float(gps.lat) * 1e7, -900000000, 900000000),
        _int_clip(float(gps.lon) * 1e7, -1800000000, 1800000000),
        _int_clip(float(gps.alt) * 1000.0, -(2**31), 2**31 - 1),
        _int_clip(float(gps.eph) * 100.0, 0, 65534),
        _int_clip(float(gps.epv) * 100.0, 0, 65534),
        _int_clip(ground * 100.0, 0, 65534),
        _int_clip(vn * 100.0, -32768, 32767),
        _int_clip(ve * 100.0, -32768, 32767),
        _int_clip(vd * 100.0, -32768, 32767),
        cog,
        _int_clip(float(gps.satellites), 0, 255),
        0,
        0,
    )


def sanitize_throttles(controls) -> tuple[tuple[float, float, float, float], int, int]:
    """Motor throttles from controls[0..3]: (throttles in [0, 1], count non-finite -> 0, count clamped).

    The one rule for both seats of the HIL link: NaN and +-inf are 0 (motor off), the rest clipped to [0, 1].
    """
    if len(controls) >= 4:  # the common case first: four Python floats already in [0, 1] (NaN fails <=)
        a, b, c, d = controls[0], controls[1], controls[2], controls[3]
        if (type(a) is float and type(b) is float and type(c) is float and type(d) is float
                and 0.0 <= a <= 1.0 and 0.0 <= b <= 1.0 and 0.0 <= c <= 1.0 and 0.0 <= d <= 1.0):
            return (a, b, c, d), 0, 0
    nonfinite = 0
    clamped = 0
    out = []
    for value in controls[:4]:
        v = float(value)
        if not math.isfinite(v):
            nonfinite += 1
            v = 0.0
        elif v < 0.0:
            clamped += 1
            v = 0.0
        elif v > 1.0:
            clamped += 1
            v = 1.0
        out.append(v)
    while len(out) < 4:
        out.append(0.0)
    return (out[0], out[1], out[2], out[3]), nonfinite, clamped


def encode_hil_actuator_controls(*args: object, lockstep: bool = True) -> HilActuatorControls:
    """HIL_ACTUATOR_CONTROLS(time_usec, throttles): controls[0..3] = motor throttles (sent as given),
    controls[4..15] = 0, mode = SAFETY_ARMED | CUSTOM_MODE_ENABLED, flags bit 0 = lockstep."""
    params = _strip_mav(args)
    time_usec, throttles = params[0], params[1]
    if len(params) > 2:
        lockstep = bool(params[2])
    controls = list(_seq(throttles))[:4]
    controls += _ZERO16[: 16 - len(controls)]
    return _make_hac(int(time_usec), controls, ARMED_MODE, LOCKSTEP_FLAG if lockstep else 0)


def encode_true_accelerations(
    time_usec: int, accel_ned: Sequence[float], angular_accel_frd: Sequence[float]
) -> DebugFloatArray:
    """DEBUG_FLOAT_ARRAY TRUE_ACC: the true acceleration NED m/s^2 and angular acceleration FRD rad/s^2."""
    data = [float(v) for v in (*accel_ned, *angular_accel_frd)] + [0.0] * 52
    return DebugFloatArray(int(time_usec), TRUE_ACCELERATIONS_WIRE, 0, data)


def encode_heartbeat(*args: object) -> Heartbeat:
    """HEARTBEAT of a PX4 quadrotor (the companion's, and the SITL's ground-link heartbeat): armed, active."""
    _strip_mav(args)
    return Heartbeat(
        mavlink.MAV_TYPE_QUADROTOR,
        mavlink.MAV_AUTOPILOT_PX4,
        mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
        0,
        mavlink.MAV_STATE_ACTIVE,
        3,
    )


# --------------------------------------------------------------------------------------------------------
# Decoders (used by the clients and the SITL). They work on wire-order value tuples (what struct.unpack
# of the payload gives), so a client can skip building pymavlink objects for the frames of every step.
# --------------------------------------------------------------------------------------------------------
_WIRE_ORDERS = {
    HilSensor: "time_usec xacc yacc zacc xgyro ygyro zgyro xmag ymag zmag abs_pressure diff_pressure "
    "pressure_alt temperature fields_updated id",
    HilStateQuaternion: "time_usec attitude_quaternion rollspeed pitchspeed yawspeed lat lon alt vx vy vz "
    "ind_airspeed true_airspeed xacc yacc zacc",
    LocalPositionNed: "time_boot_ms x y z vx vy vz",
    RawRpm: "frequency index",
    HilGps: "time_usec lat lon alt eph epv vel vn ve vd cog fix_type satellites_visible id yaw",
    HilActuatorControls: "time_usec flags controls mode",
    WindCov: "time_usec wind_x wind_y wind_z var_horiz var_vert wind_alt horiz_accuracy vert_accuracy",
}
for _cls, _order in _WIRE_ORDERS.items():
    # The index arithmetic below assumes these wire orders; fail loudly if pymavlink ever differs.
    if list(_cls.ordered_fieldnames) != _order.split():
        raise ImportError(f"unexpected wire order of {_cls.msgname}: {_cls.ordered_fieldnames}")

_values_of = {cls: spec_for(cls).values_of for cls in _WIRE_ORDERS}
ID_HIL_SENSOR = HilSensor.id
ID_HIL_STATE_QUATERNION = HilStateQuaternion.id
ID_LOCAL_POSITION_NED = LocalPositionNed.id
ID_RAW_RPM = RawRpm.id
ID_HIL_GPS = HilGps.id
ID_WIND_COV = WindCov.id
ID_DEBUG_FLOAT_ARRAY = DebugFloatArray.id
_array = np.array


def imu_from_values(v: Sequence) -> ImuSample:
    """ImuSample of HIL_SENSOR wire values: mag/baro None unless their fields_updated bits are set."""
    bits = v[14]
    return ImuSample(
        v[0],
        _array(v[1:4]),
        _array(v[4:7]),
        _array(v[7:10]) if bits & MAG_BITS else None,
        v[10] if bits & ABS_PRESSURE_BIT else None,
        v[12] if bits & PRESSURE_ALT_BIT else None,
        v[13] if bits & TEMPERATURE_BIT else None,
        bits,
    )


def true_state_from_values(hsq: Sequence, lpn: Sequence | None = None) -> TrueState:
    """TrueState of HIL_STATE_QUATERNION wire values (attitude, rates) and LOCAL_POSITION_NED's (position,
    velocity); without the latter the position is NaN and the velocity is HIL_STATE_QUATERNION's cm/s."""
    w, x, y, z = hsq[1:5]
    if lpn is not None:
        position = _array(lpn[1:4])
        velocity = _array(lpn[4:7])
    else:
        position = np.full(3, np.nan)
        velocity = _array(hsq[11:14]) * 0.01
    s = 2.0 * (w * y - z * x)
    euler = _array(
        (
            math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y)),
            math.asin(1.0 if s > 1.0 else (-1.0 if s < -1.0 else s)),
            math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)),
        )
    )
    return TrueState(hsq[0], position, velocity, _array((w, x, y, z)), euler, _array(hsq[5:8]))


def rotor_speeds_from_values(rpms: Sequence[Sequence]) -> np.ndarray:
    """Rotor speeds (4,) rad/s of RAW_RPM wire values (frequency rpm, index); NaN for a missing rotor."""
    out = [math.nan] * 4
    for freq, index in rpms:
        if 0 <= index < 4:
            out[index] = freq * RPM_TO_RAD_S
    return _array(out)


def gps_from_values(v: Sequence) -> GpsSample:
    """GpsSample of HIL_GPS wire values (deg, m, NED m/s, eph/epv m)."""
    return GpsSample(
        v[0], v[1] * 1e-7, v[2] * 1e-7, v[3] * 1e-3, _array(v[7:10]) * 0.01,
        v[11], v[12], v[4] * 0.01, v[5] * 0.01,
    )


def decode_hil_sensor(msg: HilSensor) -> ImuSample:
    """ImuSample of a HIL_SENSOR: mag/baro fields None unless their fields_updated bits are set."""
    return imu_from_values(_values_of[HilSensor](msg))


def decode_true_state(hsq: HilStateQuaternion, lpn: LocalPositionNed | None = None) -> TrueState:
    """TrueState of HIL_STATE_QUATERNION (attitude, rates) and LOCAL_POSITION_NED (precise position/velocity).

    Without LOCAL_POSITION_NED the position is NaN and the velocity is HIL_STATE_QUATERNION's cm/s ints.
    """
    lpn_values = _values_of[LocalPositionNed](lpn) if lpn is not None else None
    return true_state_from_values(_values_of[HilStateQuaternion](hsq), lpn_values)


def decode_raw_rpm(msgs: Sequence[RawRpm]) -> np.ndarray:
    """Rotor speeds (4,) rad/s of RAW_RPM messages by index 0..3; NaN for a rotor without a message."""
    return rotor_speeds_from_values([(m.frequency, m.index) for m in msgs])


def decode_hil_gps(msg: HilGps) -> GpsSample:
    """GpsSample of a HIL_GPS (deg, m, NED m/s, eph/epv m)."""
    return gps_from_values(_values_of[HilGps](msg))


def decode_hil_actuator_controls(msg: HilActuatorControls) -> ActuatorCommand:
    """ActuatorCommand of a HIL_ACTUATOR_CONTROLS: throttles = controls[0..3] exactly as received."""
    return ActuatorCommand(msg.time_usec, np.array(msg.controls[:4], dtype=float), msg.mode, msg.flags)


_STEP_CLASSES = {
    cls: cls.id for cls in (HilSensor, HilStateQuaternion, LocalPositionNed, RawRpm, HilGps, WindCov)
}
_STEP_IDS = frozenset(_STEP_CLASSES.values())


class ObservationAssembler:
    """Collects the frames of one SITL step and returns an Observation when its HIL_SENSOR arrives.

    HIL_STATE_QUATERNION, LOCAL_POSITION_NED, HIL_GPS, WIND_COV and the TRUE_ACC DEBUG_FLOAT_ARRAY are
    matched to the HIL_SENSOR by time; RAW_RPM (no time field) by arriving after the step's
    HIL_STATE_QUATERNION. Other messages (any other DEBUG_FLOAT_ARRAY too) go to Observation.extras. Takes
    pymavlink messages (add/feed) or checked raw frames (add_frame/feed_frames).
    """

    def __init__(self) -> None:
        self._reset()

    def _reset(self) -> None:
        self._hsq: tuple | None = None
        self._lpn: tuple | None = None
        self._gps: tuple | None = None
        self._wind: tuple | None = None
        self._acc: tuple | None = None
        self._rpm: list[tuple] = []
        self._extras: list = []

    def add(self, msg: object) -> Observation | None:
        """Take one pymavlink message; return the step's Observation if it was the step's HIL_SENSOR."""
        cls = type(msg)
        msg_id = _STEP_CLASSES.get(cls)
        if msg_id is None:
            if cls is DebugFloatArray and _is_true_accelerations(msg.name):
                self._acc = (msg.time_usec, *msg.data[:6])
            else:
                self._extras.append(msg)
            return None
        return self._add_values(msg_id, _values_of[cls](msg))

    def add_frame(self, spec: Any, frame: bytes, header_len: int, signature_len: int) -> Observation | None:
        """Take one checked frame (as bridge.framing.split_datagram gives it); like add()."""
        out = self.feed_frames(((spec, frame, header_len, signature_len),))
        return out[0] if out else None

    def feed(self, msgs: Sequence[object]) -> list[Observation]:
        """Observations completed by these messages, in order."""
        out = []
        for m in msgs:
            obs = self.add(m)
            if obs is not None:
                out.append(obs)
        return out

    def feed_frames(self, frames: Sequence[tuple]) -> list[Observation]:
        """Observations completed by these checked frames [(spec, frame, header_len, signature_len)]."""
        # One loop with the payload unpacking inlined: a step is 8-9 frames, and this runs for every step.
        out = []
        step_ids = _STEP_IDS
        for spec, frame, header_len, signature_len in frames:
            msg_id = spec.msg_id
            if msg_id == ID_DEBUG_FLOAT_ARRAY:
                v = unpack_frame(frame, header_len, signature_len, spec)
                if _is_true_accelerations(v[2]):
                    self._acc = (v[0], *v[3:9])
                    continue
            if msg_id not in step_ids:
                try:
                    self._extras.append(decode_frame(frame, header_len, signature_len, spec))
                except Exception:  # a payload pymavlink cannot instantiate: not part of any step, dropped
                    pass
                continue
            end = len(frame) - 2 - signature_len
            size = spec.size
            if end - header_len == size:  # not truncated: read in place
                v = spec.unpack_from(frame, header_len)
            else:
                v = unpack_frame(frame, header_len, signature_len, spec)
            if msg_id == ID_RAW_RPM:
                self._rpm.append(v)
            elif msg_id == ID_HIL_SENSOR:
                out.append(self._finish(v))
            elif msg_id == ID_HIL_STATE_QUATERNION:  # a step's first frame: earlier RAW_RPM are older
                self._hsq = v
                self._rpm = []
            elif msg_id == ID_LOCAL_POSITION_NED:
                self._lpn = v
            elif msg_id == ID_WIND_COV:
                self._wind = v
            else:
                self._gps = v
        return out

    def _add_values(self, msg_id: int, v: tuple) -> Observation | None:
        if msg_id == ID_HIL_SENSOR:
            return self._finish(v)
        if msg_id == ID_HIL_STATE_QUATERNION:  # a step's first frame: earlier RAW_RPM belong to an older step
            self._hsq = v
            self._rpm = []
        elif msg_id == ID_LOCAL_POSITION_NED:
            self._lpn = v
        elif msg_id == ID_RAW_RPM:
            self._rpm.append(v)
        elif msg_id == ID_WIND_COV:
            self._wind = v
        else:
            self._gps = v
        return None

    def _finish(self, sensor: tuple) -> Observation:
        tu = sensor[0]
        hsq = self._hsq
        if hsq is not None and hsq[0] != tu:
            hsq = None
        lpn = self._lpn
        if lpn is not None and lpn[0] != (tu // 1000) & 0xFFFFFFFF:
            lpn = None
        gps = self._gps
        if gps is not None and gps[0] != tu:
            gps = None
        wind = self._wind
        acc = self._acc
        obs = Observation(
            tu,
            tu * 1e-6,
            imu_from_values(sensor),
            true_state_from_values(hsq, lpn) if hsq is not None else None,
            rotor_speeds_from_values(self._rpm) if self._rpm else None,
            gps_from_values(gps) if gps is not None else None,
            self._extras,
            _array(wind[1:4]) if wind is not None and wind[0] == tu else None,
            _array(acc[1:7]) if acc is not None and acc[0] == tu else None,
        )
        self._reset()
        return obs


def _is_true_accelerations(name: str | bytes) -> bool:
    """True for the name of the SITL's TRUE_ACC array (as pymavlink decodes it, or as wire bytes)."""
    if isinstance(name, bytes):
        return name.rstrip(b"\0") == TRUE_ACCELERATIONS_WIRE
    return name == TRUE_ACCELERATIONS_NAME
