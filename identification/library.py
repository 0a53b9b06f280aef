"""The sparse engine's candidate-term library, built from the paper's blocks (constants, + - x /, sin, cos).

Each feature is a sympy expression in the 12 states and 4 rotor speeds; the numeric feature matrix is made by
lambdifying exactly those expressions, so a fitted sum of coefficient x feature is the expression written to
the model file. Groups:
- const: 1
- motor: the paper's f1..f4 (its basis of the squared speeds)
- thrust: f1 x every product of (1, sin, cos) of phi, theta and psi (the rotation-matrix thrust terms)
- gyro: the rotor-momentum sum (-u1-u2+u3+u4) x each body rate
- rates: wx, wy, wz and their pairwise products and squares
- velocity: vx, vy, vz and v|v| per NED axis
- body_drag: R[k,i] v_b,i |v_b,i| (body axis i's quadratic drag seen on NED axis k; abs: the one extra block)
- position: x, y, z (off by default, see DEFAULT_GROUPS)
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import sympy

from identification.kinematics import rotation_matrix_sym
from identification.model_file import SYMBOLS, VARIABLE_NAMES
from identification.true_model import body_drag_terms_sym, motor_combinations_sym

GROUPS: tuple[str, ...] = ("const", "motor", "thrust", "gyro", "rates", "velocity", "body_drag", "position")
# Position is left out by default: the equations of motion are the same wherever the vehicle is (no ground
# effect), and in a narrow closed-loop flight position terms only fit the targets' differentiation errors.
DEFAULT_GROUPS: tuple[str, ...] = tuple(g for g in GROUPS if g != "position")


@dataclass(frozen=True)
class Feature:
    """One candidate term: a display name, its sympy expression and the group it belongs to."""

    name: str
    expression: sympy.Expr
    group: str


def _trig_monomials() -> list[tuple[str, sympy.Expr]]:
    """Every product of (1, sin, cos) of phi, theta, psi (27 including 1)."""
    out = []
    per_angle = []
    for angle in ("phi", "theta", "psi"):
        a = SYMBOLS[angle]
        per_angle.append(
            [("", sympy.Integer(1)), (f"sin({angle})", sympy.sin(a)), (f"cos({angle})", sympy.cos(a))]
        )
    for combo in itertools.product(*per_angle):
        names = [n for n, _ in combo if n]
        expr = sympy.Mul(*[e for _, e in combo])
        out.append(("*".join(names), expr))
    return out


def build_library(groups: Sequence[str] = DEFAULT_GROUPS) -> list[Feature]:
    """The candidate terms of the chosen groups, in a fixed order."""
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        raise ValueError(f"unknown library groups {unknown} (known: {', '.join(GROUPS)})")
    s = SYMBOLS
    comb = motor_combinations_sym(s)
    feats: list[Feature] = []
    if "const" in groups:
        feats.append(Feature("1", sympy.Integer(1), "const"))
    if "motor" in groups:
        feats += [Feature(n, comb[n], "motor") for n in ("f1", "f2", "f3", "f4")]
    if "thrust" in groups:
        for name, trig in _trig_monomials():
            if name:  # f1 alone is in the motor group
                feats.append(Feature(f"f1*{name}", comb["f1"] * trig, "thrust"))
    if "gyro" in groups:
        feats += [Feature(f"g*{w}", comb["g"] * s[w], "gyro") for w in ("wx", "wy", "wz")]
    if "rates" in groups:
        rates = ("wx", "wy", "wz")
        feats += [Feature(w, s[w], "rates") for w in rates]
        for a, b in itertools.combinations_with_replacement(rates, 2):
            feats.append(Feature(f"{a}*{b}", s[a] * s[b], "rates"))
    if "velocity" in groups:
        vs = ("vx", "vy", "vz")
        feats += [Feature(v, s[v], "velocity") for v in vs]
        feats += [Feature(f"{v}*|{v}|", s[v] * sympy.Abs(s[v]), "velocity") for v in vs]
    if "body_drag" in groups:
        drag = body_drag_terms_sym(s)
        for k, i in itertools.product(range(3), range(3)):
            feats.append(Feature(f"D{'xyz'[k]}{'xyz'[i]}", drag[k, i], "body_drag"))
    if "position" in groups:
        feats += [Feature(p, s[p], "position") for p in ("x", "y", "z")]
    return feats


def compile_features(features: Sequence[Feature]) -> Callable[[np.ndarray], np.ndarray]:
    """A fast function X (N,16: the 12 states then u1..u4) -> (N, n_features), lambdified once."""
    args = [SYMBOLS[name] for name in VARIABLE_NAMES]
    fn = sympy.lambdify(args, [f.expression for f in features], modules="numpy", cse=True)

    def matrix(X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=float)
        n = X.shape[0]
        with np.errstate(all="ignore"):
            cols = fn(*[X[:, i] for i in range(X.shape[1])])
        out = np.empty((n, len(features)))
        for j, col in enumerate(cols):
            out[:, j] = np.broadcast_to(np.asarray(col, dtype=float), (n,))
        return out

    return matrix


def feature_matrix(features: Sequence[Feature], X: np.ndarray) -> np.ndarray:
    """Evaluate the features on X (N,16: the 12 states then u1..u4) -> (N, n_features)."""
    return compile_features(features)(X)


def engineered_inputs() -> dict[str, sympy.Expr]:
    """Extra inputs for the genetic-programming engines (name -> expression in the 16 variables).

    The paper's f1..f4, the rotor-momentum sum g, and the thrust direction R e3 in NED (thrust_x, thrust_y,
    cphi_ctheta = cos(phi)cos(theta)): giving these mattered more than the choice of engine.
    """
    comb = motor_combinations_sym(SYMBOLS)
    s = SYMBOLS
    rot = rotation_matrix_sym(s["phi"], s["theta"], s["psi"])
    return {
        "f1": comb["f1"],
        "f2": comb["f2"],
        "f3": comb["f3"],
        "f4": comb["f4"],
        "g": comb["g"],
        "thrust_x": rot[0, 2],
        "thrust_y": rot[1, 2],
        "cphi_ctheta": rot[2, 2],
    }


def input_matrix(
    X: np.ndarray, engineered: bool = True
) -> tuple[np.ndarray, list[str], dict[str, sympy.Expr]]:
    """The genetic-programming input table: the 16 variables (+ the engineered inputs) and their names."""
    X = np.asarray(X, dtype=float)
    names = list(VARIABLE_NAMES)
    if not engineered:
        return X, names, {}
    extra = engineered_inputs()
    feats = [Feature(name, expr, "engineered") for name, expr in extra.items()]
    return np.hstack([X, feature_matrix(feats, X)]), names + list(extra), extra
