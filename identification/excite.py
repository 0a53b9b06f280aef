"""The identification client's flight loop: connect to a running SITL as the companion, fly a profile in
lockstep, log every frame to a .tlog, and summarise the flight.

Motor commands are rotor speeds (rad/s) from the profile's generator, sent as throttles through the vehicle's
motor curve; the rotor speeds used for fitting later are the true ones the SITL reports in the log.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bridge.errors import UserError
from bridge.lockstep import LockstepClient
from bridge.tlog import TlogWriter
from bridge.vehicle import load_vehicle
from identification.excitation import ClosedLoopExcitation, load_profile, make_generator

STEP_S = 0.004
ALTITUDE_START_HINT = (
    "start the SITL at altitude with no ground, e.g.: quadsr sitl --ground none --initial-position 0,0,-200 "
    "--sensors ideal"
)


@dataclass
class FlightSummary:
    """What a flight did: steps, simulated and wall time, the final state and the extremes it reached."""

    profile: str
    out: Path
    steps: int = 0
    sim_time: float = 0.0  # s
    wall_time: float = 0.0  # s
    final_xi: np.ndarray = field(default_factory=lambda: np.full(12, np.nan))
    min_altitude: float = math.inf  # m above the start point
    max_altitude: float = -math.inf
    max_tilt_deg: float = 0.0
    max_rate: float = 0.0  # rad/s, largest |body rate|
    max_horizontal: float = 0.0  # m from the start point
    excitation_scale_min: float | None = None  # closed-loop: smallest excitation scale (0 = fully backed off)
    frames: int = 0
    status_texts: list[str] = field(default_factory=list)
    speaker: str = "SITL"  # who said the status texts
    unit: str = "steps"  # what a step is (setpoints, through an autopilot)

    def lines(self) -> list[str]:
        """The summary as printable lines."""
        x = self.final_xi
        rate = self.steps / self.wall_time if self.wall_time > 0 else float("nan")
        out = [
            f"profile {self.profile}: {self.steps} {self.unit}, {self.sim_time:.3f} s simulated in "
            f"{self.wall_time:.2f} s "
            f"wall ({rate:.0f} {self.unit}/s)",
            f"final state: position NED [{x[0]:.2f}, {x[1]:.2f}, {x[2]:.2f}] m, "
            f"velocity [{x[3]:.2f}, {x[4]:.2f}, "
            f"{x[5]:.2f}] m/s, roll/pitch/yaw [{math.degrees(x[6]):.1f}, {math.degrees(x[7]):.1f}, "
            f"{math.degrees(x[8]):.1f}] deg, rates [{x[9]:.2f}, {x[10]:.2f}, {x[11]:.2f}] rad/s",
            f"altitude above start {self.min_altitude:.2f}..{self.max_altitude:.2f} m, "
            f"farthest {self.max_horizontal:.2f} m "
            f"horizontally, max tilt {self.max_tilt_deg:.1f} deg, max body rate {self.max_rate:.1f} rad/s",
        ]
        if self.excitation_scale_min is not None:
            out.append(f"excitation backed off to {self.excitation_scale_min:.2f} of full at the most")
        out.append(f"telemetry log: {self.out} ({self.frames} frames)")
        out.extend(f"{self.speaker} said: {s}" for s in self.status_texts)
        return out


def fly(
    profile: str,
    out: str | Path,
    hil: str = "udp:127.0.0.1:4560",
    duration: float | None = None,
    seed: int = 0,
    vehicle: str = "fang-chen-buaa",
    signing_key: str | None = None,
    step_timeout: float = 1.0,
    connect_timeout: float = 10.0,
    progress: bool = True,
) -> FlightSummary:
    """Fly one excitation profile against the SITL at `hil`, logging to `out` (.tlog); returns the summary."""
    prof = load_profile(profile)
    veh = load_vehicle(vehicle)
    curve = veh.motor_curve
    dur = prof.duration if duration is None else float(duration)
    if not (math.isfinite(dur) and dur > 0):
        raise UserError(f"--duration must be a positive number of seconds, got {duration}")
    if prof.kind == "closed-loop" and dur <= prof.excitation_start:
        raise UserError(
            f"--duration {dur:g} s leaves no excitation: profile {prof.name} climbs and settles for "
            f"{prof.excitation_start:g} s first",
            hint=f"give more than {prof.excitation_start:g} s",
        )
    out = Path(out)
    if out.is_dir():
        raise UserError(f"--out {out} is a directory", hint="give a file name such as train.tlog")
    n_steps = int(round(dur / STEP_S))
    summary = FlightSummary(prof.name, out)
    writer = TlogWriter(out)
    client = None
    try:
        client = LockstepClient(hil=hil, signing=signing_key, tlog=writer, timeout=step_timeout)
        obs = client.connect(timeout=connect_timeout)
        if obs.truth is None or not np.isfinite(obs.truth.position).all():
            raise UserError(
                f"the SITL at {hil} sends no true state (HIL_STATE_QUATERNION/LOCAL_POSITION_NED)",
                hint="is it a quadsr SITL?",
            )
        xi0 = obs.truth.xi
        _check_start(prof.start, xi0, hil)
        gen = make_generator(prof, veh, seed, dur, xi0)
        origin_z = xi0[2]
        t0 = obs.t
        xi = xi0
        bar = _progress(n_steps, prof.name, progress)
        wall0 = time.perf_counter()
        try:
            for _ in range(n_steps):
                speeds = gen.command(obs.t - t0, xi)
                obs = client.step([curve.throttle_for_speed(float(w)) for w in speeds])
                if obs.truth is not None and np.isfinite(obs.truth.position).all():
                    xi = obs.truth.xi
                account(summary, xi, origin_z, xi0)
                summary.steps += 1
                if bar is not None:
                    bar.update(1)
        finally:
            summary.wall_time = time.perf_counter() - wall0
            if bar is not None:
                bar.close()
            summary.sim_time = obs.t - t0
            summary.final_xi = np.asarray(xi, dtype=float)
            summary.frames = writer.frames
            summary.status_texts = list(client.status_texts)
            if isinstance(gen, ClosedLoopExcitation):
                summary.excitation_scale_min = gen.min_scale
    except BaseException:
        if client is not None:
            client.close()
        writer.close()
        if summary.steps == 0:
            out.unlink(missing_ok=True)  # nothing was flown: leave no misleading log behind
        raise
    client.close()
    writer.close()
    return summary


def _check_start(start: str, xi0: np.ndarray, hil: str) -> None:
    z = float(xi0[2])
    if start == "altitude" and z >= -1.0:
        raise UserError(
            f"the vehicle at {hil} is not in the air above the ground (z = {z:.2f} m NED, needs z < -1): "
            f"this profile flies open loop from altitude and would crash",
            hint=ALTITUDE_START_HINT,
        )
    speed = float(np.linalg.norm(xi0[3:6]))
    if start == "ground" and (abs(z) > 1.0 or speed > 0.5):
        raise UserError(
            f"the vehicle at {hil} is not resting on the ground (z = {z:.2f} m NED, speed {speed:.1f} m/s): "
            f"the closed-loop profile takes off from the ground and keeps to a box above its start point",
            hint="start the SITL with its default ground plane: quadsr sitl",
        )


def account(s: FlightSummary, xi: np.ndarray, origin_z: float, xi0: np.ndarray) -> None:
    """Add the state xi (12: NED m, m/s, ZYX rad, FRD rad/s) to the summary's extremes."""
    alt = origin_z - float(xi[2])
    s.min_altitude = min(s.min_altitude, alt)
    s.max_altitude = max(s.max_altitude, alt)
    c = math.cos(xi[6]) * math.cos(xi[7])
    s.max_tilt_deg = max(s.max_tilt_deg, math.degrees(math.acos(max(-1.0, min(1.0, c)))))
    s.max_rate = max(s.max_rate, abs(xi[9]), abs(xi[10]), abs(xi[11]))
    s.max_horizontal = max(s.max_horizontal, math.hypot(xi[0] - xi0[0], xi[1] - xi0[1]))


def _progress(total: int, name: str, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(
        total=total, desc=f"excite {name}", unit="step", file=sys.stderr, mininterval=0.5, dynamic_ncols=True
    )
