"""Motors: throttle in [0, 1] -> commanded rotor speed (the vehicle's thrust model), then a first-order lag.

The thrust models (bridge.vehicle.MotorCurve): the paper's linear throttle-to-speed curve, PX4's THR_MDL_FAC
(thrust a mix of linear and quadratic in throttle) and a polynomial. Optional motor speed noise: white
Gaussian noise (std motor.speed_noise rad/s, seeded by the simulation seed) on each commanded speed, drawn
once per exchange step; the true rotor speeds the SITL reports are the lagged result, so a model in them stays
exact.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from bridge.vehicle import VehicleConfig

NOISE_BLOCK = 1024  # steps of motor noise drawn at once
NOISE_STREAM = 1  # second element of the noise generator's seed, apart from the sensors' stream


class Motors:
    """The four motors of a vehicle: the throttle curve and the lag d(w)/dt = (w_cmd - w)/Tm (rad/s)."""

    def __init__(self, vehicle: VehicleConfig):
        self.curve = vehicle.motor_curve
        self.time_constant = vehicle.motor.time_constant
        self.inv_time_constant = 1.0 / vehicle.motor.time_constant
        self._kind = self.curve.kind
        self._px4 = (1.0 - self.curve.thr_mdl_fac, self.curve.thr_mdl_fac, self.curve.full_speed)
        self._slope = self.curve.curve_slope
        self._offset = self.curve.curve_offset
        self._max = self.curve.max_speed
        self._zero_speed = self.curve.speed_for_throttle(0.0)
        self.speed_noise = vehicle.motor.speed_noise
        seed = [vehicle.simulation.seed, NOISE_STREAM]
        self._rng = np.random.default_rng(seed) if self.speed_noise else None
        self._noise: list[float] = []

    def commanded_speeds(self, throttles: Sequence[float]) -> tuple[float, float, float, float]:
        """Steady rotor speeds (rad/s) for four throttles; NaN counts as 0, others are clipped to [0, 1]."""
        if len(throttles) != 4:
            raise ValueError(f"expected 4 throttles, got {len(throttles)}")
        if self._kind == "px4":  # MotorCurve.speed_for_throttle for PX4's model, inlined
            lin, quad, full = self._px4
            sqrt = math.sqrt
            out = []
            for sigma in throttles:
                s = float(sigma)
                s = 0.0 if not s > 0.0 else (s if s < 1.0 else 1.0)
                out.append(full * sqrt(lin * s + quad * s * s))
        elif self._kind == "polynomial":
            out = [self._zero_speed if not float(s) > 0.0 else self.curve.speed_for_throttle(float(s))
                   for s in throttles]
        else:
            # MotorCurve.speed_for_throttle, inlined: this runs every step.
            slope, offset, w_max = self._slope, self._offset, self._max
            out = []
            for sigma in throttles:
                s = float(sigma)
                if not s > 0.0:  # also catches NaN
                    out.append(0.0 if offset <= 0.0 else offset)
                    continue
                w = slope * (s if s < 1.0 else 1.0) + offset
                out.append(0.0 if w < 0.0 else (w if w < w_max else w_max))
        if self._rng is not None:
            if not self._noise:  # drawn in blocks of NOISE_BLOCK steps, 4 numbers a step, in a fixed order
                self._noise = self._rng.normal(0.0, self.speed_noise, 4 * NOISE_BLOCK).tolist()[::-1]
            pop = self._noise.pop  # one draw per motor, motors 1..4 in order
            w1, w2, w3, w4 = out[0] + pop(), out[1] + pop(), out[2] + pop(), out[3] + pop()
            return (w1 if w1 > 0.0 else 0.0, w2 if w2 > 0.0 else 0.0, w3 if w3 > 0.0 else 0.0,
                    w4 if w4 > 0.0 else 0.0)
        return out[0], out[1], out[2], out[3]

    def speed_rate(self, commanded: float, speed: float) -> float:
        """d(w)/dt of one rotor, rad/s^2, for commanded and current speed (rad/s)."""
        return (commanded - speed) * self.inv_time_constant
