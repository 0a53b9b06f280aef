"""Where the rotors are and how they push: per-rotor arms about the CG, coefficients and spin (body FRD).

Rotor i at arm r_i (m, FRD, from the centre of gravity) with thrust T_i along -z body gives the moment
r_i x (0, 0, -T_i) = (-r_iy T_i, r_ix T_i, 0); its drag torque is -s_i Cm_i w_i^2 about z and its angular
momentum Jm s_i w_i along z, with s_i = -1 for a rotor spinning ccw seen from above, +1 for cw (w_i in rad/s).
"""

from __future__ import annotations

from bridge.vehicle import VehicleConfig

Vec3 = tuple[float, float, float]


class RotorGeometry:
    """The four rotors of a vehicle file (PX4 order): arms about the CG, Ct_i, Cm_i, spin signs."""

    def __init__(self, vehicle: VehicleConfig):
        rotors = vehicle.rotor_set
        self.arms: tuple[Vec3, ...] = vehicle.rotor_arms  # m, FRD
        self.thrust_coefficients = tuple(r.thrust_coefficient for r in rotors)  # N/(rad/s)^2
        self.moment_coefficients = tuple(r.moment_coefficient for r in rotors)  # N m/(rad/s)^2
        self.spins = tuple(r.spin_z for r in rotors)  # -1 ccw, +1 cw (z FRD)
        self.rotor_inertia = vehicle.motor.rotor_inertia  # kg m^2

    def rotor_airspeeds(self, ua: Vec3, rates: Vec3) -> tuple[Vec3, ...]:
        """Each hub's airspeed v_a + w x r_i, m/s FRD, for body airspeed v_a (m/s) and rates w (rad/s)."""
        ux, uy, uz = ua
        p, q, r = rates
        return tuple((ux + q * z - r * y, uy + r * x - p * z, uz + p * y - q * x) for x, y, z in self.arms)

    def heights(self, z: float, r20: float, r21: float, r22: float) -> tuple[float, ...]:
        """Each hub's height above the ground plane z = 0, m: -(z + (R r_i)_z), R's last row r20 r21 r22."""
        return tuple(-(z + r20 * x + r21 * y + r22 * zz) for x, y, zz in self.arms)

    def wrench(self, thrusts: tuple[float, ...], speeds: tuple[float, ...]) -> tuple[float, ...]:
        """(thrust N along -z, roll, pitch, yaw torque N m, angular momentum h_z N m s), FRD about the CG."""
        t = mx = my = mz = hz = 0.0
        jm = self.rotor_inertia
        for (x, y, _), ti, w, cm, s in zip(self.arms, thrusts, speeds, self.moment_coefficients,  # noqa: B905
                                           self.spins):
            t += ti
            mx -= y * ti
            my += x * ti
            mz -= s * cm * w * w
            hz += s * jm * w
        return t, mx, my, mz, hz
