"""Translational lift: a rotor moving edgewise through air gives more thrust (the issue's law).

T_i grows by k_h (v_ix^2 + v_iy^2), with v_i the hub's airspeed in the rotor plane (m/s, body FRD x and y)
and k_h in N/(m/s)^2.
"""

from __future__ import annotations

Vec3 = tuple[float, float, float]


class TranslationalLift:
    """A thrust modifier (additive, per rotor)."""

    def __init__(self, k_h: float):
        self.k_h = k_h

    def extra_thrust(self, airspeeds: tuple[Vec3, ...]) -> tuple[float, ...]:
        """The added thrust of each rotor, N along -z body, for hub airspeeds (m/s FRD)."""
        k = self.k_h
        return tuple(k * (vx * vx + vy * vy) for vx, vy, _ in airspeeds)
