"""Fly a real ArduCopter over MAVLink (pymavlink, TCP): wait for its EKF to use GPS, arm in GUIDED, take off,
hold, run System ID chirps, land, disarm. Waits are bounded in simulated time (ArduPilot's time_boot_ms),
so they do not depend on how fast the machine is; a wall-clock bound only catches a dead link.

Positions are ArduPilot's estimate, NED from its EKF origin (m); heights are -z (m, up).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink import mavutil

from bridge.errors import UserError

GUIDED = "GUIDED"
LOITER = "LOITER"
LAND = "LAND"
SYSTEMID = "SYSTEMID"
POS_HORIZ_ABS = 16  # EKF_STATUS_REPORT flags: horizontal absolute position (GPS) in use
POS_VERT_ABS = 32
STICKS_EVERY_S = 0.2  # simulated s between RC_CHANNELS_OVERRIDE while the sticks are held centred
CENTRE_PWM = 1500  # us: roll, pitch, yaw centred, throttle mid-stick (no climb in LOITER)
POSITION_AXES = (14, 15, 16, 17, 18, 19)  # SID_AXIS values ArduCopter runs under position control


class FlightError(RuntimeError):
    """ArduCopter did not do what was asked within its simulated-time bound (or the link died)."""


@dataclass
class Track:
    """ArduPilot's LOCAL_POSITION_NED samples: simulated time (s) and position NED (m)."""

    t: list[float] = field(default_factory=list)
    ned: list[tuple[float, float, float]] = field(default_factory=list)


@dataclass
class Chirp:
    """One System ID chirp flown: its axis and magnitude, simulated start and end (s), and why ArduCopter
    stopped it early ('' when it ran to the end)."""

    axis: int
    magnitude: float
    start: float
    end: float
    stopped: str


class ArduCopterLink:
    """A MAVLink connection to ArduCopter's SERIAL0, with waits in its simulated time."""

    def __init__(self, address: str, wall_timeout: float = 60.0, rate_hz: float = 25.0):
        self.address = address
        self.wall_timeout = wall_timeout  # s wall: no message at all for this long is a dead link
        deadline = time.monotonic() + wall_timeout
        while True:  # ArduCopter opens its TCP port a moment after it starts
            try:
                self.conn = mavutil.mavlink_connection(address, source_system=255, source_component=190,
                                                       autoreconnect=False)
                break
            except ConnectionRefusedError:
                if time.monotonic() > deadline:
                    raise FlightError(f"ArduCopter refused the connection at {address} for "
                                      f"{wall_timeout:g} s") from None
                time.sleep(0.2)
        self.sim_time = 0.0  # s, ArduPilot's time since boot (the latest time_boot_ms seen)
        self.texts: list[str] = []
        self.track = Track()
        self.armed = False
        self.mode = ""
        self.ekf_flags = 0
        self.sticks_centred = False  # while True, wait_until keeps RC_CHANNELS_OVERRIDE at mid-stick
        self._next_sticks = 0.0
        if self.conn.wait_heartbeat(timeout=wall_timeout) is None:
            raise FlightError(f"no HEARTBEAT from ArduCopter at {address} within {wall_timeout:g} s")
        self.conn.mav.request_data_stream_send(self.conn.target_system, self.conn.target_component,
                                               mavutil.mavlink.MAV_DATA_STREAM_ALL, int(rate_hz), 1)

    def close(self) -> None:
        """Close the connection."""
        self.conn.close()

    # ---------------------------------------------------------------------------------------------------
    # Receiving

    def poll(self, wall_wait: float = 0.1) -> Any:
        """Receive one message (or None after wall_wait s) and update the time, state and texts from it."""
        msg = self.conn.recv_match(blocking=True, timeout=wall_wait)
        if msg is None:
            return None
        kind = msg.get_type()
        stamp = getattr(msg, "time_boot_ms", None)
        if stamp is not None and kind != "BAD_DATA":
            self.sim_time = max(self.sim_time, stamp * 1e-3)
        if kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
            self.armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self.mode = mavutil.mode_string_v10(msg)
        elif kind == "STATUSTEXT":
            self.texts.append(msg.text)
        elif kind == "EKF_STATUS_REPORT":
            self.ekf_flags = msg.flags
        elif kind == "LOCAL_POSITION_NED":
            self.track.t.append(msg.time_boot_ms * 1e-3)
            self.track.ned.append((msg.x, msg.y, msg.z))
        return msg

    def wait_until(self, done: Callable[[], bool], sim_seconds: float, what: str) -> None:
        """Poll until done() holds; FlightError after sim_seconds of simulated time (or a dead link)."""
        start = self.sim_time
        last_msg = time.monotonic()
        while not done():
            if self.sticks_centred and self.sim_time >= self._next_sticks:
                self.conn.mav.rc_channels_override_send(self.conn.target_system, self.conn.target_component,
                                                        *([CENTRE_PWM] * 4), 0, 0, 0, 0)
                self._next_sticks = self.sim_time + STICKS_EVERY_S
            if self.sim_time - start > sim_seconds:
                raise FlightError(f"{what}: not within {sim_seconds:g} s of simulated time "
                                  f"(last texts: {self.texts[-4:]})")
            if self.poll() is not None:
                last_msg = time.monotonic()
            elif time.monotonic() - last_msg > self.wall_timeout:
                raise FlightError(f"{what}: ArduCopter silent for {self.wall_timeout:g} s wall (link lost)")

    def fly_for(self, sim_seconds: float) -> None:
        """Keep receiving for sim_seconds of simulated time."""
        end = self.sim_time + sim_seconds
        self.wait_until(lambda: self.sim_time >= end, sim_seconds + 1.0, f"flying {sim_seconds:g} s")

    @property
    def height(self) -> float:
        """ArduPilot's estimated height above its origin, m (up); nan before any position."""
        return -self.track.ned[-1][2] if self.track.ned else float("nan")

    # ---------------------------------------------------------------------------------------------------
    # Commands

    def command(self, command: int, *params: float) -> None:
        """COMMAND_LONG to the autopilot (up to 7 params)."""
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(self.conn.target_system, self.conn.target_component, command, 0, *p)

    def release_sticks(self) -> None:
        """Stop holding the sticks centred: RC override channels 1-8 released (0) to the RC input."""
        self.sticks_centred = False
        self.conn.mav.rc_channels_override_send(self.conn.target_system, self.conn.target_component,
                                                *([0] * 8))

    def set_param(self, name: str, value: float) -> None:
        """PARAM_SET (float)."""
        self.conn.mav.param_set_send(self.conn.target_system, self.conn.target_component, name.encode(),
                                     float(value), mavutil.mavlink.MAV_PARAM_TYPE_REAL32)

    def set_mode(self, mode: str, sim_seconds: float = 10.0) -> None:
        """Switch flight mode (asked again every 0.5 s of simulated time) until the HEARTBEAT shows it."""
        mapping = self.conn.mode_mapping()
        if mode not in mapping:
            raise UserError(f"ArduCopter has no mode {mode!r}", hint=f"modes: {', '.join(mapping)}")
        number = mapping[mode]
        self.wait_until(self._every(0.5, lambda: self.conn.set_mode(number), lambda: self.mode == mode),
                        sim_seconds, f"mode {mode}")

    def _every(self, period: float, action: Callable[[], None],
               done: Callable[[], bool]) -> Callable[[], bool]:
        """A wait_until condition that repeats action every period s of simulated time until done()."""
        next_try = [self.sim_time]

        def check() -> bool:
            if done():
                return True
            if self.sim_time >= next_try[0]:
                action()
                next_try[0] = self.sim_time + period
            return False

        return check

    def wait_ekf_gps(self, sim_seconds: float = 120.0) -> float:
        """Wait until the EKF uses GPS for horizontal and vertical position; return the simulated time (s)."""
        flags = POS_HORIZ_ABS | POS_VERT_ABS
        self.wait_until(lambda: (self.ekf_flags & flags) == flags and self.sim_time > 0, sim_seconds,
                        "EKF using GPS")
        return self.sim_time

    def arm(self, sim_seconds: float = 120.0) -> float:
        """Arm (retried every 2 s of simulated time while pre-arm checks refuse); return the sim time."""
        self.release_sticks()  # ArduCopter refuses to arm with the throttle stick above its minimum
        arm = self._every(2.0, lambda: self.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1),
                          lambda: self.armed)
        self.wait_until(arm, sim_seconds, "arming")
        return self.sim_time

    def takeoff(self, height: float, sim_seconds: float = 30.0, tolerance: float = 0.15) -> float:
        """GUIDED take-off to height m; wait until within tolerance m of it; return the simulated time."""
        self.command(mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, height)
        self.wait_until(lambda: abs(self.height - height) < tolerance, sim_seconds,
                        f"take-off to {height:g} m")
        return self.sim_time

    def land(self, sim_seconds: float = 60.0) -> float:
        """LAND mode; wait until ArduCopter disarms on the ground; return the simulated time."""
        self.set_mode(LAND)
        self.wait_until(lambda: not self.armed, sim_seconds, "landing and disarming")
        return self.sim_time

    def hold_error(self, since: float, target: tuple[float, float, float]) -> float:
        """Largest distance (m) of ArduPilot's position from target (NED, m) since simulated time `since`."""
        errors = [sum((a - b) ** 2 for a, b in zip(p, target, strict=True)) ** 0.5
                  for t, p in zip(self.track.t, self.track.ned, strict=True) if t >= since]
        if not errors:
            raise FlightError("no LOCAL_POSITION_NED samples in the hold")
        return max(errors)

    def system_id(self, axis: int, magnitude: float, f_start: float = 0.5, f_stop: float = 3.0,
                  t_fade: float = 1.0, t_rec: float = 10.0) -> Chirp:
        """One System ID chirp from a LOITER hover: SID_AXIS axis, SID_MAGNITUDE, SID_F_START/STOP_HZ (Hz),
        SID_T_FADE_IN/OUT and SID_T_REC (s; ArduCopter holds f_start for 2/f_start s first, so
        t_rec must exceed that); then back to LOITER.

        Only the position-controlled axes (14-19: 14/15 position disturbance lateral/longitudinal in m,
        16/17 velocity disturbance in m/s, 18/19 velocity input in m/s) run from LOITER; ArduCopter runs the
        attitude and mixer axes (1-13) only from a manual-throttle mode. The sticks are held centred (RC
        override) so that LOITER holds height.
        """
        if axis not in POSITION_AXES:
            raise UserError(f"SID_AXIS {axis}: only the position-controlled axes {POSITION_AXES} run from "
                            "LOITER", hint="ArduCopter needs a manual-throttle mode for axes 1-13")
        if not t_rec > 2.0 / f_start:
            raise UserError(f"System ID: t_rec {t_rec:g} s must exceed 2/f_start = {2.0 / f_start:g} s",
                            hint="raise f_start or t_rec")
        for name, value in (("SID_AXIS", axis), ("SID_MAGNITUDE", magnitude), ("SID_F_START_HZ", f_start),
                            ("SID_F_STOP_HZ", f_stop), ("SID_T_FADE_IN", t_fade), ("SID_T_REC", t_rec),
                            ("SID_T_FADE_OUT", t_fade)):
            self.set_param(name, value)
        self.sticks_centred = True
        self.set_mode(LOITER)
        self.fly_for(1.0)
        start = self.sim_time
        first_text = len(self.texts)
        self.set_mode(SYSTEMID)
        length = 1.0 + t_fade + t_rec + t_fade  # ArduCopter waits 1 s after the mode change
        self.fly_for(length + 0.5)
        if self.mode != SYSTEMID:
            raise FlightError(f"System ID chirp on axis {axis} ended early in mode {self.mode} "
                              f"(last texts: {self.texts[-4:]})")
        self.set_mode(LOITER)
        stopped = [t for t in self.texts[first_text:] if t.startswith("SystemID Stopped")]
        return Chirp(axis, magnitude, start, self.sim_time, stopped[0] if stopped else "")
