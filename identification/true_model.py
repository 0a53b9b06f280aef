"""The SITL's exact equations of motion, as sympy expressions written from a vehicle file.

Every effect the vehicle file switches on (rotor geometry and CG, rotor drag, translational lift, frame drag,
ground effect: see airframe_expressions) is written exactly; wind is not (it is not one of the model's 16
variables), so the expressions are the SITL's in still air, and the model file says so.

Earth NED, body FRD, R = Rz(psi) Ry(theta) Rx(phi). With T = Ct f1, v_b = R^T v:
  a   = g e3 + R (0, 0, -T/m) + R (-Cd/m * v_b*|v_b|)                      (NED, m/s^2)
  J w' = -w x (J w) - w x (0, 0, h_z) + tau - D w                          (FRD, rad/s^2)
with h_z = Jm (-u1 - u2 + u3 + u4) (rotors 1, 2 CCW seen from above, so their momentum points up = -z),
tau = (k f2, k f3, Cm f4), k = sqrt(2)/2 d Ct. Euler's equations give wx' = (Jyy - Jzz)/Jxx wy wz + ...
(-0.697 wy wz for the default vehicle: the paper's +0.697 has the wrong sign).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import sympy

from bridge.vehicle import VehicleConfig, load_vehicle
from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.kinematics import rotation_matrix_sym
from identification.model_file import (
    SYMBOLS,
    TARGET_NAMES,
    Model,
    TargetModel,
    display_path,
    file_sha256,
    save_model,
)


def _f(value: float) -> sympy.Float:
    return sympy.Float(float(value))


def motor_combinations_sym(symbols: dict[str, sympy.Symbol] = SYMBOLS) -> dict[str, sympy.Expr]:
    """The paper's f1..f4 (squared rotor speeds, (rad/s)^2) and the rotor-momentum sum g = -u1-u2+u3+u4."""
    u1, u2, u3, u4 = (symbols[n] for n in ("u1", "u2", "u3", "u4"))
    return {
        "f1": u1**2 + u2**2 + u3**2 + u4**2,
        "f2": -(u1**2) + u2**2 + u3**2 - u4**2,
        "f3": u1**2 - u2**2 + u3**2 - u4**2,
        "f4": u1**2 + u2**2 - u3**2 - u4**2,
        "g": -u1 - u2 + u3 + u4,
    }


def body_drag_terms_sym(symbols: dict[str, sympy.Symbol] = SYMBOLS) -> sympy.Matrix:
    """3x3 D[k, i] = R[k, i] v_b,i |v_b,i|: body axis i's quadratic drag seen on NED axis k (m^2/s^2)."""
    s = symbols
    rot = rotation_matrix_sym(s["phi"], s["theta"], s["psi"])
    v = sympy.Matrix([s["vx"], s["vy"], s["vz"]])
    vb = rot.T * v
    return sympy.Matrix(3, 3, lambda k, i: rot[k, i] * vb[i] * sympy.Abs(vb[i]))


def _inertia(vehicle: VehicleConfig) -> np.ndarray:
    j = np.asarray(vehicle.inertia, dtype=float)
    return np.diag(j) if j.shape == (3,) else j


def true_model_expressions(vehicle: VehicleConfig | str | os.PathLike[str]) -> dict[str, sympy.Expr]:
    """The six targets (ax, ay, az NED m/s^2; dwx, dwy, dwz FRD rad/s^2) exactly as the SITL computes them.

    Wind is left out (it is not one of the model's 16 variables): the expressions are exact in still air.
    """
    if not isinstance(vehicle, VehicleConfig):
        vehicle = load_vehicle(vehicle)
    if vehicle.rotors or any(vehicle.center_of_gravity) or vehicle.aero.active:
        return airframe_expressions(vehicle)
    s = SYMBOLS
    m, g = vehicle.mass, vehicle.gravity
    ct, cm = vehicle.thrust_coefficient, vehicle.moment_coefficient
    k = np.sqrt(2.0) / 2.0 * vehicle.arm_length * ct
    cd = np.broadcast_to(np.asarray(vehicle.drag.body_quadratic, dtype=float), (3,))
    damping = np.broadcast_to(np.asarray(vehicle.drag.angular_damping, dtype=float), (3,))
    jm = vehicle.motor.rotor_inertia
    comb = motor_combinations_sym(s)
    rot = rotation_matrix_sym(s["phi"], s["theta"], s["psi"])
    drag = body_drag_terms_sym(s)

    out: dict[str, sympy.Expr] = {}
    for axis, name in enumerate(("ax", "ay", "az")):
        expr = _f(-ct / m) * comb["f1"] * rot[axis, 2]
        if axis == 2 and g != 0:
            expr = _f(g) + expr
        for i in range(3):
            if cd[i] != 0:
                expr = expr + _f(-cd[i] / m) * drag[axis, i]
        out[name] = expr

    inertia = _inertia(vehicle)
    jinv = np.linalg.inv(inertia)
    w = [s["wx"], s["wy"], s["wz"]]
    # Each body-frame torque is a sum of (coefficient vector) x (term); J^-1 maps the coefficient vector.
    torque_terms: list[tuple[np.ndarray, sympy.Expr]] = []
    # -w x (J w): component a = -(w_b (Jw)_c - w_c (Jw)_b) for (a, b, c) cyclic, expanded in w_i w_j.
    for i in range(3):
        for j in range(i, 3):
            coef = np.zeros(3)
            for a, b, c in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
                # (Jw)_c = sum_l J[c, l] w_l; the product w_b w_l contributes when {b, l} == {i, j}
                for bb, cc, sign in ((b, c, -1.0), (c, b, 1.0)):
                    for l_ in range(3):
                        if sorted((bb, l_)) == [i, j]:
                            coef[a] += sign * inertia[cc, l_]
            if np.any(coef != 0):
                torque_terms.append((coef, w[i] * w[j]))
    if jm != 0:
        # -w x (0, 0, h) = (-wy h, wx h, 0)
        torque_terms.append((np.array([-jm, 0.0, 0.0]), w[1] * comb["g"]))
        torque_terms.append((np.array([0.0, jm, 0.0]), w[0] * comb["g"]))
    torque_terms.append((np.array([k, 0.0, 0.0]), comb["f2"]))
    torque_terms.append((np.array([0.0, k, 0.0]), comb["f3"]))
    torque_terms.append((np.array([0.0, 0.0, cm]), comb["f4"]))
    for i in range(3):
        if damping[i] != 0:
            coef = np.zeros(3)
            coef[i] = -damping[i]
            torque_terms.append((coef, w[i]))
    for axis, name in enumerate(("dwx", "dwy", "dwz")):
        expr = sympy.Integer(0)
        for coef, term in torque_terms:
            c = float(jinv[axis] @ coef)
            if c != 0.0:
                expr = expr + _f(c) * term
        out[name] = expr
    return {name: out[name] for name in TARGET_NAMES}


def _at_least(h: sympy.Expr, floor: float) -> sympy.Expr:
    """max(h, floor) with Abs, the building block the model file allows: (h + floor + |h - floor|) / 2."""
    return (h + _f(floor) + sympy.Abs(h - _f(floor))) / 2


def airframe_expressions(vehicle: VehicleConfig) -> dict[str, sympy.Expr]:
    """The six targets of a vehicle with its own rotor geometry and effects (as sitl.airframe_dynamics).

    Still air: v_a = R^T v (m/s FRD); each hub's airspeed v_i = v_a + w x r_i; thrust
    T_i = GE(h_i) (Ct_i u_i^2 + k_h (v_ix^2 + v_iy^2)) with GE = 1/(1 - (R/(4 max(h_i, h_min)))^2),
    h_i = -(z + (R r_i)_z) (with a ground plane only); rotor force (0, 0, -T_i) - u_i diag(k_d, k_d, k_z) v_i
    at r_i; frame drag
    -(|v_a| C + diag(Cd |v_a,j|)) v_a; yaw torque -s_i Cm_i u_i^2; h_z = Jm sum s_i u_i.
    """
    s = SYMBOLS
    rot = rotation_matrix_sym(s["phi"], s["theta"], s["psi"])
    ua = rot.T * sympy.Matrix([s["vx"], s["vy"], s["vz"]])
    force, dw = _airframe_wrench(vehicle, ua, lambda r: -(s["z"] + (rot * r)[2]))
    accel = sympy.Matrix([0, 0, _f(vehicle.gravity)]) + rot * force / _f(vehicle.mass)
    return dict(zip(TARGET_NAMES, [*accel, *dw], strict=True))


def true_body_expressions(vehicle: VehicleConfig | str | os.PathLike[str]) -> dict[str, sympy.Expr]:
    """The SITL's equations in the body frame, in the primitive names of identification.body_frame.

    fx fy fz: specific force FRD (m/s^2) = the aerodynamic and rotor force / m (gravity excluded);
    dwx dwy dwz: FRD (rad/s^2). Variables: ub vb wb (body airspeed FRD, m/s, still air), wx wy wz (rad/s),
    u1..u4 (rad/s), h = -z (m) and, only where a hub's height depends on the attitude (ground effect),
    phi and theta (rad). Any vehicle (the paper's closed form is the same physics); wind excluded.
    """
    P = PRIMITIVE_SYMBOLS
    if not isinstance(vehicle, VehicleConfig):
        vehicle = load_vehicle(vehicle)
    row = rotation_matrix_sym(P["phi"], P["theta"], sympy.Integer(0))[2, :]  # (R r)_z needs no yaw
    ua = sympy.Matrix([P["ub"], P["vb"], P["wb"]])
    force, dw = _airframe_wrench(vehicle, ua, lambda r: P["h"] - (row * r)[0])
    fb = force / _f(vehicle.mass)
    return dict(zip(("fx", "fy", "fz", "dwx", "dwy", "dwz"), [*fb, *dw], strict=True))


def _airframe_wrench(
    vehicle: VehicleConfig, ua: sympy.Matrix, hub_height: Callable[[sympy.Matrix], sympy.Expr]
) -> tuple[sympy.Matrix, sympy.Matrix]:
    """(force FRD N, angular acceleration FRD rad/s^2) of the airframe at body airspeed ua (m/s FRD);
    hub_height(r) is the height (m) of the hub at r (FRD m from the CG)."""
    s = SYMBOLS
    w = sympy.Matrix([s["wx"], s["wy"], s["wz"]])
    aero = vehicle.aero
    force = sympy.zeros(3, 1)
    moment = sympy.zeros(3, 1)
    hz = sympy.Integer(0)
    ground = aero.ground_effect if vehicle.ground == "plane" else None
    for i, (rotor, arm) in enumerate(zip(vehicle.rotor_set, vehicle.rotor_arms, strict=True)):
        u = s[f"u{i + 1}"]
        r = sympy.Matrix([_f(c) for c in arm])
        vi = ua + w.cross(r)
        thrust = _f(rotor.thrust_coefficient) * u**2
        if aero.translational_lift:
            thrust = thrust + _f(aero.translational_lift) * (vi[0] ** 2 + vi[1] ** 2)
        if ground is not None:
            h = _at_least(hub_height(r), ground.min_height)
            thrust = thrust / (1 - _f((ground.rotor_radius / 4.0) ** 2) / h**2)
        f_i = sympy.Matrix([0, 0, -thrust])
        if aero.rotor_drag is not None:
            kd, kz = _f(aero.rotor_drag.k_d), _f(aero.rotor_drag.k_z)
            f_i = f_i - u * sympy.Matrix([kd * vi[0], kd * vi[1], kz * vi[2]])
        force += f_i
        moment += r.cross(f_i)
        moment[2] += _f(-rotor.spin_z * rotor.moment_coefficient) * u**2
        hz += _f(rotor.spin_z * vehicle.motor.rotor_inertia) * u
    speed = sympy.sqrt(ua[0] ** 2 + ua[1] ** 2 + ua[2] ** 2)
    for j in range(3):
        c, cd = aero.frame_drag[j], vehicle.drag.body_quadratic[j]
        if c or cd:
            force[j] += -(_f(c) * speed + _f(cd) * sympy.Abs(ua[j])) * ua[j]
    inertia = _inertia(vehicle)
    jmat = sympy.Matrix(3, 3, lambda a, b: _f(inertia[a, b]))
    jinv = sympy.Matrix(3, 3, lambda a, b: _f(np.linalg.inv(inertia)[a, b]))
    damping = sympy.Matrix([_f(d) for d in vehicle.drag.angular_damping])
    torque = moment - w.cross(jmat * w + sympy.Matrix([0, 0, hz])) - damping.multiply_elementwise(w)
    return force, jinv * torque


def vehicle_provenance(vehicle: VehicleConfig) -> dict[str, Any]:
    """{name, file, sha256} of the vehicle a model was written from or flown with."""
    info: dict[str, Any] = {"name": vehicle.name}
    if vehicle.source_path is not None:
        info["file"] = display_path(vehicle.source_path)
        try:
            info["sha256"] = file_sha256(vehicle.source_path)
        except OSError:
            info["sha256"] = None
    return info


def true_model(vehicle: VehicleConfig | str | os.PathLike[str]) -> Model:
    """The SITL's exact equations as a Model (kind: true-model)."""
    if not isinstance(vehicle, VehicleConfig):
        vehicle = load_vehicle(vehicle)
    exprs = true_model_expressions(vehicle)
    targets = {name: TargetModel(name=name, expression=e, engine="vehicle") for name, e in exprs.items()}
    return Model(
        targets,
        kind="true-model",
        vehicle=vehicle_provenance(vehicle),
        flights=[],
        engine={"name": "vehicle", "settings": {
            "source": "bridge.vehicle parameters, sitl dynamics",
            "wind": "excluded: not one of the model's 16 variables; the expressions are exact in still air",
        }},
    )


def write_true_model(vehicle: VehicleConfig | str | os.PathLike[str], path: str | os.PathLike[str]) -> Path:
    """Write the vehicle's exact equations as a model file (kind: true-model); returns the path."""
    return save_model(true_model(vehicle), path)


def random_states(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n random states xi (n,12) and rotor speeds u (n,4) over the paper's envelope, for synthetic tests.

    Angles: roll, pitch in (-1, 1) rad, yaw in (-3, 3) rad; velocities NED +-10 m/s; rates FRD +-5 rad/s;
    rotor speeds 0..1000 rad/s; positions +-50 m.
    """
    rng = np.random.default_rng(seed)
    xi = np.empty((n, 12))
    xi[:, 0:3] = rng.uniform(-50.0, 50.0, (n, 3))
    xi[:, 3:6] = rng.uniform(-10.0, 10.0, (n, 3))
    xi[:, 6] = rng.uniform(-1.0, 1.0, n)
    xi[:, 7] = rng.uniform(-1.0, 1.0, n)
    xi[:, 8] = rng.uniform(-3.0, 3.0, n)
    xi[:, 9:12] = rng.uniform(-5.0, 5.0, (n, 3))
    u = rng.uniform(0.0, 1000.0, (n, 4))
    return xi, u
