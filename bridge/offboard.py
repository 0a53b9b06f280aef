"""The MAVLink offboard protocol of a companion computer: connect, stream setpoints, arm, switch mode, watch.

What a companion does on a real vehicle's MAVLink port (PX4's offboard link, 14580+N in SITL; ArduPilot's
companion serial/UDP link): heartbeats, message-rate requests, COMMAND_LONG with acknowledgement, arming,
a mode switch (PX4 OFFBOARD, ArduPilot GUIDED: `AutopilotFlavour`), SET_ATTITUDE_TARGET (attitude
quaternion or FRD body rates in rad/s, with normalised collective thrust in [0, 1]; common to both), and the
autopilot's state as it reports it: armed, mode, its estimate (LOCAL_POSITION_NED: NED m and m/s;
ATTITUDE_QUATERNION: body-to-NED quaternion, FRD rates rad/s), its clock (time_boot_ms; simulated time
when the autopilot runs in lockstep with a simulator) and its STATUSTEXTs.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

from bridge.link import Endpoint, UdpLink, parse_endpoint
from bridge.messages import mavlink
from bridge.stream_link import TcpClientLink, is_tcp_address, parse_tcp_endpoint
from bridge.tlog import TlogWriter

COMPANION_SYSTEM_ID = 245  # the companion's own ids (MAVSDK's defaults for a companion/GCS)
COMPANION_COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
COMMAND_RESEND_S = 0.25  # wall s between re-sends of an unacknowledged command
HEARTBEAT_PERIOD_S = 1.0  # wall s
IGNORE_RATES = 0b0000_0111  # SET_ATTITUDE_TARGET type_mask: body roll, pitch, yaw rate ignored
IGNORE_ATTITUDE = 0b1000_0000  # attitude quaternion ignored
POSITION_AND_YAW = 0b1101_1111_1000  # SET_POSITION_TARGET_LOCAL_NED type_mask: velocity, accel, yaw rate off


@dataclass(frozen=True)
class FlightMode:
    """A mode: the DO_SET_MODE parameters that select it, and how HEARTBEAT.custom_mode shows it."""

    name: str
    set_params: tuple[float, float, float]  # DO_SET_MODE param1 (base mode), param2, param3
    custom_mode: int  # HEARTBEAT.custom_mode while in it (masked by mask)
    mask: int = 0xFFFFFFFF


@dataclass(frozen=True)
class AutopilotFlavour:
    """The autopilot-specific part: its companion-control mode and the mode to hand back control in."""

    name: str
    offboard: FlightMode
    hold: FlightMode


_CUSTOM = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
# PX4: custom_mode = main_mode << 16 | sub_mode << 24 (px4_custom_mode.h): OFFBOARD main 6; AUTO 4, LOITER 3.
PX4 = AutopilotFlavour(
    "PX4",
    offboard=FlightMode("OFFBOARD", (_CUSTOM, 6.0, 0.0), 6 << 16, 0x00FF0000),
    hold=FlightMode("AUTO.LOITER", (_CUSTOM, 4.0, 3.0), (4 << 16) | (3 << 24), 0xFFFF0000),
)
# ArduCopter: custom_mode is the mode number: GUIDED 4, LOITER 5.
ARDUPILOT = AutopilotFlavour(
    "ArduPilot",
    offboard=FlightMode("GUIDED", (_CUSTOM, 4.0, 0.0), 4),
    hold=FlightMode("LOITER", (_CUSTOM, 5.0, 0.0), 5),
)


def default_local(autopilot: Endpoint) -> str | None:
    """The companion's own address for an autopilot address: PX4 SITL's offboard port 14580+N (N <= 9) is
    answered from 14540+N, the port PX4 sends to, so that every run reaches it (PX4 keeps answering the
    first address that spoke to a link after its boot); otherwise None (an ephemeral port)."""
    if 14580 <= autopilot.port <= 14589:
        return f"udp:{'127.0.0.1' if autopilot.host.startswith('127.') else '0.0.0.0'}:{autopilot.port - 40}"
    return None


@dataclass
class AutopilotState:
    """What the autopilot last reported (None/empty until it did)."""

    system_id: int | None = None
    armed: bool = False
    custom_mode: int | None = None
    time_boot_ms: int = 0  # its clock, ms
    position: tuple[float, float, float] | None = None  # NED m, its estimate
    velocity: tuple[float, float, float] | None = None  # NED m/s
    quaternion: tuple[float, float, float, float] | None = None  # body to NED, scalar first
    rates: tuple[float, float, float] | None = None  # FRD rad/s
    attitude_ms: int = -1  # time_boot_ms of the last ATTITUDE_QUATERNION
    status_texts: list[str] = field(default_factory=list)
    last_heard: float = 0.0  # time.monotonic() of its last message


class OffboardLink:
    """A companion's MAVLink link to the autopilot at `address` (udp:HOST:PORT, where it listens, or
    tcp:HOST:PORT, connected to for up to connect_timeout wall s)."""

    def __init__(self, address: str, flavour: AutopilotFlavour = PX4, tlog: TlogWriter | None = None,
                 local: str | None = None, connect_timeout: float = 30.0):
        self.address = address
        self.flavour = flavour
        if is_tcp_address(address):  # ArduPilot SITL's SERIAL0: tcp:HOST:5760+10N
            self.link = TcpClientLink(parse_tcp_endpoint(address), COMPANION_SYSTEM_ID,
                                      COMPANION_COMPONENT_ID,
                                      tlog, connect_timeout)
        else:
            if local is None:
                local = default_local(parse_endpoint(address))
            self.link = UdpLink(local=local, remote=address, system_id=COMPANION_SYSTEM_ID,
                                component_id=COMPANION_COMPONENT_ID, tlog=tlog)
        self.state = AutopilotState()
        self._acks: dict[int, int] = {}
        self._next_heartbeat = 0.0

    # -- receiving -----------------------------------------------------------------------------------
    def silent(self, timeout: float, limit: float) -> bool:
        """Read the link (up to timeout s wall); True if nothing has come from the autopilot for more than
        limit s wall. A read after the clock is taken confirms the silence, so a stall of this process (it
        was descheduled or stopped while the autopilot's messages queued) is not taken for a lost link."""
        if self.poll(timeout) or time.monotonic() - self.state.last_heard <= limit:
            return False
        return not self.poll(0.0)

    def poll(self, timeout: float = 0.0) -> list:
        """The autopilot's messages of every queued datagram (up to timeout s wall for the first); the state
        is updated, so after a stall it is the newest, not the oldest queued."""
        self._heartbeat()
        msgs = self.link.recv(timeout)
        if msgs:
            msgs += self.link.drain()
        s = self.state
        out = []
        for msg in msgs:
            src = msg.get_srcSystem()
            if s.system_id is None:
                if msg.get_type() != "HEARTBEAT" or msg.get_srcComponent() != 1 or \
                        msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
                    continue
                s.system_id = src
            if src != s.system_id:
                continue
            out.append(msg)
            s.last_heard = time.monotonic()
            kind = msg.get_type()
            if kind == "ATTITUDE_QUATERNION":
                s.quaternion = (msg.q1, msg.q2, msg.q3, msg.q4)
                s.rates = (msg.rollspeed, msg.pitchspeed, msg.yawspeed)
                s.attitude_ms = msg.time_boot_ms
            elif kind == "LOCAL_POSITION_NED":
                s.position = (msg.x, msg.y, msg.z)
                s.velocity = (msg.vx, msg.vy, msg.vz)
            elif kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
                s.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                s.custom_mode = msg.custom_mode
            elif kind == "COMMAND_ACK" and msg.result != mavlink.MAV_RESULT_IN_PROGRESS:
                self._acks[msg.command] = msg.result
            elif kind == "STATUSTEXT":
                text = msg.text.decode("ascii", "replace") if isinstance(msg.text, bytes) else str(msg.text)
                s.status_texts.append(text.rstrip("\x00"))
            boot_ms = getattr(msg, "time_boot_ms", None)
            if boot_ms is not None and boot_ms > s.time_boot_ms:
                s.time_boot_ms = boot_ms
        return out

    def _heartbeat(self) -> None:
        now = time.monotonic()
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + HEARTBEAT_PERIOD_S
            self.link.send([mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                mavlink.MAV_STATE_ACTIVE, 3)])

    def connect(self, timeout: float) -> int:
        """Heartbeats until the autopilot's HEARTBEAT arrives (wall s); its system id. TimeoutError if not."""
        deadline = time.monotonic() + timeout
        while self.state.system_id is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no HEARTBEAT from an autopilot at {self.address} within {timeout:g} s")
            self._next_heartbeat = 0.0
            self.poll(0.2)
        return self.state.system_id

    # -- commands ------------------------------------------------------------------------------------
    def command(self, command: int, params: Sequence[float] = (), timeout: float = 5.0) -> int | None:
        """COMMAND_LONG (re-sent every 0.25 s wall) -> its COMMAND_ACK result; None after timeout s."""
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        self._acks.pop(command, None)
        deadline = time.monotonic() + timeout
        confirmation = 0
        while time.monotonic() < deadline:
            self.link.send([mavlink.MAVLink_command_long_message(
                self.state.system_id or 0, 1, command, confirmation, *p)])
            confirmation = min(confirmation + 1, 255)
            resend = time.monotonic() + COMMAND_RESEND_S
            while time.monotonic() < min(resend, deadline):
                self.poll(0.02)
                if command in self._acks:
                    return self._acks.pop(command)
        return None

    def request_rate(self, message_id: int, hz: float) -> int | None:
        """Ask the autopilot to stream a message at hz (its clock); the ack result."""
        return self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (message_id, 1e6 / hz))

    def arm(self, arm: bool = True) -> int | None:
        """Arm (or disarm); the ack result."""
        return self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1.0 if arm else 0.0,))

    def set_mode(self, mode: FlightMode) -> int | None:
        """DO_SET_MODE to `mode`; the ack result."""
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, mode.set_params)

    def set_param(self, name: str, value: float, timeout: float = 5.0) -> bool:
        """PARAM_SET (float), re-sent every 0.25 s wall until echoed in PARAM_VALUE; False after timeout s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.link.send([mavlink.MAVLink_param_set_message(self.state.system_id or 0, 1, name.encode(),
                                                              float(value), mavlink.MAV_PARAM_TYPE_REAL32)])
            resend = time.monotonic() + COMMAND_RESEND_S
            while time.monotonic() < min(resend, deadline):
                for msg in self.poll(0.02):
                    if msg.get_type() == "PARAM_VALUE" and _param_name(msg.param_id) == name and \
                            abs(msg.param_value - value) <= 1e-6 * max(1.0, abs(value)):
                        return True
        return False

    def get_param(self, name: str, timeout: float = 5.0) -> float | None:
        """PARAM_REQUEST_READ, re-sent every 0.25 s wall until its PARAM_VALUE; None after timeout s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.link.send([mavlink.MAVLink_param_request_read_message(self.state.system_id or 0, 1,
                                                                       name.encode(), -1)])
            resend = time.monotonic() + COMMAND_RESEND_S
            while time.monotonic() < min(resend, deadline):
                for msg in self.poll(0.02):
                    if msg.get_type() == "PARAM_VALUE" and _param_name(msg.param_id) == name:
                        return float(msg.param_value)
        return None

    def in_mode(self, mode: FlightMode) -> bool:
        """True if the last HEARTBEAT showed `mode`."""
        c = self.state.custom_mode
        return c is not None and (c & mode.mask) == mode.custom_mode

    # -- setpoints -----------------------------------------------------------------------------------
    def attitude_target(self, quaternion: Sequence[float], thrust: float) -> None:
        """SET_ATTITUDE_TARGET: attitude (body to NED, scalar first) and normalised thrust in [0, 1]."""
        self._attitude_target(IGNORE_RATES, quaternion, (0.0, 0.0, 0.0), thrust)

    def rates_target(self, rates: Sequence[float], thrust: float) -> None:
        """SET_ATTITUDE_TARGET: body rates (FRD, rad/s) and normalised thrust in [0, 1]."""
        self._attitude_target(IGNORE_ATTITUDE, (1.0, 0.0, 0.0, 0.0), rates, thrust)

    def position_target(self, position: Sequence[float], yaw: float) -> None:
        """SET_POSITION_TARGET_LOCAL_NED: position NED (m, from the autopilot's EKF origin) and yaw (rad);
        the autopilot's own position controller flies there (ArduCopter GUIDED)."""
        x, y, z = (float(v) for v in position)
        self.link.send([mavlink.MAVLink_set_position_target_local_ned_message(
            self.state.time_boot_ms & 0xFFFFFFFF, self.state.system_id or 0, 1, mavlink.MAV_FRAME_LOCAL_NED,
            POSITION_AND_YAW, x, y, z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, float(yaw), 0.0)])

    def _attitude_target(self, mask: int, q: Sequence[float], rates: Sequence[float], thrust: float) -> None:
        t = min(max(float(thrust), 0.0), 1.0) if math.isfinite(thrust) else 0.0
        self.link.send([mavlink.MAVLink_set_attitude_target_message(
            self.state.time_boot_ms & 0xFFFFFFFF, self.state.system_id or 0, 1, mask,
            [float(v) for v in q], float(rates[0]), float(rates[1]), float(rates[2]), t)])

    def close(self) -> None:
        """Close the socket."""
        self.link.close()


def _param_name(raw: bytes | str) -> str:
    return (raw.decode("ascii", "replace") if isinstance(raw, bytes) else str(raw)).rstrip("\x00")
