"""Drag of the frame (parasitic drag) on the body airspeed v_a (m/s, body FRD), two forms that add up.

Isotropic-magnitude form: F = -|v_a| C v_a, C = diag(c_x, c_y, c_z) kg/m (the vehicle file's
aerodynamics.frame_drag); per-axis form (the paper's vehicle): F_i = -Cd_i v_a,i |v_a,i| (drag.body_quadratic,
N/(m/s)^2). The frame's centre of pressure is taken at the CG: a force, no moment.
"""

from __future__ import annotations

import math
from collections.abc import Callable

Vec3 = tuple[float, float, float]


def frame_drag(c: Vec3, cd: Vec3) -> Callable[[float, float, float], Vec3]:
    """A wrench source (force only): f(ux, uy, uz m/s FRD) -> (fx, fy, fz) N, FRD."""
    cx, cy, cz = c
    dx, dy, dz = cd
    sqrt = math.sqrt

    def force(ux: float, uy: float, uz: float) -> Vec3:
        speed = sqrt(ux * ux + uy * uy + uz * uz)
        return (-(speed * cx + dx * abs(ux)) * ux, -(speed * cy + dy * abs(uy)) * uy,
                -(speed * cz + dz * abs(uz)) * uz)

    return force
