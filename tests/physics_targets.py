"""Test helpers: the SITL's exact accelerations at a dataset's rows, and R^2 per column."""

from __future__ import annotations

import numpy as np

from bridge.vehicle import load_vehicle
from sitl.dynamics import Quadrotor


def physics_targets(ds, ground: str = "none") -> np.ndarray:
    """The SITL's exact accelerations (N,6: NED m/s^2, FRD rad/s^2) at each row's state and rotor speeds."""
    return sitl_accelerations(load_vehicle("fang-chen-buaa").with_overrides(ground=ground), ds.xi, ds.u)


def sitl_accelerations(vehicle, xi: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The SITL's exact accelerations (N,6: NED m/s^2, FRD rad/s^2) of `vehicle` at xi (N,12), u (N,4)."""
    quad = Quadrotor(vehicle)
    out = np.empty((len(xi), 6))
    for i, (x, w) in enumerate(zip(xi, u, strict=True)):
        quad.reset(
            position=x[0:3], yaw=x[8], rotor_speeds=w, velocity=x[3:6], rates=x[9:12], roll=x[6], pitch=x[7]
        )
        out[i, :3] = quad.acceleration_earth()
        out[i, 3:] = quad.angular_acceleration()
    return out


def r2(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Coefficient of determination of each column of estimate against truth."""
    return 1.0 - ((estimate - truth) ** 2).sum(0) / ((truth - truth.mean(0)) ** 2).sum(0)
