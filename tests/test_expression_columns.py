"""The discovery engine's expression columns (discovery._lambdify): each (primitive matrix, expression) is
evaluated once and kept, so the polish's hundreds of term lists that share all but one term cost one new
column each; the values are those of evaluating every expression anew."""

from __future__ import annotations

import numpy as np
import sympy

import identification.discovery as discovery
import identification.rows_cache as rows_cache
from identification.body_frame import PRIMITIVE_SYMBOLS

PRIMS = ["wx", "wz", "u1"]


def _counting(monkeypatch) -> list[sympy.Expr]:
    """Patch the compiled expressions so that each evaluation is recorded; the list of expressions run."""
    runs: list[sympy.Expr] = []
    compiled = discovery._expression_fn

    def counted(prims: tuple[str, ...], expr: sympy.Expr):
        fn = compiled(prims, expr)

        def run(*args: np.ndarray) -> np.ndarray:
            runs.append(expr)
            return fn(*args)

        return run

    monkeypatch.setattr(discovery, "_expression_fn", counted)
    return runs


def test_columns_are_the_expressions_values_and_shared_terms_are_evaluated_once(monkeypatch) -> None:
    """Two term lists sharing a term on one primitive matrix: the second evaluates only its new term, and
    every column (a constant expression broadcast to the rows) equals a fresh evaluation."""
    runs = _counting(monkeypatch)
    wx, wz, u1 = (PRIMITIVE_SYMBOLS[n] for n in PRIMS)
    P = np.random.default_rng(5).normal(size=(50, 3))
    first = discovery._lambdify(PRIMS, [wx * wz, u1**2, sympy.Integer(2)])(P)
    second = discovery._lambdify(PRIMS, [u1**2, wz * abs(wx)])(P)
    assert runs == [wx * wz, u1**2, sympy.Integer(2), wz * abs(wx)]
    np.testing.assert_array_equal(first, np.column_stack([P[:, 0] * P[:, 1], P[:, 2] ** 2, np.full(50, 2.0)]))
    np.testing.assert_array_equal(second, np.column_stack([P[:, 2] ** 2, P[:, 1] * np.abs(P[:, 0])]))
    second[:, 0] = 0.0  # the caller's matrix is its own: the kept column is not changed through it
    again = discovery._lambdify(PRIMS, [u1**2])(P)
    np.testing.assert_array_equal(again[:, 0], P[:, 2] ** 2)


def test_columns_are_kept_per_matrix_object(monkeypatch) -> None:
    """Another array (even with the same values) is evaluated anew: columns are kept by the primitive
    matrix's identity (identification.rows_cache), while it lives."""
    runs = _counting(monkeypatch)
    wx = PRIMITIVE_SYMBOLS["wx"]
    P = np.random.default_rng(6).normal(size=(20, 3))
    discovery._lambdify(PRIMS, [wx**2])(P)
    discovery._lambdify(PRIMS, [wx**2])(P.copy())
    assert len(runs) == 2
    runs.clear()
    np.testing.assert_array_equal(discovery._lambdify(PRIMS, [wx**2])(P)[:, 0], P[:, 0] ** 2)
    assert runs == []


def test_a_full_store_keeps_no_more_columns(monkeypatch) -> None:
    """Past rows_cache.MAX_BYTES_PER_ARRAY a matrix's store keeps no new column (each is evaluated anew,
    with the same values): memory stays bounded whatever the number of expressions."""
    runs = _counting(monkeypatch)
    monkeypatch.setattr(rows_cache, "MAX_BYTES_PER_ARRAY", 2 * 10 * 8)  # two columns of 10 rows
    wx, wz, u1 = (PRIMITIVE_SYMBOLS[n] for n in PRIMS)
    P = np.random.default_rng(7).normal(size=(10, 3))
    discovery._lambdify(PRIMS, [wx**2, wz**2, u1**2])(P)
    again = discovery._lambdify(PRIMS, [wx**2, wz**2, u1**2])(P)
    assert runs == [wx**2, wz**2, u1**2, u1**2]
    np.testing.assert_array_equal(again, P**2)
