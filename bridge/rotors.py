"""Where a vehicle's rotors are and which way they spin: the one place the rotor geometry is read from.

Today's vehicle file gives a Quad-X arm length; a file with per-rotor positions would be read here too, so
every user of the geometry (the PX4 airframe, allocation checks) gets it from `rotors_of(vehicle)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from bridge.vehicle import VehicleConfig

# PX4 Quad-X order: (x sign, y sign, spin) of motors 1..4; spin +1 = counter-clockwise seen from above.
QUAD_X = ((1.0, 1.0, 1), (-1.0, -1.0, 1), (1.0, -1.0, -1), (-1.0, 1.0, -1))


@dataclass(frozen=True)
class Rotor:
    """One rotor: position in the body frame FRD (m) and spin (+1 CCW, -1 CW seen from above)."""

    x: float  # m, forward of the centre of mass
    y: float  # m, right of the centre of mass
    z: float  # m, below the centre of mass
    spin: int  # +1 counter-clockwise, -1 clockwise (seen from above)


def rotors_of(vehicle: VehicleConfig) -> list[Rotor]:
    """The vehicle's rotors in motor order 1..4 (PX4 Quad-X), positions FRD in m."""
    r = vehicle.arm_length / math.sqrt(2.0)
    return [Rotor(sx * r, sy * r, 0.0, spin) for sx, sy, spin in QUAD_X]
