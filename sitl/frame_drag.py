"""Drag of the frame (parasitic drag) on the body airspeed v_a (m/s, body FRD), two forms that add up.

Isotropic-magnitude form: F = -|v_a| C v_a, C = diag(c_x, c_y, c_z) kg/m (the vehicle file's
aerodynamics.frame_drag);
per-axis form (the paper's vehicle): F_i = -Cd_i v_a,i |v_a,i| (drag.body_quadratic, N/(m/s)^2).
"""

from __future__ import annotations

import math

Vec3 = tuple[float, float, float]


class FrameDrag:
    """A body wrench source (force only: the frame's centre of pressure is taken at the CG)."""

    def __init__(self, frame_drag: Vec3, body_quadratic: Vec3):
        self.c = frame_drag
        self.cd = body_quadratic

    def force(self, ua: Vec3) -> Vec3:
        """(fx, fy, fz) N, body FRD, for body airspeed ua (m/s)."""
        ux, uy, uz = ua
        cx, cy, cz = self.c
        dx, dy, dz = self.cd
        speed = math.sqrt(ux * ux + uy * uy + uz * uz)
        return (-(speed * cx + dx * abs(ux)) * ux, -(speed * cy + dy * abs(uy)) * uy,
                -(speed * cz + dz * abs(uz)) * uz)
