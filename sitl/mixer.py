"""Quad-X mixing in PX4 order: rotor speeds -> thrust, body torques and rotor angular momentum (FRD).

Motor 1 front-right CCW, 2 rear-left CCW, 3 front-left CW, 4 rear-right CW (seen from above).
"""

from __future__ import annotations

import math

from bridge.vehicle import VehicleConfig


class QuadXMixer:
    """Forces and moments of the four rotors on the body (the paper's f1..f4 times their coefficients)."""

    def __init__(self, vehicle: VehicleConfig):
        self.ct = vehicle.thrust_coefficient
        self.cm = vehicle.moment_coefficient
        self.k = math.sqrt(2.0) / 2.0 * vehicle.arm_length * vehicle.thrust_coefficient
        self.jm = vehicle.motor.rotor_inertia

    def wrench(self, w1: float, w2: float, w3: float, w4: float) -> tuple[float, float, float, float, float]:
        """(T N along -z body, roll/pitch/yaw torque N m FRD, rotor momentum h_z N m s along +z body).

        A CCW rotor (seen from above) spins about -z in FRD, so h_z = Jm*(-w1 - w2 + w3 + w4); its drag
        torque on the body is about +z, hence yaw = Cm*(w1^2 + w2^2 - w3^2 - w4^2).
        """
        s1 = w1 * w1
        s2 = w2 * w2
        s3 = w3 * w3
        s4 = w4 * w4
        k = self.k
        return (
            self.ct * (s1 + s2 + s3 + s4),
            k * (-s1 + s2 + s3 - s4),
            k * (s1 - s2 + s3 - s4),
            self.cm * (s1 + s2 - s3 - s4),
            self.jm * (-w1 - w2 + w3 + w4),
        )
