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

A chosen model can also look well conditioned because the engine dropped a true term tied to one it kept
(the roll torque f2 absorbs the rate damping wx when a rate controller makes f2 follow -wx). So each
candidate feature not in the model is also tried beside the model's terms: when adding it would push a
term's VIF over CONFOUNDER_VIF_LIMIT (100, "severe"), that term and that candidate cannot be told apart from
this flight. The higher limit because a left-out candidate is a suspicion, not a term of the model: on the
open-loop paper-train flight (pitch within a few tenths of a rad) the closest pairs, thrust terms with and
without a cos(theta) factor, give 34-38 and are still separated exactly on noise-free data; a roll torque
tied to -wx by a rate controller gives 3,200 and loses the damping term.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg
import sympy

from identification.column_buffer import ColumnBuffer
from identification.model_file import SYMBOLS, VARIABLE_NAMES, expression_to_string
from identification.sparse import ADD_ORDER
from identification.weak_noise import Whitener, column_scale, estimate_covariance

VIF_LIMIT = 10.0
CONFOUNDER_VIF_LIMIT = 100.0

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
    **{n: "velocity" for n in ("vx", "vy", "vz", "ub", "vb", "wb")},  # NED and body FRD
    **{n: "position" for n in ("x", "y", "z", "h")},
    **{n: "angle" for n in ("gx", "gy", "gz")},  # the gravity direction in the body frame
}


@dataclass(frozen=True)
class TermCollinearity:
    """One regressor column: its VIF and the other column that weighs most in explaining it (the largest
    standardised coefficient when it is regressed on all the others), with that coefficient."""

    term: str
    vif: float
    partner: str
    weight: float


@dataclass(frozen=True)
class Collinearity:
    """Condition number of the standardised columns and each column's VIF (inf when exactly dependent)."""

    condition_number: float
    terms: tuple[TermCollinearity, ...]
    vif_limit: float = VIF_LIMIT
    confounders: tuple[TermCollinearity, ...] = ()  # a model term, with a candidate not in the model

    @property
    def unidentifiable(self) -> list[TermCollinearity]:
        """The terms whose VIF exceeds the limit, worst first."""
        bad = [t for t in self.terms if not t.vif <= self.vif_limit]
        return sorted(bad, key=lambda t: -t.vif if np.isfinite(t.vif) else -np.inf)

    def advice(self) -> str:
        """What excitation would separate the unidentifiable terms ('' when every term is identifiable): the
        factor tied pairs differ by, where they have one (tie_factor), then the advice per kind of variable
        in the pairs."""
        kinds: list[str] = []
        factors: dict[str, list[str]] = {}  # factor -> the pairs it ties
        for t in [*self.unidentifiable, *self.confounders]:
            factor = tie_factor(t.term, t.partner)
            pair = " and ".join(sorted((t.term, t.partner)))
            if factor and pair not in factors.setdefault(factor, []):
                factors[factor].append(pair)
            for name in (t.term, t.partner):
                for sym in sorted(_symbols_in(name)):
                    k = _KIND.get(sym)
                    if k and k not in kinds:
                        kinds.append(k)
        lines = [f"vary {f} more during the flight ({'; '.join(pairs[:2])}{'; ...' * (len(pairs) > 2)} "
                 "differ by this factor, which varies too little on this flight to tell them apart)"
                 for f, pairs in factors.items()]
        return "; ".join([*lines, *(_ADVICE[k] for k in kinds)])

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
                    "weight": round(t.weight, 6),
                }
                for t in self.unidentifiable
            ],
            "confused_with_candidates": [
                {"term": t.term, "candidate": t.partner, "vif_with_it": _finite(t.vif)}
                for t in self.confounders
            ],
            "excitation": self.advice(),
        }


def tie_factor(term: str, partner: str, max_ops: int = 12) -> str:
    """The factor two tied terms differ by: term / partner (or partner / term) when it simplifies to a
    non-constant expression without a denominator, of at most max_ops operations, else ''. Such terms
    are told apart only by that factor's variation: the rate damping wx and the rotor drag's
    wx (u1 + u2 + u3 + u4) are tied on a flight whose rotor sum (the collective thrust) barely varies, and
    only a flight that varies the collective separates them, however its body rates are excited."""
    a, b = _parse(term), _parse(partner)
    if a is None or b is None or a == 0 or b == 0:
        return ""
    for num, den in ((a, b), (b, a)):
        if sympy.count_ops(num) > 4 * max_ops + 40:  # the quotient of two large expressions: not a factor
            return ""
        ratio = sympy.cancel(num / den)
        _, ratio = sympy.Mul(ratio).as_coeff_Mul()
        if ratio.free_symbols and sympy.fraction(ratio)[1].is_number and sympy.count_ops(ratio) <= max_ops:
            return expression_to_string(ratio)
    return ""


def _parse(text: str) -> sympy.Expr | None:
    try:
        return sympy.sympify(text, locals=dict(SYMBOLS))
    except (sympy.SympifyError, TypeError, SyntaxError):
        return None


def _finite(v: float) -> float | str:
    return float(f"{v:.6g}") if np.isfinite(v) else "inf"


def _symbols_in(text: str) -> set[str]:
    expr = _parse(text)
    return set() if expr is None else {str(s) for s in expr.free_symbols}


def column_collinearity(
    columns: np.ndarray, names: Sequence[str], vif_limit: float = VIF_LIMIT, condition: bool = True
) -> Collinearity:
    """Condition number and VIFs of the columns (N,k) named `names` (module docstring); condition=False
    skips the condition number (an SVD of the columns; NaN then) where only the VIFs are wanted."""
    a = np.asarray(columns, dtype=float)
    a = a[np.all(np.isfinite(a), axis=1)]
    if len(a) < 2:
        return Collinearity(1.0, (), vif_limit)
    z, varying = _standardise(a)
    idx = np.flatnonzero(varying)
    if len(idx) == 0:
        return Collinearity(1.0, (), vif_limit)
    z = z[:, idx]
    cond = float("nan")
    if condition:
        sv = np.linalg.svd(z, compute_uv=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > sv[0] * 1e-15 else float("inf")
    corr = (z.T @ z) / len(z)
    terms = []
    for k, j in enumerate(idx):
        if len(idx) == 1:
            terms.append(TermCollinearity(names[j], 1.0, "", 0.0))
            continue
        others = np.delete(np.arange(len(idx)), k)
        # regression of column k on the others, from the correlation matrix (normal equations)
        coef, *_ = np.linalg.lstsq(corr[np.ix_(others, others)], corr[others, k], rcond=1e-13)
        unexplained = 1.0 - float(coef @ corr[others, k])
        vif = 1.0 / unexplained if unexplained > 1e-12 else float("inf")
        p = int(np.argmax(np.abs(coef)))
        terms.append(TermCollinearity(names[j], max(vif, 1.0), names[idx[others[p]]], float(coef[p])))
    return Collinearity(cond, tuple(terms), vif_limit)


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


def model_collinearity(
    expr: sympy.Expr,
    X: np.ndarray,
    candidates: tuple[np.ndarray, Sequence[str]] | None = None,
    vif_limit: float = VIF_LIMIT,
    confounder_limit: float = CONFOUNDER_VIF_LIMIT,
) -> Collinearity:
    """Collinearity of a chosen expression's terms on the fit rows X (N,16: the 12 states then u1..u4),
    and, given candidate feature columns (N,m) with names, the candidates confused with its terms."""
    cols, names = expression_columns(expr, X)
    return terms_collinearity(cols, names, candidates, vif_limit, confounder_limit)


def terms_collinearity(
    cols: np.ndarray,
    names: Sequence[str],
    candidates: tuple[np.ndarray, Sequence[str]] | None = None,
    vif_limit: float = VIF_LIMIT,
    confounder_limit: float = CONFOUNDER_VIF_LIMIT,
) -> Collinearity:
    """Collinearity of a model's term columns (N,k) named `names` (any variables: the 16 of the model
    file, or the body-frame primitives), and, given candidate columns (N,m) with names, the candidates
    confused with its terms (model_collinearity)."""
    own = column_collinearity(cols, names, vif_limit)
    if candidates is None or not names:
        return own
    return replace(own, confounders=_confounders(cols, names, *candidates, confounder_limit))


def _standardise(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(columns scaled to zero mean and unit variance, mask of the columns that vary)."""
    std = a.std(axis=0)
    varying = std > 1e-12 * np.maximum(np.abs(a).max(axis=0), 1e-300)
    z = np.zeros_like(a)
    z[:, varying] = (a[:, varying] - a[:, varying].mean(axis=0)) / std[varying]
    return z, varying


def _confounders(
    cols: np.ndarray, names: Sequence[str], cand: np.ndarray, cand_names: Sequence[str], vif_limit: float
) -> tuple[TermCollinearity, ...]:
    """Per model term, the candidate (not in the model) whose addition gives it the largest VIF, when
    that VIF exceeds the limit; a candidate equal to a model term is the term itself and is skipped."""
    k = cols.shape[1]
    both = np.hstack([cols, np.asarray(cand, dtype=float)])
    both = both[np.all(np.isfinite(both), axis=1)]
    if len(both) < 2:
        return ()
    z, varying = _standardise(both)
    corr = (z.T @ z) / len(z)
    own = [j for j in range(k) if varying[j]]
    worst: dict[int, TermCollinearity] = {}
    for c in range(k, both.shape[1]):
        if not varying[c] or any(abs(corr[c, j]) > 1 - 1e-12 for j in own):
            continue  # constant, or the very same column as a model term
        group = [*own, c]
        for j in own:
            others = [g for g in group if g != j]
            coef, *_ = np.linalg.lstsq(corr[np.ix_(others, others)], corr[others, j], rcond=1e-13)
            unexplained = 1.0 - float(coef @ corr[others, j])
            vif = 1.0 / unexplained if unexplained > 1e-12 else float("inf")
            if vif > vif_limit and (j not in worst or vif > worst[j].vif):
                worst[j] = TermCollinearity(names[j], vif, cand_names[c - k], float(coef[-1]))
    return tuple(worst[j] for j in sorted(worst))


def weakest_t(columns: np.ndarray, y: np.ndarray, max_lag: int | None = None) -> float:
    """The smallest t ratio |c_j| / se_j over a linear model's non-constant terms (term_identification)."""
    return term_identification(columns, y, max_lag)[0]


def term_identification(
    columns: np.ndarray, y: np.ndarray, max_lag: int | None = None, noise: Whitener | None = None
) -> tuple[float, float]:
    """(the smallest t ratio |c_j| / se_j, the largest VIF) over a linear model's non-constant terms.

    columns (N,k): the model's term columns (a constant column is fitted but not measured; without one, the
    terms are measured beside a constant offset: term_t_ratios), y (N,): the target; c the least-squares
    coefficients, se_j = s sqrt(VIF_j) / (sqrt(N_eff) std_j) the least-squares standard error (s the
    residual's RMS). Rows of a flight are not independent: the residual of one sample
    is close to the next one's, so N_eff = N (1 - rho) / (1 + rho), rho the residual's lag-1
    autocorrelation (an AR(1) residual's effective sample size), not N. A term whose coefficient cannot be
    told from zero given its collinearity with the others and what the model leaves unexplained has a small
    t: wz beside |wz| when the yaw rate almost never changes sign (VIF 4e6); small terms fitting the
    targets' errors; noise-free data gives t ~1e9. t is 0 when there are fewer rows than columns, inf for a
    model without a varying term. The VIF says how far the flight separates the terms at all: on noise-free
    closed-loop data a signed rotor combination written as three tied terms has t ~1e9 and VIF ~100.
    The RMS, not a robust scale: an absolute-error fit's standard error (Koenker's tau from the median
    absolute deviation) let terms fitting the targets' small systematic errors through (a 16 s closed-loop
    flight's fz took h*wz, h^2|wz|, wz|v| at t 7.5; with the RMS the true structure), so the rule stays
    conservative where a few rows carry large errors (fang-chen-aero's dwy wx^2: t 3.0).
    Weak-form rows (columns and y integrated against overlapping test functions) give max_lag, the
    windows' overlap in rows (weak_form.overlap_lag), for their effective sample size (effective_rows).
    Weak rows whose raw targets' noise the log states (noise: their whitener, identification.weak_noise)
    get se_j under that noise instead (term_t_ratios): the effective sample size assumes the residual's
    autocorrelation is the noise's, and on a differenced gyro's weak rows it gave t ratios 2.4x too large
    (wx', wy') and 3x too small (wz') against the exact ones.
    """
    t, vif = term_t_ratios(columns, y, max_lag, noise)
    if t is None:
        return 0.0, float("inf")
    measured = ~np.isnan(vif)  # NaN: a column that does not vary; inf: a term tied exactly to the others
    if not measured.any():
        return float("inf"), 1.0
    return float(t[measured].min()), float(vif[measured].max())


def term_t_ratios(
    columns: np.ndarray, y: np.ndarray, max_lag: int | None = None, noise: Whitener | None = None,
    offset: bool = True,
) -> tuple[np.ndarray | None, np.ndarray]:
    """(t ratio |c_j| / se_j, VIF_j) of each column (k,) of the least-squares fit of y (N,) on columns (N,k),
    with the effective sample size of term_identification (max_lag: weak-form rows, effective_rows);
    (None, [inf]) when there are fewer rows than columns. A column that does not vary (a constant) is
    fitted but gets NaN for both; t is inf for every column of an exact fit with a nonzero coefficient, 0
    where a coefficient is 0. With noise (the whitener of exactly these N weak rows, every row finite):
    se_j from the fit's weights on the rows' stated noise, its scale the whitened residual's variance
    (weak_noise.estimate_covariance; the least-squares fit's sandwich under that noise).
    offset: the columns are measured beside a constant offset, fitted with them when none of them is
    constant: a term this flight cannot tell from an offset is not identified by it, whether or not its
    model has one. A sensor's bias or any unmodelled trim is such an offset: on a fast paper flight
    (|v_b|^2 = 341 +- 73 m^2/s^2) -4.5e-5 (ub^2 + vb^2 + wb^2) held the accelerometer's -0.015 m/s^2 bias,
    t 19.0 under the weak rows' stated noise without a constant and 3.8 beside one. The standard errors
    without noise (centred VIF and spread) are those of a fit with an offset already (3.6 either way)."""
    a = np.asarray(columns, dtype=float)
    y = np.asarray(y, dtype=float)
    ok = np.all(np.isfinite(a), axis=1) & np.isfinite(y)
    if not ok.all() or not a.flags.c_contiguous:  # a row-major copy of the finite rows, else a itself
        a, y = a[ok], y[ok]
    if len(y) <= a.shape[1]:
        return None, np.array([np.inf])
    # the columns less their means, and their spread as a.std(axis=0) computes it (the same sums, to the
    # bit): the centred path reuses both
    deviation = a - a.mean(axis=0)
    std = np.sqrt(np.add.reduce(deviation * deviation, axis=0) / len(y))
    largest = np.maximum(a.max(axis=0), -a.min(axis=0))  # |a|'s column maxima, without a copy of |a|
    measured = std > 1e-12 * np.maximum(largest, 1e-300)
    if offset and measured.all() and len(y) > a.shape[1] + 1:
        if noise is None and (fast := _centred_t_ratios(a, y, max_lag, (deviation, std))) is not None:
            return fast
        whole = noise if ok.all() else None  # the whitener holds exactly the rows it was given
        t, vif = term_t_ratios(np.hstack([np.ones((len(y), 1)), a]), y, max_lag, whole, offset=False)
        return (None, vif) if t is None else (t[1:], vif[1:])
    full_t, full_vif = np.full(a.shape[1], np.nan), np.full(a.shape[1], np.nan)
    if not measured.any():
        return full_t, full_vif
    if noise is None and np.count_nonzero(~measured) == 1 and np.any(a[:, ~measured]):  # one offset
        if (fast := _centred_t_ratios(a[:, measured], y, max_lag)) is not None:
            full_t[measured], full_vif[measured] = fast
            return full_t, full_vif
    scale = np.where(measured, std, np.maximum(np.abs(a).max(axis=0), 1e-300))
    z = a / scale  # unit spread (measured columns): least squares well scaled whatever the terms' units
    c = np.linalg.lstsq(z, y, rcond=None)[0]
    resid = y - z @ c
    s = float(np.sqrt(np.mean(resid * resid)))
    names = [str(j) for j in range(a.shape[1])]
    vif = np.array([t.vif for t in column_collinearity(a, names, condition=False).terms])
    c = np.abs(c[measured])
    full_vif[measured] = vif
    if s == 0.0:
        full_t[measured] = np.where(c > 0, np.inf, 0.0)
        return full_t, full_vif
    if noise is not None and noise.rows == len(ok) and ok.all() and len(y) > a.shape[1]:
        white = noise.apply(resid)
        s2 = float(white @ white) / (len(y) - a.shape[1])
        se = np.sqrt(np.maximum(np.diag(estimate_covariance(np.linalg.pinv(z), [noise], s2)), 0.0))
        se = se[measured]
    else:
        se = s * np.sqrt(vif) / np.sqrt(effective_rows(resid, max_lag))
    with np.errstate(all="ignore"):
        t = c / se
    full_t[measured] = np.nan_to_num(t, nan=0.0)
    return full_t, full_vif


# the centred path answers up to this VIF; above it (nearly tied columns) the general path's pseudo-inverse
# and its "inf" at 1e12 decide, as before
_CENTRED_MAX_VIF = 1e10


def _centred_t_ratios(x: np.ndarray, y: np.ndarray, max_lag: int | None,
                      centred: tuple[np.ndarray, np.ndarray] | None = None
                      ) -> tuple[np.ndarray, np.ndarray] | None:
    """term_t_ratios of varying columns x (N,k) beside a constant offset, without stated noise: the columns
    centred and scaled to unit spread, one QR factorisation of them beside the centred target gives the
    coefficients, the residual and every VIF (N times the squared row norms of R^-1: the diagonal of the
    inverse correlation matrix), where the general path solves least squares once and each column's
    regression on the others once more (a 58-term model: 58 solves, 2.5x the time). The same least
    squares; None (the general path) when a VIF exceeds _CENTRED_MAX_VIF or the rows are too few.
    centred: x less its column means and x.std(axis=0), when the caller has them."""
    if len(y) <= x.shape[1] + 1:
        return None
    deviation, std = centred if centred is not None else (x - x.mean(axis=0), x.std(axis=0))
    z = deviation / std
    yc = y - y.mean()
    r = np.linalg.qr(np.hstack([z, yc[:, None]]), mode="r")
    return _t_ratios_from_factor(r, z, yc, max_lag)


def _t_ratios_from_factor(r: np.ndarray, z: np.ndarray, yc: np.ndarray, max_lag: int | None
                          ) -> tuple[np.ndarray, np.ndarray] | None:
    """_centred_t_ratios from the triangular factor r (k+1, k+1) of [z | yc], z (N,k) the centred columns
    at unit spread and yc (N,) the centred target."""
    k = z.shape[1]
    with np.errstate(all="ignore"):
        rinv = scipy.linalg.solve_triangular(r[:k, :k], np.eye(k), check_finite=False)
        vif = len(yc) * np.sum(rinv * rinv, axis=1)
    if not np.all(np.isfinite(vif)) or vif.max() > _CENTRED_MAX_VIF:
        return None
    coef = rinv @ r[:k, k]
    resid = yc - z @ coef
    s = float(np.sqrt(np.mean(resid * resid)))
    c, vif = np.abs(coef), np.maximum(vif, 1.0)
    if s == 0.0:
        return np.where(c > 0, np.inf, 0.0), vif
    se = s * np.sqrt(vif) / np.sqrt(effective_rows(resid, max_lag))
    with np.errstate(all="ignore"):
        return np.nan_to_num(c / se, nan=0.0), vif


_ROOM = 64  # CentredPool's buffers grow by this many columns beyond what they must hold


class CentredPool:
    """term_identification of subsets of a growing set of columns on the same rows, from one thin QR
    factorisation [yc | Z] = QR kept up to date as columns join (Z the columns centred at unit spread, yc
    the centred target): a subset's factor is that of R's columns for it (its (m+1) rows, not N), the same
    least squares as factorising the subset's own columns. cv_polish measures ~1,000 moves of one pool per
    target, each factorised on its own before: a tenth of a racer's closed-loop wx'."""

    def __init__(self, y: np.ndarray, max_lag: int | None = None):
        """y (N,) finite: the target on the rows; max_lag as term_identification's."""
        self.rows = len(y)
        self.max_lag = max_lag
        self.yc = np.asarray(y, dtype=float) - float(np.mean(y))
        self._z = ColumnBuffer(self.rows, 0, _ROOM, order="F")  # the columns centred at unit spread
        self._q = ColumnBuffer(self.rows, 0, _ROOM, order="F")  # orthonormal basis of [yc | Z]
        self._r = np.zeros((0, 0))  # [yc | Z] = Q R (R's columns: yc, then Z's; Q's columns its rows)
        self._columns = 0  # columns of R held (of its buffer's)
        self._varying = np.zeros(0, bool)
        self._append(self.yc)

    def add(self, columns: np.ndarray) -> range:
        """Columns (N,e) joined (finite); their indices for identification()."""
        a = np.asarray(columns, dtype=float).reshape(self.rows, -1)
        first = self._z.used
        for j in range(a.shape[1]):
            col = a[:, j]
            deviation = col - col.mean()
            std = float(np.sqrt(np.add.reduce(deviation * deviation) / max(self.rows, 1)))
            varying = std > 1e-12 * max(float(np.max(np.abs(col))) if self.rows else 0.0, 1e-300)
            self._varying = np.append(self._varying, varying)
            z = deviation / std if varying else deviation
            self._z.append(z[:, None])
            self._append(z)
        return range(first, self._z.used)

    def _append(self, z: np.ndarray) -> None:
        """One column into [yc | Z] = QR: Gram-Schmidt against Q twice ("twice is enough"). A column within
        1e-10 of its norm of Q's span joins R without a new direction of Q: its remainder is left out, which
        moves its Gram matrix entries by at most 1e-10 of the columns' norms' product; any set that holds
        it and what it nearly is then has a VIF far above _CENTRED_MAX_VIF and goes to the caller."""
        q, rank = self._q.view(), self._q.used
        c = q.T @ z
        b = z - q @ c
        c2 = q.T @ b
        b -= q @ c2
        c += c2
        norm = float(np.linalg.norm(b))
        n = self._columns + 1
        if n > self._r.shape[1]:
            grown = np.zeros((max(2 * n, 16), max(2 * n, 16)))
            grown[:self._r.shape[0], :self._r.shape[1]] = self._r
            self._r = grown
        self._r[:rank, n - 1] = c
        if norm > 1e-10 * max(float(np.linalg.norm(z)), 1e-300):
            self._q.append((b / norm)[:, None])
            self._r[rank, n - 1] = norm
        self._columns = n

    def identification(self, idx: Sequence[int]) -> tuple[float, float] | None:
        """term_identification's (weakest t, largest VIF) of the columns idx (add's indices); None where its
        centred path would not answer (a column that does not vary, too few rows, a VIF above
        _CENTRED_MAX_VIF): the caller measures those columns themselves."""
        idx = list(idx)
        if not idx or not self._varying[idx].all() or self.rows <= len(idx) + 1:
            return None
        r = np.linalg.qr(self._r[:max(self._q.used, 1), [*(i + 1 for i in idx), 0]], mode="r")
        if r.shape[0] < len(idx) + 1:  # fewer directions than columns (an exact fit, tied columns): R
            r = np.vstack([r, np.zeros((len(idx) + 1 - r.shape[0], r.shape[1]))])  # padded, R^T R the same
        out = _t_ratios_from_factor(r, self._z.view()[:, idx], self.yc, self.max_lag)
        if out is None:
            return None
        t, vif = out
        return float(t.min()), float(vif.max())


def offset_t_ratio(
    columns: np.ndarray, y: np.ndarray, max_lag: int | None = None, noise: Whitener | None = None
) -> float:
    """The t ratio |c_0| / se_0 of the constant offset c_0 fitted beside the varying columns (N, k) to y (N,),
    under term_t_ratios' noise model (the residual's RMS over the effective rows, or the weak rows' stated
    noise): how far the flight tells a constant (a sensor's bias) from zero given the terms beside it. Terms
    whose sum barely varies over the rows (four rotors' u_i^2 in a hover) can stand for the offset, and its t
    falls. 0 with fewer rows than columns; inf for an exact fit with a nonzero offset."""
    a = np.asarray(columns, dtype=float).reshape(len(y), -1)
    y = np.asarray(y, dtype=float)
    ok = np.all(np.isfinite(a), axis=1) & np.isfinite(y)
    a, y = a[ok], y[ok]
    if len(y) <= a.shape[1] + 1:
        return 0.0
    design = np.hstack([np.ones((len(y), 1)), a / column_scale(a)])
    pinv = np.linalg.pinv(design)
    c = pinv @ y
    resid = y - design @ c
    s2 = float(resid @ resid) / (len(y) - design.shape[1])
    if s2 == 0.0:
        return float("inf") if c[0] != 0.0 else 0.0
    if noise is not None and noise.rows == len(ok) and ok.all():
        white = noise.apply(resid)
        var = estimate_covariance(pinv[:1], [noise], float(white @ white) / (len(y) - design.shape[1]))[0, 0]
    else:  # least squares' variance, the rows counted as their effective number
        var = s2 * float(pinv[0] @ pinv[0]) * len(y) / effective_rows(resid, max_lag)
    return float(abs(c[0]) / np.sqrt(var)) if var > 0 else float("inf")


def describe(target: str, c: Collinearity) -> list[str]:
    """Terminal lines: which terms of a target are not identifiable from this flight and what would help."""
    bad = c.unidentifiable
    lines = []
    if bad:
        parts = [f"{t.term} (VIF {t.vif:.3g}, tied most to {t.partner})" for t in bad]
        lines.append(
            f"warning: {target}: {len(bad)} term(s) not identifiable from this flight (condition number "
            f"{c.condition_number:.3g}): " + "; ".join(parts)
        )
    if c.confounders:
        parts = [f"{t.term} with {t.partner} (VIF {t.vif:.3g})" for t in c.confounders]
        lines.append(
            f"warning: {target}: terms that cannot be told apart from candidates left out of the model on "
            "this flight (the coefficient may hold both): " + "; ".join(parts)
        )
    if lines:
        lines.append(f"  to separate them: {c.advice()}")
    return lines


def effective_rows(resid: np.ndarray, max_lag: int | None = None) -> float:
    """The effective number of independent rows of a residual (N,), between 1 and N.

    max_lag None (a flight's rows): N (1 - rho) / (1 + rho), rho the lag-1 autocorrelation (an AR(1)
    residual's effective sample size; term_identification). max_lag q (weak-form rows, whose test-function
    windows overlap up to q rows apart: weak_form.overlap_lag): N / (1 + 2 sum_{l=1..q} rho_l), the sample
    autocorrelations summed up to q (Hansen and Hodrick 1980: averages over overlapping windows of white
    noise are an MA(q) process). AR(1) extrapolated from rho_1 overstates how long a window average stays
    correlated: on 0.4 s windows every 0.02 s (q = 20) rho_1 is 0.97-0.98, AR(1) counts ~80 rows per
    independent one where the windows give ~10, and the t ratios came out ~3x too small."""
    d = np.asarray(resid, dtype=float) - float(np.mean(resid))
    n = len(d)
    den = float(d @ d)
    if den <= 0 or n < 2:
        return float(max(n, 1))
    if max_lag is None:
        rho = float(np.clip((d[:-1] @ d[1:]) / den, 0.0, 0.999))
        return max(n * (1.0 - rho) / (1.0 + rho), 1.0)
    lags = range(1, min(int(max_lag), n - 1) + 1)
    inflation = 1.0 + 2.0 * sum(float(d[:-k] @ d[k:]) / den for k in lags)
    return float(np.clip(n / max(inflation, 1e-12), 1.0, n))


def term_shapes(expr: sympy.Expr) -> list[sympy.Expr]:
    """The distinct additive terms of an expression (nested sums flattened), coefficients dropped (a
    constant term gives the shape 1)."""
    return list(_term_shapes(expr))


def forget_term_shapes() -> None:
    """Empty term_shapes' cache (identify does at each target: its candidates are not asked for again)."""
    _term_shapes.cache_clear()


@functools.cache
def _term_shapes(expr: sympy.Expr) -> tuple[sympy.Expr, ...]:
    # cached: the selection asks for the same candidates' shapes thousands of times, and rebuilding the sum
    # makes sympy deduce its assumptions anew each time (5 % of a closed-loop target's fit). Unbounded, and
    # emptied per target (forget_term_shapes): each polish reads every candidate's shapes, some 8,600 on
    # closed-loop heavy-650-aero's wx', and a cache of 4,096 read in that order never hit (that wx' alone
    # 119.2 -> 117.1 s). A sum that is already flat (no nested sum, one term per shape, in sympy's order)
    # would be rebuilt as itself: read it as it is (most candidates are; 2-3 % of a closed-loop fit's CPU);
    # out of sympy's order, the rebuilt sum is its terms sorted, so sort them (a polish's moves are written
    # in their own order: rebuilding those sums, 0.1-0.2 s each for 30 terms, was 5.6 of 100 s of the heavy
    # closed loop's wx', seed 71)
    args = sympy.Add.make_args(expr)
    if not any(a.is_Add for a in args):
        shapes = tuple(a.as_coeff_Mul()[1] for a in args)
        if len(set(shapes)) == len(shapes):
            number = args[:1] if args[0].is_Number else ()  # a sum's number leads it, the rest sorted
            rest = list(args[len(number):])
            ordered = sorted(rest, key=ADD_ORDER)
            return shapes if rest == ordered else tuple(a.as_coeff_Mul()[1] for a in (*number, *ordered))
    out: list[sympy.Expr] = []
    for term in sympy.Add.make_args(sympy.Add(*sympy.Add.make_args(expr))):  # flatten unevaluated sums
        _, shape = term.as_coeff_Mul()
        if shape not in out:
            out.append(shape)
    return tuple(out)
