"""Ground effect: the Cheeseman-Bennett law (Cheeseman & Bennett 1955), as used for multirotors.

T / T_inf = 1 / (1 - (R / (4 h))^2) for a rotor of radius R (m) at height h (m) above the ground; it diverges
at h = R/4, so h is held at h_min (> R/4) below it. Only with a ground plane (free space has no ground).
"""

from __future__ import annotations

from bridge.airframe import GroundEffectConfig


class GroundEffect:
    """A thrust modifier (multiplicative, per rotor)."""

    def __init__(self, config: GroundEffectConfig):
        self.quarter_radius = config.rotor_radius / 4.0
        self.min_height = config.min_height

    def ratio(self, height: float) -> float:
        """T/T_inf at a rotor height (m) above the ground."""
        h = height if height > self.min_height else self.min_height
        a = self.quarter_radius / h
        return 1.0 / (1.0 - a * a)

    def ratios(self, heights: tuple[float, ...]) -> tuple[float, ...]:
        """T/T_inf for each rotor height (m)."""
        return tuple(self.ratio(h) for h in heights)
