"""The SITL serving a real autopilot (PX4) on PX4's simulator transport, instead of a quadsr companion.

Transports (`quadsr sitl --hil ...`):
- `tcp:HOST:PORT`: listen for the autopilot's TCP connection, as PX4's `simulator_mavlink -c PORT` expects
  (PX4 instance N connects to 127.0.0.1:4560+N), like Gazebo classic and jMAVSim.
- `udpout:HOST:PORT`: send first to an autopilot that bound HOST:PORT (PX4's `simulator_mavlink -u PORT`).

Start-up differs from a quadsr companion's (sitl.server): PX4 takes its clock from HIL_SENSOR.time_usec and
treats 0 as "not set", and its modules wait in simulated time while booting, so once the autopilot is there
the vehicle steps freely on the ground at zero throttle, paced to the wall clock, from time_usec 4000 on
(never 0, never one stamp twice), until the autopilot's first HIL_ACTUATOR_CONTROLS; then lockstep as with a
companion (one step per reply). The autopilot's system id is accepted (PX4 instance N sends from N+1; any id
unless one is given). A step is never re-sent (the autopilot would see one timestamp twice; TCP loses
nothing). If the autopilot disconnects, the lockstep wait bound engages the failsafe (motors off, stepping
at wall pace at zero throttle), which is also how a reconnecting autopilot boots again.
"""

from __future__ import annotations

import math
import time
from typing import TextIO

from bridge.link import UdpLink
from bridge.signing import Signing
from bridge.stream_link import TcpLink
from bridge.vehicle import EXCHANGE_STEP
from sitl.hil import HIL_COMPONENT_ID, SYSTEM_ID
from sitl.server import MAX_LAG_S, MAX_WAIT_S, ZERO, SitlOptions, SitlServer

AUTOPILOT_KINDS = ("tcp", "udpout")  # --hil kinds that serve an autopilot


def serves_autopilot(options: SitlOptions) -> bool:
    """True if the --hil address is one of PX4's simulator transports (tcp: or udpout:)."""
    return options.hil.kind in AUTOPILOT_KINDS


class AutopilotSitlServer(SitlServer):
    """A SitlServer whose HIL peer is an autopilot on PX4's simulator transport (TCP or send-first UDP)."""

    NEVER_REPEAT_SENSORS = True  # PX4 fails a magnetometer or barometer whose readings repeat exactly

    def __init__(self, options: SitlOptions, autopilot_sysid: int | None = None, max_rtf: float = 0.0,
                 out: TextIO | None = None):
        self.autopilot_sysid = autopilot_sysid
        self.step_wall = EXCHANGE_STEP / max_rtf if max_rtf > 0 else 0.0  # wall s per lockstep step, at least
        self._pace_next = 0.0
        super().__init__(options, out)

    def _open_link(self, signing: Signing | None) -> TcpLink | UdpLink:
        """TCP: listen for the autopilot; udpout: send to it from an ephemeral port."""
        o = self.options
        accept = None if self.autopilot_sysid is None else [self.autopilot_sysid]
        tlog = str(o.log) if o.log else None
        if o.hil.kind == "tcp":
            return TcpLink(o.hil, SYSTEM_ID, HIL_COMPONENT_ID, signing, tlog, accept, on_change=self._on_link)
        return UdpLink(remote=o.hil, system_id=SYSTEM_ID, component_id=HIL_COMPONENT_ID, signing=signing,
                       tlog=tlog, accept_system_ids=accept)

    def _listening_line(self) -> str:
        o = self.options
        if o.hil.kind == "tcp":
            where = f"listening for the autopilot on tcp:{self.link.local.host}:{self.link.local.port}"
        else:
            where = f"sending to the autopilot at udp:{o.hil.host}:{o.hil.port}"
        who = "any system id" if self.autopilot_sysid is None else f"system id {self.autopilot_sysid}"
        return (
            f"quadsr sitl: {where} (PX4 simulator protocol, {o.mode}"
            + (f" at most {EXCHANGE_STEP / self.step_wall:g}x real time" if self.step_wall else "")
            + f", {who}); vehicle {o.vehicle.name}"
            + (f"; logging to {o.log}" if o.log else "")
        )

    def _on_link(self, text: str) -> None:
        t = self.quad.time_usec * 1e-6
        if text.startswith("connected"):
            self._say(f"quadsr sitl: autopilot {text} at t={t:.3f}s")
        elif text.startswith("refused"):
            self._say(f"quadsr sitl: {text} at t={t:.3f}s (the autopilot stays connected)")
        else:
            self._say(f"quadsr sitl: autopilot {text} at t={t:.3f}s; motors off until it is back")
            self.held = ZERO

    def _send_step(self) -> None:
        # Never the same time_usec twice: PX4's IMU checks trip on a repeated stamp (TCP loses nothing).
        if self.quad.time_usec == self.last_sent_usec:
            return
        if self.step_wall and self.phase == "stepping":  # lockstep, but no faster than max_rtf x real time
            now = time.monotonic()
            if now < self._pace_next:
                time.sleep(self._pace_next - now)
            self._pace_next = max(self._pace_next + self.step_wall, now - MAX_LAG_S)
        super()._send_step()

    def _autopilot_there(self) -> bool:
        return self.link.connected if isinstance(self.link, TcpLink) else True

    def _serve_connect(self) -> None:
        """Waiting (TCP: no connection yet); then free steps at zero throttle, paced to the wall clock, until
        the autopilot's first HIL_ACTUATOR_CONTROLS."""
        link = self.link
        monotonic = time.monotonic
        next_step = math.inf
        while not self._stop and self.phase in ("waiting", "starting"):
            now = monotonic()
            if now >= self._next_status:
                self._status(now)
            if self.phase == "waiting":
                if self._autopilot_there():
                    self.phase = "starting"
                    next_step = now
                else:
                    link.recv_split(min(MAX_WAIT_S, max(0.0, self._next_status - now)))
                    continue
            if not self._autopilot_there():  # gone while starting: wait for it again, time kept
                self.phase = "waiting"
                continue
            if now >= next_step:
                self._advance(ZERO)
                next_step += EXCHANGE_STEP
                if now - next_step > MAX_LAG_S:
                    next_step = now + EXCHANGE_STEP
                continue
            wait = min(next_step - now, MAX_WAIT_S)
            frames = link.recv_split(wait)
            if not frames:
                continue
            _, reply = self._read(frames, accept_from=0)
            if reply is not None:
                self.companion = link.peer
                self._say(f"quadsr sitl: first actuator command from the autopilot at "
                          f"t={self.quad.time_usec * 1e-6:.3f}s: lockstep")
                self._start_stepping(reply)
