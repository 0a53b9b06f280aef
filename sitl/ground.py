"""The ground: a flat plane at z = 0 (NED, z down) that the vehicle rests on and takes off from."""

from __future__ import annotations

import math


class GroundPlane:
    """Contact with a rigid, frictionless-to-take-off flat ground at z = 0.

    Applied after each physics substep to the state list
    [x y z, vx vy vz, qw qx qy qz, wx wy wz, w1..w4] (NED m, m/s, body->earth quaternion, FRD rad/s).
    If the vehicle is at or below the plane and not climbing, the ground's reaction stops it: z = 0, zero
    velocity and body rates, attitude level keeping yaw. While thrust < weight this repeats every substep
    (the vehicle rests); once thrust > weight the substep ends above the plane and it takes off.
    """

    def apply(self, s: list[float]) -> bool:
        """Resolve contact in place; True when the vehicle rests on the ground after this substep."""
        if s[2] < 0.0 or s[5] < 0.0:
            return False
        qw, qx, qy, qz = s[6], s[7], s[8], s[9]
        yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        s[2] = 0.0
        s[3] = s[4] = s[5] = 0.0
        s[6] = math.cos(0.5 * yaw)
        s[7] = s[8] = 0.0
        s[9] = math.sin(0.5 * yaw)
        s[10] = s[11] = s[12] = 0.0
        return True


class NoGround:
    """No ground: free space at every altitude (open-loop excitation experiments)."""

    def apply(self, s: list[float]) -> bool:
        """Nothing to resolve; never on the ground."""
        return False


def make_ground(kind: str) -> GroundPlane | NoGround:
    """The ground model named in a vehicle file: 'plane' or 'none'."""
    if kind == "plane":
        return GroundPlane()
    if kind == "none":
        return NoGround()
    raise ValueError(f"unknown ground model {kind!r}")
