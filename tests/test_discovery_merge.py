"""The merge repair (DiscoveryEngine._merge_repair, DiscoverySettings.polish_merge): a model the VIF rule
alone sets aside because of how a family of terms is written (one factor times rotor combinations) is
rewritten by merging two of its terms into one feature of the grown space; a tied pair whose difference no
single feature holds stays set aside. Small seeded synthetic data with a known answer."""

from __future__ import annotations

import dataclasses

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.discovery import DiscoveryEngine, _Columns, term_merges
from identification.effects_physics import Effects, flight_rows
from identification.engine import split_holdout
from identification.engine_settings import DiscoverySettings, SelectionSettings
from identification.pareto import admissible, attach_holdout, select

wz, u1, u2, u3, u4 = (PRIMITIVE_SYMBOLS[n] for n in ("wz", "u1", "u2", "u3", "u4"))
SUM, BALANCED = u1 + u2 + u3 + u4, u1 - u2 + u3 - u4  # two of the space's signed sums


def test_term_merges_match_brute_force_least_squares() -> None:
    """Every merge's RSS from one QR equals the least-squares RSS of the merged model refit; a candidate in
    the span of the model without the pair is left out, one in the full model's span is kept."""
    rng = np.random.default_rng(3)
    n = 400
    M, C = rng.normal(size=(n, 4)), rng.normal(size=(n, 6))
    C[:, 4] = M[:, 1] - M[:, 2]  # a combination of terms 1 and 2
    C[:, 5] = M[:, 0]  # a copy of term 0
    y = M @ [1.0, -2.0, 2.0, 0.5] + 0.1 * rng.normal(size=n)
    ranked = term_merges(M, C, y, block=4)  # blocks smaller than the candidates: the same answer
    assert len(ranked) == 6 * 6 - 1 - 3  # C4 in the span without (0, 3); C5 without (1, 2), (1, 3), (2, 3)
    for j, k, f, rss in ranked:
        A = np.hstack([np.ones((n, 1)), np.delete(M, [j, k], axis=1), C[:, [f]]])
        r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        assert abs(rss - float(r @ r)) <= 1e-8 * float(r @ r)
    best = ranked[0]
    assert best[:3] == (1, 2, 4)  # terms 1 and 2 (coefficients -2, 2) merged into their difference
    assert ranked == sorted(ranked, key=lambda e: e[3])


def _closed_loop(truth: sympy.Expr, noise: float = 1e-3, n: int = 1500, seed: int = 0):
    """An engine, its space and the fit/pick rows of `truth` on rotor commands tied as a controller ties them:
    a common part (the collective) large beside each rotor's own part, so wz (u1+u2+u3+u4), u2 wz, u4 wz
    are tied (VIF ~900) and wz (u1+u2+u3+u4), wz (u1-u2+u3-u4), wz are not (VIF <= 16)."""
    rng = np.random.default_rng(seed)
    xi, _, _ = flight_rows(n, 0, "fang-chen-buaa", Effects())
    u = 600.0 + 150.0 * rng.normal(size=(n, 1)) + 40.0 * rng.normal(size=(n, 4))
    X = np.hstack([xi, u])
    engine = DiscoveryEngine(DiscoverySettings(polish_passes=3))
    space = engine.build_space(X)
    columns = _Columns(space)
    P = columns.primitives(X)
    y = sympy.lambdify([PRIMITIVE_SYMBOLS[k] for k in space.primitives], truth)(*P.T)
    y = y + noise * np.std(y) * rng.normal(size=n)
    Xt, yt, Xh, yh = split_holdout(X, y)
    return engine, space, columns, columns(Xt, np.arange(len(space))), Xt, yt, Xh, yh


def _fit(engine, space, columns, Xt, yt, Xh, yh, shapes):
    c = engine._linear_candidate(shapes, list(space.primitives), columns, Xt, yt, "absolute", None)
    attach_holdout([c], Xh, yh, "absolute")
    return c


def test_merge_repair_rewrites_a_rotor_family_in_the_signed_sum_basis() -> None:
    """y = a wz (u1+u2+u3+u4) + b wz (u1-u2+u3-u4) + c wz: written with u2 wz and u4 wz for the balanced
    sum (the same span but one direction more), the t rule passes the model and the VIF rule sets it aside
    (VIF 926 asks for t 46, it has 28); the repair merges u2 wz and u4 wz into wz (u1-u2+u3-u4): the true
    structure, passing both rules, its coefficients recovered, and the pick takes it."""
    truth = -3.3e-4 * wz * SUM - 3.0e-5 * wz * BALANCED - 2.7e-3 * wz
    engine, space, columns, F, Xt, yt, Xh, yh = _closed_loop(truth)
    tied = _fit(engine, space, columns, Xt, yt, Xh, yh, [wz * SUM, u2 * wz, u4 * wz, wz])
    sel = engine.selection
    assert tied.weakest_t >= sel.min_t and tied.largest_vif > sel.max_vif
    assert not admissible(tied, sel) and not admissible(tied, dataclasses.replace(sel, vif_rule="cap"))
    scale = float(np.std(yh))
    out = engine._merge_repair(tied, columns, F, yt, Xt, Xh, yh, "absolute", scale)
    assert len(out) == 1 and admissible(out[0], sel)
    got = sympy.expand(out[0].expression).as_coefficients_dict()
    want = sympy.expand(truth).as_coefficients_dict()
    assert {m for m in got if not m.is_number} == set(want)  # the monomials of the truth, no others
    for m, coef in want.items():
        assert abs(float(got[m]) - float(coef)) <= 0.02 * abs(float(coef))
    simpler = _fit(engine, space, columns, Xt, yt, Xh, yh, [wz * SUM, wz])  # misses the balanced sum
    assert select([tied, simpler, *out], sel, scale=scale) is out[0]


def test_merge_repair_leaves_a_tied_pair_set_aside() -> None:
    """y = a wz (u1+u2+u3+u4) + c wz + k wz (u2 - u4), a small effect no single feature of the space holds
    (standing for the targets' small errors that a tied pair fits): u2 wz and u4 wz fit it with cancelling
    coefficients (t >= min_t, VIF ~900), so the pick without the VIF rule takes the tied model. No merge
    keeps that fit, so the repair returns nothing and the pick keeps the model without the pair."""
    truth = -3.3e-4 * wz * SUM - 2.7e-3 * wz + 1e-5 * wz * (u2 - u4)
    engine, space, columns, F, Xt, yt, Xh, yh = _closed_loop(truth)
    tied = _fit(engine, space, columns, Xt, yt, Xh, yh, [wz * SUM, u2 * wz, u4 * wz, wz])
    plain = _fit(engine, space, columns, Xt, yt, Xh, yh, [wz * SUM, wz])
    sel = engine.selection
    scale = float(np.std(yh))
    loose = dataclasses.replace(SelectionSettings(), max_vif=float("inf"))
    assert select([tied, plain], loose, scale=scale) is tied and not admissible(tied, sel)
    coef = tied.expression.as_coefficients_dict()
    assert float(coef[u2 * wz]) * float(coef[u4 * wz]) < 0  # cancelling
    assert engine._merge_repair(tied, columns, F, yt, Xt, Xh, yh, "absolute", scale) == []
    assert select([tied, plain], sel, scale=scale) is plain
