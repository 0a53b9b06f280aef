"""The gravity in a flight log's data, from its accelerations and its accelerometer, against the one assumed.

Body-frame learning (identification.body_frame) turns NED accelerations a (m/s^2) into the specific force
f_b = R^T (a - g e_z) with the g it is given. With truth targets, a g other than the data's is left in
f_b as (g_data - g) R^T e_z: on the paper vehicle's SITL flight (g 9.8) learned with the default 9.80665,
fx and fz took linear drag terms -0.00038 ub and -0.00038 wb that its physics does not have. A log that
holds both the velocity (NED) and the accelerometer (FRD) says which g it was made with: per row

    a - R f = g e_z + R b

with b a constant accelerometer bias (FRD), linear in (g, b); least squares over the rows gives g and its
standard error (from blocks of rows: neighbouring rows' errors are not independent). Where the attitude
barely varies, g and the bias's z part are one column and the error is large: then the log says nothing
firm. Sensor targets need none of this: they add back the same g that body-frame learning removes.
"""

from __future__ import annotations

import numpy as np

from bridge.rotations import rotation_matrix

BLOCKS = 20  # blocks of consecutive rows for the standard error
# m/s^2: a difference below this is not reported (0.03 % of g). The central difference of the velocity is
# the mean acceleration over two steps, the accelerometer a sample: on closed-loop SITL flights (commands
# change every step, thrust follows u_i^2 through the motor lag) that leaves 1.1e-3 (g 9.7989 +- 0.0001
# from a flight with g 9.8), on open-loop flights 2e-4; 9.8 against 9.80665 is 6.7e-3
TOLERANCE = 3e-3
EVIDENCE = 5.0  # standard errors a difference must exceed to be reported


def log_gravity(
    t: np.ndarray, vel: np.ndarray, euler: np.ndarray, accel: np.ndarray, usable: np.ndarray
) -> tuple[float, float] | None:
    """(g m/s^2, its standard error) fitted to a - R f = g e_z + R b over the rows usable (N,) with both
    neighbours usable and equally spaced; t (N,) s, vel (N,3) NED m/s, euler (N,3) ZYX rad, accel (N,3)
    FRD m/s^2. None with too few rows, or where g and the bias cannot be told apart (a level flight)."""
    t = np.asarray(t, float)
    n = len(t)
    if n < 3 * BLOCKS:
        return None
    dt = np.diff(t)
    ok = np.zeros(n, bool)
    ok[1:-1] = usable[1:-1] & usable[:-2] & usable[2:] & np.isclose(dt[:-1], dt[1:], rtol=1e-6, atol=0.0)
    ok &= np.isfinite(accel).all(axis=1) & np.isfinite(vel).all(axis=1) & np.isfinite(euler).all(axis=1)
    idx = np.flatnonzero(ok)
    if len(idx) < 3 * BLOCKS:
        return None
    a = (vel[idx + 1] - vel[idx - 1]) / (t[idx + 1] - t[idx - 1])[:, None]
    R = rotation_matrix(euler[idx, 0], euler[idx, 1], euler[idx, 2])
    r = a - np.einsum("nij,nj->ni", R, accel[idx])  # (m, 3)
    A = np.zeros((len(idx), 3, 4))
    A[:, 2, 0] = 1.0
    A[:, :, 1:] = R
    A2, y = A.reshape(-1, 4), r.reshape(-1)
    x, *_ = np.linalg.lstsq(A2, y, rcond=None)
    residual = (y - A2 @ x).reshape(len(idx), 3)
    # blocked sandwich: the rows' errors are correlated in time, so sum the score per block of rows
    normal = A2.T @ A2
    if np.linalg.cond(normal) > 1e12:  # a level flight: g and the bias's z part are one column
        return None
    bread = np.linalg.inv(normal)
    scores = np.einsum("nij,ni->nj", A, residual)
    blocks = np.array_split(np.arange(len(idx)), BLOCKS)
    meat = sum(np.outer(scores[b].sum(axis=0), scores[b].sum(axis=0)) for b in blocks)
    cov = bread @ meat @ bread * BLOCKS / (BLOCKS - 1)
    return float(x[0]), float(np.sqrt(max(cov[0, 0], 0.0)))


def gravity_note(estimate: tuple[float, float] | None, assumed: float) -> str | None:
    """A warning when the log's gravity (g, its standard error) differs from the assumed g (m/s^2) by more
    than TOLERANCE and EVIDENCE standard errors; None otherwise."""
    if estimate is None:
        return None
    g, se = estimate
    if not np.isfinite(g) or abs(g - assumed) <= max(TOLERANCE, EVIDENCE * se):
        return None
    return (f"this log's accelerations and accelerometer agree on g = {g:.4f} +- {se:.4f} m/s^2, not the "
            f"{assumed:g} that body-frame learning removes: the difference ({g - assumed:+.4f} m/s^2 along "
            f"R^T e_z) would be learned as drag or constant terms; pass --gravity {g:.4f} (or --vehicle with "
            "the vehicle it was flown with)")
