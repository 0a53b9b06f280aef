"""Rotor drag (blade flapping and induced drag), after Faessler et al. 2018 and RotorPy.

Rotor i with speed w_i (rad/s) and hub airspeed v_i = v_a + w x r_i (m/s, body FRD) feels
F_i = -w_i K v_i with K = diag(k_d, k_d, k_z) (kg/rad), applied at the hub: moment r_i x F_i (N m, FRD,
about the CG).
"""

from __future__ import annotations

from collections.abc import Callable

from bridge.airframe import RotorDragConfig

Vec3 = tuple[float, float, float]


def rotor_drag(config: RotorDragConfig, arms: tuple[Vec3, ...]) -> Callable[..., tuple[float, ...]]:
    """A wrench source f(w1..w4 rad/s, hub airspeeds 12 floats m/s) -> (fx, fy, fz N, mx, my, mz N m), FRD."""
    kd, kz = config.k_d, config.k_z
    (x1, y1, z1), (x2, y2, z2), (x3, y3, z3), (x4, y4, z4) = arms

    def wrench(w1: float, w2: float, w3: float, w4: float, a: tuple[float, ...]) -> tuple[float, ...]:
        d1, d2, d3, d4 = -w1 * kd, -w2 * kd, -w3 * kd, -w4 * kd
        fx1, fy1, fz1 = d1 * a[0], d1 * a[1], -w1 * kz * a[2]
        fx2, fy2, fz2 = d2 * a[3], d2 * a[4], -w2 * kz * a[5]
        fx3, fy3, fz3 = d3 * a[6], d3 * a[7], -w3 * kz * a[8]
        fx4, fy4, fz4 = d4 * a[9], d4 * a[10], -w4 * kz * a[11]
        return (fx1 + fx2 + fx3 + fx4, fy1 + fy2 + fy3 + fy4, fz1 + fz2 + fz3 + fz4,
                (y1 * fz1 - z1 * fy1) + (y2 * fz2 - z2 * fy2) + (y3 * fz3 - z3 * fy3) + (y4 * fz4 - z4 * fy4),
                (z1 * fx1 - x1 * fz1) + (z2 * fx2 - x2 * fz2) + (z3 * fx3 - x3 * fz3) + (z4 * fx4 - x4 * fz4),
                (x1 * fy1 - y1 * fx1) + (x2 * fy2 - y2 * fx2) + (x3 * fy3 - y3 * fx3) + (x4 * fy4 - y4 * fx4))

    return wrench
