"""identification.rows_cache: a value computed once per rows array, dropped with the array; and
body_frame.expression_columns through it giving the same columns as a fresh evaluation."""

from __future__ import annotations

import gc

import numpy as np
import sympy

from identification import rows_cache
from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns, primitive_matrix


def test_a_value_is_computed_once_per_rows_array_and_dropped_with_it():
    calls = []

    def compute():
        calls.append(1)
        return np.arange(5.0)

    X = np.zeros((5, 16))
    first = rows_cache.cached(X, "k", compute)
    again = rows_cache.cached(X, "k", compute)
    assert len(calls) == 1 and again is first
    assert not first.flags.writeable  # shared between callers: nobody may change it in place
    other = X.copy()  # the same content, another array: its own entry
    rows_cache.cached(other, "k", compute)
    assert len(calls) == 2
    key = id(X)
    del X, first, again
    gc.collect()
    assert key not in rows_cache._stores  # the entry went with its array


def test_past_the_byte_limit_values_are_computed_and_not_kept(monkeypatch):
    monkeypatch.setattr(rows_cache, "MAX_BYTES_PER_ARRAY", 100)
    X = np.zeros((20, 16))
    calls = []

    def compute():
        calls.append(1)
        return np.ones(20)  # 160 bytes

    rows_cache.cached(X, "big", compute)
    rows_cache.cached(X, "big", compute)
    assert len(calls) == 2


def test_expression_columns_through_the_cache_equal_a_fresh_evaluation():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(200, 16))
    ub, wz, h = (PRIMITIVE_SYMBOLS[n] for n in ("ub", "wz", "h"))
    exprs = [ub * abs(ub), wz ** 2 / h, sympy.Integer(1)]
    cols = expression_columns(exprs, X)
    again = expression_columns(exprs[::-1], X)  # from the cache, in another order
    np.testing.assert_array_equal(again, cols[:, ::-1])
    P = primitive_matrix(X, ("ub", "wz", "h"))
    with np.errstate(all="ignore"):
        expected = np.column_stack([P[:, 0] * np.abs(P[:, 0]), P[:, 1] ** 2 / P[:, 2], np.ones(200)])
    np.testing.assert_allclose(cols, expected, rtol=1e-12)
    cols[:, 0] = 0.0  # the caller's copy: the cached columns are untouched
    np.testing.assert_array_equal(expression_columns(exprs[:1], X)[:, 0], expected[:, 0])
