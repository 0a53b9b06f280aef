"""The discovery engine's faster linear algebra gives what the plain computations give (issue 12, speed).

- the pool's independence test (discovery._Basis) tests candidates in blocks: a column is accepted exactly
  when it raises the rank of the pool (the constant and the columns accepted before it), in order, up to
  the limit;
- the backward path keeps its triangular factor up to date by Givens rotations: the same active sets as
  recomputing the removal costs from a fresh QR at every step;
- a problem's solves are kept by active set: the same coefficients, to the bit, as a fresh solve.
"""

from __future__ import annotations

import numpy as np

from identification.discovery import _Basis
from identification.sparse import LeastSquaresProblem, backward_path


def _columns(seed: int, n: int = 600) -> np.ndarray:
    """Independent columns, exact combinations and repeats of them, a zero and a NaN column, shuffled."""
    rng = np.random.default_rng(seed)
    base = rng.standard_normal((n, 12))
    cols = [base[:, j] for j in range(12)]
    for _ in range(60):
        a, b = rng.integers(0, 12, 2)
        cols.append([2.0 * base[:, a] - 3.0 * base[:, b], base[:, a] * base[:, b], base[:, a] + 5.0][_ % 3])
    cols += [np.zeros(n), np.full(n, np.nan)]
    return np.column_stack(cols)[:, rng.permutation(len(cols))]


def test_the_blocked_basis_accepts_a_column_exactly_when_it_raises_the_rank():
    F = _columns(0)
    order = np.arange(F.shape[1])
    for limit in (None, 5, 40):
        basis = _Basis(len(F))
        added = basis.add_first(F, order, limit)
        kept = [np.ones(len(F))]
        expected = []
        for i in order:
            if limit is not None and len(expected) >= limit:
                break
            col = F[:, i]
            if not np.all(np.isfinite(col)):
                continue
            if np.linalg.matrix_rank(np.column_stack([*kept, col])) > len(kept):
                kept.append(col)
                expected.append(int(i))
        assert added == expected
        assert basis.q.shape == (len(F), len(added) + 1)
        assert np.allclose(basis.q.T @ basis.q, np.eye(basis.k), atol=1e-12)
    # a later call extends the same basis: what is already in is rejected
    basis = _Basis(len(F))
    first = basis.add_first(F, order[:30])
    assert basis.add_first(F, np.asarray(first)) == []


def test_the_updated_backward_path_equals_the_path_of_fresh_factorizations():
    rng = np.random.default_rng(2)
    n = 2000
    base = rng.standard_normal((n, 10))
    theta = np.column_stack([np.ones(n), base, base[:, :5] * base[:, 5:], base**2])  # 1 + 10 + 5 + 10
    y = theta[:, [1, 3, 12, 20]] @ np.array([1.0, -0.5, 0.2, 0.01]) + 1e-4 * rng.standard_normal(n)
    problem = LeastSquaresProblem(theta, y)
    path = backward_path(problem, problem.usable.copy())
    idx = np.flatnonzero(problem.usable)
    fresh = []
    while idx.size:
        fresh.append(idx.copy())
        if idx.size == 1:
            break
        idx = np.delete(idx, int(np.argmin(problem.removal_costs(idx))))
    assert [list(np.flatnonzero(a)) for a in path] == [list(i) for i in fresh]
    # the true four terms are the path's four-term set
    assert set(np.flatnonzero(path[-4])) == {1, 3, 12, 20}


def test_a_kept_solve_is_the_fresh_solve_and_a_caller_cannot_change_it():
    rng = np.random.default_rng(4)
    n = 1500
    base = rng.standard_normal((n, 6))
    theta = np.column_stack([np.ones(n), base, base[:, :3] ** 2])
    y = theta[:, [0, 2, 7]] @ np.array([0.3, 1.5, -0.7]) + 1e-3 * rng.standard_normal(n)
    masks = [np.ones(10, bool), np.isin(np.arange(10), [0, 2, 7]), np.isin(np.arange(10), [2, 7])]
    kept = LeastSquaresProblem(theta, y)
    for active in masks:
        first = kept.solve(active)
        first[:] = 99.0  # a caller's edit of its answer
        again = kept.solve(active)
        fresh = LeastSquaresProblem(theta, y).solve(active)  # a new problem: nothing kept yet
        assert np.array_equal(again, fresh)
    assert np.allclose(kept.solve(masks[1])[[0, 2, 7]], [0.3, 1.5, -0.7], atol=1e-3)
