"""The cross-validated polish fits only the moves its pick could ever take (identification.cv_polish
_pickable_moves): while the pick passes its rule, a move whose loss is above the tolerance of the best loss
the rule passes is never picked nor sets that tolerance, since the best only falls as candidates join; nor is
a move more complex than the pick and no better (the pick is within the tolerance wherever it is, ahead).

The same pick as fitting every move within the tolerance of the current pick (the polish before session 64,
written out here as the reference); on closed-loop heavy-650-aero's wx' (58 terms) that was 11,475 moves
fitted and marked, 2,577 within the final tolerance. Seeded synthetic data: wx (u1 + .. + u4) and vb with
noise, the polish started from a pick without vb; every one-term move over a pool of products of the rates
and speeds."""

from __future__ import annotations

import numpy as np
import pytest

import identification.cv_polish as cv_polish
from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns
from identification.collinearity import term_shapes
from identification.cross_validation import FoldedRows
from identification.cv_polish import move_candidate, new_shapes, polish_by_cross_validation
from identification.engine import EngineSettings
from identification.pareto import admissible, pick_limit
from identification.refit import terms_candidate
from identification.self_feedback import mark_self_feedback
from identification.true_model import random_states
from tests.test_cv_polish_beam import ONE, ROTORS, TRUTH, VB, WX, _rows

S = PRIMITIVE_SYMBOLS
_BASE = [S["wy"], S["wz"], S["ub"], S["wb"], S["h"], VB, WX]
POOL = [*_BASE, *(a * b for i, a in enumerate(_BASE) for b in _BASE[i:]), ROTORS[0] ** 2, ROTORS[1] ** 2]


def _every_move(eligible, candidates, pool, folded, kind, selection, mark, engine, base, current, size):
    """The reference: every move within the current pick's tolerance fitted (none worse by the rows)."""
    new = [c for value, shapes in eligible
           if not cv_polish._worse(folded, shapes, base, value, current, kind, selection.cv_polish_z)
           and (c := move_candidate(shapes, value, folded, kind, engine)) is not None]
    mark(new)
    return new


def _polish(seed: int, all_tolerated: bool = False) -> tuple:
    rows = _rows(seed)
    selection = EngineSettings().selection
    start = TRUTH[:2]  # vb missing: the move that adds it lowers the best, and most others fall above it
    picked = move_candidate(start, rows.terms_loss(start, "absolute"), rows, "absolute", "discovery")
    other = move_candidate([ONE, *POOL], rows.terms_loss([ONE, *POOL], "absolute"), rows, "absolute", "t")
    candidates = [picked, other]
    final = polish_by_cross_validation(picked, candidates, rows, "absolute", selection, lambda new: None,
                                       rounds=selection.cv_polish_rounds, beam=selection.cv_polish_beam,
                                       all_tolerated=all_tolerated)
    return final, candidates, pick_limit(candidates, selection, rows.scale)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_polish_fits_only_moves_its_pick_could_take_and_picks_the_same(seed, monkeypatch):
    final, candidates, limit = _polish(seed)
    with monkeypatch.context() as m:
        m.setattr(cv_polish, "_pickable_moves", _every_move)
        reference, every, reference_limit = _polish(seed)
    assert term_shapes(final.expression) == term_shapes(reference.expression)
    assert final.holdout_loss == reference.holdout_loss and limit == reference_limit
    kept = {frozenset(term_shapes(c.expression)) for c in candidates}
    left_out = [c for c in every if frozenset(term_shapes(c.expression)) not in kept]
    assert left_out  # the reference fitted moves this polish did not
    # none of them could be picked: above the final tolerance, or a simpler candidate the rule passes is no
    # worse (the pick it was a move of)
    passing = [c for c in candidates if admissible(c, EngineSettings().selection)]
    assert all(c.holdout_loss > limit or any(p.complexity < c.complexity and p.holdout_loss <= c.holdout_loss
                                             for p in passing) for c in left_out)
    assert any(c.holdout_loss <= limit for c in left_out)  # and some left out were within it
    assert kept <= {frozenset(term_shapes(c.expression)) for c in every}


@pytest.mark.parametrize("seed", [0, 1])
def test_with_every_tolerated_move_kept_only_moves_above_the_tolerance_are_left_out(seed, monkeypatch):
    """Where the specification pick follows (it chooses among every candidate within the tolerance), the
    moves more complex than the pick and no better are fitted too: what is left out is above the limit."""
    final, candidates, limit = _polish(seed, all_tolerated=True)
    with monkeypatch.context() as m:
        m.setattr(cv_polish, "_pickable_moves", _every_move)
        reference, every, reference_limit = _polish(seed)
    assert term_shapes(final.expression) == term_shapes(reference.expression) and limit == reference_limit
    kept = {frozenset(term_shapes(c.expression)) for c in candidates}
    left_out = [c for c in every if frozenset(term_shapes(c.expression)) not in kept]
    assert left_out and all(c.holdout_loss > limit for c in left_out)
    within = {frozenset(term_shapes(c.expression)) for c in every if c.holdout_loss <= limit}
    assert within <= kept  # every move within the final tolerance joined



def test_a_moves_expression_is_built_when_read_and_is_the_fitted_sum():
    """The polish fits thousands of moves and reads a few expressions (the pick's, its ties', the front's):
    a move's expression is built when first read, the sum of its fitted terms in sympy's order, and marking
    its self-feedback reads its terms, not the expression. A move whose sum would leave a term out (a zero
    coefficient) is none, as before."""
    rows = _rows(0)
    X = rows.parts[0][0]  # the fit rows' 16 variables
    c = move_candidate(TRUTH, rows.terms_loss(TRUTH, "absolute"), rows, "absolute", "discovery")
    assert c is not None and c.build is not None  # not built yet
    mark_self_feedback([c], X, np.zeros(len(X)), "dwy")  # no term in wy: none, read from its terms
    assert c.self_feedback == 0.0 and c.build is not None
    coef = c.linear[1]
    eager = terms_candidate(TRUTH, coef, "discovery", ordered=True)
    assert c.expression == eager.expression and c.build is None
    assert set(term_shapes(c.expression)) == set(TRUTH)
    np.testing.assert_allclose(c.evaluate(X), eager.evaluate(X), rtol=1e-12)
    # a later polish reads its terms without building it where at most one is new to its pool, and in the
    # order its expression writes them where more are
    d = move_candidate(TRUTH, rows.terms_loss(TRUTH, "absolute"), rows, "absolute", "discovery")
    assert new_shapes(d, {TRUTH[0], TRUTH[2]}) == [TRUTH[1]] and d.build is not None
    assert new_shapes(d, set()) == term_shapes(eager.expression) and d.build is None
    with pytest.MonkeyPatch.context() as m:  # a zero coefficient: its sum would not read back
        m.setattr(rows, "fit_coefficients", lambda s: np.array([coef[0], 0.0, coef[2]]))
        assert move_candidate(TRUTH, 1.0, rows, "absolute", "discovery") is None


def test_a_terms_negation_offered_by_another_candidate_adds_no_move():
    """u1^2 - u2^2 and u2^2 - u1^2 are one column to a linear model: every move with one ties exactly with the
    same move with the other, so which was taken was left to rounding. The polish's pool holds one of them:
    the moves fitted and the pick are those of the polish without the negation offered."""
    twin = ROTORS[0] ** 2 - ROTORS[1] ** 2
    assert -twin != twin  # two shapes to sympy
    xi, _ = random_states(6000, 3)
    rng = np.random.default_rng(3)
    X = np.hstack([xi, 500.0 + 100.0 * rng.standard_normal((6000, 4))])
    y = expression_columns([*TRUTH, twin], X) @ np.array([0.3, 2e-3, -0.4, 2e-6])
    y = y + 0.002 * float(np.std(y)) * rng.standard_normal(len(y))
    rows = FoldedRows([(X[:4800], y[:4800], None, 3), (X[4800:], y[4800:], None, 3)], folds=5)
    selection = EngineSettings().selection

    def terms(c) -> frozenset:
        """A model's terms as the polish chose them (a sum of rotor speeds is one term)."""
        return frozenset(c.linear[0] if c.linear is not None else term_shapes(c.expression))

    def polish(offered: list) -> tuple[set, frozenset]:
        start = TRUTH  # the rotor difference missing: the moves that add it are fitted
        picked = move_candidate(start, rows.terms_loss(start, "absolute"), rows, "absolute", "discovery")
        candidates = [picked] + [move_candidate(s, rows.terms_loss(s, "absolute"), rows, "absolute", "t")
                                 for s in offered]
        first = len(candidates)
        final = polish_by_cross_validation(picked, candidates, rows, "absolute", selection, lambda new: None,
                                           rounds=selection.cv_polish_rounds, beam=selection.cv_polish_beam)
        return {terms(c) for c in candidates[first:]}, terms(final)

    without, pick = polish([[ONE, VB, twin]])
    assert pick == frozenset([*TRUTH, twin])
    with_negation, pick_negation = polish([[ONE, VB, twin], [ONE, -twin]])
    assert not any(-twin in m for m in with_negation)
    assert with_negation == without and pick_negation == pick
