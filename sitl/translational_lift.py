"""Translational lift: a rotor moving edgewise through air gives more thrust (the issue's law).

T_i grows by k_h (v_ix^2 + v_iy^2), with v_i the hub's airspeed in the rotor plane (m/s, body FRD x and y)
and k_h in N/(m/s)^2.
"""

from __future__ import annotations

from collections.abc import Callable


def translational_lift(k_h: float) -> Callable[[tuple[float, ...]], tuple[float, float, float, float]]:
    """A thrust modifier (additive): f(hub airspeeds, 12 floats m/s FRD) -> each rotor's added thrust, N."""

    def extra_thrust(a: tuple[float, ...]) -> tuple[float, float, float, float]:
        return (k_h * (a[0] * a[0] + a[1] * a[1]), k_h * (a[3] * a[3] + a[4] * a[4]),
                k_h * (a[6] * a[6] + a[7] * a[7]), k_h * (a[9] * a[9] + a[10] * a[10]))

    return extra_thrust
