"""The companion's side of the HIL lockstep protocol: `step(throttles) -> Observation`.

The client sits in the autopilot's seat (sysid 1, compid 1): it connects by sending HEARTBEAT to the SITL's
HIL address until the first step arrives, then answers each step's HIL_SENSOR with HIL_ACTUATOR_CONTROLS
stamped with that step's time_usec, and waits for the next step.
"""

from __future__ import annotations

import select
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from bridge.framing import Framer, kind
from bridge.link import LOCKSTEP_SPIN_S, Endpoint, UdpLink, parse_endpoint
from bridge.messages import (
    ARMED_MODE,
    LOCKSTEP_FLAG,
    HilActuatorControls,
    Observation,
    ObservationAssembler,
    encode_heartbeat,
    sanitize_throttles,
)
from bridge.signing import Signing
from bridge.stats import LinkStats
from bridge.tlog import TlogWriter

HEARTBEAT_PERIOD_S = 0.1  # while connecting
STEP_USEC = 4000
# The SITL re-sends an unanswered step every 0.1 s wall. A copy of our current step arriving at least this
# long after our reply went out means the reply was lost: send it again. (A copy arriving sooner was queued
# while we computed the reply, before the SITL could have seen it.)
RESEND_GUARD_S = 0.05
_UNUSED_CONTROLS = (0.0,) * 12  # HIL_ACTUATOR_CONTROLS controls[4..15]


class LinkLost(UserError):
    """Nothing (or no new step) arrived from the SITL within the timeout."""


def _as_signing(signing: Signing | str | Path | bytes | None) -> Signing | None:
    if signing is None or isinstance(signing, Signing):
        return signing
    if isinstance(signing, (bytes, bytearray)):
        return Signing(bytes(signing))
    return Signing.from_file(signing)


class LockstepClient:
    """Steps the SITL in lockstep over its HIL link; one Observation per 4 ms step."""

    def __init__(
        self,
        hil: str | Endpoint = "udp:127.0.0.1:4560",
        signing: Signing | str | Path | bytes | None = None,
        tlog: TlogWriter | str | Path | None = None,
        timeout: float = 1.0,
        system_id: int = 1,
        component_id: int = 1,
        spin: float = LOCKSTEP_SPIN_S,
    ):
        self.endpoint = hil if isinstance(hil, Endpoint) else parse_endpoint(hil)
        if not timeout > 0:
            raise UserError(f"lockstep timeout must be > 0 s (got {timeout})")
        self.timeout = float(timeout)
        if not 0.0 <= spin <= 1.0:
            raise UserError(f"lockstep spin must be 0..1 s (got {spin})")
        self.link = UdpLink(
            local=None,
            remote=self.endpoint,
            system_id=system_id,
            component_id=component_id,
            signing=_as_signing(signing),
            tlog=str(tlog) if isinstance(tlog, Path) else tlog,
        )
        self.link.spin_s = float(spin)  # s wall: poll for the next step this long before sleeping for it
        self.assembler = ObservationAssembler()
        # HIL_ACTUATOR_CONTROLS packed straight from floats (wire order: time_usec, flags, controls[16], mode)
        self._framer = Framer(system_id, component_id, self.link, self.link.signing)
        self._command_kind = kind(HilActuatorControls)
        # poll(0) tells whether more is queued for a third of the cost of a recvfrom that finds nothing
        self._queued = select.poll()
        self._queued.register(self.link.fileno(), select.POLLIN)
        self.observation: Observation | None = None
        self.steps = 0
        self.resends = 0  # commands sent again because the SITL re-sent the step they answer
        self._command: tuple[int, bytes] | None = None  # (time_usec answered, HIL_ACTUATOR_CONTROLS payload)
        self._repeated = False  # the last frames read held a copy of the current step
        self.status_texts: list[str] = []  # STATUSTEXTs from the SITL (failsafe reasons), in order

    @property
    def stats(self) -> LinkStats:
        """The HIL link's counters."""
        return self.link.stats

    def connect(self, timeout: float = 10.0) -> Observation:
        """Send HEARTBEAT every 0.1 s until the SITL's first step arrives; return it (normally time 0)."""
        deadline = time.monotonic() + timeout
        heartbeat = encode_heartbeat()
        next_beat = 0.0
        while True:
            now = time.monotonic()
            if now >= deadline:
                raise LinkLost(
                    f"no SITL answered at {self.endpoint} within {timeout:g} s",
                    hint="start it with `quadsr sitl` and check that --hil and --signing-key match",
                )
            if now >= next_beat:
                self.link.send([heartbeat])
                next_beat = now + HEARTBEAT_PERIOD_S
            obs = self._latest(self.link.recv_split(min(next_beat, deadline) - now))
            if obs is not None:
                self.observation = obs
                return obs

    def step(self, throttles: Sequence[float]) -> Observation:
        """Send throttles (4, in [0,1]; NaN -> 0, clipped) for the current step; return the next step."""
        current = self.observation
        if current is None:
            raise RuntimeError("LockstepClient.step() before connect()")
        if len(throttles) != 4:
            raise ValueError(f"step() takes 4 motor throttles, got {len(throttles)}")
        clean = sanitize_throttles(throttles)[0]  # the SITL's rule: NaN/inf -> 0, clipped to [0, 1]
        msg_id, extra, pack = self._command_kind
        payload = pack(current.time_usec, LOCKSTEP_FLAG, *clean, *_UNUSED_CONTROLS, ARMED_MODE)
        self._command = (current.time_usec, payload)
        self.link.send_frames(self._framer.frames([(msg_id, extra, payload)]))
        obs = self.wait_observation(self.timeout)
        self.steps += 1
        return obs

    def step_speeds(self, speeds_rad_s: Sequence[float], motor_curve: Any) -> Observation:
        """step() with commanded rotor speeds (rad/s) turned into throttles by the vehicle's motor curve."""
        return self.step([float(motor_curve.throttle_for_speed(float(w))) for w in speeds_rad_s])

    def wait_observation(self, timeout: float | None = None) -> Observation:
        """Wait (up to timeout s, default the client's) for a step newer than the current one; return the
        newest one queued.

        Everything queued is read each time, so after a failsafe (the SITL stepping at wall-clock pace) the
        newest step is returned, not the backlog. When the SITL re-sends the current step (our reply was
        lost), the command that answered it is sent again.
        """
        timeout = self.timeout if timeout is None else timeout
        after = -1 if self.observation is None else self.observation.time_usec
        start = time.monotonic()
        deadline = start + timeout
        resend_after = start + RESEND_GUARD_S
        link = self.link
        remaining = timeout
        while True:
            frames = link.recv_split(remaining)
            if frames:
                if self._queued.poll(0):
                    frames += link.drain_split()
                obs = self._latest(frames, after)
                if obs is not None:
                    self.observation = obs
                    return obs
                if self._repeated and self._command is not None and self._command[0] == after:
                    now = time.monotonic()
                    if now >= resend_after:
                        msg_id, extra, _ = self._command_kind
                        link.send_frames(self._framer.frames([(msg_id, extra, self._command[1])]))
                        self.resends += 1
                        resend_after = now + RESEND_GUARD_S
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise LinkLost(
                    f"no step from the SITL at {self.endpoint} within {timeout:g} s "
                    f"(last step t = {max(after, 0) * 1e-6:.3f} s)",
                    hint="did the SITL stop, or go into failsafe? its status line says why",
                )

    def _latest(self, frames: list[tuple], after: int = -1) -> Observation | None:
        """The newest step in frames newer than `after` (or None); _repeated: `after` itself came again."""
        latest = None
        repeated = False
        for obs in self.assembler.feed_frames(frames):
            for m in obs.extras:
                if m.get_type() == "STATUSTEXT":
                    self.status_texts.append(m.text)
            if obs.time_usec > after:
                latest = obs
                after = obs.time_usec
            elif obs.time_usec == after:
                repeated = True
        self._repeated = repeated
        return latest

    def close(self) -> None:
        """Close the link; nothing more is sent (the SITL goes to failsafe after its wait bound)."""
        self.link.close()

    def __enter__(self) -> LockstepClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
