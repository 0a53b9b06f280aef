"""A screened feature that is a combination of pool features takes one's place (issue 12, seeded, fast).

The pool keeps independent columns only, so with u2 wz, u4 wz and wz (u1 - u2 + u3 - u4) in it,
wz (u1 + u2 + u3 + u4) = wz (u1 - u2 + u3 - u4) + 2 u2 wz + 2 u4 wz never came in, and a small common
part c wz (u1 + u2 + u3 + u4) had to be written as two terms of coefficient 2c, each below the pick's t
ratio (fang-chen-aero's dwx). identification.discovery._swap_in_combinations swaps it in for one member:
the pool spans the same space and stays independent.
"""

from __future__ import annotations

import numpy as np

from identification.discovery import _Basis, _model_t, _swap_in_combinations


def _columns(n: int = 3000, seed: int = 0) -> np.ndarray:
    """Columns: 0 wz (u1 - u2 + u3 - u4), 1 u2 wz, 2 u4 wz, 3 ub, 4 wz (u1 + u2 + u3 + u4), 5 vb wz."""
    rng = np.random.default_rng(seed)
    u = 600.0 * (1.0 + rng.uniform(-0.05, 0.05, (n, 4)))
    wz, ub, vb = rng.normal(0.0, 1.0, (3, n))
    return np.column_stack([wz * (u[:, 0] - u[:, 1] + u[:, 2] - u[:, 3]), u[:, 1] * wz, u[:, 3] * wz, ub,
                            wz * u.sum(axis=1), vb * wz])


def _rank(F: np.ndarray, cols: list[int]) -> int:
    A = np.hstack([np.ones((len(F), 1)), F[:, cols]])
    return int(np.linalg.matrix_rank(A / np.linalg.norm(A, axis=0)))


def test_a_combination_of_model_terms_replaces_the_one_the_flight_pins_down_least():
    F = _columns()
    rng = np.random.default_rng(1)
    # the truth: -7.1e-5 wz (u1 - u2 + u3 - u4) - 2.2e-6 wz (u1 + ..): in the pool's terms u2 wz and u4 wz
    # carry 2 x (-2.2e-6) each, small against the noise
    truth = -7.1e-5 * F[:, 0] - 2.2e-6 * F[:, 4] + 0.3 * F[:, 3]
    y = truth + rng.normal(0.0, 2e-3, len(F))
    pool = [3, 0, 1, 2]
    model_t = _model_t(F, np.array([3, 0, 1, 2]), y)
    weakest = min((1, 2), key=lambda i: model_t[i])
    scores = np.zeros(F.shape[1])
    swapped = _swap_in_combinations(F, pool, [4, 5], {3}, scores, model_t)
    assert swapped == [4]  # vb wz is independent of the pool: left alone
    assert pool == [3, 0, 1, 2][:pool.index(4)] + [4] + [3, 0, 1, 2][pool.index(4) + 1:]
    assert weakest not in pool and 4 in pool and len(pool) == 4
    assert _rank(F, pool) == _rank(F, [3, 0, 1, 2]) == 5  # the same span, still independent
    # rewritten with the combination, the split part is one term and the other member's weight vanishes
    A = np.hstack([np.ones((len(F), 1)), F[:, pool]])
    coef = np.linalg.lstsq(A, truth, rcond=None)[0]
    other = ({1, 2} - {weakest}).pop()
    assert abs(coef[1 + pool.index(other)]) < 1e-6 * 2.2e-6
    assert abs(coef[1 + pool.index(4)] / -2.2e-6 - 1.0) < 1e-6
    assert model_t[weakest] < 5.0  # the pick's min_t: written with u2 wz and u4 wz, not identified


def test_a_member_outside_the_model_goes_first_by_its_screening_score():
    F = _columns()
    pool = [3, 0, 1, 2]
    scores = np.array([0.0, 0.4, 0.1, 0.0, 0.0, 0.0])  # u4 wz adds least to the model
    assert _swap_in_combinations(F, pool, [4], set(), scores, {3: 50.0, 0: 40.0}) == [4]
    assert pool == [3, 0, 1, 4]


def test_rung_one_members_are_never_replaced_and_an_independent_feature_is_left_alone():
    F = _columns()
    pool = [3, 0, 1, 2]
    assert _swap_in_combinations(F, pool, [4], {0, 1, 2}, np.zeros(6), {}) == []
    assert pool == [3, 0, 1, 2]
    pool = [3, 0, 1]  # without u4 wz the sum is no combination of the pool
    assert _swap_in_combinations(F, pool, [4], set(), np.zeros(6), {}) == []
    assert pool == [3, 0, 1]


def test_the_rounds_basis_gives_the_swaps_the_rows_give():
    """With the rounds' basis of the pool (_Basis.coordinates) the least squares runs on the columns'
    coordinates, not the N rows: the same swaps, and after a swap and a grown basis the same again."""
    F = _columns()
    rng = np.random.default_rng(1)
    y = -7.1e-5 * F[:, 0] - 2.2e-6 * F[:, 4] + 0.3 * F[:, 3] + rng.normal(0.0, 2e-3, len(F))
    model_t = _model_t(F, np.array([3, 0, 1, 2]), y)
    for scores in (np.zeros(6), np.array([0.0, 0.4, 0.1, 0.0, 0.0, 0.0])):
        for fixed, t in (({3}, model_t), (set(), {3: 50.0, 0: 40.0}), ({0, 1, 2}, {})):
            rows, coords = [3, 0, 1, 2], [3, 0, 1, 2]
            basis = _Basis(len(F))
            assert basis.add_first(F, coords) == coords
            expected = _swap_in_combinations(F, rows, [4, 5], fixed, scores, t)
            assert _swap_in_combinations(F, coords, [4, 5], fixed, scores, t, basis=basis) == expected
            assert coords == rows
    basis = _Basis(len(F))
    pool = basis.add_first(F, [3, 0, 1])
    assert _swap_in_combinations(F, pool, [4], set(), np.zeros(6), {}, basis=basis) == []  # not in the span
    pool += basis.add_first(F, [2, 5])  # the basis grows: the kept coordinates are extended
    assert _swap_in_combinations(F, pool, [4], {3, 5}, np.zeros(6), {}, basis=basis) == [4]
    assert 4 in pool and len(pool) == 5
    assert basis.coordinates(F, []).shape == (basis.k, 0)
