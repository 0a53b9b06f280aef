"""Written-down body-frame physics with effects beyond the SITL's, for tests and the discovery benchmark.

The vehicle's equations (identification.true_model) in the body frame, in the primitive names of
identification.body_frame, plus effects each switched on by a nonzero parameter:
  thrust of rotor i     T_i/m = Ct/m a_i u_i^2 (1 + ground_effect / h^2) GE(h) + linear_thrust u_i   (m/s^2)
                        GE(h) = 1 / (1 - (ground_effect_radius / (4 h))^2), the Cheeseman-Bennett law at the
                        CG's height (no monomial of the primitives; 1 when ground_effect_radius is 0)
                        a_i = rotor_scale[i] (a weak rotor: a_i < 1)
  specific force FRD    f_b = (0, 0, -sum T_i/m) - Cd/m v_b,k |v_b,k| - rotor_drag sum(u_i) (ub, vb, 0)
                              - frame_drag |v_b| v_b                                            (m/s^2)
  angular accel FRD     J w' = -w x J w - w x (0, 0, Jm (-u1 - u2 + u3 + u4)) + tau - D w     (rad/s^2)
                        tau = (k' (-T1 + T2 + T3 - T4), k' (T1 - T2 + T3 - T4), Cm/Ct (T1 + T2 - T3 - T4)) m,
                        k' = sqrt(2)/2 d: every torque follows the rotors' actual thrusts
With every effect off this is exactly the SITL's model. The NED targets are a = R f_b + g e_z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy

from bridge.rotations import rotation_matrix
from bridge.vehicle import VehicleConfig, load_vehicle
from identification.body_frame import PRIMITIVE_SYMBOLS, primitive_matrix
from identification.true_model import random_states


@dataclass(frozen=True)
class Effects:
    """Effects added to a vehicle's equations (all off by default); units in the module docstring."""

    rotor_drag: float = 0.0  # 1/rad: f_b,xy = -rotor_drag * sum(u_i) * (ub, vb)
    rotor_scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)  # per-rotor thrust factor
    ground_effect: float = 0.0  # m^2: thrust x (1 + ground_effect / h^2)
    ground_effect_radius: float = 0.0  # m, rotor radius R: thrust x 1 / (1 - (R / (4 h))^2)
    frame_drag: float = 0.0  # 1/m: f_b = -frame_drag |v_b| v_b
    linear_thrust: float = 0.0  # m/(s rad): T_i/m += linear_thrust u_i
    quadratic_thrust: bool = True  # False: the thrust is linear in u alone (the u_i^2 part off)


def _vehicle(vehicle: VehicleConfig | str) -> VehicleConfig:
    return vehicle if isinstance(vehicle, VehicleConfig) else load_vehicle(vehicle)


def body_expressions(vehicle: VehicleConfig | str, effects: Effects = Effects()) -> dict[str, sympy.Expr]:
    """fx fy fz (m/s^2) and dwx dwy dwz (rad/s^2), FRD, as sympy expressions in the primitive names."""
    v = _vehicle(vehicle)
    p = PRIMITIVE_SYMBOLS
    u = [p[f"u{i}"] for i in range(1, 5)]
    ub, vb, wb, h = p["ub"], p["vb"], p["wb"], p["h"]
    m, ct, cm = v.mass, v.thrust_coefficient, v.moment_coefficient
    F = sympy.Float
    ground = 1 + F(effects.ground_effect) / h**2 if effects.ground_effect else 1
    if effects.ground_effect_radius:
        ground = ground / (1 - F((effects.ground_effect_radius / 4.0) ** 2) / h**2)
    quad = 1.0 if effects.quadratic_thrust else 0.0
    # T_i / m (m/s^2), kept as sums of monomials
    thrust = [
        sympy.expand(F(quad * ct / m * a) * ui**2 * ground + F(effects.linear_thrust) * ui)
        for a, ui in zip(effects.rotor_scale, u, strict=True)
    ]
    cd = np.broadcast_to(np.asarray(v.drag.body_quadratic, float), (3,))
    vel = (ub, vb, wb)
    f = [-F(cd[k] / m) * vel[k] * sympy.Abs(vel[k]) if cd[k] else sympy.Integer(0) for k in range(3)]
    f[2] = f[2] - sympy.Add(*thrust)
    if effects.rotor_drag:
        f[0] = f[0] - F(effects.rotor_drag) * sympy.Add(*[ui * ub for ui in u])
        f[1] = f[1] - F(effects.rotor_drag) * sympy.Add(*[ui * vb for ui in u])
    if effects.frame_drag:
        speed = sympy.sqrt(ub**2 + vb**2 + wb**2)
        f = [f[k] - F(effects.frame_drag) * vel[k] * speed for k in range(3)]
    inertia = np.asarray(v.inertia, float)
    inertia = np.diag(inertia) if inertia.shape == (3,) else inertia
    w = sympy.Matrix([p["wx"], p["wy"], p["wz"]])
    J = sympy.Matrix(3, 3, lambda i, j: F(inertia[i, j]))
    arm = np.sqrt(2.0) / 2.0 * v.arm_length
    T1, T2, T3, T4 = (t * F(m) for t in thrust)  # N
    tau = sympy.Matrix(
        [F(arm) * (-T1 + T2 + T3 - T4), F(arm) * (T1 - T2 + T3 - T4), F(cm / ct) * (T1 + T2 - T3 - T4)]
    )
    rotor_momentum = F(v.motor.rotor_inertia) * (-u[0] - u[1] + u[2] + u[3])
    damping = np.broadcast_to(np.asarray(v.drag.angular_damping, float), (3,))
    torque = -w.cross(J * w) - w.cross(sympy.Matrix([0, 0, rotor_momentum])) + tau
    torque -= sympy.Matrix([F(damping[i]) * w[i] for i in range(3)])
    dw = J.inv() * torque
    out = {"fx": f[0], "fy": f[1], "fz": f[2]}
    for k, name in enumerate(("dwx", "dwy", "dwz")):
        out[name] = sympy.expand(dw[k])
    return {n: sympy.expand(e) if n in ("fx", "fy", "fz") else e for n, e in out.items()}


def flight_rows(
    n: int,
    seed: int,
    vehicle: VehicleConfig | str = "fang-chen-buaa",
    effects: Effects = Effects(),
    height: tuple[float, float] = (0.3, 3.0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n random rows: xi (n,12), u (n,4), NED targets (n,6) = ax ay az dwx dwy dwz from the written physics.

    States as identification.true_model.random_states, but the height h = -z drawn in `height` (m, > 0).
    """
    v = _vehicle(vehicle)
    xi, u = random_states(n, seed)
    xi[:, 2] = -np.random.default_rng(seed + 7).uniform(height[0], height[1], n)
    body = body_expressions(v, effects)
    names = ("ub", "vb", "wb", "wx", "wy", "wz", "u1", "u2", "u3", "u4", "h")
    P = primitive_matrix(np.hstack([xi, u]), names)
    fn = sympy.lambdify([PRIMITIVE_SYMBOLS[k] for k in names], list(body.values()), modules="numpy")
    cols = fn(*[P[:, k] for k in range(P.shape[1])])
    Y = np.column_stack([np.broadcast_to(np.asarray(c, float), (n,)) for c in cols])
    rot = rotation_matrix(xi[:, 6], xi[:, 7], xi[:, 8])
    targets = np.empty((n, 6))
    targets[:, 0:3] = np.einsum("nij,nj->ni", rot, Y[:, 0:3])
    targets[:, 2] += v.gravity
    targets[:, 3:6] = Y[:, 3:6]
    return xi, u, targets
