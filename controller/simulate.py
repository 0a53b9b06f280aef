"""In-process closed-loop simulation for tests and fast tuning (no MAVLink, no processes).

The plant integrates a model's own expressions (ax, ay, az NED; dwx, dwy, dwz FRD) with the Euler kinematics
(phi', theta', psi') = W(phi, theta) w, an optional first-order motor lag (the vehicle's Tm) and the SITL's
ground plane (rest at z = 0, level, until the thrust lifts the vehicle), by fixed-step RK4. Any other plant
with `reset()`, `step(commanded_speeds)` (one control period) and `observe() -> VehicleState` works too
(tests use `sitl.dynamics.Quadrotor` through a small adapter; this package never imports sitl).

The controller runs at 250 Hz (dt = 4 ms) with a zero-order hold, as over the HIL link.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import sympy

from bridge.integration import lag_path, rk4_step
from controller.derivation import normalise
from controller.plugin import Controller, Trajectory, VehicleState
from identification.model_file import INPUT_NAMES, STATE_NAMES, SYMBOLS, TARGET_NAMES

CONTROL_DT = 0.004  # s, 250 Hz as the HIL exchange step


class Plant(Protocol):
    """Something the controller can fly: one `step` is one control period."""

    def reset(self) -> None:
        """Back to the initial state."""

    def step(self, commanded_speeds: np.ndarray) -> None:
        """Advance one control period holding the commanded rotor speeds [rad/s]."""

    def observe(self) -> VehicleState:
        """The current true state (NED/FRD) and rotor speeds."""


class ModelPlant:
    """A quadrotor whose accelerations are a model's expressions, integrated by RK4 (xi + rotor speeds)."""

    def __init__(self, model: Any, motor_time_constant: float = 0.0, ground: bool = True,
                 physics_step: float = CONTROL_DT, dt: float = CONTROL_DT,
                 initial_position: tuple[float, float, float] = (0.0, 0.0, 0.0), initial_yaw: float = 0.0):
        exprs: Mapping[str, sympy.Expr] = model.expressions if hasattr(model, "expressions") else model
        exprs = normalise(exprs)
        args = [SYMBOLS[n] for n in STATE_NAMES + INPUT_NAMES]
        self._acc = sympy.lambdify(args, [exprs[n] for n in TARGET_NAMES], modules="math", cse=True)
        self.tm = float(motor_time_constant)
        self.ground = ground
        self.dt = dt
        self.substeps = max(1, int(round(dt / physics_step)))
        self.initial_position = tuple(float(v) for v in initial_position)
        self.initial_yaw = float(initial_yaw)
        self.reset()

    def reset(self) -> None:
        """At rest at the initial position and yaw, motors stopped."""
        s = [0.0] * 16
        s[0:3] = self.initial_position
        s[8] = self.initial_yaw
        self._s = s
        self._cmd = [0.0] * 4
        self.on_ground = False
        self._apply_ground()

    def set_state(self, xi: list[float] | np.ndarray, rotor_speeds: list[float] | np.ndarray) -> None:
        """Put the plant at state xi (12) with rotor speeds (4) [rad/s]."""
        self._s = [float(v) for v in xi] + [float(v) for v in rotor_speeds]
        self._cmd = [float(v) for v in rotor_speeds]

    def _deriv(self, s: list[float], cmd: list[float]) -> list[float]:
        x, y, z, vx, vy, vz, phi, theta, psi, wx, wy, wz, u1, u2, u3, u4 = s
        ax, ay, az, dwx, dwy, dwz = self._acc(*s)
        sf, cf, ct, tt = math.sin(phi), math.cos(phi), math.cos(theta), math.tan(theta)
        dphi = wx + (sf * wy + cf * wz) * tt
        dtheta = cf * wy - sf * wz
        dpsi = (sf * wy + cf * wz) / ct
        if self.tm > 0.0:
            du = [(cmd[i] - s[12 + i]) / self.tm for i in range(4)]
        else:
            du = [0.0] * 4
        return [vx, vy, vz, ax, ay, az, dphi, dtheta, dpsi, dwx, dwy, dwz, *du]

    def step(self, commanded_speeds: np.ndarray | list[float]) -> None:
        """Advance one control period [s] holding the commanded speeds [rad/s] (instant if no motor lag)."""
        cmd = [float(v) for v in commanded_speeds]
        self._cmd = cmd
        if self.tm <= 0.0:
            self._s[12:16] = cmd
        h = self.dt / self.substeps
        # the motor lag from its closed form over each substep, as the SITL takes it (sitl.dynamics)
        lag_half = math.exp(-0.5 * h / self.tm) if self.tm > 0.0 else 0.0
        for _ in range(self.substeps):
            known = lag_path(self._s[12:16], cmd, lag_half) if self.tm > 0.0 else None
            self._s = rk4_step(self._deriv, self._s, cmd, h, None, known)
            self._apply_ground()

    def _apply_ground(self) -> None:
        s = self._s
        self.on_ground = False
        if self.ground and s[2] >= 0.0 and s[5] >= 0.0:
            s[2] = 0.0
            s[3] = s[4] = s[5] = 0.0
            s[6] = s[7] = 0.0
            s[9] = s[10] = s[11] = 0.0
            self.on_ground = True

    def observe(self) -> VehicleState:
        """The true state xi (12) and rotor speeds (4)."""
        return VehicleState(xi=np.array(self._s[:12]), rotor_speeds=np.array(self._s[12:16]))


@dataclass
class SimResult:
    """A simulated flight sampled at each control step (SI, NED/FRD)."""

    t: np.ndarray  # (N,) s
    xi: np.ndarray  # (N, 12)
    rotor_speeds: np.ndarray  # (N, 4) rad/s, actual
    commands: np.ndarray  # (N, 4) rad/s, commanded
    ref_position: np.ndarray  # (N, 3) m
    ref_yaw: np.ndarray  # (N,) rad
    saturated: np.ndarray  # (N,) bool
    step_time: np.ndarray  # (N,) s, wall time of each controller update
    infos: list[dict]

    @property
    def error(self) -> np.ndarray:
        """3-D position error [m] at each step."""
        return np.linalg.norm(self.ref_position - self.xi[:, :3], axis=1)

    def rms_after(self, t0: float = 5.0) -> float:
        """RMS of the 3-D position error [m] for t >= t0 [s]."""
        e = self.error[self.t >= t0]
        return float(np.sqrt(np.mean(e**2))) if e.size else math.nan

    def max_error_after(self, t0: float) -> float:
        """Largest 3-D position error [m] for t >= t0 [s]."""
        e = self.error[self.t >= t0]
        return float(np.max(e)) if e.size else math.nan

    @property
    def max_tilt_deg(self) -> float:
        """Largest tilt [deg] of the flight."""
        c = np.cos(self.xi[:, 6]) * np.cos(self.xi[:, 7])
        return float(np.degrees(np.arccos(np.clip(c, -1, 1))).max())


def simulate(controller: Controller, trajectory: Trajectory, plant: Plant, duration: float,
             dt: float = CONTROL_DT, keep_info: bool = False) -> SimResult:
    """Fly `trajectory` for `duration` [s] with `controller` on `plant` at 1/dt Hz; samples of each step."""
    plant.reset()
    controller.reset()
    n = int(round(duration / dt)) + 1
    ts = np.arange(n) * dt
    xi = np.empty((n, 12))
    speeds = np.empty((n, 4))
    cmds = np.empty((n, 4))
    refp = np.empty((n, 3))
    refy = np.empty(n)
    sat = np.zeros(n, dtype=bool)
    wall = np.empty(n)
    infos: list[dict] = []
    for k in range(n):
        t = float(ts[k])
        state = plant.observe()
        ref = trajectory.reference(t)
        t0 = time.perf_counter()
        cmd = controller.update(t, state, ref)
        wall[k] = time.perf_counter() - t0
        xi[k] = state.xi
        speeds[k] = state.rotor_speeds
        cmds[k] = cmd.rotor_speeds
        refp[k] = ref.position
        refy[k] = ref.yaw
        sat[k] = cmd.saturated
        if keep_info:
            infos.append(cmd.info)
        if not np.all(np.isfinite(state.xi)):
            break
        plant.step(cmd.rotor_speeds)
    return SimResult(ts[: k + 1], xi[: k + 1], speeds[: k + 1], cmds[: k + 1], refp[: k + 1], refy[: k + 1],
                     sat[: k + 1], wall[: k + 1], infos)
