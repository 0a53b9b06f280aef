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


def test_a_flat_sum_out_of_sympys_order_reads_as_its_rebuilt_sum():
    u1, u2, u3, u4, wx, wz, z = (SYMBOLS[k] for k in ("u1", "u2", "u3", "u4", "wx", "wz", "z"))
    terms = [sympy.Mul(sympy.Float(-1.3e-6), u1**2 + u2**2 + u3**2 + u4**2, evaluate=False),
             -0.006 / z, sympy.Float(0.25), 2.1e-4 * wz * (u1 - u2 + u3 - u4), 0.3 * wx * wz,
             sympy.Mul(sympy.Float(-7e-10), u1 - u2 + u3 + u4, u1**2 - u2**2 - u3**2 + u4**2, evaluate=False)]
    for order in (terms, terms[::-1], terms[2:] + terms[:2]):  # written in the polish's own orders
        expr = sympy.Add(*order, evaluate=False)
        rebuilt = [t.as_coeff_Mul()[1] for t in sympy.Add.make_args(sympy.Add(*order))]
        assert term_shapes(expr) == rebuilt
        assert term_shapes(expr)[0] == 1  # the constant leads, as in sympy's sum
