"""The built-in hover check: start the SITL, take off to a hover altitude over MAVLink, and check the hold."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

from bridge.lockstep import LockstepClient
from bridge.tlog import TlogWriter
from bridge.vehicle import VehicleConfig, load_vehicle
from quadsr.sitl_process import SitlProcess


@dataclass(frozen=True)
class HoverResult:
    """What the hover check measured: altitude error [m], tilt [rad], speed [m/s], steps and wall rate."""

    target_altitude: float
    final_altitude: float
    altitude_error_rms: float
    max_tilt: float
    final_speed: float
    steps: int
    steps_per_second: float

    @property
    def passed(self) -> bool:
        """True when the hold was within 2 cm, level within 0.01 rad, and still within 2 cm/s."""
        return self.altitude_error_rms < 0.02 and self.max_tilt < 0.01 and self.final_speed < 0.02


def _altitude_command(vehicle: VehicleConfig, z_ref: float, z: float, vz: float) -> float:
    """Equal rotor speed [rad/s] from an altitude PD loop (NED: z up is negative), level vehicle."""
    acc_cmd = 16.0 * (z_ref - z) + 8.0 * (0.0 - vz)          # m/s^2, NED; poles at -4 rad/s (critical)
    thrust = vehicle.mass * (vehicle.gravity - acc_cmd)       # N, along -Z body
    thrust = min(max(thrust, 0.0), 4 * vehicle.thrust_coefficient * vehicle.motor_curve.max_speed**2)
    return math.sqrt(thrust / (4 * vehicle.thrust_coefficient))


def fly_hover(hil: str, vehicle: VehicleConfig, altitude: float = 2.0, duration: float = 10.0,
              tlog: Path | None = None) -> HoverResult:
    """Fly a take-off to `altitude` [m] and hold it for `duration` [s] against a SITL at `hil`."""
    writer = TlogWriter(tlog) if tlog else None
    curve = vehicle.motor_curve
    steps = int(round(duration / 0.004))
    ramp = 1.5                                   # s: climb to the hover altitude
    hold_from = ramp + 2.0                       # s: the hold is judged from here on
    errors: list[float] = []
    max_tilt = 0.0
    with LockstepClient(hil=hil, tlog=writer) as client:
        obs = client.connect(timeout=10.0)
        start = time.perf_counter()
        for _ in range(steps):
            xi = obs.truth.xi
            t = obs.t
            z_ref = -altitude * min(1.0, t / ramp)
            w = _altitude_command(vehicle, z_ref, xi[2], xi[5])
            obs = client.step([curve.throttle_for_speed(w)] * 4)
            if obs.t >= hold_from:
                errors.append(obs.truth.xi[2] + altitude)
                max_tilt = max(max_tilt, abs(obs.truth.xi[6]), abs(obs.truth.xi[7]))
        wall = time.perf_counter() - start
    if writer:
        writer.close()
    xi = obs.truth.xi
    return HoverResult(
        target_altitude=altitude,
        final_altitude=-xi[2],
        altitude_error_rms=math.sqrt(sum(e * e for e in errors) / len(errors)),
        max_tilt=max_tilt,
        final_speed=math.sqrt(xi[3] ** 2 + xi[4] ** 2 + xi[5] ** 2),
        steps=steps,
        steps_per_second=steps / wall,
    )


def run_hover_check(out: Path | None, vehicle_name: str, altitude: float, duration: float) -> HoverResult:
    """Start a SITL child on free ports, fly the hover check against it, stop it; return the result."""
    vehicle = load_vehicle(vehicle_name)
    if out:
        out.mkdir(parents=True, exist_ok=True)
    log = out / "sitl.log" if out else None
    with SitlProcess(["--vehicle", str(vehicle.source_path)], log_path=log) as sitl:
        return fly_hover(sitl.hil, vehicle, altitude, duration, tlog=out / "hover.tlog" if out else None)
