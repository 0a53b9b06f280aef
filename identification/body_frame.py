"""Known physics apart from unknown: the body-frame primitives, body-frame targets, and the exact composition.

Rotation and gravity are known, so they are not learned. With R = Rz(psi) Ry(theta) Rx(phi) (body FRD to
earth NED) and g the gravity (m/s^2, +z down):
  specific force f_b = R^T (a_NED - g e_z)      (FRD, m/s^2; targets fx, fy, fz)
  a_NED = R f_b + g e_z                          (composed exactly, as sympy expressions in the 16 variables)
The angular accelerations dwx, dwy, dwz are body-frame (FRD, rad/s^2) already.

Primitives (what the body-frame models are functions of), each with its unit as exponents of (m, s), rad
counting as dimensionless (PhySO-style unit vectors):
  ub, vb, wb   body velocity FRD = R^T v (m/s; the airspeed when there is no wind)
  wx, wy, wz   body rates FRD (rad/s)
  u1..u4       rotor speeds (rad/s)
  h            height above the ground = -z (m; > 0 when flying; for ground effect)
  phi, theta   roll, pitch (rad; not in the default set: with gravity removed the body-frame physics does
               not depend on attitude, so they only let closed-loop correlations in)
  gx, gy, gz   the gravity direction in the body frame, R^T e_z = (-sin(theta), sin(phi) cos(theta),
               cos(phi) cos(theta)) (FRD, dimensionless), known from the attitude like gravity itself; it is
               the ground plane's normal, so a body point r (FRD, m) is at height h - r . (gx, gy, gz): the
               discovery engine uses gx, gy only there, in how a height law changes across the airframe
               (identification.feature_space, "ground-plane gradient")
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy

from bridge.rotations import rotation_matrix
from identification.kinematics import rotation_matrix_sym
from identification.metrics import weak_metrics
from identification.model_file import (
    SYMBOLS,
    TARGET_NAMES,
    VARIABLE_NAMES,
    BodyModel,
    Model,
    TargetModel,
    expression_to_string,
)
from identification.rows_cache import cached

STANDARD_GRAVITY = 9.80665  # m/s^2, when the vehicle's is not known
BODY_FORCE_NAMES: tuple[str, ...] = ("fx", "fy", "fz")
BODY_TARGET_NAMES: tuple[str, ...] = ("fx", "fy", "fz", "dwx", "dwy", "dwz")

Unit = tuple[int, int]  # exponents of (m, s)


@dataclass(frozen=True)
class Primitive:
    """One body-frame primitive: name, unit exponents (m, s), its vector group, description."""

    name: str
    unit: Unit
    group: str  # primitives of one group with like units form a vector (for the norm operator)
    description: str
    angle: bool = False  # an angle in rad: sin/cos apply
    ground_normal: bool = False  # a component of the ground plane's normal in the body frame: enters only as
    # the gradient of a height law across the airframe (feature_space), not on its own
    positive: bool = False  # physically bounded away from zero: 1/x applies (height, not a velocity)
    summable: bool = False  # one scalar of a kind per member (rotor speeds): signed sums over the group;
    # not vector components (ub + vb mixes axes: no rotation-covariant law adds them)


PRIMITIVES: dict[str, Primitive] = {
    p.name: p
    for p in (
        Primitive("ub", (1, -1), "v_b", "body forward velocity FRD (m/s)"),
        Primitive("vb", (1, -1), "v_b", "body right velocity FRD (m/s)"),
        Primitive("wb", (1, -1), "v_b", "body down velocity FRD (m/s)"),
        Primitive("wx", (0, -1), "w_b", "body roll rate FRD (rad/s)"),
        Primitive("wy", (0, -1), "w_b", "body pitch rate FRD (rad/s)"),
        Primitive("wz", (0, -1), "w_b", "body yaw rate FRD (rad/s)"),
        Primitive("u1", (0, -1), "rotor", "rotor 1 speed (rad/s)", summable=True),
        Primitive("u2", (0, -1), "rotor", "rotor 2 speed (rad/s)", summable=True),
        Primitive("u3", (0, -1), "rotor", "rotor 3 speed (rad/s)", summable=True),
        Primitive("u4", (0, -1), "rotor", "rotor 4 speed (rad/s)", summable=True),
        Primitive("h", (1, 0), "height", "height above ground = -z (m)", positive=True),
        Primitive("phi", (0, 0), "attitude", "roll (rad)", angle=True),
        Primitive("theta", (0, 0), "attitude", "pitch (rad)", angle=True),
        Primitive("gx", (0, 0), "gravity", "gravity direction FRD x = -sin(theta) (1)", ground_normal=True),
        Primitive("gy", (0, 0), "gravity", "gravity direction FRD y = sin(phi) cos(theta) (1)",
                  ground_normal=True),
        Primitive("gz", (0, 0), "gravity", "gravity direction FRD z = cos(phi) cos(theta) (1)",
                  ground_normal=True),
    )
}

# the primitives as symbols of their own (body-frame expressions are written in these names)
PRIMITIVE_SYMBOLS: dict[str, sympy.Symbol] = {
    name: (SYMBOLS[name] if name in SYMBOLS else sympy.Symbol(name, real=True)) for name in PRIMITIVES
}


def primitive_definitions() -> dict[str, sympy.Expr]:
    """Each primitive as a sympy expression in the 16 variables (ub = (R^T v)_x, h = -z, ...)."""
    s = SYMBOLS
    rot = rotation_matrix_sym(s["phi"], s["theta"], s["psi"])
    vb = rot.T * sympy.Matrix([s["vx"], s["vy"], s["vz"]])
    down = rot.T * sympy.Matrix([0, 0, 1])  # R^T e_z
    out: dict[str, sympy.Expr] = {"ub": vb[0], "vb": vb[1], "wb": vb[2], "h": -s["z"],
                                  "gx": down[0], "gy": down[1], "gz": down[2]}
    for name in PRIMITIVES:
        if name not in out:
            out[name] = s[name]
    return out


def primitive_matrix(X: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """The primitives' values (N, len(names)) from X (N,16: the 12 states then u1..u4), in their units."""
    X = np.asarray(X, dtype=float)
    col = {n: i for i, n in enumerate(VARIABLE_NAMES)}
    rot = rotation_matrix(X[:, col["phi"]], X[:, col["theta"]], X[:, col["psi"]])
    vb = np.einsum("nji,nj->ni", rot, X[:, 3:6])  # R^T v
    down = rot[:, 2, :]  # row 3 of R: R^T e_z (the gravity direction FRD)
    derived = {"ub": vb[:, 0], "vb": vb[:, 1], "wb": vb[:, 2], "h": -X[:, col["z"]],
               "gx": down[:, 0], "gy": down[:, 1], "gz": down[:, 2]}
    return np.column_stack([derived[n] if n in derived else X[:, col[n]] for n in names])


_DERIVED = ("ub", "vb", "wb", "h", "gx", "gy", "gz")  # the primitives that are not among the 16 variables


@functools.lru_cache(maxsize=4096)
def _compiled(expr: sympy.Expr) -> Callable[..., Any]:
    """One expression lambdified over the 16 variables and the derived primitives (cached: candidates of
    one target share many terms)."""
    args = [SYMBOLS[n] for n in VARIABLE_NAMES] + [PRIMITIVE_SYMBOLS[n] for n in _DERIVED]
    return sympy.lambdify(args, expr, modules="numpy")


def expression_columns(exprs: Sequence[sympy.Expr], X: np.ndarray) -> np.ndarray:
    """Expressions in the 16 variables and/or the primitive names evaluated on X (N,16): (N, len(exprs)).

    Each expression's column is computed once per rows array (identification.rows_cache)."""
    X = np.asarray(X, dtype=float)
    values: list[np.ndarray] = []

    def column(e: sympy.Expr) -> np.ndarray:
        if not values:
            values.extend([*X.T, *cached(X, _DERIVED, lambda: primitive_matrix(X, _DERIVED)).T])
        with np.errstate(all="ignore"):
            return np.array(np.broadcast_to(np.asarray(_compiled(e)(*values), float), (len(X),)))

    return np.column_stack([cached(X, e, lambda e=e: column(e)) for e in exprs])


def to_variables(expr: sympy.Expr) -> sympy.Expr:
    """A body-frame expression in primitive names rewritten in the 16 variables."""
    defs = primitive_definitions()
    free = expr.free_symbols
    subs = {PRIMITIVE_SYMBOLS[n]: defs[n] for n in _DERIVED if PRIMITIVE_SYMBOLS[n] in free}
    return expr.xreplace(subs) if subs else expr


def body_targets(xi: np.ndarray, targets: np.ndarray, gravity: float) -> np.ndarray:
    """(N,6) fx fy fz (specific force FRD, m/s^2) and dwx dwy dwz (FRD, rad/s^2) from NED targets (N,6)."""
    xi = np.asarray(xi, dtype=float)
    targets = np.asarray(targets, dtype=float)
    rot = rotation_matrix(xi[:, 6], xi[:, 7], xi[:, 8])
    a = targets[:, 0:3].copy()
    a[:, 2] -= gravity
    out = np.empty_like(targets)
    out[:, 0:3] = np.einsum("nji,nj->ni", rot, a)
    out[:, 3:6] = targets[:, 3:6]
    return out


def composed_values(body: dict[str, np.ndarray], X: np.ndarray, names: Sequence[str], gravity: float
                    ) -> np.ndarray:
    """The targets `names` (N, len(names)) from the body targets' values (N,) each on rows X (N,16):
    ax ay az = R f_b + g e_z (m/s^2, NED), dwx dwy dwz as they are (rad/s^2, FRD); compose_ned in numbers."""
    X = np.asarray(X, dtype=float)
    out = np.empty((len(X), len(names)))
    forces = ("ax", "ay", "az")
    a = np.zeros((len(X), 3))
    if any(n in forces for n in names):
        f = np.column_stack([body[n] for n in BODY_FORCE_NAMES])
        with np.errstate(all="ignore"):
            a = np.einsum("nij,nj->ni", rotation_matrix(X[:, 6], X[:, 7], X[:, 8]), f)
        a[:, 2] += gravity
    for j, n in enumerate(names):
        out[:, j] = a[:, forces.index(n)] if n in forces else body[n]
    return out


def compose_ned(body: dict[str, sympy.Expr], gravity: float) -> dict[str, sympy.Expr]:
    """ax, ay, az (NED, m/s^2) = R f_b + g e_z from fx, fy, fz (in primitive names or the 16 variables)."""
    s = SYMBOLS
    rot = rotation_matrix_sym(s["phi"], s["theta"], s["psi"])
    f = [to_variables(body[n]) for n in BODY_FORCE_NAMES]
    out: dict[str, sympy.Expr] = {}
    for k, name in enumerate(("ax", "ay", "az")):
        terms = [rot[k, i] * f[i] for i in range(3) if f[i] != 0]
        expr = sympy.Add(*terms) if terms else sympy.Integer(0)
        if k == 2 and gravity != 0:
            expr = sympy.Float(float(gravity)) + expr
        out[name] = expr
    return out


def body_fit_names(targets: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """The body-frame targets to learn for the wanted model targets (any of ax, ay, az needs fx, fy, fz)."""
    need = set(BODY_FORCE_NAMES) if any(t in ("ax", "ay", "az") for t in targets) else set()
    need |= {t for t in targets if t in ("dwx", "dwy", "dwz")}
    return tuple(n for n in BODY_TARGET_NAMES if n in need)


def primitive_info(names: tuple[str, ...] | None = None) -> dict[str, dict[str, str]]:
    """The primitives for the model file: {name: {expression (16 variables), unit, frame, description}}."""
    defs = primitive_definitions()
    names = tuple(PRIMITIVES) if names is None else names
    out: dict[str, dict[str, str]] = {}
    for n in names:
        p = PRIMITIVES[n]
        unit = {(1, -1): "m/s", (0, -1): "rad/s", (1, 0): "m", (0, 0): "rad" if p.angle else "1"}[p.unit]
        frame = {"v_b": "FRD", "w_b": "FRD", "height": "NED (-z)", "attitude": "ZYX Euler",
                 "gravity": "FRD"}.get(p.group, "-")
        out[n] = {"expression": expression_to_string(defs[n]), "unit": unit, "frame": frame,
                  "description": p.description}
    return out


def composed_targets(
    body: BodyModel,
    wanted: tuple[str, ...] | list[str],
    splits: dict[str, tuple[np.ndarray, np.ndarray]],
    operators: dict[str, Any] | None = None,
    predictions: dict[str, dict[str, np.ndarray]] | None = None,
) -> dict[str, TargetModel]:
    """The wanted NED/FRD targets composed from the body model, with metrics per split on the NED data.

    splits: name (train, pick, validation) -> (X (N,16), Y (N,6) the NED targets ax ay az dwx dwy dwz).
    operators: name -> weak-form matrix V (M, N) (identification.weak_form): metrics on V Y and V f(X).
    predictions: body target -> split -> its values on the split's rows (N,) when already computed (identify's
    workers): the NED ones are composed from them (composed_values), the composed expressions not compiled.
    """
    exprs: dict[str, sympy.Expr] = {}
    bt = body.targets
    if all(n in bt for n in BODY_FORCE_NAMES):
        exprs.update(compose_ned({n: bt[n].expression for n in BODY_FORCE_NAMES}, body.gravity))
    for n in ("dwx", "dwy", "dwz"):
        if n in bt:
            exprs[n] = to_variables(bt[n].expression)
    exprs = {n: exprs[n] for n in TARGET_NAMES if n in wanted and n in exprs}
    model = Model(exprs)
    out: dict[str, TargetModel] = {}
    for split, (Xs, Ys) in splits.items():
        if len(Xs) == 0:
            continue
        parts = body_fit_names(model.target_names)
        if predictions is not None and all(split in predictions.get(b, {}) for b in parts):
            pred = composed_values({b: predictions[b][split] for b in parts}, Xs, model.target_names,
                                   body.gravity)
        else:
            pred = np.atleast_2d(model.evaluate(Xs[:, :12], Xs[:, 12:]))
        for j, n in enumerate(model.target_names):
            y = Ys[:, TARGET_NAMES.index(n)]
            op = (operators or {}).get(split)
            out.setdefault(n, TargetModel(n, exprs[n])).metrics[split] = weak_metrics(y, pred[:, j], op)
    for n, t in out.items():
        parts = [bt[b] for b in (BODY_FORCE_NAMES if n in ("ax", "ay", "az") else (n,))]
        t.engine = "+".join(sorted({p.engine for p in parts if p.engine})) or None
        t.wall_time_s = sum(p.wall_time_s or 0.0 for p in parts) if n not in ("ax", "ay", "az") else None
    return out
