"""An excitation flight through PX4 OFFBOARD (`quadsr excite --autopilot`): body-rate and thrust setpoints.

The closed-loop profile's reference (take-off, climb, settle, a slow Lissajous path with a turning heading;
with a `schedule`, its hover heights and yaw rates), its signal (PRBS or chirp; a rotor-speed `collective`
is not used here: thrust_amplitude is the collective channel) and its fading near the box and tilt limits,
flown as a real vehicle's companion
would: the hover stabiliser's outer loops on PX4's estimate (LOCAL_POSITION_NED, ATTITUDE_QUATERNION at
rate_hz of PX4's clock) give body rates FRD (rad/s) and the collective thrust (N); the excitation is added to
the rates and the thrust; SET_ATTITUDE_TARGET carries them (thrust normalised through PX4's thrust model
fitted to the vehicle's motor curve, bridge.px4_thrust), one per attitude message. Start-up and the watch
on PX4 are bridge.offboard_flight's, as for `quadsr fly --autopilot`. At the end PX4 holds (AUTO.LOITER).

Logs: the offboard link as this process saw it (`out`, a .tlog); PX4 writes its ULog and `quadsr px4` the
SITL's truth .tlog (WORK/rootfs/log, WORK/truth.tlog): `quadsr identify` reads each.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bridge.errors import UserError
from bridge.offboard import PX4, OffboardLink
from bridge.offboard_flight import OffboardWatch, start_px4_offboard
from bridge.px4_thrust import fit_thrust_model, normalised_thrust
from bridge.rotations import euler_from_quaternion
from bridge.tlog import TlogWriter
from bridge.vehicle import load_vehicle
from identification.excitation import ClosedLoopExcitation, ClosedLoopProfile, load_profile
from identification.excite import FlightSummary, account


@dataclass(frozen=True)
class OffboardExcitationSettings:
    """How to reach PX4 and pace the setpoints: rates in Hz of PX4's clock, timeouts in wall s."""

    autopilot: str  # udp:HOST:PORT of PX4's offboard link (instance N: udp:127.0.0.1:14580+N)
    rate_hz: float = 100.0  # ATTITUDE_QUATERNION / LOCAL_POSITION_NED requested; one setpoint per attitude
    prestream_s: float = 1.0  # s of PX4's clock
    link_timeout: float = 2.0
    connect_timeout: float = 30.0


@dataclass
class OffboardFlight:
    """The summary of an excitation flight through PX4, and why it ended early ('' if it did not)."""

    summary: FlightSummary
    message: str = ""
    link_lost: bool = False
    window: tuple[float, float] | None = None  # the excitation, s of PX4's clock (its ULog's time)

    def lines(self) -> list[str]:
        """The summary, and where the excitation lies in PX4's ULog and quadsr's truth .tlog."""
        out = self.summary.lines()
        if self.window is not None:
            a, b = self.window
            out.append(f"excitation from {a:.2f} to {b:.2f} s of PX4's clock (the ULog's and the truth "
                       f".tlog's time): quadsr identify LOG --window {a:.2f}:{b:.2f}")
        return out


def fly_offboard(profile: str, out: str | Path, settings: OffboardExcitationSettings,
                 duration: float | None = None, seed: int = 0,
                 vehicle: str = "fang-chen-buaa") -> OffboardFlight:
    """Fly a closed-loop profile through PX4 OFFBOARD for `duration` s of PX4's clock, logging the offboard
    link to `out` (.tlog); the summary (state NED m, rad) and why it ended early, if it did."""
    prof = load_profile(profile)
    if not isinstance(prof, ClosedLoopProfile):
        raise UserError(f"profile {prof.name} ({prof.kind}) flies open loop on motor speeds: through an "
                        f"autopilot only a closed-loop profile can be flown",
                        hint="use --profile px4-offboard (or closed-loop, or your closed-loop file)")
    veh = load_vehicle(vehicle)
    dur = prof.duration if duration is None else float(duration)
    if not (math.isfinite(dur) and dur > prof.excitation_start):
        raise UserError(f"--duration {duration} s leaves no excitation: profile {prof.name} climbs and "
                        f"settles for {prof.excitation_start:g} s first",
                        hint=f"give more than {prof.excitation_start:g} s")
    out = Path(out)
    if out.is_dir():
        raise UserError(f"--out {out} is a directory", hint="give a file name such as px4-excite.tlog")
    factor = fit_thrust_model(veh)[0]
    summary = FlightSummary(prof.name, out, speaker="PX4", unit="setpoints")
    tlog = TlogWriter(out)
    link = OffboardLink(settings.autopilot, PX4, tlog)
    flight = OffboardFlight(summary)
    wall0 = time.perf_counter()
    try:
        flight.message = start_px4_offboard(link, settings.autopilot, settings.rate_hz, settings.prestream_s,
                                            settings.connect_timeout, settings.link_timeout)
        if not flight.message:
            try:
                _excite(link, prof, veh, factor, seed, dur, settings, flight)
            finally:  # also on Ctrl-C: PX4 holds where the flight ended, no offboard-loss failsafe
                link.set_mode(PX4.hold)
    finally:
        summary.wall_time = time.perf_counter() - wall0
        summary.frames = tlog.frames
        summary.status_texts = list(dict.fromkeys(link.state.status_texts))
        link.close()
        tlog.close()
    return flight


def _excite(link: OffboardLink, prof: ClosedLoopProfile, veh, factor: float, seed: int, duration: float,
            settings: OffboardExcitationSettings, flight: OffboardFlight) -> None:
    """The flight: one rate-and-thrust setpoint per new attitude message, for duration s of PX4's clock."""
    st = link.state
    summary = flight.summary
    xi0 = _estimate(link)
    gen = ClosedLoopExcitation(prof, veh, seed, duration, xi0)
    t0_ms = last_ms = st.attitude_ms
    watch = OffboardWatch(link, settings.autopilot, settings.link_timeout)
    xi = xi0
    try:
        while True:
            why = watch.poll(0.05) or watch.stalled(last_ms)
            if why:
                flight.message, flight.link_lost = why, why.startswith("link lost")
                return
            if st.attitude_ms == last_ms:
                continue
            last_ms = st.attitude_ms
            t = (last_ms - t0_ms) * 1e-3
            if t >= duration:
                return
            xi = _estimate(link)
            rates, thrust = gen.rates_and_thrust(t, xi)
            link.rates_target(rates, normalised_thrust(veh, factor, thrust / veh.thrust_coefficient))
            account(summary, xi, float(xi0[2]), xi0)
            summary.steps += 1
            summary.sim_time = t
            if t >= prof.excitation_start:
                start = flight.window[0] if flight.window else last_ms * 1e-3
                flight.window = (start, last_ms * 1e-3)
    finally:
        summary.final_xi = np.asarray(xi, dtype=float)
        summary.excitation_scale_min = gen.min_scale


def _estimate(link: OffboardLink) -> np.ndarray:
    """PX4's estimate as the 12-state xi (NED m, m/s, ZYX rad, FRD rad/s)."""
    st = link.state
    phi, theta, psi = (float(a) for a in euler_from_quaternion(st.quaternion))
    return np.array([*st.position, *st.velocity, phi, theta, psi, *st.rates], dtype=float)
