"""Which terms a flight can identify: condition number and variance inflation of regressor columns.

Closed-loop data makes regressors collinear: an attitude controller ties the rotor speeds to the angles and
rates, so (for example) the roll torque f2 moves with -wx and the least-squares split between them is
arbitrary. Two measures on the columns (each standardised to zero mean and unit variance on the fit rows):
- the condition number of the column matrix (ratio of its largest to smallest singular value; 1 for
  orthogonal columns, large when some combination is nearly zero);
- each column's variance inflation factor VIF_j = 1 / (1 - R_j^2), R_j^2 that of the column regressed on
  the others (the diagonal of the inverse correlation matrix): by how much the coefficient's variance is
  inflated by the other columns. VIF above `vif_limit` (default 10, the usual rule of thumb) marks the term
  as not identifiable from this flight: its coefficient trades off against the columns it is tied to.
A constant column has no variance; it is left out of both measures (the intercept is not a collinearity).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import sympy

from identification.model_file import SYMBOLS, VARIABLE_NAMES, expression_to_string

VIF_LIMIT = 10.0

# Advice per kind of variable in a collinear term: what excitation separates it from the others.
_ADVICE = {
    "rotor": "excite each motor independently of the attitude controller (open-loop motor steps at altitude "
    "as in paper-train, or a larger per-motor PRBS added to the controller's output as in closed-loop)",
    "angle": "fly larger and more varied attitudes (roll, pitch and yaw through wider ranges)",
    "rate": "excite body rates independently of the rotor commands (sharper attitude steps or motor PRBS "
    "at different frequencies)",
    "velocity": "fly at several speeds in several directions (forward, sideways, climbing, descending)",
    "position": "fly over a wider range of positions and heights",
}
_KIND = {
    **{n: "rotor" for n in ("u1", "u2", "u3", "u4")},
    **{n: "angle" for n in ("phi", "theta", "psi")},
    **{n: "rate" for n in ("wx", "wy", "wz")},
    **{n: "velocity" for n in ("vx", "vy", "vz")},
    **{n: "position" for n in ("x", "y", "z")},
}


@dataclass(frozen=True)
class TermCollinearity:
    """One regressor column: its VIF and the other column it is most correlated with (|r|)."""

    term: str
    vif: float
    partner: str
    correlation: float


@dataclass(frozen=True)
class Collinearity:
    """Condition number of the standardised columns and each column's VIF (inf when exactly dependent)."""

    condition_number: float
    terms: tuple[TermCollinearity, ...]
    vif_limit: float = VIF_LIMIT

    @property
    def unidentifiable(self) -> list[TermCollinearity]:
        """The terms whose VIF exceeds the limit, worst first."""
        bad = [t for t in self.terms if not t.vif <= self.vif_limit]
        return sorted(bad, key=lambda t: -t.vif if np.isfinite(t.vif) else -np.inf)

    def advice(self) -> str:
        """What excitation would separate the unidentifiable terms ('' when every term is identifiable)."""
        kinds: list[str] = []
        for t in self.unidentifiable:
            for name in (t.term, t.partner):
                for sym in sorted(_symbols_in(name)):
                    k = _KIND.get(sym)
                    if k and k not in kinds:
                        kinds.append(k)
        return "; ".join(_ADVICE[k] for k in kinds)

    def as_dict(self) -> dict:
        """Plain mapping for the model file."""
        return {
            "condition_number": _finite(self.condition_number),
            "vif_limit": self.vif_limit,
            "not_identifiable": [
                {
                    "term": t.term,
                    "vif": _finite(t.vif),
                    "tied_to": t.partner,
                    "correlation": round(t.correlation, 6),
                }
                for t in self.unidentifiable
            ],
            "excitation": self.advice(),
        }


def _finite(v: float) -> float | str:
    return float(f"{v:.6g}") if np.isfinite(v) else "inf"


def _symbols_in(text: str) -> set[str]:
    try:
        expr = sympy.sympify(text, locals=dict(SYMBOLS))
    except (sympy.SympifyError, TypeError, SyntaxError):
        return set()
    return {str(s) for s in expr.free_symbols}


def column_collinearity(
    columns: np.ndarray, names: Sequence[str], vif_limit: float = VIF_LIMIT
) -> Collinearity:
    """Condition number and VIFs of the columns (N,k) named `names` (module docstring)."""
    a = np.asarray(columns, dtype=float)
    ok = np.all(np.isfinite(a), axis=1)
    a = a[ok]
    std = a.std(axis=0) if len(a) else np.zeros(a.shape[1])
    scale = np.maximum(np.abs(a).max(axis=0), 1e-300) if len(a) else np.ones(a.shape[1])
    varying = std > 1e-12 * scale
    idx = np.flatnonzero(varying)
    z = (a[:, idx] - a[:, idx].mean(axis=0)) / std[idx]
    if len(idx) == 0 or len(z) < 2:
        return Collinearity(1.0, (), vif_limit)
    sv = np.linalg.svd(z, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > sv[0] * 1e-15 else float("inf")
    corr = (z.T @ z) / len(z)
    if len(idx) == 1:
        vifs = np.ones(1)
    else:
        eig_min = float(np.linalg.eigvalsh(corr)[0])
        vifs = np.diag(np.linalg.inv(corr)) if eig_min > 1e-13 else _vif_by_regression(z)
    terms = []
    for k, j in enumerate(idx):
        r = np.abs(corr[k]).copy()
        r[k] = -1.0
        p = int(np.argmax(r)) if len(idx) > 1 else k
        terms.append(
            TermCollinearity(
                names[j],
                float(vifs[k]) if vifs[k] > 0 else float("inf"),
                names[idx[p]] if p != k else "",
                float(max(r[p], 0.0)) if p != k else 0.0,
            )
        )
    return Collinearity(cond, tuple(terms), vif_limit)


def _vif_by_regression(z: np.ndarray) -> np.ndarray:
    """VIFs of standardised columns z (N,k) one least-squares fit at a time (inf where R^2 is 1)."""
    out = np.empty(z.shape[1])
    for j in range(z.shape[1]):
        others = np.delete(z, j, axis=1)
        coef, *_ = np.linalg.lstsq(others, z[:, j], rcond=None)
        resid = z[:, j] - others @ coef
        one_minus_r2 = float(resid @ resid) / float(z[:, j] @ z[:, j])
        out[j] = 1.0 / one_minus_r2 if one_minus_r2 > 1e-15 else float("inf")
    return out


def expression_columns(expr: sympy.Expr, X: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """The additive terms of an expression, coefficient dropped, as columns on X (N,16) and their names."""
    shapes: list[sympy.Expr] = []
    for term in sympy.Add.make_args(expr):
        _, shape = term.as_coeff_Mul()
        if shape != 1 and shape not in shapes:
            shapes.append(shape)
    args = [SYMBOLS[n] for n in VARIABLE_NAMES]
    X = np.asarray(X, dtype=float)
    cols = np.empty((len(X), len(shapes)))
    for j, shape in enumerate(shapes):
        fn = sympy.lambdify(args, shape, modules="numpy")
        with np.errstate(all="ignore"):
            cols[:, j] = np.broadcast_to(np.asarray(fn(*X.T), dtype=float), (len(X),))
    return cols, [expression_to_string(s) for s in shapes]


def model_collinearity(expr: sympy.Expr, X: np.ndarray, vif_limit: float = VIF_LIMIT) -> Collinearity:
    """Collinearity of a chosen expression's terms on the fit rows X (N,16: the 12 states then u1..u4)."""
    cols, names = expression_columns(expr, X)
    return column_collinearity(cols, names, vif_limit)


def describe(target: str, c: Collinearity) -> list[str]:
    """Terminal lines: which terms of a target are not identifiable from this flight and what would help."""
    bad = c.unidentifiable
    if not bad:
        return []
    parts = [
        f"{t.term} (VIF {t.vif:.3g}" + (f", |r| {t.correlation:.3f} with {t.partner})" if t.partner else ")")
        for t in bad
    ]
    return [
        f"warning: {target}: {len(bad)} term(s) not identifiable from this flight (condition number "
        f"{c.condition_number:.3g}): " + "; ".join(parts),
        f"  to separate them: {c.advice()}",
    ]
