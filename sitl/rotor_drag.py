"""Rotor drag (blade flapping and induced drag), after Faessler et al. 2018 and RotorPy.

Rotor i with speed w_i (rad/s) and hub airspeed v_i = v_a + w x r_i (m/s, body FRD) feels
F_i = -w_i K v_i with K = diag(k_d, k_d, k_z) (kg/rad), applied at the hub: moment r_i x F_i (N m, FRD,
about the CG).
"""

from __future__ import annotations

from bridge.airframe import RotorDragConfig

Vec3 = tuple[float, float, float]


class RotorDrag:
    """A body wrench source: the sum over rotors of -w_i K v_i and its moment r_i x F_i."""

    def __init__(self, config: RotorDragConfig, arms: tuple[Vec3, ...]):
        self.k_d = config.k_d
        self.k_z = config.k_z
        self.arms = arms

    def wrench(self, speeds: tuple[float, ...], airspeeds: tuple[Vec3, ...]) -> tuple[float, ...]:
        """(fx, fy, fz N, mx, my, mz N m), FRD about the CG, for rotor speeds (rad/s) and hub airspeeds."""
        kd, kz = self.k_d, self.k_z
        fx = fy = fz = mx = my = mz = 0.0
        for (x, y, z), w, (vx, vy, vz) in zip(self.arms, speeds, airspeeds):  # noqa: B905
            ax, ay, az = -w * kd * vx, -w * kd * vy, -w * kz * vz
            fx += ax
            fy += ay
            fz += az
            mx += y * az - z * ay
            my += z * ax - x * az
            mz += x * ay - y * ax
        return fx, fy, fz, mx, my, mz
