"""A PX4 airframe file for a quadsr vehicle, so that PX4's allocation, thrust model and hover estimate match
the simulated vehicle (`quadsr px4-airframe`, and the airframe `quadsr px4` adds to PX4's airframes).

What is matched (PX4 parameter: from the vehicle):
- CA_ROTORn_PX/PY/PZ (m, body FRD) and CA_ROTORn_KM (moment ratio Cm/Ct, + for a counter-clockwise rotor):
  from the vehicle's rotor set (VehicleConfig.rotor_set), positions from its centre of gravity (motor
  order 1..4 = PX4 outputs 1..4, PWM_MAIN_FUNCn 101..104).
- THR_MDL_FAC: PX4 models normalised thrust as (1-f) u + f u^2 of the output u in [0, 1]; the vehicle's
  thrust fraction is (w(u)/w_max)^2 with w = Cr u + wb clipped at 0. f is the least-squares fit over
  u in [0, 1], clipped to PX4's [0, 1].
- MPC_THR_HOVER: the normalised thrust at hover in PX4's model, (1-f) u_h + f u_h^2, u_h the hover throttle.
- Limits from the thrust-to-weight ratio TW = 4 Ct w_max^2 / (m g): MPC_TILTMAX_AIR (deg) at most 45 and at
  most 80% of acos(1/TW) (the tilt at which full thrust still holds altitude), MPC_ACC_UP_MAX (m/s^2) at most
  4 and at most half of g (TW - 1), MPC_ACC_HOR_MAX (m/s^2) at most 5 and at most half of g tan(tilt max),
  MPC_THR_MIN (normalised) where the rotors spin.
- SDLOG_PROFILE: PX4 SITL's logging set (default, estimator replay, vision: 131) plus system identification
  (bit 3): actuator_motors and vehicle_angular_velocity at the control rate, so that `quadsr identify` reads
  the motor commands of a PX4-flown flight at that rate rather than actuator_outputs' 10 Hz.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

from bridge.errors import UserError
from bridge.px4_thrust import fit_thrust_model, px4_thrust
from bridge.vehicle import VehicleConfig

AIRFRAME_ID = 10099  # SYS_AUTOSTART of quadsr's airframes (free in PX4's init.d-posix/airframes)
MIN_THRUST_TO_WEIGHT = 1.2  # below it PX4 cannot hold altitude with any margin
SDLOG_PROFILE = 131 | 8  # PX4 SITL's rcS default | SYSTEM_IDENTIFICATION


@dataclass(frozen=True)
class Px4Airframe:
    """The matched PX4 parameters of one vehicle (see the module docstring for each)."""

    vehicle: str
    params: dict[str, float | int]
    thrust_to_weight: float
    hover_throttle: float  # output u in [0, 1] at hover
    fit_rms: float  # RMS error of PX4's thrust model over u in [0, 1], in fractions of full thrust

    def model_name(self) -> str:
        """PX4_SIM_MODEL that selects this airframe (`none_quadsr_<vehicle>`)."""
        return "none_quadsr_" + re.sub(r"[^A-Za-z0-9]+", "_", self.vehicle).strip("_").lower()

    def file_name(self, airframe_id: int = AIRFRAME_ID) -> str:
        """Its file name in etc/init.d-posix/airframes (`<id>_none_quadsr_<vehicle>`)."""
        return f"{airframe_id}_{self.model_name()}"

    def text(self, source: str) -> str:
        """The airframe file (a PX4 init script), `source` naming where the vehicle came from."""
        lines = [
            "#!/bin/sh",
            "#",
            f"# @name quadsr {self.vehicle} (simulated by quadsr sitl)",
            "#",
            "# @type Quadrotor x",
            "#",
            f"# Written by quadsr px4-airframe from {source}.",
            f"# Thrust-to-weight {self.thrust_to_weight:.2f}, hover throttle {self.hover_throttle:.3f}.",
            f"# PX4's thrust model (THR_MDL_FAC {self.params['THR_MDL_FAC']:.3f}) is within "
            f"{self.fit_rms * 100:.2f}% RMS of full thrust.",
            "",
            ". ${R}etc/init.d/rc.mc_defaults",
            "",
        ]
        for name, value in self.params.items():
            text = str(value) if isinstance(value, int) else f"{value:.6g}"
            lines.append(f"param set-default {name} {text}")
        return "\n".join(lines) + "\n"


def airframe_for(vehicle: VehicleConfig) -> Px4Airframe:
    """The PX4 airframe parameters matched to a vehicle (UserError if PX4 could not fly it)."""
    curve = vehicle.motor_curve
    weight = vehicle.mass * vehicle.gravity
    tw = 4.0 * vehicle.thrust_coefficient * curve.max_speed**2 / weight
    where = f"vehicle {vehicle.name}" + (f" ({vehicle.source_path})" if vehicle.source_path else "")
    if tw < MIN_THRUST_TO_WEIGHT:
        raise UserError(
            f"{where}: thrust-to-weight {tw:.2f} is below {MIN_THRUST_TO_WEIGHT}: "
            "PX4 could not hold altitude",
            hint="raise thrust_coefficient or the motor curve's full-throttle speed, or lower the mass",
        )
    factor, rms = fit_thrust_model(vehicle)
    u_hover = curve.throttle_for_speed(vehicle.hover_speed)
    hover = px4_thrust(factor, u_hover)
    if not 0.1 <= hover <= 0.8:
        raise UserError(
            f"{where}: hover thrust {hover:.3f} (throttle {u_hover:.3f}) is outside PX4's MPC_THR_HOVER "
            "range [0.1, 0.8]",
            hint="match the motor curve to the vehicle's weight",
        )
    tilt_max = min(45.0, 0.8 * math.degrees(math.acos(1.0 / tw)))
    acc_up = min(4.0, 0.5 * vehicle.gravity * (tw - 1.0))
    acc_hor = min(5.0, 0.5 * vehicle.gravity * math.tan(math.radians(tilt_max)))
    spin_up = curve.throttle_for_speed(0.1 * curve.max_speed)  # rotors at 10% of full speed
    thr_min = min(max(0.05, px4_thrust(factor, spin_up)), 0.5 * hover)
    params: dict[str, float | int] = {"CA_AIRFRAME": 0, "CA_ROTOR_COUNT": 4}
    for i, (rotor, arm) in enumerate(zip(vehicle.rotor_set, vehicle.rotor_arms, strict=True)):
        params[f"CA_ROTOR{i}_PX"] = round(arm[0], 6)  # m, FRD, from the centre of gravity
        params[f"CA_ROTOR{i}_PY"] = round(arm[1], 6)
        params[f"CA_ROTOR{i}_PZ"] = round(arm[2], 6)
        spin = 1.0 if rotor.direction == "ccw" else -1.0  # PX4: KM > 0 for a counter-clockwise rotor
        params[f"CA_ROTOR{i}_KM"] = round(spin * rotor.moment_coefficient / rotor.thrust_coefficient, 6)
    for i in range(4):
        params[f"PWM_MAIN_FUNC{i + 1}"] = 101 + i
    params.update({
        "THR_MDL_FAC": round(factor, 4),
        "MPC_THR_HOVER": round(hover, 4),
        "MPC_THR_MIN": round(thr_min, 3),
        "MPC_THR_MAX": 1.0,
        "MPC_TILTMAX_AIR": round(tilt_max, 1),
        "MPC_ACC_UP_MAX": round(acc_up, 2),
        "MPC_ACC_HOR_MAX": round(acc_hor, 2),
        "SDLOG_PROFILE": SDLOG_PROFILE,
    })
    return Px4Airframe(vehicle.name, params, tw, u_hover, rms)
