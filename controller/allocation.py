"""Control allocation: the paper's f = (f1..f4) <-> the four rotor speeds, with saturation priorities.

f1 = u1^2+u2^2+u3^2+u4^2 (collective), f2 = -u1^2+u2^2+u3^2-u4^2 (roll), f3 = u1^2-u2^2+u3^2-u4^2 (pitch),
f4 = u1^2+u2^2-u3^2-u4^2 (yaw), all in (rad/s)^2, PX4 Quad-X order (docs/design.md). The mixing matrix M has
orthogonal rows of squared norm 4, so the squared speeds are q = M^T f / 4.

When q leaves [0, w_max^2] the request is changed in the order a multirotor mixer uses: roll and pitch are
kept, yaw is reduced first, then the collective is shifted, and only then roll and pitch are scaled down.
Squared speeds are never negative and never above w_max^2, so the speeds are real and within [0, w_max].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIX = np.array(
    [
        [1.0, 1.0, 1.0, 1.0],
        [-1.0, 1.0, 1.0, -1.0],
        [1.0, -1.0, 1.0, -1.0],
        [1.0, 1.0, -1.0, -1.0],
    ]
)
# q_i = (f1 + ROLL_SIGN[i] f2 + PITCH_SIGN[i] f3 + YAW_SIGN[i] f4) / 4, the columns of M.
ROLL_SIGN = (-1.0, 1.0, 1.0, -1.0)
PITCH_SIGN = (1.0, -1.0, 1.0, -1.0)
YAW_SIGN = (1.0, 1.0, -1.0, -1.0)


@dataclass(frozen=True)
class Allocation:
    """The rotor speeds [rad/s, PX4 order] within [0, w_max] and the f they realise [(rad/s)^2]."""

    speeds: np.ndarray
    applied: np.ndarray  # f realised by the speeds (equals the request when not saturated)
    saturated: bool  # True when the request had to be changed
    stage: str  # "none" | "yaw" | "thrust" | "attitude": the last priority stage used


def f_from_speeds(speeds: np.ndarray) -> np.ndarray:
    """f1..f4 [(rad/s)^2] of four rotor speeds [rad/s] (PX4 order)."""
    q = np.square(np.asarray(speeds, dtype=float))
    return MIX @ q


def squared_speeds(f: np.ndarray) -> np.ndarray:
    """The squared rotor speeds q = M^-1 f [(rad/s)^2] of a request f (may be negative: not clipped)."""
    return MIX.T @ np.asarray(f, dtype=float) / 4.0


def _q(t: float, r: float, p: float, y: float) -> list[float]:
    # M^T f / 4 written out (the columns ROLL_SIGN, PITCH_SIGN, YAW_SIGN): this runs every control step
    return [(t - r + p + y) * 0.25, (t + r - p + y) * 0.25, (t + r + p - y) * 0.25, (t - r - p - y) * 0.25]


def _yaw_scale(t: float, att: list[float], yaw: list[float], q4max: float) -> float | None:
    """Largest lam in [0, 1] with 0 <= t + att_i + lam*yaw_i <= q4max for all i; None if even lam=0 fails."""
    lo, hi = 0.0, 1.0
    for a, y in zip(att, yaw, strict=True):
        base = t + a
        if base < -1e-9 * q4max or base > q4max * (1.0 + 1e-12):
            return None
        if y > 0.0:
            hi = min(hi, (q4max - base) / y)
        elif y < 0.0:
            hi = min(hi, -base / y)
    return max(lo, min(hi, 1.0))


def allocate_floats(f: np.ndarray | list[float], w_max: float) -> tuple[list[float], list[float], str]:
    """allocate() without its arrays, for the control loop: (squared speeds [(rad/s)^2], speeds, stage)."""
    t, r, p, y = f
    t, r, p, y = float(t), float(r), float(p), float(y)
    isfinite = math.isfinite
    stage_bad = not (isfinite(t) and isfinite(r) and isfinite(p) and isfinite(y))
    if stage_bad:
        t, r, p, y = 0.0, 0.0, 0.0, 0.0
    qmax = w_max * w_max
    q = _q(t, r, p, y)
    q0, q1, q2, q3 = q
    stage = "none"  # and q within [0, w_max^2] as it stands
    if stage_bad or not (0.0 <= q0 <= qmax and 0.0 <= q1 <= qmax and 0.0 <= q2 <= qmax and 0.0 <= q3 <= qmax):
        q4max = 4.0 * qmax
        att = [ROLL_SIGN[i] * r + PITCH_SIGN[i] * p for i in range(4)]
        yaw = [YAW_SIGN[i] * y for i in range(4)]
        lam = _yaw_scale(t, att, yaw, q4max)
        if lam is not None:
            stage = "yaw"
            y *= lam
        else:
            lo, hi = -min(att), q4max - max(att)
            if lo <= hi:
                stage = "thrust"
                t = min(max(t, lo), hi)
                lam = _yaw_scale(t, att, yaw, q4max)
                y *= lam if lam is not None else 0.0
            else:
                stage = "attitude"
                spread = max(att) - min(att)
                mu = q4max / spread
                r *= mu
                p *= mu
                t = -min(att) * mu
                y = 0.0
        if stage_bad:
            stage = "attitude"
        q = [0.0 if v < 0.0 else qmax if v > qmax else v for v in _q(t, r, p, y)]
        q0, q1, q2, q3 = q
    sqrt = math.sqrt
    return q, [sqrt(q0), sqrt(q1), sqrt(q2), sqrt(q3)], stage


def allocate(f: np.ndarray | list[float], w_max: float) -> Allocation:
    """Rotor speeds [rad/s] in [0, w_max] realising f [(rad/s)^2], with roll/pitch > thrust > yaw priority."""
    sq, speeds, stage = allocate_floats(f, w_max)
    applied = [
        sq[0] + sq[1] + sq[2] + sq[3],
        -sq[0] + sq[1] + sq[2] - sq[3],
        sq[0] - sq[1] + sq[2] - sq[3],
        sq[0] + sq[1] - sq[2] - sq[3],
    ]
    return Allocation(speeds=np.array(speeds), applied=np.array(applied), saturated=stage != "none",
                      stage=stage)
