"""ArduCopter parameters matched to a quadsr vehicle, so that ArduPilot's mixer and hover learning fit it.

ArduPilot's motor output for a thrust demand t in [0, 1] is a = spin_min + (spin_max - spin_min) x, where x
solves t = (1 - expo) x + expo x^2 (MOT_THST_EXPO), a being the fraction of the PWM range. quadsr's motors
give thrust 4 Ct w^2 with w = Cr a + wb (rad/s). MOT_THST_EXPO is the least-squares fit of that quadratic to
the vehicle's thrust over x in [0, 1], normalised by the thrust at spin_max; MOT_THST_HOVER is the thrust
demand of hover on the same scale; MOT_SPIN_ARM and MOT_SPIN_MIN sit just above the throttle at which the
rotors start to turn (-wb/Cr).
"""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np

from bridge.errors import UserError
from bridge.vehicle import VehicleConfig

SPIN_MAX = 0.95  # ArduPilot's default MOT_SPIN_MAX
SPIN_ARM_MARGIN = 0.02  # MOT_SPIN_ARM above the throttle where the rotors start (fraction of PWM range)
SPIN_MIN_MARGIN = 0.05  # MOT_SPIN_MIN above it
HOVER_RANGE = (0.125, 0.6875)  # MOT_THST_HOVER's allowed range in ArduCopter
BATTERY_VOLTAGE = 16.8  # V, a full 4S pack (quadsr has no battery model: compensation is switched off)
LOG_BITMASK_DEFAULT = 176126  # ArduCopter's default LOG_BITMASK
ATTITUDE_FAST = 1 << 0  # ANG (attitude) and RATE (rates, the mixer's inputs) at the loop rate, not 10 Hz
IMU_FAST = 1 << 18  # IMU (gyro, specific force) at the loop rate, not 25 Hz
LOG_BITMASK = LOG_BITMASK_DEFAULT | ATTITUDE_FAST | IMU_FAST


def thrust_expo_fit(vehicle: VehicleConfig, spin_min: float, spin_max: float) -> tuple[float, float]:
    """(MOT_THST_EXPO, RMS error of the fit as a fraction of the thrust at spin_max) for the motor curve."""
    curve = vehicle.motor_curve
    x = np.linspace(0.0, 1.0, 201)
    a = spin_min + (spin_max - spin_min) * x
    w = np.clip(curve.curve_slope * a + curve.curve_offset, 0.0, curve.max_speed)
    t = (w / w[-1]) ** 2
    basis = x * x - x
    expo = float(np.clip(np.dot(t - x, basis) / np.dot(basis, basis), -1.0, 1.0))
    rms = float(np.sqrt(np.mean(((1.0 - expo) * x + expo * x * x - t) ** 2)))
    return expo, rms


def ardupilot_parameters(vehicle: VehicleConfig) -> tuple[dict[str, float], list[str]]:
    """(ArduCopter parameters by name, notes on how they were derived) for a quadsr Quad-X vehicle."""
    curve = vehicle.motor_curve
    start = min(max(-curve.curve_offset / curve.curve_slope, 0.0), 1.0)  # throttle where w leaves 0
    spin_arm = round(start + SPIN_ARM_MARGIN, 3)
    spin_min = round(start + SPIN_MIN_MARGIN, 3)
    if spin_min >= SPIN_MAX - 0.1:
        raise UserError(f"vehicle {vehicle.name}: its rotors start turning only at throttle {start:.3f}, too "
                        "close to full throttle for ArduPilot's MOT_SPIN_MIN < MOT_SPIN_MAX",
                        hint="check motor.curve_slope and motor.curve_offset (w = Cr*throttle + wb, rad/s)")
    expo, rms = thrust_expo_fit(vehicle, spin_min, SPIN_MAX)
    w_top = curve.speed_for_throttle(SPIN_MAX)
    hover = (vehicle.hover_speed / w_top) ** 2  # thrust demand of hover, on ArduPilot's linearised scale
    notes = [
        f"MOT_THST_EXPO {expo:.3f} fits thrust ~ (Cr*a + wb)^2 over a in [{spin_min:g}, {SPIN_MAX:g}] "
        f"with an RMS error of {100 * rms:.2f}% of the thrust at MOT_SPIN_MAX",
        f"MOT_THST_HOVER {hover:.4f}: hover at {vehicle.hover_speed:.1f} rad/s of {w_top:.1f} rad/s at "
        f"MOT_SPIN_MAX",
        f"rotors start at throttle {start:.3f} (-wb/Cr); MOT_SPIN_ARM {spin_arm:g}, "
        f"MOT_SPIN_MIN {spin_min:g}",
    ]
    notes.append(
        f"LOG_BITMASK {LOG_BITMASK}: ArduCopter's default {LOG_BITMASK_DEFAULT} plus ATTITUDE_FAST (ANG and "
        "RATE at the loop rate: attitude, body rates and the mixer's inputs, from which quadsr identify "
        "rebuilds the motor outputs at the loop rate, as ArduCopter logs RCOU only at 10 Hz) and IMU_FAST "
        "(IMU at the loop rate, for --targets sensors); INS_LOG_BAT_* stay off (bursts of raw IMU for FFT, "
        "not rows)"
    )
    if not HOVER_RANGE[0] <= hover <= HOVER_RANGE[1]:
        clipped = min(max(hover, HOVER_RANGE[0]), HOVER_RANGE[1])
        notes.append(f"hover demand {hover:.4f} is outside ArduCopter's range {HOVER_RANGE}: written as "
                     f"{clipped:g} (hover learning will move it)")
        hover = clipped
    params = {
        "FRAME_CLASS": 1,  # quad
        "FRAME_TYPE": 1,  # X: motors 1 front-right CCW, 2 rear-left CCW, 3 front-left CW, 4 rear-right CW
        "MOT_PWM_TYPE": 0,  # normal PWM
        "MOT_PWM_MIN": round(vehicle.motor.pwm_min),
        "MOT_PWM_MAX": round(vehicle.motor.pwm_max),
        "MOT_SPIN_ARM": spin_arm,
        "MOT_SPIN_MIN": spin_min,
        "MOT_SPIN_MAX": SPIN_MAX,
        "MOT_THST_EXPO": round(expo, 4),
        "MOT_THST_HOVER": round(hover, 4),
        "MOT_HOVER_LEARN": 2,  # learn and save
        "MOT_BAT_VOLT_MAX": 0,  # no voltage compensation: quadsr's motors do not sag
        "MOT_BAT_VOLT_MIN": 0,
        "BATT_MONITOR": 4,  # analog voltage and current (ArduPilot's simulated battery)
        "BATT_CAPACITY": 5000,  # mAh
        "SIM_BATT_VOLTAGE": BATTERY_VOLTAGE,
        "LOG_BITMASK": LOG_BITMASK,  # what identification needs at the loop rate (see the notes)
    }
    return params, notes


def write_parm(vehicle: VehicleConfig, path: Path) -> list[str]:
    """Write the vehicle's ArduCopter parameters as a .parm file (NAME VALUE lines); return the notes."""
    params, notes = ardupilot_parameters(vehicle)
    source = vehicle.source_path or vehicle.name
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    lines = [f"# ArduCopter parameters for quadsr vehicle {vehicle.name} ({source}), written {stamp}",
             *(f"# {n}" for n in notes)]
    lines += [f"{name} {value:g}" if isinstance(value, float) else f"{name} {value}"
              for name, value in params.items()]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + "\n")
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror}", hint="give a writable file path") from None
    return notes
