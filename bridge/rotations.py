"""The one rotation toolkit: ZYX Euler angles, scalar-first quaternions, rotation matrices (FRD to NED).

Conventions (docs/design.md): R = Rz(psi) Ry(theta) Rx(phi) maps body FRD to earth NED; quaternions are
(w, x, y, z), body to earth; angles in rad. The scalar functions use `math` and return tuples (9 floats row by
row for a matrix): they run in control loops every 4 ms, where numpy's per-call overhead was measured to
matter; the array functions take (N, ...) numpy arrays for logs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def rotation_from_euler(phi: float, theta: float, psi: float) -> tuple[float, ...]:
    """R = Rz(psi) Ry(theta) Rx(phi) of ZYX Euler angles (rad), as 9 floats row by row."""
    cf, sf = math.cos(phi), math.sin(phi)
    ct, st = math.cos(theta), math.sin(theta)
    cp, sp = math.cos(psi), math.sin(psi)
    return (ct * cp, sf * st * cp - cf * sp, cf * st * cp + sf * sp,
            ct * sp, sf * st * sp + cf * cp, cf * st * sp - sf * cp,
            -st, sf * ct, cf * ct)


def rotation_from_quaternion(w: float, x: float, y: float, z: float) -> tuple[float, ...]:
    """Rotation matrix body->earth of a unit quaternion (w, x, y, z), as 9 floats row by row."""
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


def quaternion_from_euler(phi: float, theta: float, psi: float) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of ZYX Euler angles (rad)."""
    cr, sr = math.cos(0.5 * phi), math.sin(0.5 * phi)
    cp, sp = math.cos(0.5 * theta), math.sin(0.5 * theta)
    cy, sy = math.cos(0.5 * psi), math.sin(0.5 * psi)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def quaternion_from_rotation(rows: Sequence[Sequence[float]]) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix given as rows ((r00, r01, r02), ...)."""
    (a, b, c), (d, e, f), (g, h, i) = rows
    tr = a + e + i
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        qw, qx, qy, qz = 0.25 * s, (h - f) / s, (c - g) / s, (d - b) / s
    elif a > e and a > i:
        s = math.sqrt(1.0 + a - e - i) * 2.0
        qw, qx, qy, qz = (h - f) / s, 0.25 * s, (b + d) / s, (c + g) / s
    elif e > i:
        s = math.sqrt(1.0 + e - a - i) * 2.0
        qw, qx, qy, qz = (c - g) / s, (b + d) / s, 0.25 * s, (f + h) / s
    else:
        s = math.sqrt(1.0 + i - a - e) * 2.0
        qw, qx, qy, qz = (d - b) / s, (c + g) / s, (f + h) / s, 0.25 * s
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return qw / n, qx / n, qy / n, qz / n


def euler_from_quaternion(q: Sequence[float]) -> np.ndarray:
    """ZYX Euler angles (phi roll, theta pitch, psi yaw) in rad of a scalar-first body-to-NED quaternion."""
    w, x, y, z = (float(c) for c in q)
    phi = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    s = 2.0 * (w * y - z * x)
    theta = math.asin(1.0 if s > 1.0 else (-1.0 if s < -1.0 else s))
    psi = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.array((phi, theta, psi))


def euler_from_quaternions(q: np.ndarray) -> np.ndarray:
    """ZYX Euler angles (N,3) rad (phi, theta, psi) of scalar-first body-to-NED quaternions (N,4)."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    phi = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    theta = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    psi = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.stack((phi, theta, psi), axis=1)


def rotation_matrix(
    phi: np.ndarray | float, theta: np.ndarray | float, psi: np.ndarray | float
) -> np.ndarray:
    """Body FRD -> earth NED rotation, numeric: (3,3) for scalars, (N,3,3) for arrays of angles (rad)."""
    phi, theta, psi = np.broadcast_arrays(
        np.asarray(phi, float), np.asarray(theta, float), np.asarray(psi, float)
    )
    cf, sf, ct, st, cp, sp = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta), np.cos(psi), np.sin(psi)
    r = np.empty(phi.shape + (3, 3))
    r[..., 0, 0] = ct * cp
    r[..., 0, 1] = sf * st * cp - cf * sp
    r[..., 0, 2] = cf * st * cp + sf * sp
    r[..., 1, 0] = ct * sp
    r[..., 1, 1] = sf * st * sp + cf * cp
    r[..., 1, 2] = cf * st * sp - sf * cp
    r[..., 2, 0] = -st
    r[..., 2, 1] = sf * ct
    r[..., 2, 2] = cf * ct
    return r
