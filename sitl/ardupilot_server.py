"""`quadsr sitl --ardupilot`: the SITL's physics and sensors stepped by ArduPilot over its JSON interface.

Lockstep with ArduPilot's frame_count, pipelined: a new frame is answered at once with the state 1 ms on,
computed before it came, and its PWM (through the vehicle's PWM range and motor curve) drives the next 1 ms
step, computed right after the answer is sent, while ArduCopter runs its loop on that answer. So the two
processes work at the same time on two cores instead of in turn (lockstep is otherwise serial), at the price
of a 1 ms actuator delay: the PWM of frame k acts from the time of its answer on, i.e. over the step after
it (the motors' own lag is tens of ms). Still deterministic: the answers are a function of the frames. The
first answer after a (re)start comes from the throttle that holds the initial rotor speed.
The same frame again (ArduPilot re-sends after about 1.1 s without an answer) gets the last answer again
without stepping; a frame_count going back, or frames from a new source address (another ArduPilot
process), is a restarted ArduPilot: the vehicle is put back at its start and time restarts (ArduPilot takes
the falling timestamp as a physics reset). Packets with a wrong magic or size are dropped and counted.
The first answer carries timestamp 0.001 s: ArduPilot's clock advances by differences of timestamps.

The truth .tlog holds what `quadsr sitl --log` writes for a HIL flight (the step frames of sitl.hil, from
sysid 1 compid 51) every 4 ms, plus the motor throttles then as HIL_ACTUATOR_CONTROLS (sysid 1 compid 1),
so every quadsr tool reads ArduPilot-flown flights as it reads its own.
"""

from __future__ import annotations

import math
import signal
import socket
import sys
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TextIO

from bridge.errors import UserError
from bridge.framing import Framer, kind
from bridge.link import Endpoint
from bridge.messages import ARMED_MODE, LOCKSTEP_FLAG, mavlink
from bridge.tlog import TlogWriter
from bridge.vehicle import VehicleConfig
from sitl.ardupilot_json import BadPacket, sensor_json, servo_motors, throttles_from_pwm
from sitl.dynamics import EXCHANGE_STEP_USEC, Quadrotor
from sitl.hil import HIL_COMPONENT_ID, SYSTEM_ID, HilEncoder
from sitl.sensors import SensorModel

JSON_STEP_USEC = 1000  # physics step per servo frame: ArduCopter's 400 Hz loop needs a gyro at >= 720 Hz
TLOG_EVERY_USEC = EXCHANGE_STEP_USEC  # the .tlog keeps quadsr's 4 ms grid (its readers expect 250 Hz)
TLOG_BATCH_USEC = 25 * TLOG_EVERY_USEC  # simulated us of tlog frames written at once (one os.write)
MAX_WAIT_S = 0.25  # longest single blocking wait, so SIGINT/SIGTERM are honoured promptly
AUTOPILOT_COMPONENT_ID = 1  # the throttles are logged as the autopilot's HIL_ACTUATOR_CONTROLS
LISTENING = "listening for ArduPilot on"
_UNUSED_CONTROLS = (0.0,) * 12  # HIL_ACTUATOR_CONTROLS controls[4..15]


@dataclass
class ArduPilotOptions:
    """What `quadsr sitl --ardupilot` runs with (validated by sitl.cli)."""

    vehicle: VehicleConfig
    endpoint: Endpoint  # where ArduPilot sends its servo packets (its 9002 + 10*instance)
    log: Path | None = None
    initial_rotor_speed: float = 0.0  # rad/s, all four rotors
    status_interval: float = 5.0  # s wall; 0: no periodic status line
    silence_timeout: float = 3.0  # s wall without servo packets, once flying, before saying ArduPilot stopped
    max_steps: int | None = None


@dataclass
class ServoStats:
    """What came from ArduPilot: packets used, re-sent, missed, restarts, and bad packets dropped."""

    packets: int = 0  # servo packets received (good ones)
    resent: int = 0  # the same frame_count again: answered with the last reply, no step
    missed: int = 0  # frame_count jumped forward by more than 1: frames never received
    restarts: int = 0  # frame_count went back or a new sender: ArduPilot restarted, the vehicle was reset
    bad_magic: int = 0  # dropped: not a servo packet magic
    bad_size: int = 0  # dropped: wrong length for its magic
    senders: int = 0  # distinct ArduPilot addresses seen

    def as_dict(self) -> dict[str, int]:
        """All counters as a plain dict."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class _Sequence:
    """The identity and sequence number a Framer stamps on frames (what a UdpLink holds for a HilEncoder)."""

    system_id: int
    component_id: int
    seq: int = 0
    signing: None = None


class ArduPilotServer:
    """One simulated quadrotor stepped by ArduPilot's servo packets, answered with its JSON sensor object."""

    def __init__(self, options: ArduPilotOptions, out: TextIO | None = None):
        self.options = options
        self.out = out if out is not None else sys.stdout
        v = options.vehicle
        self.quad = Quadrotor(v, JSON_STEP_USEC)
        self.sensors = SensorModel(v.sensors, v.home, v.simulation.seed)
        self.pwm_range = (v.motor.pwm_min, v.motor.pwm_max)
        self._pending: list[bytes] = []  # tlog frames not yet written (see _log_state)
        self.stats = ServoStats()
        self.steps = 0
        self.last_count: int | None = None
        self.last_reply = b""
        self.answered_usec = 0  # simulated time of the last answer sent (the physics is 1 ms ahead of it)
        self._ready: bytes | None = None  # the answer to the next new frame, once computed (advance)
        self._throttles = (0.0, 0.0, 0.0, 0.0)  # what drives the next step: the last frame's PWM
        self.peer: tuple[str, int] | None = None
        self._state = HilEncoder(v.home, _Sequence(SYSTEM_ID, HIL_COMPONENT_ID))  # type: ignore[arg-type]
        autopilot = _Sequence(SYSTEM_ID, AUTOPILOT_COMPONENT_ID)
        self._commands = Framer(SYSTEM_ID, AUTOPILOT_COMPONENT_ID, autopilot)
        self._actuators = kind(mavlink.MAVLink_hil_actuator_controls_message)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind(options.endpoint.address)
        except OSError as exc:
            self.sock.close()
            raise UserError(f"--ardupilot {options.endpoint}: cannot listen there ({exc.strerror})",
                            hint="is another simulator there? use another port or -I N") from None
        self.port = self.sock.getsockname()[1]
        try:
            self.tlog = TlogWriter(options.log) if options.log else None
        except UserError:
            self.sock.close()
            raise
        self._stop = False
        self._silent_said = False
        self._reset()

    # -------------------------------------------------------------------------------------------------
    # The protocol

    def _reset(self) -> None:
        """The vehicle back at its start, time 0, the noise stream restarted; time 0 logged."""
        v = self.options.vehicle
        speed = self.options.initial_rotor_speed
        self.quad.reset(position=v.initial.position, yaw=v.initial.yaw, rotor_speeds=[speed] * 4)
        self.sensors.reset()
        self._log_state()
        held = v.motor_curve.throttle_for_speed(speed) if speed > 0.0 else 0.0
        self._throttles = (held, held, held, held)
        self._ready = None
        self.answered_usec = 0

    def handle(self, data: bytes, sender: tuple[str, int]) -> bytes | None:
        """The reply to one datagram from ArduPilot (None: dropped and counted); a new frame's PWM is kept
        for the next step (`advance`, which the server runs after sending the reply)."""
        stats = self.stats
        try:
            count, p1, p2, p3, p4 = servo_motors(data)
        except BadPacket as exc:
            if exc.reason == "magic":
                stats.bad_magic += 1
            else:
                stats.bad_size += 1
            return None
        stats.packets += 1
        last = self.last_count
        if sender != self.peer:
            stats.senders += 1
            self.peer = sender
            if last is not None:  # another ArduPilot process (a new source port): a restart
                self._restart(count, f"a new sender {sender[0]}:{sender[1]}")
        elif last is not None and count <= last:
            if count == last:
                stats.resent += 1
                return self.last_reply
            self._restart(count, f"frame {count} after {last}")  # frame_count going back
        elif last is not None and count > last + 1:
            stats.missed += count - last - 1
        self.last_count = count
        self._silent_said = False
        if self._ready is None:  # not computed ahead (the first frame, or a caller that never advances)
            self.advance()
        self.last_reply = reply = self._ready  # type: ignore[assignment]
        self._ready = None
        self.answered_usec = self.quad.time_usec
        self._throttles = throttles_from_pwm((p1, p2, p3, p4), *self.pwm_range)
        return reply

    def advance(self) -> None:
        """Step the physics 1 ms with the last frame's throttles and keep the answer for the next new frame
        (nothing when it is already computed)."""
        if self._ready is None:
            self._ready = self._step(self._throttles)

    def _restart(self, count: int, why: str) -> None:
        """ArduPilot restarted: say so, put the vehicle back at its start."""
        self.stats.restarts += 1
        self._say(f"quadsr sitl: ArduPilot restarted ({why}) at t={self.answered_usec * 1e-6:.3f}s: "
                  "vehicle reset to its start")
        self._reset()
        self.last_count = None

    def _step(self, throttles: tuple[float, float, float, float]) -> bytes:
        """Log the command at the current time, step 1 ms, return the new state's JSON line: on the tlog's
        4 ms grid from the full sensor sample (logged), between from the IMU alone (the JSON object has no
        magnetometer, barometer or GPS: ArduPilot simulates its own from the position and attitude)."""
        quad = self.quad
        logging = self.tlog is not None
        if logging and quad.time_usec % TLOG_EVERY_USEC == 0:  # as encode_hil_actuator_controls, packed here
            msg_id, extra, pack = self._actuators  # wire order: time_usec, flags, controls[16], mode
            payload = pack(quad.time_usec, LOCKSTEP_FLAG, *throttles, *_UNUSED_CONTROLS, ARMED_MODE)
            self._pending.extend(self._commands.frames([(msg_id, extra, payload)]))
        quad.step(throttles)
        self.steps += 1
        if logging and quad.time_usec % TLOG_EVERY_USEC == 0:
            s = self._log_state()
            accel, gyro = s.accel, s.gyro
        else:
            accel, gyro = self.sensors.imu(quad)
        return sensor_json(quad.time_usec * 1e-6, gyro, accel, quad.position, quad.velocity, quad.quaternion)

    def _log_state(self):
        """Sample the sensors at the current step and queue its HIL frames for the tlog; return the sample.

        The tlog is written every TLOG_BATCH_USEC of simulated time (one os.write of whole records), so a
        killed run leaves a readable file that lacks at most that much."""
        s = self.sensors.sample(self.quad)
        t = self.quad.time_usec
        if self.tlog is not None and t % TLOG_EVERY_USEC == 0:
            self._pending.extend(self._state.step_frames(self.quad, s))
            if t % TLOG_BATCH_USEC == 0:
                self.flush_tlog()
        return s

    def flush_tlog(self) -> None:
        """Write the queued tlog frames (one write)."""
        if self._pending and self.tlog is not None:
            self.tlog.write_frames(self._pending)
        self._pending = []

    # -------------------------------------------------------------------------------------------------
    # Running

    def run(self) -> int:
        """Serve until SIGINT/SIGTERM or --max-steps; returns the exit code (0)."""
        previous = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        opts = self.options
        try:
            self._say(
                f"quadsr sitl: {LISTENING} udp:{opts.endpoint.host}:{self.port} (JSON physics, lockstep on "
                f"frame_count); vehicle {opts.vehicle.name}; "
                f"PWM {self.pwm_range[0]:g}-{self.pwm_range[1]:g} us"
                + (f"; logging to {opts.log}" if opts.log else "")
            )
            now = time.monotonic()
            next_status = now + opts.status_interval if opts.status_interval else math.inf
            last_packet = now
            status_steps, status_wall = 0, now
            # A Python socket timeout (poll before each call). A blocking socket with the bound in
            # SO_RCVTIMEO makes half the system calls but measured 10-20 us more CPU per frame here.
            sock = self.sock
            sock.settimeout(MAX_WAIT_S)
            recvfrom, sendto, monotonic = sock.recvfrom, sock.sendto, time.monotonic
            handle, advance = self.handle, self.advance
            while not self._stop and not self._done():
                try:
                    data, sender = recvfrom(4096)
                except OSError:  # the wait bound (TimeoutError), or e.g. ICMP port unreachable of a reply
                    data = None
                now = monotonic()
                if data is not None:
                    reply = handle(data, sender)
                    if reply is not None:
                        last_packet = now
                        try:
                            sendto(reply, sender)
                        except OSError:
                            pass
                        advance()  # the next answer, while ArduCopter works on this one
                elif self.steps and not self._silent_said and now - last_packet > opts.silence_timeout:
                    self._silent_said = True
                    self.flush_tlog()
                    self._say(f"quadsr sitl: ArduPilot silent for {opts.silence_timeout:g} s at "
                              f"t={self.answered_usec * 1e-6:.3f}s (frame {self.last_count}): stopped or "
                              "killed? waiting for it (a restarted ArduPilot resets the vehicle)")
                if now >= next_status:
                    self._say(self.status_line(now - status_wall, self.steps - status_steps))
                    status_steps, status_wall = self.steps, now
                    next_status = now + opts.status_interval
            self._say(self.status_line(max(time.monotonic() - status_wall, 1e-9), self.steps - status_steps)
                      + " (exit)")
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
            self.close()
        return 0

    def status_line(self, wall_s: float, steps: int) -> str:
        """One line: sim time, steps, rate, real-time factor, peer, position NED and the packet counters."""
        rate = steps / max(wall_s, 1e-9)
        n, e, d = self.quad.position
        who = f"{self.peer[0]}:{self.peer[1]}" if self.peer else "none"
        counters = " ".join(f"{k}={v}" for k, v in self.stats.as_dict().items())
        return (f"quadsr sitl: t={self.answered_usec * 1e-6:.3f}s steps={self.steps} rate={rate:.0f}/s "
                f"rtf={rate * JSON_STEP_USEC * 1e-6:.2f} ardupilot={who} frame={self.last_count} "
                f"pos_ned=({n:.3f},{e:.3f},{d:.3f})m {counters}")

    def close(self) -> None:
        """Close the socket and the tlog (its queued frames written first)."""
        self.sock.close()
        if self.tlog is not None:
            self.flush_tlog()
            self.tlog.close()

    def _done(self) -> bool:
        return self.options.max_steps is not None and self.steps >= self.options.max_steps

    def _on_signal(self, signum, frame) -> None:
        self._stop = True

    def _say(self, line: str) -> None:
        if self.out is None:
            return
        try:
            print(line, file=self.out, flush=True)
        except (BrokenPipeError, ValueError, OSError):
            self.out = None
