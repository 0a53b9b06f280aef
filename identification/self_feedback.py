"""Self-feedback of a candidate: how its target responds to the target's own state, and how sure the flight
is of it.

A rigid body with rotors and drag has no positive self-feedback: d(wx')/d(wx) <= 0 (rate damping), and
likewise for wy, wz, and for the specific force along a body axis against the velocity along it (drag),
or the NED acceleration against the NED velocity. A candidate whose slope is positive ("anti-damping")
fits something else: on a hover log whose rates are noise, a rate derivative estimated from the same noisy
rates correlates with them (+1/dt for a backward difference), and a model of it, though it predicts the
held-out rows, is not the vehicle's; a controller or a simulation built on it diverges.

Measured per candidate on the fit rows X (N,16), y (N,), in the target's unit per the state's unit (1/s):
- slope: the mean over the rows of d(candidate)/d(own state), by central differences (the step 5% of the
  state's spread, at least 1e-3): the own state is wx, wy, wz for dwx, dwy, dwz (FRD rad/s); vx, vy, vz
  for ax, ay, az (NED m/s); the body velocity ub, vb, wb for fx, fy, fz (FRD m/s, moved along the body
  axis in NED);
- its standard error, from the candidate's additive terms (coefficients dropped; identification.collinearity
  .term_shapes) as a linear model on the fit rows: se = sqrt(g' Cov g), g the terms' mean slopes and Cov
  the least-squares covariance s^2 (A'A)^-1 scaled by N / N_eff (the residual's effective rows,
  collinearity.effective_rows), s the candidate's residual RMS.
The pick (identification.pareto) sets aside a candidate whose slope is positive beyond max_self_feedback_t
standard errors, as long as one candidate passes. Only positive slopes get a standard error (the others
pass whatever it is).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import sympy

from bridge.rotations import rotation_matrix
from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns, primitive_matrix
from identification.candidate import Candidate
from identification.collinearity import effective_rows, term_shapes
from identification.model_file import SYMBOLS
from identification.rows_cache import cached

# target -> own state: ("x", column of X) or ("body", body axis 0..2) for the body-frame specific force
OWN_STATE: dict[str, tuple[str, int]] = {
    "ax": ("x", 3), "ay": ("x", 4), "az": ("x", 5),
    "dwx": ("x", 9), "dwy": ("x", 10), "dwz": ("x", 11),
    "fx": ("body", 0), "fy": ("body", 1), "fz": ("body", 2),
}


# the symbol a candidate must hold to feed back on its own state (in the 16 variables or the primitives)
OWN_SYMBOL: dict[str, sympy.Symbol] = {
    **{t: SYMBOLS[n] for t, n in (("ax", "vx"), ("ay", "vy"), ("az", "vz"))},
    **{t: SYMBOLS[n] for t, n in (("dwx", "wx"), ("dwy", "wy"), ("dwz", "wz"))},
    **{t: PRIMITIVE_SYMBOLS[n] for t, n in (("fx", "ub"), ("fy", "vb"), ("fz", "wb"))},
}


def _moved(X: np.ndarray, target: str, step: float) -> np.ndarray:
    """X (N,16) with the target's own state moved by step (its unit)."""
    kind, k = OWN_STATE[target]
    out = np.array(X, dtype=float, copy=True)
    if kind == "x":
        out[:, k] += step
    else:  # the body velocity along axis k, moved in NED: v += step R[:, k]
        out[:, 3:6] += step * rotation_matrix(X[:, 6], X[:, 7], X[:, 8])[:, :, k]
    return out


def _step(X: np.ndarray, target: str) -> float:
    """The finite-difference step: 5% of the own state's spread on the rows, at least 1e-3 (kept while X
    lives: the body velocity's rotation of every row was 1.7 s of a heavy closed loop's fz polish, which
    marks its moves one at a time)."""
    def step() -> np.ndarray:
        kind, k = OWN_STATE[target]
        col = X[:, k] if kind == "x" else primitive_matrix(X, (("ub", "vb", "wb")[k],))[:, 0]
        return np.array([max(1e-3, 0.05 * float(np.std(col) or 1.0))])

    return float(cached(X, ("self_feedback step", target), step)[0])


def slope(candidate: Candidate, X: np.ndarray, target: str, moved: tuple | None = None) -> float:
    """Mean over the rows of d(candidate)/d(own state) (module docstring), target unit per state unit.

    moved: (X moved up, X moved down, step) when already made (one pair shared by every candidate)."""
    if moved is None:
        h = _step(X, target)
        moved = (_moved(X, target, h), _moved(X, target, -h), h)
    up, down, h = moved
    if candidate.linear is not None:
        shapes, coef = candidate.linear
        means = [_term_slope(s, up, down, h) for s in shapes]
        if all(m is not None for m in means):  # each term finite on every row: the mean is the terms' sum
            return float(np.asarray(means) @ coef)
    if candidate.term_means is not None:  # the engine's own columns: their means, not the candidate's sums
        term_mean, coef = candidate.term_means
        value = float((term_mean(up) - term_mean(down)) @ coef / (2 * h)) if len(coef) else 0.0
        if np.isfinite(value):
            return value
    d = (candidate.evaluate(up) - candidate.evaluate(down)) / (2 * h)
    return float(np.nanmean(d)) if np.isfinite(d).any() else float("nan")


def _term_slope(shape: sympy.Expr, up: np.ndarray, down: np.ndarray, h: float) -> float | None:
    """A term's mean central difference over the moved rows (None where it is not finite on every row),
    kept while the rows live: the polish marks thousands of moves of a few hundred terms, and evaluating
    each move's sum on both moved arrays was 5 % of a closed-loop target's time."""
    def mean() -> np.ndarray:
        d = (expression_columns([shape], up)[:, 0] - expression_columns([shape], down)[:, 0]) / (2 * h)
        return np.array([np.mean(d) if np.all(np.isfinite(d)) else np.nan])

    value = float(cached(up, ("term slope", shape, id(down), h), mean)[0])
    return value if np.isfinite(value) else None


def slope_standard_error(candidate: Candidate, X: np.ndarray, y: np.ndarray, target: str) -> float:
    """The standard error of slope() from the candidate's terms as a linear model on (X, y) (module
    docstring); inf when the terms cannot be evaluated or the rows are too few."""
    shapes = term_shapes(candidate.expression)
    n = len(X)
    try:
        h = _step(X, target)
        cols = expression_columns(shapes, np.vstack([X, _moved(X, target, h), _moved(X, target, -h)]))
    except (TypeError, ValueError, ZeroDivisionError, OverflowError, NameError, KeyError):
        return float("inf")
    a = cols[:n]
    with np.errstate(all="ignore"):
        gbar = np.nanmean((cols[n:2 * n] - cols[2 * n:]) / (2 * h), axis=0)
    resid = y - candidate.evaluate(X)
    ok = np.all(np.isfinite(a), axis=1) & np.isfinite(resid)
    if ok.sum() <= a.shape[1] or not np.all(np.isfinite(gbar)):
        return float("inf")
    a, resid = a[ok], resid[ok]
    scale = np.maximum(np.sqrt(np.mean(a * a, axis=0)), 1e-300)  # unit RMS columns: a well-scaled inverse
    z = a / scale
    s2 = float(np.mean(resid * resid))
    cov = s2 * np.linalg.pinv(z.T @ z) * (len(resid) / effective_rows(resid))
    gz = gbar / scale  # d = sum_j c_j gbar_j = sum_j b_j gbar_j / scale_j, b_j = c_j scale_j on z
    return float(np.sqrt(max(float(gz @ cov @ gz), 0.0)))


def mark_self_feedback(candidates: Sequence[Candidate], X: np.ndarray, y: np.ndarray, target: str) -> None:
    """Set each candidate's self_feedback (slope) and self_feedback_se (standard error, for positive
    slopes only) on the fit rows X (N,16), y (N,); nothing for a target without an own state."""
    if target not in OWN_STATE or len(X) == 0:
        return
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float)
    h = _step(X, target)
    # the moved rows kept while X lives: a caller marking candidates one at a time (the polish, the
    # specification search) then evaluates their terms on the same arrays, whose columns are kept too
    moved = (cached(X, ("self_feedback", target, h), lambda: _moved(X, target, h)),
             cached(X, ("self_feedback", target, -h), lambda: _moved(X, target, -h)), h)
    own = OWN_SYMBOL[target]
    for c in candidates:
        # no term of its own state: no self-feedback (a sum of terms read from its terms, its expression
        # not built: the polish marks thousands of moves)
        if not (any(s.has(own) for s in c.linear[0]) if c.linear is not None else c.expression.has(own)):
            c.self_feedback, c.self_feedback_se = 0.0, None
            continue
        c.self_feedback = slope(c, X, target, moved)
        c.self_feedback_se = (
            slope_standard_error(c, X, y, target) if c.self_feedback > 0 else None
        )
