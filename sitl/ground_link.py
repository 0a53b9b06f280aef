"""The ground-tool side of the SITL: a PX4-like quadrotor (sysid 1, compid 1) towards GCSs and offboard APIs.

It sends first, to each configured endpoint, and answers whatever address talks back on the same socket.
Streams are scheduled on a clock the server passes in (simulated microseconds while the simulation steps,
wall-clock microseconds while it waits for a companion).
"""

from __future__ import annotations

import math
import socket
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from bridge.errors import UserError
from bridge.framing import Framer, kind, part_of
from bridge.signing import Signing
from sitl.hil import int16_of, int32_of, lat_e7, lon_e7

SYSTEM_ID = 1
COMPONENT_ID = 1  # MAV_COMP_ID_AUTOPILOT1: ground tools look for the autopilot here

MSG_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
MSG_SYS_STATUS = mavlink.MAVLINK_MSG_ID_SYS_STATUS
MSG_ATTITUDE = mavlink.MAVLINK_MSG_ID_ATTITUDE
MSG_ATTITUDE_QUATERNION = mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
MSG_LOCAL_POSITION_NED = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
MSG_GLOBAL_POSITION_INT = mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
MSG_HOME_POSITION = mavlink.MAVLINK_MSG_ID_HOME_POSITION
MSG_AUTOPILOT_VERSION = mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
MSG_EXTENDED_SYS_STATE = mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE

# Default stream intervals, microseconds (of the schedule clock). 0 means "on request only".
DEFAULT_INTERVALS_US: dict[int, int] = {
    MSG_HEARTBEAT: 1_000_000,
    MSG_SYS_STATUS: 500_000,
    MSG_EXTENDED_SYS_STATE: 1_000_000,
    MSG_ATTITUDE: 20_000,
    MSG_ATTITUDE_QUATERNION: 20_000,
    MSG_LOCAL_POSITION_NED: 20_000,
    MSG_GLOBAL_POSITION_INT: 20_000,
    MSG_HOME_POSITION: 1_000_000,
    MSG_AUTOPILOT_VERSION: 0,
}
# Messages that can be streamed (SET_MESSAGE_INTERVAL); all of DEFAULT_INTERVALS_US can be requested once.
STREAMABLE = frozenset(k for k in DEFAULT_INTERVALS_US if k != MSG_AUTOPILOT_VERSION)

SENSORS_PRESENT = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
)
# PX4 custom mode, main mode in bits 16..23: OFFBOARD while a companion drives, MANUAL otherwise.
PX4_MODE_MANUAL = 1 << 16
PX4_MODE_OFFBOARD = 6 << 16
QUADSR_FLIGHT_SW_VERSION = (0 << 24) | (1 << 16) | (0 << 8) | mavlink.FIRMWARE_VERSION_TYPE_DEV
_ATT, _ATQ, _LPN, _GPI = map(kind, (
    mavlink.MAVLink_attitude_message,
    mavlink.MAVLink_attitude_quaternion_message,
    mavlink.MAVLink_local_position_ned_message,
    mavlink.MAVLink_global_position_int_message,
))


MIN_INTERVAL_US = 4_000  # fastest stream a ground tool may ask for: one exchange step
MAX_INTERVAL_US = 3_600_000_000  # slowest: once an hour


def message_id_of(param: float) -> int:
    """A command parameter as a MAVLink message id, or -1 if it is none (NaN, inf, fraction, out of range)."""
    if not math.isfinite(param) or param != int(param) or not 0 <= param < 1 << 24:
        return -1
    return int(param)


@dataclass
class GroundState:
    """What the ground link reports about the vehicle at one instant."""

    time_boot_ms: int  # schedule clock, ms
    position: tuple[float, float, float]  # NED, m, relative to home
    velocity: tuple[float, float, float]  # NED, m/s
    quaternion: tuple[float, float, float, float]  # (w, x, y, z), body FRD to earth NED
    euler: tuple[float, float, float]  # (roll, pitch, yaw), rad
    rates: tuple[float, float, float]  # body FRD, rad/s
    lat_deg: float
    lon_deg: float
    alt_m: float  # AMSL, m
    armed: bool
    companion: bool  # a companion drives the motors
    failsafe: bool
    on_ground: bool


@dataclass(frozen=True)
class Home:
    """The home position: origin of the local NED frame."""

    lat_deg: float
    lon_deg: float
    alt_m: float  # AMSL, m


class _Channel:
    """One UDP socket sending first to a fixed ground-tool address and parsing what comes back."""

    def __init__(self, host: str, port: int, signing: Signing | None = None):
        try:
            address = socket.gethostbyname(host)
        except OSError:
            raise UserError(f"cannot resolve the ground-link host {host!r}",
                            hint="give --gcs/--offboard as udp:HOST:PORT with a reachable host") from None
        self.remote = (address, port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1" if address.startswith("127.") else "0.0.0.0", 0))
        self.sock.setblocking(False)
        self.parser = mavlink.MAVLink(None, srcSystem=SYSTEM_ID, srcComponent=COMPONENT_ID)
        self.parser.robust_parsing = True
        self.signing = signing
        self.received = 0
        self.bad = 0
        self.refused = 0  # unsigned, wrongly signed or replayed frames (signing on)

    def send(self, data: bytes) -> bool:
        """Send one datagram; a missing listener is not an error for a UDP ground link."""
        try:
            self.sock.sendto(data, self.remote)
            return True
        except OSError:
            return False

    def drain(self) -> list:
        """Read every pending datagram without blocking and return the parsed messages."""
        out = []
        while True:
            try:
                data = self.sock.recv(65535)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:  # e.g. ECONNREFUSED reported from an earlier send
                continue
            # A UDP datagram holds whole frames: a partial frame left by the last one (a hostile or truncated
            # datagram) must not swallow the start of this one.
            self.parser.buf = bytearray()
            self.parser.buf_index = 0
            try:
                msgs = self.parser.parse_buffer(data) or []
            except Exception:  # a malformed frame from a ground tool must never stop the SITL
                self.bad += 1
                continue
            for msg in msgs:
                if msg.get_type() == "BAD_DATA":
                    self.bad += 1
                elif self.signing is not None and self.signing.verify(
                    bytes(msg.get_msgbuf()), msg.get_srcSystem(), msg.get_srcComponent()
                ):
                    self.refused += 1
                else:
                    self.received += 1
                    out.append(msg)

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()


class GroundLink:
    """Streams PX4-like telemetry to GCS/offboard endpoints and answers their commands."""

    def __init__(self, endpoints: list[tuple[str, int]], home: Home, signing: Signing | None = None):
        """signing: sign every frame sent, accept only validly signed, fresh frames (one key, all tools)."""
        self.channels = [_Channel(host, port, signing) for host, port in endpoints]
        self.home = home
        self.seq = 0
        self.framer = Framer(SYSTEM_ID, COMPONENT_ID, self, signing)
        self.intervals_us = dict(DEFAULT_INTERVALS_US)
        self.next_due_us: dict[int, int] = {}
        self.requested: list[int] = []  # one-shot messages to send at the next service
        self.acks: list = []  # answers and queued messages, sent at the next service
        self.sent = 0
        self.commands = 0
        self.rejected = 0  # messages that failed a check while being answered (dropped)
        self.last_clock_us: int | None = None

    def queue(self, msg) -> None:
        """Send a message (e.g. a STATUSTEXT) with the next service."""
        if self.channels:
            self.acks.append(msg)

    @property
    def active(self) -> bool:
        """Whether there is any endpoint to serve."""
        return bool(self.channels)

    def service(self, clock_us: int, state: Callable[[], GroundState]) -> None:
        """Handle incoming commands and send whatever streams are due at clock_us (schedule clock, us)."""
        if not self.channels:
            return
        for channel in self.channels:
            for msg in channel.drain():
                self._handle(msg)
        if self.last_clock_us is not None and clock_us < self.last_clock_us:
            self.next_due_us.clear()  # the clock was rebased: start every stream afresh
        self.last_clock_us = clock_us
        due = []
        for msg_id, interval in self.intervals_us.items():
            if interval <= 0:
                continue
            next_due = self.next_due_us.get(msg_id)
            if next_due is None or clock_us >= next_due:
                due.append(msg_id)
                next_due = clock_us + interval if next_due is None else next_due + interval
                if next_due <= clock_us:
                    next_due = clock_us + interval
                self.next_due_us[msg_id] = next_due
        for msg_id in self.requested:
            if msg_id not in due:
                due.append(msg_id)
        self.requested.clear()
        if not due and not self.acks:
            return
        snapshot = state() if due else None
        parts = [part_of(ack) for ack in self.acks]
        self.acks.clear()
        for msg_id in due:
            part = self._part(msg_id, snapshot)
            if part is not None:
                parts.append(part)
        frames = self.framer.frames(parts)
        datagram = b"".join(frames)
        for channel in self.channels:
            if channel.send(datagram):
                self.sent += len(frames)

    def _handle(self, msg) -> None:
        """Answer one message; any field it uses is checked first (a hostile frame never stops the SITL)."""
        try:
            self._answer(msg)
        except Exception:  # noqa: BLE001 - a message no check foresaw is dropped and counted, never fatal
            self.rejected += 1

    def _answer(self, msg) -> None:
        kind = msg.get_type()
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            if msg.target_system not in (0, SYSTEM_ID) or msg.target_component not in (0, COMPONENT_ID):
                return
            self.commands += 1
            result = self._command(msg)
            self.acks.append(
                mavlink.MAVLink_command_ack_message(
                    msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )
        elif kind == "PARAM_REQUEST_LIST":
            if msg.target_system in (0, SYSTEM_ID):
                # No parameters: one PARAM_VALUE announcing a count of 0 ends a client's list download.
                self.acks.append(
                    mavlink.MAVLink_param_value_message(b"", 0.0, mavlink.MAV_PARAM_TYPE_REAL32, 0, 65535)
                )

    def _command(self, msg) -> int:
        command = msg.command
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval = message_id_of(msg.param1), msg.param2
            if msg_id not in STREAMABLE or not math.isfinite(interval):
                return mavlink.MAV_RESULT_UNSUPPORTED
            if interval == 0:
                self.intervals_us[msg_id] = DEFAULT_INTERVALS_US[msg_id]
            elif interval < 0:
                self.intervals_us[msg_id] = 0
            else:  # us; no faster than one exchange step, no slower than once an hour
                self.intervals_us[msg_id] = int(min(max(interval, MIN_INTERVAL_US), MAX_INTERVAL_US))
            self.next_due_us.pop(msg_id, None)
            return mavlink.MAV_RESULT_ACCEPTED
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            msg_id = message_id_of(msg.param1)
            if msg_id not in DEFAULT_INTERVALS_US:
                return mavlink.MAV_RESULT_UNSUPPORTED
            self.requested.append(msg_id)
            return mavlink.MAV_RESULT_ACCEPTED
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self.requested.append(MSG_AUTOPILOT_VERSION)
            return mavlink.MAV_RESULT_ACCEPTED
        if command == mavlink.MAV_CMD_GET_HOME_POSITION:
            self.requested.append(MSG_HOME_POSITION)
            return mavlink.MAV_RESULT_ACCEPTED
        return mavlink.MAV_RESULT_UNSUPPORTED

    def _part(self, msg_id: int, s: GroundState) -> tuple[bytes, bytes, bytes] | None:
        """(id, CRC extra, payload) of a message: the 50 Hz streams packed straight from floats."""
        t_ms = s.time_boot_ms & 0xFFFFFFFF
        if msg_id == MSG_ATTITUDE:
            return _ATT[0], _ATT[1], _ATT[2](t_ms, *s.euler, *s.rates)
        if msg_id == MSG_ATTITUDE_QUATERNION:
            return _ATQ[0], _ATQ[1], _ATQ[2](t_ms, *s.quaternion, *s.rates, 0.0, 0.0, 0.0, 0.0)
        if msg_id == MSG_LOCAL_POSITION_NED:
            return _LPN[0], _LPN[1], _LPN[2](t_ms, *s.position, *s.velocity)
        if msg_id == MSG_GLOBAL_POSITION_INT:
            vn, ve, vd = s.velocity
            yaw_cdeg = math.degrees(s.euler[2]) * 100.0
            heading = round(yaw_cdeg) % 36000 if math.isfinite(yaw_cdeg) else 65535
            return _GPI[0], _GPI[1], _GPI[2](
                t_ms, lat_e7(s.lat_deg), lon_e7(s.lon_deg), int32_of(s.alt_m * 1000.0, -(2**31), 2**31 - 1),
                int32_of(-s.position[2] * 1000.0, -(2**31), 2**31 - 1),
                int16_of(vn * 100.0), int16_of(ve * 100.0), int16_of(vd * 100.0), heading,
            )
        msg = self._build(msg_id, s)
        return None if msg is None else part_of(msg)

    def _build(self, msg_id: int, s: GroundState):
        """The pymavlink message of a 1 Hz or on-request stream."""
        if msg_id == MSG_HEARTBEAT:
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_HIL_ENABLED
            if s.armed:
                base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            if s.failsafe:
                status = mavlink.MAV_STATE_CRITICAL
            elif s.armed:
                status = mavlink.MAV_STATE_ACTIVE
            else:
                status = mavlink.MAV_STATE_STANDBY
            custom = PX4_MODE_OFFBOARD if s.companion else PX4_MODE_MANUAL
            return mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, custom, status, 3
            )
        if msg_id == MSG_SYS_STATUS:
            return mavlink.MAVLink_sys_status_message(
                SENSORS_PRESENT, SENSORS_PRESENT, SENSORS_PRESENT, 0, 0xFFFF, -1, -1, 0, 0, 0, 0, 0, 0
            )
        if msg_id == MSG_EXTENDED_SYS_STATE:
            landed = mavlink.MAV_LANDED_STATE_ON_GROUND if s.on_ground else mavlink.MAV_LANDED_STATE_IN_AIR
            return mavlink.MAVLink_extended_sys_state_message(mavlink.MAV_VTOL_STATE_MC, landed)
        if msg_id == MSG_HOME_POSITION:
            h = self.home
            return mavlink.MAVLink_home_position_message(
                lat_e7(h.lat_deg),
                lon_e7(h.lon_deg),
                int32_of(h.alt_m * 1000.0, -(2**31), 2**31 - 1),
                0.0,
                0.0,
                0.0,
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
                s.time_boot_ms * 1000,
            )
        if msg_id == MSG_AUTOPILOT_VERSION:
            return mavlink.MAVLink_autopilot_version_message(
                mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT,
                QUADSR_FLIGHT_SW_VERSION,
                0,
                0,
                0,
                [0] * 8,
                [0] * 8,
                [0] * 8,
                0,
                0,
                0x7175616473720001,  # "quadsr" + instance
                [0] * 18,
            )
        return None

    def close(self) -> None:
        """Close every socket."""
        for channel in self.channels:
            channel.close()

