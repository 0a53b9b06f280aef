"""A height law (ground effect) in a body-frame expression: its part that falls off with height, compared.

A ground-effect law such as Cheeseman-Bennett's T/T_inf = 1/(1 - (R/4h)^2) is no monomial of the
primitives, so a learned model holds it as other terms (a series in 1/h, a quotient found by genetic
programming) and a monomial-by-monomial comparison cannot judge it. Instead: the height-dependent part of
an expression is its additive terms that fall off with the height h (m) (a negative power of h, or of a
polynomial in h, among their factors); the rest is what the expression becomes far from the ground. A
learned part is compared with the true one (the true expression minus its no-ground form) by their
relative RMS difference over the rows of a flight, so over the heights, attitudes and rotor speeds flown.
"""

from __future__ import annotations

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, primitive_matrix


def height_terms(expr: sympy.Expr) -> sympy.Expr:
    """The additive terms of a body-frame expression (primitive names) that fall off with the height h."""
    h = PRIMITIVE_SYMBOLS["h"]
    near = []
    for term in sympy.Add.make_args(sympy.expand(expr)):
        power = 0
        for base, exp in term.as_powers_dict().items():
            if h in base.free_symbols and base.is_polynomial(h) and exp.is_number:
                power += sympy.degree(base, h) * exp
        if power < 0:
            near.append(term)
    return sympy.Add(*near)


def body_values(expr: sympy.Expr, X: np.ndarray) -> np.ndarray:
    """A body-frame expression's values (N,) at the rows X (N,16: the 12 states then u1..u4)."""
    names = tuple(sorted(str(s) for s in expr.free_symbols))
    fn = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in names], expr, modules="numpy")
    with np.errstate(all="ignore"):
        values = fn(*primitive_matrix(X, names).T) if names else fn()
    return np.broadcast_to(np.asarray(values, float), (X.shape[0],))


def height_law_error(learned: sympy.Expr, truth: sympy.Expr, X: np.ndarray) -> float | None:
    """The relative RMS difference of the learned height-dependent part from the true one over the rows X
    (N,16); None when the learned expression has no height-dependent part."""
    part = height_terms(learned)
    if part == 0:
        return None
    a, b = body_values(truth, X), body_values(part, X)
    return float(np.sqrt(np.mean((b - a) ** 2) / np.mean(a**2)))
