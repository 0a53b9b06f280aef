"""The discovery engine's term-substitution polish (DiscoveryEngine._polish): a picked model with a wrong
term that the sparse paths never leave gets the right one by a single swap (small seeded synthetic data)."""

from __future__ import annotations

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.discovery import DiscoveryEngine, _Columns, term_splits, term_substitutions
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


def test_term_splits_match_brute_force_least_squares() -> None:
    """Every split's RSS (one term for two candidates) from one projection equals the refit's RSS, and the
    best split is the wrong term out and the two missing ones in."""
    rng = np.random.default_rng(4)
    n = 500
    M, C = rng.normal(size=(n, 3)), rng.normal(size=(n, 6))
    M[:, 2] = C[:, 0] + C[:, 1] + 0.3 * rng.normal(size=n)  # a stand-in for the two: near their sum
    y = M[:, :2] @ [1.0, -2.0] + 2.0 * C[:, 0] + 2.0 * C[:, 1] + 0.05 * rng.normal(size=n)
    splits = term_splits(M, C, y, width=6)
    assert splits and all(a < b for _, a, b, _ in splits)
    for j, a, b, rss in splits:
        A = np.hstack([np.ones((n, 1)), np.delete(M, j, axis=1), C[:, [a, b]]])
        r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        assert abs(rss - float(r @ r)) <= 1e-8 * float(r @ r)
    assert splits[0][:3] == (2, 0, 1)
    single = term_substitutions(M, C, y)[0][2]
    assert splits[0][3] < 0.1 * single  # no one-term swap comes near


def test_polish_splits_a_stand_in_for_two_true_terms() -> None:
    """A model holding |wx| |wy| where the data has wx^2 + wy^2 (even in both rates, like the pair) is
    polished into the true structure by a split; without splits (polish_split_width 0) it stays."""
    xi, u, _ = flight_rows(1500, 0, "fang-chen-buaa", Effects())
    X = np.hstack([xi, u])
    wx, wy, wz = (PRIMITIVE_SYMBOLS[n] for n in ("wx", "wy", "wz"))
    truth = 2.0 * wx * wz + 0.3 * wx**2 + 0.3 * wy**2 - 1.5 * wy
    results = {}
    for width in (30, 0):
        engine = DiscoveryEngine(DiscoverySettings(polish_passes=3, polish_split_width=width))
        space = engine.build_space(X)
        columns = _Columns(space)
        P = columns.primitives(X)
        y = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in space.primitives], truth)(*P.T)
        y = y + 1e-3 * np.std(y) * np.random.default_rng(0).normal(size=len(y))
        Xt, yt, Xh, yh = split_holdout(X, y)
        stand_in = engine._linear_candidate([wx * wz, sympy.Abs(wx) * sympy.Abs(wy), wy],
                                            list(space.primitives), columns, Xt, yt, "absolute", None)
        attach_holdout([stand_in], Xh, yh, "absolute")
        F = columns(Xt, np.arange(len(space)))
        pool = [i for i in range(len(space)) if space.rungs[i] <= 2]
        assert {wx**2, wy**2} <= {space.expressions[i] for i in pool}
        out = engine._polish(stand_in, pool, columns, F, yt, Xt, Xh, yh, "absolute", float(np.std(yh)))
        results[width] = sympy.expand(out[-1].expression) if out else sympy.expand(stand_in.expression)
    got = results[30]
    assert got.coeff(wx**2) != 0 and got.coeff(wy**2) != 0 and not got.has(sympy.Abs), got
    assert abs(float(got.coeff(wx**2)) - 0.3) < 1e-2 and abs(float(got.coeff(wy**2)) - 0.3) < 1e-2
    assert results[0].has(sympy.Abs)  # one-term swaps alone do not leave the stand-in


def _polished(X: np.ndarray, truth: sympy.Expr, shift: float, noise: float, terms: list[sympy.Expr],
              settings: DiscoverySettings, rungs: int, constant: bool = True) -> sympy.Expr:
    """The polish of the model `terms` (fitted to truth + shift + noise x its std on X's rows) over the pool
    of the space's features up to `rungs`: the last accepted model's expression, or the start's."""
    engine = DiscoveryEngine(settings)
    space = engine.build_space(X)
    columns = _Columns(space)
    P = columns.primitives(X)
    y = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in space.primitives], truth)(*P.T)
    y = y + shift + noise * np.std(y) * np.random.default_rng(0).normal(size=len(y))
    Xt, yt, Xh, yh = split_holdout(X, y)
    pick = engine._linear_candidate(terms, list(space.primitives), columns, Xt, yt, "absolute", None,
                                    constant=constant)
    attach_holdout([pick], Xh, yh, "absolute")
    F = columns(Xt, np.arange(len(space)))
    pool = [i for i in range(len(space)) if space.rungs[i] <= rungs]
    shapes = {space.expressions[i] for i in pool}
    assert all(t.as_coeff_Mul()[1] in shapes | set(terms) for t in sympy.Add.make_args(truth))
    out = engine._polish(pick, pool, columns, F, yt, Xt, Xh, yh, "absolute", float(np.std(yh)))
    return sympy.expand(out[-1].expression if out else pick.expression)


def test_polish_adds_a_constant_the_model_left_out() -> None:
    """A sensor bias beside a large term: the pick without a constant gets it from the polish's toggle
    (polish_constant), and keeps its structure; with the toggle off it stays without."""
    xi, u, _ = flight_rows(1500, 0, "fang-chen-buaa", Effects())
    X = np.hstack([xi, u])
    wx, wy = (PRIMITIVE_SYMBOLS[n] for n in ("wx", "wy"))
    truth = 2.0 * wx * wy - 0.8 * wy
    got = {toggle: _polished(X, truth, -0.015, 1e-3, [wx * wy, wy],
                             DiscoverySettings(polish_passes=3, polish_constant=toggle), 1, constant=False)
           for toggle in (True, False)}
    constant = sum(t for t in sympy.Add.make_args(got[True]) if t.is_number)
    assert abs(float(constant) + 0.015) < 1e-3, got[True]
    assert set(got[True].free_symbols) == {wx, wy} and len(sympy.Add.make_args(got[True])) == 3, got[True]
    assert abs(float(got[True].coeff(wx * wy)) - 2.0) < 1e-2
    assert not any(t.is_number for t in sympy.Add.make_args(got[False])), got[False]


def test_polish_joins_two_stand_ins_into_the_true_term() -> None:
    """A model holding |vb| + vb^2 |vb| where the noisy data has vb^2: neither one-term swap is better by the
    standard errors (each leaves the other stand-in in), so the swaps never leave it; a join (two terms for
    one pool feature, term_merges) does, coefficients recovered. With polish_joins off the model stays."""
    xi, u, _ = flight_rows(3000, 0, "fang-chen-buaa", Effects())
    X = np.hstack([xi, u])
    wx, wy, wz, vb = (PRIMITIVE_SYMBOLS[n] for n in ("wx", "wy", "wz", "vb"))
    truth = 2.0 * wx * wz + 0.3 * vb**2 - 1.5 * wy
    got = {joins: _polished(X, truth, 0.0, 0.05, [wx * wz, sympy.Abs(vb), vb**2 * sympy.Abs(vb), wy],
                            DiscoverySettings(polish_passes=3, polish_joins=joins), 2)
           for joins in (True, False)}
    assert not got[True].has(sympy.Abs) and abs(float(got[True].coeff(vb**2)) - 0.3) < 3e-3, got[True]
    assert got[False].has(sympy.Abs), got[False]


def test_the_polish_measures_its_moves_where_the_pick_does() -> None:
    """With DiscoveryEngine.identification set (identify: FoldedRows.identification, the fit and pick rows)
    the polish's moves are measured by it, not on the fit rows: a rule that identifies no term leaves the
    polish nothing to take, where the fit rows let it swap in the true term."""
    xi, u, _ = flight_rows(1500, 0, "fang-chen-buaa", Effects())
    X = np.hstack([xi, u])
    wx, wy, wz = (PRIMITIVE_SYMBOLS[n] for n in ("wx", "wy", "wz"))
    results = {}
    for hook in (None, "never"):
        engine = DiscoveryEngine(DiscoverySettings(polish_passes=3))
        space = engine.build_space(X)
        columns = _Columns(space)
        P = columns.primitives(X)
        truth = 2.0 * wx * wy + 0.5 * wz**2 - 1.5 * wy
        y = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in space.primitives], truth)(*P.T)
        y = y + 1e-3 * np.std(y) * np.random.default_rng(0).normal(size=len(y))
        Xt, yt, Xh, yh = split_holdout(X, y)
        prims = list(space.primitives)
        asked: list[list[sympy.Expr]] = []
        if hook == "never":
            def never(shapes: list[sympy.Expr], asked: list = asked) -> tuple[float, float]:
                asked.append(list(shapes))
                return 0.0, float("inf")
            engine.identification = never
        wrong = engine._linear_candidate([wx * wy, wz**2 * sympy.Abs(wz), wy], prims, columns, Xt, yt,
                                         "absolute", None)
        attach_holdout([wrong], Xh, yh, "absolute")
        F = columns(Xt, np.arange(len(space)))
        pool = [i for i in range(len(space)) if space.rungs[i] == 1]
        results[hook] = engine._polish(wrong, pool, columns, F, yt, Xt, Xh, yh, "absolute", float(np.std(yh)))
        if hook == "never":
            assert asked and all(shapes for shapes in asked)  # every move measured by the hook
            assert wrong.measured().weakest_t == 0.0
    assert results[None] and not results["never"]
