"""PX4's thrust model beside a vehicle's motor curve: the one fit both the airframe and the companion use.

PX4 maps a normalised collective thrust t in [0, 1] to each output u in [0, 1] through
t = (1 - f) u + f u^2 (f = THR_MDL_FAC). A quadsr vehicle's rotor gives the thrust fraction (w(u) / w_max)^2,
w = Cr u + wb clipped at 0 (bridge.vehicle.MotorCurve).
"""

from __future__ import annotations

import math

from bridge.vehicle import VehicleConfig, px4_thrust  # noqa: F401  (px4_thrust is this module's model too)

FIT_POINTS = 201  # throttle samples of the fit


def thrust_fraction(vehicle: VehicleConfig, u: float) -> float:
    """The vehicle's steady rotor thrust at output u in [0, 1], as a fraction of full thrust."""
    curve = vehicle.motor_curve
    return (curve.speed_for_throttle(u) / curve.max_speed) ** 2


def fit_thrust_model(vehicle: VehicleConfig) -> tuple[float, float]:
    """(THR_MDL_FAC f in [0, 1], RMS error in fractions of full thrust), least squares over u in [0, 1]."""
    us = [i / (FIT_POINTS - 1) for i in range(FIT_POINTS)]
    num = den = 0.0
    for u in us:
        basis = u * u - u
        num += basis * (thrust_fraction(vehicle, u) - u)
        den += basis * basis
    factor = min(max(num / den, 0.0), 1.0)
    rms = math.sqrt(sum((px4_thrust(factor, u) - thrust_fraction(vehicle, u)) ** 2 for u in us) / len(us))
    return factor, rms


def normalised_thrust(vehicle: VehicleConfig, factor: float, f1: float) -> float:
    """PX4's normalised collective thrust in [0, 1] that makes each rotor spin at sqrt(f1 / 4) rad/s.

    f1 = w1^2 + w2^2 + w3^2 + w4^2 in (rad/s)^2 (the model's collective input); the output u PX4 must
    command is the vehicle's throttle for that speed, and t = (1-f) u + f u^2 is what makes PX4 command it.
    """
    speed = math.sqrt(max(f1, 0.0) / 4.0)
    return px4_thrust(factor, vehicle.motor_curve.throttle_for_speed(speed))
