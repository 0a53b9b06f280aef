"""Ground effect: the Cheeseman-Bennett law (Cheeseman & Bennett 1955), as used for multirotors.

T / T_inf = 1 / (1 - (R / (4 h))^2) for a rotor of radius R (m) at height h (m) above the ground; it diverges
at h = R/4, so h is held at h_min (> R/4) below it. Only with a ground plane (free space has no ground).
"""

from __future__ import annotations

from collections.abc import Callable

from bridge.airframe import GroundEffectConfig


def ground_effect(config: GroundEffectConfig) -> Callable[..., tuple[float, float, float, float]]:
    """A thrust modifier (multiplicative): f(h1..h4 m) -> each rotor's T/T_inf."""
    q2 = (config.rotor_radius / 4.0) ** 2  # m^2
    hmin = config.min_height

    def ratios(h1: float, h2: float, h3: float, h4: float) -> tuple[float, float, float, float]:
        h1 = h1 if h1 > hmin else hmin
        h2 = h2 if h2 > hmin else hmin
        h3 = h3 if h3 > hmin else hmin
        h4 = h4 if h4 > hmin else hmin
        return (1.0 / (1.0 - q2 / (h1 * h1)), 1.0 / (1.0 - q2 / (h2 * h2)),
                1.0 / (1.0 - q2 / (h3 * h3)), 1.0 / (1.0 - q2 / (h4 * h4)))

    return ratios
