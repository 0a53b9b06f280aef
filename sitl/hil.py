"""The HIL side of the SITL: one step's datagram from the physics and sensors, and actuator input checks.

Per step, in this order: HIL_STATE_QUATERNION (true state), LOCAL_POSITION_NED (precise true position and
velocity), RAW_RPM x4 (true rotor speeds after the motor lag, rpm, index 0..3 = motors 1..4 in PX4 order;
pymavlink's common dialect has no ESC_STATUS), HIL_GPS on GPS steps (10 Hz), WIND_COV when the vehicle flies
in wind (the true wind over the coming step, NED m/s), DEBUG_FLOAT_ARRAY TRUE_ACC (the true accelerations at
the step's state: NED m/s^2, FRD rad/s^2; bridge.messages), HIL_SENSOR last. All carry the
step's time_usec (LOCAL_POSITION_NED: time_boot_ms = time_usec // 1000).

The frames are packed here straight from floats with precompiled structs: building pymavlink message objects
and packing them through bridge.messages costs about 4x more, and this runs 5000+ times per wall second.
`reference_messages` builds the same step through bridge.messages; a test checks both give equal fields.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as mavlink

from bridge import messages
from bridge.framing import Framer, kind
from bridge.geodesy import LocalFrame
from bridge.link import UdpLink
from bridge.vehicle import HomeConfig
from sitl.dynamics import Quadrotor
from sitl.sensors import SensorFrame

HIL_COMPONENT_ID = 51  # the simulator's component id on the HIL link
SYSTEM_ID = 1

_HSQ = mavlink.MAVLink_hil_state_quaternion_message
_LPN = mavlink.MAVLink_local_position_ned_message
_RPM = mavlink.MAVLink_raw_rpm_message
_GPS = mavlink.MAVLink_hil_gps_message
_SENSOR = mavlink.MAVLink_hil_sensor_message
_WIND = mavlink.MAVLink_wind_cov_message
_ACC = mavlink.MAVLink_debug_float_array_message
for _cls, _order in (
    (_HSQ, "time_usec attitude_quaternion rollspeed pitchspeed yawspeed lat lon alt vx vy vz ind_airspeed "
           "true_airspeed xacc yacc zacc"),
    (_LPN, "time_boot_ms x y z vx vy vz"),
    (_RPM, "frequency index"),
    (_GPS, "time_usec lat lon alt eph epv vel vn ve vd cog fix_type satellites_visible id yaw"),
    (_SENSOR, "time_usec xacc yacc zacc xgyro ygyro zgyro xmag ymag zmag abs_pressure diff_pressure "
              "pressure_alt temperature fields_updated id"),
    (_WIND, "time_usec wind_x wind_y wind_z var_horiz var_vert wind_alt horiz_accuracy vert_accuracy"),
    (_ACC, "time_usec array_id name data"),
):
    # The payload tuples below are written in these wire orders; fail loudly if pymavlink ever differs.
    if list(_cls.ordered_fieldnames) != _order.split():
        raise ImportError(f"unexpected wire order of {_cls.msgname}: {_cls.ordered_fieldnames}")

RAD_S_TO_RPM = messages.RAD_S_TO_RPM
ACCEL_LIMIT = messages.ACCEL_LIMIT
GYRO_LIMIT = messages.GYRO_LIMIT
MG_PER_M_S2 = 1000.0 / messages.G0
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1
TRUE_ACC_WIRE = messages.TRUE_ACCELERATIONS_WIRE
_ACC_PADDING = (0.0,) * 52  # DEBUG_FLOAT_ARRAY's data[58] past our six values
LAT_E7_MAX, LON_E7_MAX = 900_000_000, 1_800_000_000  # degE7


def int16_of(v: float) -> int:
    """v rounded into int16 (saturated, also for +-inf; NaN -> 0)."""
    if v >= 32767.0:
        return 32767
    if v <= -32768.0:
        return -32768
    return 0 if v != v else round(v)


def uint16_of(v: float, hi: int = 65535) -> int:
    """v rounded into [0, hi] (saturated, also for +-inf; NaN -> 0)."""
    if v >= hi:
        return hi
    if v <= 0.0:
        return 0
    return 0 if v != v else round(v)


def int32_of(v: float, lo: int, hi: int) -> int:
    """v rounded into [lo, hi] (saturated, also for +-inf; NaN -> 0)."""
    if v >= hi:
        return hi
    if v <= lo:
        return lo
    return 0 if v != v else round(v)


def lat_e7(deg: float) -> int:
    """Latitude in deg to the degE7 int of MAVLink."""
    return int32_of(deg * 1e7, -LAT_E7_MAX, LAT_E7_MAX)


def lon_e7(deg: float) -> int:
    """Longitude in deg to the degE7 int of MAVLink."""
    return int32_of(deg * 1e7, -LON_E7_MAX, LON_E7_MAX)


class HilEncoder:
    """Builds the frames the SITL sends for one step on a HIL link (its ids, sequence numbers, signing)."""

    def __init__(self, home: HomeConfig, link: UdpLink):
        self.frame = LocalFrame.at(home)
        self.link = link
        self._frames = Framer(link.system_id, link.component_id, link, link.signing).frames
        kinds = map(kind, (_HSQ, _LPN, _RPM, _GPS, _SENSOR, _WIND, _ACC))
        self._hsq, self._lpn, self._rpm, self._gps, self._sensor, self._wind, self._acc = kinds

    def step_frames(self, quad: Quadrotor, s: SensorFrame) -> list[bytes]:
        """The frames of the current step, HIL_SENSOR last; all stamped with the step's time_usec."""
        t = quad.time_usec
        x, y, z, vx, vy, vz, qw, qx, qy, qz, p, q, r, w1, w2, w3, w4 = quad.state  # one read of 17 floats
        lat, lon, alt = self.frame.to_geodetic(x, y, z)
        fx, fy, fz = quad.specific_force_body()
        speed = uint16_of(100.0 * math.sqrt(vx * vx + vy * vy + vz * vz))  # cm/s over ground: both airspeeds
        msg_id, extra, pack = self._hsq
        parts = [
            (msg_id, extra, pack(
                t, qw, qx, qy, qz, p, q, r,
                int32_of(lat * 1e7, -LAT_E7_MAX, LAT_E7_MAX), int32_of(lon * 1e7, -LON_E7_MAX, LON_E7_MAX),
                int32_of(alt * 1000.0, INT32_MIN, INT32_MAX),
                int16_of(vx * 100.0), int16_of(vy * 100.0), int16_of(vz * 100.0), speed, speed,
                int16_of(fx * MG_PER_M_S2), int16_of(fy * MG_PER_M_S2), int16_of(fz * MG_PER_M_S2),
            )),
        ]
        msg_id, extra, pack = self._lpn
        parts.append((msg_id, extra, pack((t // 1000) & 0xFFFFFFFF, x, y, z, vx, vy, vz)))
        msg_id, extra, pack = self._rpm
        parts.append((msg_id, extra, pack(w1 * RAD_S_TO_RPM, 0)))
        parts.append((msg_id, extra, pack(w2 * RAD_S_TO_RPM, 1)))
        parts.append((msg_id, extra, pack(w3 * RAD_S_TO_RPM, 2)))
        parts.append((msg_id, extra, pack(w4 * RAD_S_TO_RPM, 3)))
        if s.new_gps:
            g = s.gps
            vn, ve, vd = g.vel
            ground = math.hypot(vn, ve)
            cog = 65535 if ground < 0.01 else int(round(math.degrees(math.atan2(ve, vn)) * 100.0)) % 36000
            msg_id, extra, pack = self._gps
            parts.append((msg_id, extra, pack(
                t, lat_e7(g.lat), lon_e7(g.lon), int32_of(g.alt * 1000.0, INT32_MIN, INT32_MAX),
                uint16_of(g.eph * 100.0, 65534), uint16_of(g.epv * 100.0, 65534),
                uint16_of(ground * 100.0, 65534), int16_of(vn * 100.0), int16_of(ve * 100.0),
                int16_of(vd * 100.0), cog,
                g.fix_type, min(max(g.satellites, 0), 255), 0, 0,
            )))
        wind = quad.wind_model
        if wind is not None:
            wn, we, wd = quad.wind
            msg_id, extra, pack = self._wind
            var_h, var_v = wind.variance
            parts.append((msg_id, extra, pack(t, wn, we, wd, var_h, var_v, alt, 0.0, 0.0)))
        msg_id, extra, pack = self._acc
        parts.append((msg_id, extra, pack(t, 0, TRUE_ACC_WIRE, *quad.accelerations(), *_ACC_PADDING)))
        ax, ay, az = s.accel
        gx, gy, gz = s.gyro
        mx, my, mz = s.mag
        a, w = ACCEL_LIMIT, GYRO_LIMIT
        msg_id, extra, pack = self._sensor
        parts.append((msg_id, extra, pack(
            t,
            a if ax > a else (-a if ax < -a else ax),
            a if ay > a else (-a if ay < -a else ay),
            a if az > a else (-a if az < -a else az),
            w if gx > w else (-w if gx < -w else gx),
            w if gy > w else (-w if gy < -w else gy),
            w if gz > w else (-w if gz < -w else gz),
            mx, my, mz, s.abs_pressure, 0.0, s.pressure_alt, s.temperature, s.fields_updated, 0,
        )))
        return self._frames(parts)

    def frames_of(self, msgs: list) -> list[bytes]:
        """Frames of pymavlink messages (e.g. STATUSTEXT), in this link's sequence."""
        return self.link.pack(msgs)


def reference_messages(quad: Quadrotor, s: SensorFrame, home: HomeConfig) -> list:
    """The step's messages built through bridge.messages (the slow, obviously-right path; for tests)."""
    t = quad.time_usec
    lat, lon, alt = LocalFrame.at(home).to_geodetic(*quad.position)
    state = messages.TrueState(t, quad.position, quad.velocity, quad.quaternion, quad.euler, quad.rates)
    out = [
        messages.encode_hil_state_quaternion(state, lat, lon, alt, quad.specific_force_body()),
        messages.encode_local_position_ned(state),
    ]
    out.extend(messages.encode_raw_rpm(quad.rotor_speeds))
    if s.new_gps:
        g = s.gps
        out.append(messages.encode_hil_gps(
            messages.GpsSample(t, g.lat, g.lon, g.alt, g.vel, g.fix_type, g.satellites, g.eph, g.epv)))
    if quad.wind_model is not None:
        out.append(wind_cov(t, quad.wind, quad.wind_model.variance, alt))
    acc = quad.accelerations()
    out.append(messages.encode_true_accelerations(t, acc[:3], acc[3:]))
    out.append(messages.encode_hil_sensor(messages.ImuSample(
        t, s.accel, s.gyro, s.mag, s.abs_pressure, s.pressure_alt, s.temperature, s.fields_updated)))
    return out


def wind_cov(time_usec: int, wind: tuple[float, float, float], variance: tuple[float, float], alt: float):
    """A WIND_COV message: true wind (NED m/s), turbulence variance (horizontal, vertical) (m/s)^2, alt m."""
    return mavlink.MAVLink_wind_cov_message(time_usec, *wind, variance[0], variance[1], alt, 0.0, 0.0)


def statustext(severity: int, text: str):
    """A STATUSTEXT message (text cut to the 50 characters MAVLink carries)."""
    return mavlink.MAVLink_statustext_message(severity, text.encode("ascii", "replace")[:50])
