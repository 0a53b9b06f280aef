"""Motors: throttle in [0, 1] -> commanded rotor speed (the vehicle's curve), then a first-order lag."""

from __future__ import annotations

from collections.abc import Sequence

from bridge.vehicle import VehicleConfig


class Motors:
    """The four motors of a vehicle: the throttle curve and the lag d(w)/dt = (w_cmd - w)/Tm (rad/s)."""

    def __init__(self, vehicle: VehicleConfig):
        self.curve = vehicle.motor_curve
        self.time_constant = vehicle.motor.time_constant
        self.inv_time_constant = 1.0 / vehicle.motor.time_constant
        self._slope = self.curve.curve_slope
        self._offset = self.curve.curve_offset
        self._max = self.curve.max_speed

    def commanded_speeds(self, throttles: Sequence[float]) -> tuple[float, float, float, float]:
        """Steady rotor speeds (rad/s) for four throttles; NaN counts as 0, others are clipped to [0, 1]."""
        if len(throttles) != 4:
            raise ValueError(f"expected 4 throttles, got {len(throttles)}")
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
        return out[0], out[1], out[2], out[3]

    def speed_rate(self, commanded: float, speed: float) -> float:
        """d(w)/dt of one rotor, rad/s^2, for commanded and current speed (rad/s)."""
        return (commanded - speed) * self.inv_time_constant
