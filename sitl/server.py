"""The SITL process: waits for a companion, steps the physics in lockstep (or real time), serves both links.

Phases: waiting (no companion yet: on the ground, no stepping), starting (a companion spoke: the time-0
datagram is re-sent every 0.1 s wall until its first HIL_ACTUATOR_CONTROLS), stepping (lockstep: one step per
reply to the last HIL_SENSOR; realtime: paced to the wall clock holding the last command), failsafe (motors
commanded to zero, stepping at wall-clock pace until actuator messages return).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from bridge.framing import unpack_frame
from bridge.link import LOCKSTEP_SPIN_S, Endpoint, UdpLink
from bridge.messages import Heartbeat, HilActuatorControls, mavlink, sanitize_throttles
from bridge.shutdown import StopSignals
from bridge.signing import Signing
from bridge.vehicle import EXCHANGE_STEP, VehicleConfig
from sitl import compiled_physics
from sitl.dynamics import EXCHANGE_STEP_USEC, Quadrotor
from sitl.ground_link import GroundLink, GroundState, Home
from sitl.hil import HIL_COMPONENT_ID, SYSTEM_ID, HilEncoder, statustext
from sitl.sensors import SensorModel
from sitl.status import CommandStats, StatusSnapshot, format_status

RESEND_PERIOD_S = 0.1  # wall s: the last step is re-sent this often while its reply is missing
GROUND_EVERY_STEPS = 5  # ground link serviced every 5th step (50 Hz of simulated time)
GROUND_WAIT_PERIOD_S = 0.02  # ground link service period while not stepping (wall clock)
MAX_WAIT_S = 0.25  # longest single blocking wait, so SIGINT/SIGTERM are honoured promptly
MAX_LAG_S = 0.1  # wall-paced stepping that falls this far behind restarts its schedule instead of bursting
ZERO = (0.0, 0.0, 0.0, 0.0)
ACTUATOR_ID = HilActuatorControls.id
HEARTBEAT_ID = Heartbeat.id
if HilActuatorControls.ordered_fieldnames[:3] != ["time_usec", "flags", "controls"]:
    raise ImportError("unexpected HIL_ACTUATOR_CONTROLS wire order")
SPINNING_RAD_S = 1.0  # a rotor faster than this counts as spinning (HEARTBEAT armed flag)


@dataclass
class SitlOptions:
    """Everything `quadsr sitl` runs with (validated by sitl.cli)."""

    vehicle: VehicleConfig
    hil: Endpoint
    ground: list[Endpoint] = field(default_factory=list)
    mode: str = "lockstep"  # lockstep | realtime
    log: Path | None = None
    signing_key: bytes | None = None
    initial_rotor_speed: float = 0.0  # rad/s, all four rotors
    lockstep_timeout: float = 1.0  # s wall: lockstep wait bound before the failsafe
    lockstep_spin: float = LOCKSTEP_SPIN_S  # s wall: lockstep, poll for a reply this long before sleeping
    realtime_timeout: float = 0.2  # s simulated: realtime silence before the failsafe
    status_interval: float = 5.0  # s wall; 0: no periodic status line
    max_steps: int | None = None
    companion_sysid: int = 1


class SitlServer:
    """One simulated quadrotor serving a companion on the HIL link and ground tools on the ground link."""

    NEVER_REPEAT_SENSORS = False  # a companion takes noise-free readings as they are (sitl.sensors)

    def __init__(self, options: SitlOptions, out: TextIO | None = None):
        self.options = options
        self.out = out if out is not None else sys.stdout
        v = options.vehicle
        self.quad = Quadrotor(v)
        self.quad.reset(
            position=v.initial.position, yaw=v.initial.yaw, rotor_speeds=[options.initial_rotor_speed] * 4
        )
        self.sensors = SensorModel(v.sensors, v.home, v.simulation.seed,
                                   never_repeat=self.NEVER_REPEAT_SENSORS)
        signing = Signing(options.signing_key, link_id=0) if options.signing_key else None
        self.link = self._open_link(signing)
        self.encoder = HilEncoder(v.home, self.link)
        try:
            ground_signing = Signing(options.signing_key, link_id=1) if options.signing_key else None
            self.ground = GroundLink(
                [(e.host, e.port) for e in options.ground], Home(v.home.lat, v.home.lon, v.home.alt),
                ground_signing,
            )
        except BaseException:
            self.link.close()
            raise
        self.commands = CommandStats()
        self.phase = "waiting"
        self.companion: tuple[str, int] | None = None
        self.held = ZERO  # throttles the motors get (lockstep: the last reply; realtime: the last message)
        self.last_sent_usec = -1  # time_usec of the last HIL_SENSOR sent
        self.last_cmd_usec = -1  # time_usec stamped on the last applied actuator command
        self.last_cmd_sim_usec = 0  # simulated time when the last actuator command was applied
        self._last_reply_usec = -1  # time_usec of the last accepted actuator message, as stamped
        self._rejoining = False  # lockstep failsafe left for a companion's hello; its first reply resumes
        self._companion_heard = 0.0  # wall time (monotonic s) the bound companion last spoke
        # another sender may take the HIL link over only after the companion was silent this long (wall s)
        lockstep = options.mode == "lockstep"
        self._takeover_after = options.lockstep_timeout if lockstep else options.realtime_timeout
        self.steps = 0
        self.pending_text: list = []
        self._stop = False
        self._t_start = time.monotonic()
        self._ground_base_us = 0  # ground clock = base + simulated time once stepping
        self._next_ground_wall = 0.0
        self._next_status = self._t_start + options.status_interval if options.status_interval else math.inf
        self._status_steps = 0
        self._status_wall = self._t_start

    def _open_link(self, signing: Signing | None) -> UdpLink:
        """The HIL link: UDP bound to the --hil address, accepting the companion's system id."""
        o = self.options
        return UdpLink(
            local=o.hil,
            system_id=SYSTEM_ID,
            component_id=HIL_COMPONENT_ID,
            signing=signing,
            tlog=str(o.log) if o.log else None,
            accept_system_ids=[o.companion_sysid],
        )

    # -------------------------------------------------------------------------------------------------
    # Running

    def run(self) -> int:
        """Serve until SIGINT/SIGTERM or --max-steps; returns the exit code (0)."""
        # The first SIGINT/SIGTERM stops the loop; later ones are absorbed, so the shutdown always completes.
        with StopSignals(on_stop=self.stop):
            try:
                self._say(self._listening_line())
                while not self._stop and not self._done():
                    if self.phase in ("waiting", "starting"):
                        self._serve_connect()
                    elif self.phase == "failsafe" or self.options.mode == "realtime":
                        self._serve_paced()
                    else:
                        self._serve_lockstep()
                self._say(self._status_line(time.monotonic()) + " (exit)")
            finally:
                self.close()
        return 0

    def close(self) -> None:
        """Close both links (and the tlog)."""
        self.link.close()
        self.ground.close()

    def stop(self) -> None:
        """Ask the serving loop to end (it returns within MAX_WAIT_S); safe to call any number of times."""
        self._stop = True

    def _done(self) -> bool:
        return self.options.max_steps is not None and self.steps >= self.options.max_steps

    def _listening_line(self) -> str:
        o = self.options
        ground = ", ".join(str(e) for e in o.ground) or "none"
        return (
            f"quadsr sitl: listening for the companion on udp:{self.link.local.host}:{self.link.local.port} "
            f"({o.mode}); vehicle {o.vehicle.name}; ground link to {ground}"
            + ("" if compiled_physics.available() else "; physics in Python (sitl._derivative not built)")
            + ("; signing on" if o.signing_key else "")
            + (f"; logging to {o.log}" if o.log else "")
        )

    def _say(self, line: str) -> None:
        if self.out is None:
            return
        try:
            print(line, file=self.out, flush=True)
        except (BrokenPipeError, ValueError, OSError):  # nobody reads our output any more: keep serving
            self.out = None

    # -------------------------------------------------------------------------------------------------
    # Phases

    def _serve_connect(self) -> None:
        """Waiting/starting: no stepping; ground link at wall pace; time-0 datagram re-sent while starting."""
        link = self.link
        next_resend = time.monotonic() if self.phase == "starting" else math.inf
        while not self._stop and self.phase in ("waiting", "starting"):
            now = time.monotonic()
            if now >= self._next_ground_wall:
                self._service_ground_wall(now)
            if now >= self._next_status:
                self._status(now)
            if self.phase == "starting" and now >= next_resend:
                self._send_step()
                next_resend = now + RESEND_PERIOD_S
            wake = min(self._next_ground_wall, next_resend, self._next_status, now + MAX_WAIT_S)
            frames = link.recv_split(max(0.0, wake - now))
            if not frames:
                self._keep_peer()
                continue
            hello, reply = self._read(frames, accept_from=0)
            if hello or reply is not None:
                self.companion = link.peer
                if self.phase == "waiting":
                    self.phase = "starting"
                    self._send_step()
                    next_resend = time.monotonic() + RESEND_PERIOD_S
            else:
                self._keep_peer()
            if reply is not None:
                self._start_stepping(reply)

    def _start_stepping(self, throttles) -> None:
        self.phase = "stepping"
        self._ground_base_us = int((time.monotonic() - self._t_start) * 1e6)
        self.last_cmd_sim_usec = self.quad.time_usec
        self._advance(throttles)

    def _serve_lockstep(self) -> None:
        """Lockstep: step k+1 only after the reply to step k's HIL_SENSOR; past the wait bound, failsafe.

        UDP may lose a datagram (even on loopback, under load): the last step is re-sent every 0.1 s wall
        while its reply is missing, so a companion that answers every HIL_SENSOR recovers before the bound.
        The reply is polled for up to lockstep_spin before the process sleeps for it (UdpLink.spin_s).
        """
        link = self.link
        link.spin_s = self.options.lockstep_spin
        try:
            self._lockstep_loop(link)
        finally:
            link.spin_s = 0.0

    def _lockstep_loop(self, link: UdpLink) -> None:
        """The lockstep loop of _serve_lockstep."""
        timeout = self.options.lockstep_timeout
        monotonic = time.monotonic
        sent_at = monotonic()
        deadline = sent_at + timeout
        next_resend = sent_at + RESEND_PERIOD_S
        while not self._stop:
            now = monotonic()
            if now >= self._next_status:
                self._status(now)
            remaining = deadline - now
            if remaining <= 0.0:
                self._engage_failsafe(
                    f"no reply for {timeout:g} s",
                    f"no actuator reply for {timeout:g} s (lockstep wait bound)",
                )
                return
            if now >= next_resend:
                self._send_step()
                self.commands.resent += 1
                next_resend = now + RESEND_PERIOD_S
            # A constant timeout spares a settimeout call per step; the resend may come up to 0.1 s late.
            frames = link.recv_split(RESEND_PERIOD_S if RESEND_PERIOD_S < remaining else remaining)
            if not frames:
                continue
            hello, reply = self._read(frames, accept_from=self.last_sent_usec)
            if hello or reply is not None:
                self.companion = link.peer
            else:
                self._keep_peer()
            if reply is not None:
                if self._rejoining:
                    self._rejoining = False
                    self._queue_text(mavlink.MAV_SEVERITY_INFO, "quadsr failsafe: actuator commands resumed")
                self._advance(reply)
                if self._done():
                    return
                sent_at = monotonic()
                deadline = sent_at + timeout
                next_resend = sent_at + RESEND_PERIOD_S

    def _serve_paced(self) -> None:
        """Real time, or failsafe in either mode: one step per 4 ms of wall clock holding the last command."""
        link = self.link
        monotonic = time.monotonic
        realtime = self.options.mode == "realtime"
        limit_usec = int(round(self.options.realtime_timeout * 1e6))
        next_step = monotonic() + EXCHANGE_STEP
        while not self._stop and not self._done():
            now = monotonic()
            if now >= self._next_status:
                self._status(now)
            if now >= next_step:
                if (
                    realtime
                    and self.phase != "failsafe"
                    and self.quad.time_usec - self.last_cmd_sim_usec >= limit_usec
                ):
                    silence = self.options.realtime_timeout
                    self._engage_failsafe(
                        f"no command for {silence:g} s",
                        f"no actuator message for {silence:g} s of simulated time",
                    )
                self._advance(ZERO if self.phase == "failsafe" else self.held)
                next_step += EXCHANGE_STEP
                if now - next_step > MAX_LAG_S:
                    next_step = now + EXCHANGE_STEP
                continue
            wait = next_step - now
            frames = link.recv_split(wait if wait < MAX_WAIT_S else MAX_WAIT_S)
            if not frames:
                self._keep_peer()
                continue
            # In the failsafe of lockstep any actuator message resumes; in real time it must not be older.
            floor = self.last_cmd_usec if realtime else -1
            hello, reply = self._read(frames, accept_from=floor)
            if hello or reply is not None:
                self.companion = link.peer
            else:
                self._keep_peer()
            if reply is None:
                if hello and not realtime and self.phase == "failsafe":
                    # A companion (re)connects: wait for its reply to the current step instead of stepping on
                    # at wall pace, so its first command applies to the step it answers, however slow it is.
                    self.phase = "stepping"
                    self._rejoining = True
                    self._send_step()
                    return
                continue
            self.held = reply
            self.last_cmd_sim_usec = self.quad.time_usec
            if self.phase == "failsafe":
                self.phase = "stepping"
                self._queue_text(mavlink.MAV_SEVERITY_INFO, "quadsr failsafe: actuator commands resumed")
                if not realtime:
                    if self._last_reply_usec >= self.last_sent_usec:
                        self._advance(reply)
                    return

    def _engage_failsafe(self, why: str, explanation: str) -> None:
        """Motors to zero, a STATUSTEXT (`why` is short: it must fit in 50 characters), a console line."""
        self.phase = "failsafe"
        self._rejoining = False
        self.held = ZERO
        self.commands.failsafes += 1
        text = f"quadsr failsafe: {why}, motors off"
        self._queue_text(mavlink.MAV_SEVERITY_WARNING, text)
        self._say(f"quadsr sitl: FAILSAFE at t={self.quad.time_usec * 1e-6:.3f}s: {explanation}; motors off")

    def _queue_text(self, severity: int, text: str) -> None:
        msg = statustext(severity, text)
        self.pending_text.append(msg)
        self.ground.queue(msg)
        if severity == mavlink.MAV_SEVERITY_INFO:
            self._say(f"quadsr sitl: {text} at t={self.quad.time_usec * 1e-6:.3f}s")

    # -------------------------------------------------------------------------------------------------
    # HIL input

    def _read(self, frames: list, accept_from: int) -> tuple[bool, tuple | None]:
        """(the companion spoke, the throttles of its newest reply to a HIL_SENSOR sent at >= accept_from).

        frames are one datagram's checked, undecoded frames: only HIL_ACTUATOR_CONTROLS payloads are unpacked.
        Binding: only the companion's frames count; another sender is ignored (counted as foreign) until the
        companion has been silent past the failsafe bound. A reply counts only if its time_usec is that of a
        HIL_SENSOR the SITL sent (on the step grid, not after the last one sent) and not before accept_from.
        """
        sender = self.link.peer
        if sender != self.companion and self.companion is not None and (
            time.monotonic() - self._companion_heard <= self._takeover_after
        ):
            self.commands.foreign += len(frames)
            return False, None
        hello = False
        reply = None
        stats = self.commands
        last_sent = self.last_sent_usec
        for spec, frame, header_len, signature_len in frames:
            msg_id = spec.msg_id
            if msg_id == ACTUATOR_ID:
                values = unpack_frame(frame, header_len, signature_len, spec)  # time_usec, flags, controls..
                time_usec = values[0]
                hello = True  # the companion speaks (its first reply may come before any step was sent)
                if accept_from <= time_usec <= last_sent and time_usec % EXCHANGE_STEP_USEC == 0:
                    throttles, nonfinite, clamped = sanitize_throttles(values[2:6])
                    stats.nonfinite += nonfinite
                    stats.clamped += clamped
                    reply = throttles
                    stats.commands += 1
                    self.last_cmd_usec = time_usec
                    self._last_reply_usec = time_usec
                else:
                    stats.stale += 1
            elif msg_id == HEARTBEAT_ID:
                hello = True
            else:
                stats.ignored += 1
        if hello:
            self.companion = sender
            self._companion_heard = time.monotonic()
        return hello, reply

    def _keep_peer(self) -> None:
        """Answer the companion, not a sender whose frames were neither a HEARTBEAT nor an accepted reply."""
        self.link.peer = self.companion

    # -------------------------------------------------------------------------------------------------
    # Stepping and sending

    def _advance(self, throttles) -> None:
        """One 4 ms step with these throttles, then its datagram; the ground link every 5th step."""
        self.quad.step(throttles)
        self.steps += 1
        self._send_step()
        if self.steps % GROUND_EVERY_STEPS == 0 and self.ground.active:
            self.ground.service(self._ground_base_us + self.quad.time_usec, self._ground_state)

    def _send_step(self) -> None:
        quad = self.quad
        if self.pending_text:
            frames = self.encoder.frames_of(self.pending_text)
            self.pending_text = []
            frames += self.encoder.step_frames(quad, self.sensors.sample(quad))
        else:
            frames = self.encoder.step_frames(quad, self.sensors.sample(quad))
        self.link.send_frames(frames)
        self.last_sent_usec = quad.time_usec

    def _service_ground_wall(self, now: float) -> None:
        self._next_ground_wall = now + GROUND_WAIT_PERIOD_S
        if self.ground.active:
            self.ground.service(int((now - self._t_start) * 1e6), self._ground_state)

    def _ground_state(self) -> GroundState:
        q = self.quad
        x, y, z = q.position
        lat, lon, alt = self.encoder.frame.to_geodetic(x, y, z)
        spinning = max(q.rotor_speeds) > SPINNING_RAD_S
        clock_us = (self._ground_base_us + q.time_usec) if self.phase in ("stepping", "failsafe") else int(
            (time.monotonic() - self._t_start) * 1e6
        )
        return GroundState(
            time_boot_ms=clock_us // 1000,
            position=q.position,
            velocity=q.velocity,
            quaternion=q.quaternion,
            euler=q.euler,
            rates=q.rates,
            lat_deg=lat,
            lon_deg=lon,
            alt_m=alt,
            armed=spinning,
            companion=self.companion is not None and self.phase == "stepping",
            failsafe=self.phase == "failsafe",
            on_ground=q.on_ground,
        )

    # -------------------------------------------------------------------------------------------------
    # Status

    def _status(self, now: float) -> None:
        self._say(self._status_line(now))
        self._next_status = now + self.options.status_interval if self.options.status_interval else math.inf

    def _status_line(self, now: float) -> str:
        dt = max(now - self._status_wall, 1e-9)
        rate = (self.steps - self._status_steps) / dt
        self._status_steps = self.steps
        self._status_wall = now
        return format_status(
            StatusSnapshot(
                sim_time_s=self.quad.time_usec * 1e-6,
                steps=self.steps,
                steps_per_s=rate,
                realtime_factor=rate * EXCHANGE_STEP_USEC * 1e-6,
                mode=self.options.mode,
                phase=self.phase,
                companion=self.companion,
                position=self.quad.position,
                link=self.link.stats,
                commands=self.commands,
            )
        )
