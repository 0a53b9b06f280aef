"""Where the rotors are and how they push: per-rotor arms about the CG, coefficients and spin (body FRD).

Rotor i at arm r_i (m, FRD, from the centre of gravity) with thrust T_i along -z body gives the moment
r_i x (0, 0, -T_i) = (-r_iy T_i, r_ix T_i, 0); its drag torque is -s_i Cm_i w_i^2 about z and its angular
momentum Jm s_i w_i along z, with s_i = -1 for a rotor spinning ccw seen from above, +1 for cw (w_i in rad/s).

The functions run four times per physics substep, so they are closures over the constants with the four
rotors unrolled (a loop or generator over rotors costs more than the arithmetic).
"""

from __future__ import annotations

from collections.abc import Callable

from bridge.vehicle import VehicleConfig

Vec3 = tuple[float, float, float]


class RotorGeometry:
    """The four rotors of a vehicle file (PX4 order): arms about the CG (m FRD), Ct_i, Cm_i, spin signs."""

    def __init__(self, vehicle: VehicleConfig):
        rotors = vehicle.rotor_set
        self.arms: tuple[Vec3, ...] = vehicle.rotor_arms  # m, FRD
        self.thrust_coefficients = tuple(r.thrust_coefficient for r in rotors)  # N/(rad/s)^2
        self.moment_coefficients = tuple(r.moment_coefficient for r in rotors)  # N m/(rad/s)^2
        self.spins = tuple(r.spin_z for r in rotors)  # -1 ccw, +1 cw (z FRD)
        self.rotor_inertia = vehicle.motor.rotor_inertia  # kg m^2

    def airspeeds(self) -> Callable[..., tuple[float, ...]]:
        """f(ux, uy, uz, p, q, r) -> each hub's airspeed v_a + w x r_i (12 floats, m/s FRD, by rotor)."""
        (x1, y1, z1), (x2, y2, z2), (x3, y3, z3), (x4, y4, z4) = self.arms

        def airspeeds(ux: float, uy: float, uz: float, p: float, q: float, r: float) -> tuple[float, ...]:
            return (ux + q * z1 - r * y1, uy + r * x1 - p * z1, uz + p * y1 - q * x1,
                    ux + q * z2 - r * y2, uy + r * x2 - p * z2, uz + p * y2 - q * x2,
                    ux + q * z3 - r * y3, uy + r * x3 - p * z3, uz + p * y3 - q * x3,
                    ux + q * z4 - r * y4, uy + r * x4 - p * z4, uz + p * y4 - q * x4)

        return airspeeds

    def heights(self) -> Callable[..., tuple[float, float, float, float]]:
        """f(z, r20, r21, r22) -> each hub's height above z = 0 (m): -(z + (R r_i)_z), R's last row r2j."""
        (x1, y1, z1), (x2, y2, z2), (x3, y3, z3), (x4, y4, z4) = self.arms

        def heights(z: float, r20: float, r21: float, r22: float) -> tuple[float, float, float, float]:
            return (-(z + r20 * x1 + r21 * y1 + r22 * z1), -(z + r20 * x2 + r21 * y2 + r22 * z2),
                    -(z + r20 * x3 + r21 * y3 + r22 * z3), -(z + r20 * x4 + r21 * y4 + r22 * z4))

        return heights

    def wrench(self) -> Callable[..., tuple[float, float, float, float, float]]:
        """f(T1..T4 N, w1..w4 rad/s) -> (thrust N along -z, roll, pitch, yaw torque N m, h_z N m s), FRD."""
        (x1, y1, _), (x2, y2, _), (x3, y3, _), (x4, y4, _) = self.arms
        jm = self.rotor_inertia
        q1, q2, q3, q4 = (-s * cm for s, cm in zip(self.spins, self.moment_coefficients, strict=True))
        j1, j2, j3, j4 = (s * jm for s in self.spins)

        def wrench(t1: float, t2: float, t3: float, t4: float,
                   w1: float, w2: float, w3: float, w4: float) -> tuple[float, float, float, float, float]:
            return (t1 + t2 + t3 + t4,
                    -(y1 * t1 + y2 * t2 + y3 * t3 + y4 * t4),
                    x1 * t1 + x2 * t2 + x3 * t3 + x4 * t4,
                    q1 * w1 * w1 + q2 * w2 * w2 + q3 * w3 * w3 + q4 * w4 * w4,
                    j1 * w1 + j2 * w2 + j3 * w3 + j4 * w4)

        return wrench
