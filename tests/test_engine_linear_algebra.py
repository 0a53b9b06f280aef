"""The discovery engine's faster linear algebra gives what the plain computations give (issue 12, speed).

- the pool's independence test (discovery._Basis) tests candidates in blocks: a column is accepted exactly
  when it raises the rank of the pool (the constant and the columns accepted before it), in order, up to
  the limit;
- the backward path keeps its triangular factor up to date by Givens rotations: the same active sets as
  recomputing the removal costs from a fresh QR at every step;
- a problem's solves are kept by active set: the same coefficients, to the bit, as a fresh solve;
- a problem is reduced by one factorisation of [S | y] with the constant first, the centred problem read off
  its rows: subset solves and residuals equal plain least squares on the raw rows, with and without the
  constant, with row weights and with features of large mean;
- lstsq_by_qr equals SVD least squares, also on dependent columns;
- the pool's combination test factorises once for every pending feature (lstsq_by_qr with a matrix of
  right-hand sides): the coefficients and the rests of one least-squares solve per feature;
- a term set with dependent columns: each column's removal cost, the set's residual and each candidate's
  gain are those of rank-aware least squares (its dependencies counted once); the backward and forward
  paths drop a dependency's latest column first.
"""

from __future__ import annotations

import numpy as np

from identification.discovery import _Basis
from identification.sparse import LeastSquaresProblem, backward_path, forward_path, lstsq_by_qr


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


def _raw_fit(theta: np.ndarray, y: np.ndarray, w: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted least squares on the raw rows: coefficients and the residual sum of squares."""
    sw = np.sqrt(w)
    coef = np.linalg.lstsq(theta[:, cols] * sw[:, None], y * sw, rcond=None)[0]
    d = (y - theta[:, cols] @ coef) * sw
    return coef, float(d @ d)


def test_one_factorisation_gives_the_raw_least_squares_with_and_without_the_constant():
    rng = np.random.default_rng(7)
    n = 2500
    base = rng.standard_normal((n, 5))
    big = 1e6 + 2e3 * base[:, 0]  # a rotor-speed-squared-like column: large mean, small spread
    theta = np.column_stack([base[:, 1], np.ones(n), big, base[:, 2] * base[:, 3], base[:, 4] ** 2, base[:, 1]
                             * big])
    y = theta @ np.array([0.5, 2.0, 3e-6, -1.2, 0.0, 1e-6]) + 1e-3 * rng.standard_normal(n)
    for w in (np.ones(n), rng.uniform(0.0, 2.0, n)):
        problem = LeastSquaresProblem(theta, y, weights=w)
        assert problem.const_col == 1
        subsets = [[1, 2, 3], [0, 1, 2, 3, 5], [0, 2, 3], [2, 4], [0, 1, 2, 3, 4, 5]]
        rss = {}
        for cols in subsets:
            active = np.isin(np.arange(6), cols)
            expected, rss[tuple(cols)] = _raw_fit(theta, y, w, np.asarray(cols))
            got = problem.solve(active)[cols]
            assert np.allclose(got, expected, rtol=1e-7, atol=1e-12 * np.abs(expected).max())
        # residuals up to a constant per kind (with / without the constant column): differences are exact
        with_c = [c for c in subsets if 1 in c]
        for a, b in zip(with_c, with_c[1:], strict=False):
            mask_a, mask_b = np.isin(np.arange(6), a), np.isin(np.arange(6), b)
            got = problem.rss_reduced(mask_a) - problem.rss_reduced(mask_b)
            assert np.isclose(got, rss[tuple(a)] - rss[tuple(b)], rtol=1e-6, atol=1e-9)
        no_c = [c for c in subsets if 1 not in c]
        got = problem.rss_reduced(np.isin(np.arange(6), no_c[0])) - problem.rss_reduced(
            np.isin(np.arange(6), no_c[1]))
        assert np.isclose(got, rss[tuple(no_c[0])] - rss[tuple(no_c[1])], rtol=1e-6)
        # removal costs: the rise of the residual without each column
        idx = np.array([0, 2, 3, 5])
        costs = problem.removal_costs(idx)
        full = _raw_fit(theta, y, w, idx)[1]
        plain = [_raw_fit(theta, y, w, np.delete(idx, j))[1] - full for j in range(idx.size)]
        assert np.allclose(costs, plain, rtol=1e-6)


def test_lstsq_by_qr_is_svd_least_squares_also_on_dependent_columns():
    rng = np.random.default_rng(8)
    a = rng.standard_normal((300, 6))
    b = rng.standard_normal(300)
    assert np.allclose(lstsq_by_qr(a, b)[0], np.linalg.lstsq(a, b, rcond=None)[0], rtol=1e-10, atol=1e-12)
    dependent = np.column_stack([a, a[:, 2]])  # a repeated column: the minimum-norm answer, as numpy's
    assert np.allclose(lstsq_by_qr(dependent, b)[0], np.linalg.lstsq(dependent, b, rcond=None)[0], atol=1e-10)
    wide = a[:4]  # more columns than rows
    assert np.allclose(lstsq_by_qr(wide, b[:4])[0], np.linalg.lstsq(wide, b[:4], rcond=None)[0], atol=1e-10)


def test_the_batched_combination_test_equals_one_solve_per_feature():
    rng = np.random.default_rng(9)
    n = 800
    A = rng.standard_normal((n, 7))
    A /= np.linalg.norm(A, axis=0)
    V = np.column_stack([A[:, [1, 4]] @ [2.0, -1.0], rng.standard_normal(n), A[:, 0] + 1e-3 * A[:, 6],
                         A @ rng.standard_normal(7) + 1e-5 * rng.standard_normal(n)])
    coefs, rests = lstsq_by_qr(A, V)
    for j in range(V.shape[1]):
        c = np.linalg.lstsq(A, V[:, j], rcond=None)[0]
        assert np.allclose(coefs[:, j], c, rtol=1e-9, atol=1e-11)
        assert np.isclose(rests[j], np.linalg.norm(V[:, j] - A @ c), rtol=1e-8, atol=1e-13)
    assert rests[0] < 1e-12 and rests[1] > 0.5  # an exact combination and an independent feature
    # dependent columns in A (a repeat): the SVD path, the same rests
    Ad = np.column_stack([A, A[:, 3]])
    coefs_d, rests_d = lstsq_by_qr(Ad, V)
    assert np.allclose(rests_d, rests, atol=1e-10)
    assert np.allclose(Ad @ coefs_d, A @ coefs, atol=1e-9)


def _rank_aware_rss(a: np.ndarray, y: np.ndarray) -> float:
    """The least-squares residual sum of squares of y on a's columns, dependent columns counted once."""
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    q = u[:, : int(np.sum(s > 1e-10 * s[0]))].T @ y
    return float(y @ y - q @ q)


def test_removal_costs_of_dependent_columns_are_the_refits_differences():
    """Where some columns are combinations of others, each column's removal cost is what the fit loses
    without it: 0 for every column of a dependency (the others span it), the refit's rise for the rest."""
    rng = np.random.default_rng(1)
    n, p = 500, 30
    theta = rng.normal(size=(n, p))
    theta[:, 7] = theta[:, 2] - 0.5 * theta[:, 11]
    theta[:, 20] = 3.0 * theta[:, 4]
    y = theta[:, :10] @ rng.normal(size=10) + 0.1 * rng.normal(size=n)
    problem = LeastSquaresProblem(theta, y)
    idx = np.arange(p)
    costs = problem.removal_costs(idx)
    base = _rank_aware_rss(problem.scaled, y)
    exact = np.array([_rank_aware_rss(np.delete(problem.scaled, j, axis=1), y) - base for j in range(p)])
    assert np.allclose(costs, exact, rtol=1e-6, atol=1e-9 * float(y @ y)), np.c_[costs, exact]
    assert set(np.flatnonzero(costs == 0.0)) == {2, 4, 7, 11, 20}
    assert costs[0] > 100.0  # a true term: its removal costs the fit
    # the backward path's first step drops a dependency's last column (20), not its other member (4)
    first = backward_path(problem, np.ones(p, bool))[1]
    assert not first[20] and first[4] and first.sum() == p - 1


def test_residuals_and_gains_of_a_dependent_term_set_count_its_dependencies_once():
    """A term set with dependent columns (a forward path started from a model found before) has the
    residual of its independent part, and a candidate's gain is what it takes off that residual; the
    forward path's pruning drops a dependency's latest columns first."""
    rng = np.random.default_rng(2)
    n, p = 400, 30
    theta = rng.normal(size=(n, p))
    theta[:, 2] = theta[:, 0] + theta[:, 1]
    theta[:, 5] = 2.0 * theta[:, 3] - theta[:, 4]
    y = theta[:, :6] @ rng.normal(size=6) + rng.normal(size=n)
    problem = LeastSquaresProblem(theta, y)
    idx = np.arange(6)
    base = _rank_aware_rss(theta[:, idx], y)
    assert abs(problem.rss(idx) - base) <= 1e-9 * base, (problem.rss(idx), base)
    pool = np.arange(6, p)
    gains = problem.addition_gains(idx, pool)
    exact = np.array([base - _rank_aware_rss(theta[:, np.r_[idx, j]], y) for j in pool])
    assert np.allclose(gains, exact, rtol=1e-8, atol=1e-9 * base), np.c_[gains, exact]
    first = forward_path(problem, np.ones(p, bool), 8, initial=idx)[0]
    kept = set(np.flatnonzero(first))
    assert {0, 1, 3, 4} <= kept and not kept & {2, 5}, sorted(kept)
