"""The discovery engine's term-substitution polish (DiscoveryEngine._polish): a picked model with a wrong
term that the sparse paths never leave gets the right one by a single swap (small seeded synthetic data)."""

from __future__ import annotations

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.discovery import DiscoveryEngine, _Columns, term_substitutions
from identification.effects_physics import Effects, flight_rows
from identification.engine import split_holdout
from identification.engine_settings import DiscoverySettings
from identification.pareto import attach_holdout


def test_term_substitutions_match_brute_force_least_squares() -> None:
    """Every swap's RSS from one projection equals the least-squares RSS of the swapped model refit."""
    rng = np.random.default_rng(3)
    n = 400
    M, C = rng.normal(size=(n, 4)), rng.normal(size=(n, 6))
    C[:, 5] = M[:, 1]  # a copy of a model term: no new direction, left out
    y = M @ [1.0, -2.0, 0.5, 0.0] + 3.0 * C[:, 2] + 0.1 * rng.normal(size=n)
    ranked = term_substitutions(M, C, y)
    assert {f for _, f, _ in ranked} == set(range(5))
    for j, f, rss in ranked:
        A = np.hstack([np.ones((n, 1)), np.delete(M, j, axis=1), C[:, [f]]])
        r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        assert abs(rss - float(r @ r)) <= 1e-8 * float(r @ r)
    assert ranked[0][:2] == (3, 2)  # the useless term out, the missing one in


def test_polish_swaps_a_near_copy_for_the_true_term() -> None:
    """A model holding wz^2 |wz| where the data has wz^2 (both even in wz, nearly collinear) is polished into
    the true structure, coefficients recovered."""
    xi, u, _ = flight_rows(1500, 0, "fang-chen-buaa", Effects())
    X = np.hstack([xi, u])
    engine = DiscoveryEngine(DiscoverySettings(polish_passes=3))
    space = engine.build_space(X)
    columns = _Columns(space)
    wx, wy, wz = (PRIMITIVE_SYMBOLS[n] for n in ("wx", "wy", "wz"))
    truth = 2.0 * wx * wy + 0.5 * wz**2 - 1.5 * wy
    P = columns.primitives(X)
    y = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in space.primitives], truth)(*P.T)
    y = y + 1e-3 * np.std(y) * np.random.default_rng(0).normal(size=len(y))
    Xt, yt, Xh, yh = split_holdout(X, y)
    prims = list(space.primitives)
    wrong = engine._linear_candidate([wx * wy, wz**2 * sympy.Abs(wz), wy], prims, columns, Xt, yt,
                                     "absolute", None)
    attach_holdout([wrong], Xh, yh, "absolute")
    F = columns(Xt, np.arange(len(space)))
    pool = [i for i in range(len(space)) if space.rungs[i] == 1]
    assert wz**2 in [space.expressions[i] for i in pool]
    out = engine._polish(wrong, pool, columns, F, yt, Xt, Xh, yh, "absolute", float(np.std(yh)))
    assert out, "no swap accepted"
    best = out[-1]
    assert best.holdout_loss < wrong.holdout_loss
    got = sympy.expand(best.expression)
    assert got.coeff(wz**2) != 0 and not got.has(sympy.Abs)
    assert abs(float(got.coeff(wz**2)) - 0.5) < 1e-2
