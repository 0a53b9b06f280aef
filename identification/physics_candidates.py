"""The physics-only candidates every pick compares, and the minimal physical model of a target the flight
does not excite.

Physics-only candidates (least squares on the fit rows, least absolute error for the 'absolute' loss, as
the sparse engines refit): a constant, then thrust and gravity, rate damping and control torque, drag:
  body frame (the default engine; fx fy fz specific force FRD m/s^2, the NED accelerations are
  composed as R f_b + g e_z, so thrust direction and gravity come with the composition):
    fx: 1 | 1, ub            fy: 1 | 1, vb           fz: f1 | 1, f1 | 1, f1, wb
  NED (the other engines; T_k = f1 R[k, 2], f1 times the thrust direction's component on axis k):
    ax: 1 | 1, T_x | 1, T_x, vx     ay: likewise     az: 1, T_z | 1, T_z, vz
  both: dwx: 1 | 1, f2 | 1, f2, wx    dwy: 1 | 1, f3 | 1, f3, wy    dwz: 1 | 1, f4 | 1, f4, wz
f1..f4 the paper's combinations of the squared rotor speeds (docs/design.md), ub vb wb the body velocity
(m/s), wx wy wz the body rates (rad/s). They go through the same pick rules as the engine's (terms
identified, no anti-damping: identification.pareto), so the engine is never worse than the plain physics
on the pick rows by more than the pick's tolerance.

The minimal physical model (MINIMAL_TERMS) is what a target gets when the flight does not excite it
(identification.pareto.excited): the constant for fx, fy (the thrust stays along the body z axis, gravity
and the thrust direction come with the composition), thrust proportional to f1 for fz (no rotor, no
specific force: gravity alone), the constant for the angular accelerations and the horizontal NED ones,
the constant and thrust for az.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns
from identification.candidate import Candidate
from identification.collinearity import term_identification
from identification.kinematics import rotation_matrix_sym
from identification.library import Feature
from identification.metrics import loss as loss_fn
from identification.model_file import SYMBOLS, complexity
from identification.sparse import LeastSquaresProblem, sparse_expression
from identification.true_model import motor_combinations_sym
from identification.weak_form import overlap_lag
from identification.weak_noise import Whitener

ENGINE_NAME = "physics"
_COMB = motor_combinations_sym(SYMBOLS)
_ROT = rotation_matrix_sym(SYMBOLS["phi"], SYMBOLS["theta"], SYMBOLS["psi"])
TERMS: dict[str, sympy.Expr] = {
    "1": sympy.Integer(1),
    **{n: _COMB[n] for n in ("f1", "f2", "f3", "f4")},
    **{n: PRIMITIVE_SYMBOLS[n] for n in ("ub", "vb", "wb")},
    **{n: SYMBOLS[n] for n in ("vx", "vy", "vz", "wx", "wy", "wz")},
    **{f"T_{a}": _COMB["f1"] * _ROT[k, 2] for k, a in enumerate("xyz")},
}
_RATES = {
    "dwx": (("1",), ("1", "f2"), ("1", "f2", "wx")),
    "dwy": (("1",), ("1", "f3"), ("1", "f3", "wy")),
    "dwz": (("1",), ("1", "f4"), ("1", "f4", "wz")),
}
TERM_SETS: dict[str, tuple[tuple[str, ...], ...]] = {
    "fx": (("1",), ("1", "ub")),
    "fy": (("1",), ("1", "vb")),
    "fz": (("f1",), ("1", "f1"), ("1", "f1", "wb")),
    "ax": (("1",), ("1", "T_x"), ("1", "T_x", "vx")),
    "ay": (("1",), ("1", "T_y"), ("1", "T_y", "vy")),
    "az": (("1", "T_z"), ("1", "T_z", "vz")),
    **_RATES,
}
MINIMAL_TERMS: dict[str, tuple[str, ...]] = {
    "fx": ("1",), "fy": ("1",), "fz": ("f1",), "ax": ("1",), "ay": ("1",), "az": ("1", "T_z"),
    "dwx": ("1",), "dwy": ("1",), "dwz": ("1",),
}


def fit_terms(
    names: Sequence[str], X: np.ndarray, y: np.ndarray, loss: str, operator: np.ndarray | None = None,
    noise: Whitener | None = None,
) -> Candidate:
    """The candidate sum of coefficient x term (TERMS names) fitted on X (N,16), y (N,) (least absolute error
    for loss 'absolute'); operator: a weak-form matrix V (M,N): fitted on V columns, V y; noise: those weak
    rows' whitener, for the t ratios under the log's stated noise (collinearity.term_identification)."""
    exprs = [TERMS[n] for n in names]
    cols = expression_columns(exprs, X)
    ok = np.all(np.isfinite(cols), axis=1) & np.isfinite(y)
    a, b = cols, np.asarray(y, dtype=float)
    lag = None  # point rows; weak rows: the windows' overlap for the t ratios (collinearity.effective_rows)
    if operator is not None:
        a, b = operator[:, ok] @ cols[ok], operator[:, ok] @ b[ok]
        lag = overlap_lag(operator[:, ok])
    else:
        a, b = a[ok], b[ok]
    problem = LeastSquaresProblem(a, b)
    active = np.ones(len(names), dtype=bool)
    coef = problem.solve(active)
    if loss == "absolute":
        coef = problem.l1_refit(active, coef, 10)
    feats = [Feature(n, e, ENGINE_NAME) for n, e in zip(names, exprs, strict=True)]
    expr = sparse_expression(feats, coef)

    def predict(X_: np.ndarray, exprs: list[sympy.Expr] = exprs, coef: np.ndarray = coef) -> np.ndarray:
        return expression_columns(exprs, X_) @ coef

    c = Candidate(expr, complexity(expr), loss_fn(b, a @ coef, loss), ENGINE_NAME, predict=predict)
    c.weakest_t, c.largest_vif = term_identification(a, b, lag, noise)
    return c


def physics_candidates(
    target: str, X: np.ndarray, y: np.ndarray, loss: str, operator: np.ndarray | None = None,
    noise: Whitener | None = None,
) -> list[Candidate]:
    """The physics-only candidates of a target (module docstring; none for an unknown target name)."""
    return [fit_terms(names, X, y, loss, operator, noise) for names in TERM_SETS.get(target, ())]


def minimal_candidate(
    target: str, X: np.ndarray, y: np.ndarray, loss: str, operator: np.ndarray | None = None
) -> Candidate:
    """The minimal physical model of a target the flight does not excite (module docstring)."""
    return fit_terms(MINIMAL_TERMS.get(target, ("1",)), X, y, loss, operator)
