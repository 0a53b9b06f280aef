"""term_shapes: the distinct additive terms of an expression, coefficients dropped; cached, so a caller that
edits the list it got must not change what the next caller gets."""

from __future__ import annotations

import sympy

from identification.collinearity import term_shapes
from identification.model_file import SYMBOLS


def test_nested_sums_flatten_coefficients_drop_and_a_constant_is_one():
    u1, u2, wx, wz = (SYMBOLS[k] for k in ("u1", "u2", "wx", "wz"))
    shared = sympy.Mul(sympy.Float(3.5e-6), sympy.Add(u1**2, u2**2), evaluate=False)  # one coefficient
    inner = sympy.Add(-0.2 * wx * wz, 9.8, evaluate=False)
    expr = sympy.Add(shared, inner, 0.1 * wx * wz, evaluate=False)
    assert term_shapes(expr) == [sympy.Integer(1), u1**2 + u2**2, wx * wz]


def test_a_caller_editing_its_list_does_not_change_the_next_answer():
    wx, wy = SYMBOLS["wx"], SYMBOLS["wy"]
    expr = 2.0 * wx + 3.0 * wy
    first = term_shapes(expr)
    first.append(sympy.Symbol("junk"))
    first.remove(wx)
    assert term_shapes(expr) == [wx, wy]
