"""The controller plug-in contract: every tracking controller is a class with `update(t, state, reference)`.

Like RotorPy's controllers: a small explicit contract, selectable by name from the registry below.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np


@dataclass(frozen=True)
class VehicleState:
    """What the controller feeds back, NED/FRD: the 12-state xi and the rotor speeds.

    xi = (x, y, z [m, NED], vx, vy, vz [m/s, NED], phi, theta, psi [rad, ZYX Euler], wx, wy, wz [rad/s, FRD]);
    rotor_speeds [rad/s], PX4 order; quaternion (w, x, y, z) body->earth when known (else derived from Euler).
    """

    xi: np.ndarray
    rotor_speeds: np.ndarray
    quaternion: np.ndarray | None = None


@dataclass(frozen=True)
class Reference:
    """Desired flat outputs at time t: position NED [m] with derivatives up to snap, yaw [rad] with two."""

    position: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(3))
    jerk: np.ndarray = field(default_factory=lambda: np.zeros(3))
    snap: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw: float = 0.0
    yaw_rate: float = 0.0
    yaw_acceleration: float = 0.0


def reference_from_values(values: Any) -> Reference:
    """A Reference from 18 numbers: position, velocity, acceleration, jerk, snap (NED), yaw, rate, accel."""
    a = np.asarray(values, dtype=float)
    return Reference(position=a[0:3], velocity=a[3:6], acceleration=a[6:9], jerk=a[9:12], snap=a[12:15],
                     yaw=float(a[15]), yaw_rate=float(a[16]), yaw_acceleration=float(a[17]))


@dataclass(frozen=True)
class Command:
    """A controller's output: the four motor speeds [rad/s, PX4 order], already within [0, w_max]."""

    rotor_speeds: np.ndarray
    saturated: bool = False          # True when any motor was clipped this step
    info: dict = field(default_factory=dict)  # e.g. phi_d, theta_d, f1..f4, for logs and plots


class Controller(Protocol):
    """A tracking controller. `dt` [s] is the control period; `reset()` clears integrators and filters."""

    name: str

    def reset(self) -> None:
        """Clear internal state (integrators, filters) before a new flight."""

    def update(self, t: float, state: VehicleState, reference: Reference) -> Command:
        """Return the motor speeds [rad/s] for the state and reference at time t [s]."""


class Trajectory(Protocol):
    """A reference trajectory: the desired flat outputs at time t [s]."""

    name: str

    def reference(self, t: float) -> Reference:
        """Return position NED [m], its derivatives, and yaw [rad] with derivatives at time t [s]."""


def as_floats(values: Any) -> list[float]:
    """A state or reference vector as plain Python floats (math on those is several times faster than on
    numpy scalars, which matters in a 4 ms loop)."""
    if isinstance(values, np.ndarray) and values.dtype.kind == "f":
        return values.tolist()
    return [float(v) for v in values]
