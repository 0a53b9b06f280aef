"""The cross-validated polish leaves out, unfitted and unmeasured, the moves that keep a set of terms the rows
do not separate (identification.cv_polish.tied_subsets): while the pick passes the identification rule, such
a move can never be picked nor set the tolerance, because a term's VIF only grows with the terms beside it.

The library engine's candidates are not measured; on an ArduCopter flight near hover with the yaw held, az's
pick held a tied family of thrust terms and the polish fitted and measured some 12,000 tied swaps one by one
(a test timed out). Seeded synthetic data with the yaw held at 0.3 rad (spread 0.01): wx, wx cos(psi) and
wx sin(psi) are nearly one column."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns
from identification.collinearity import column_collinearity, term_identification, term_shapes
from identification.cross_validation import FoldedRows
from identification.cv_polish import move_candidate, polish_by_cross_validation
from identification.engine import EngineSettings
from identification.model_file import SYMBOLS, VARIABLE_NAMES
from identification.pareto import within_tolerance
from identification.true_model import random_states

S = PRIMITIVE_SYMBOLS
ROTORS = [S[f"u{i}"] for i in range(1, 5)]
ONE, VB, WX, PSI = sympy.Integer(1), S["vb"], S["wx"], SYMBOLS["psi"]
TRUTH = [ONE, WX * sum(ROTORS), VB]
TIED = [WX, WX * sympy.cos(PSI), WX * sympy.sin(PSI)]
_BASE = [S["wy"], S["wz"], S["ub"], S["wb"], S["h"], VB]
POOL = [*_BASE[:-1], *(a * b for i, a in enumerate(_BASE) for b in _BASE[i:]), ROTORS[0] ** 2, ROTORS[1] ** 2]


def _rows(seed: int) -> FoldedRows:
    xi, _ = random_states(5000, seed)
    rng = np.random.default_rng(seed)
    X = np.hstack([xi, 500.0 + 100.0 * rng.standard_normal((5000, 4))])
    X[:, VARIABLE_NAMES.index("psi")] = 0.3 + 0.01 * rng.standard_normal(5000)  # the yaw held
    y = expression_columns(TRUTH, X) @ np.array([0.3, 2e-3, -0.4])
    y = y + 0.002 * float(np.std(y)) * rng.standard_normal(len(y))
    return FoldedRows([(X[:4000], y[:4000], None, 3), (X[4000:], y[4000:], None, 3)], folds=5)


@pytest.mark.parametrize("seed", [0, 1])
def test_moves_keeping_a_tied_set_are_left_out_unfitted_and_each_fails_the_rule(seed):
    rows = _rows(seed)
    selection = EngineSettings().selection
    pick_terms = [*TRUTH, *TIED]
    picked = move_candidate(pick_terms, rows.terms_loss(pick_terms, "absolute"), rows, "absolute", "library")
    picked.measure, picked.weakest_t, picked.largest_vif = None, None, None  # unmeasured, as the library's
    other = move_candidate([ONE, *POOL], rows.terms_loss([ONE, *POOL], "absolute"), rows, "absolute", "t")
    candidates = [picked, other]
    final = polish_by_cross_validation(picked, candidates, rows, "absolute", selection, lambda new: None,
                                       rounds=selection.cv_polish_rounds, beam=selection.cv_polish_beam)
    assert final.holdout_loss <= picked.holdout_loss
    joined = {frozenset(term_shapes(c.expression)) for c in candidates}
    limit = within_tolerance(float(picked.holdout_loss), selection, rows.scale)
    moves = [[*pick_terms, p] for p in POOL]
    moves += [pick_terms[:i] + [p] + pick_terms[i + 1:] for i in range(len(pick_terms)) for p in POOL]
    near = [m for m in moves if rows.terms_loss(m, "absolute") <= limit]
    left_out = [m for m in near if frozenset(m) not in joined]
    assert len(left_out) >= len(POOL)  # at least the additions, each within the tolerance
    for m in left_out:  # the VIF rule would have rejected each of them
        assert rows.identification(m)[1] > selection.max_vif, m


def test_the_polish_fits_every_move_when_no_candidate_passes_the_rule():
    """With no identified candidate the rule does not decide the pick: moves holding a tied set join."""
    rows = _rows(0)
    selection = replace(EngineSettings().selection, max_vif=0.5)  # no model passes: every VIF is >= 1
    pick_terms = [*TRUTH, *TIED]
    picked = move_candidate(pick_terms, rows.terms_loss(pick_terms, "absolute"), rows, "absolute", "t")
    other = move_candidate([ONE, *POOL], rows.terms_loss([ONE, *POOL], "absolute"), rows, "absolute", "t")
    candidates = [picked, other]
    polish_by_cross_validation(picked, candidates, rows, "absolute", selection, lambda new: None, rounds=1)
    limit = within_tolerance(float(picked.holdout_loss), selection, rows.scale)
    adds = [[*pick_terms, p] for p in POOL if rows.terms_loss([*pick_terms, p], "absolute") <= limit]
    joined = {frozenset(term_shapes(c.expression)) for c in candidates}
    assert any(frozenset(m) in joined for m in adds)  # each holds the tied pair of the pick


@pytest.mark.parametrize("seed", range(5))
def test_a_terms_vif_only_grows_with_the_terms_beside_it(seed):
    rng = np.random.default_rng(seed)
    base = rng.standard_normal((2000, 3))
    cols = np.column_stack([base, base @ rng.standard_normal((3, 4)) + 0.3 * rng.standard_normal((2000, 4))])
    names = [str(j) for j in range(cols.shape[1])]
    full = {t.term: t.vif for t in column_collinearity(cols, names, condition=False).terms}
    for drop in range(cols.shape[1]):
        keep = [j for j in range(cols.shape[1]) if j != drop]
        sub = column_collinearity(cols[:, keep], [names[j] for j in keep], condition=False).terms
        assert all(full[t.term] >= t.vif * (1 - 1e-9) for t in sub)


def test_terms_tied_exactly_are_not_identified():
    """A term tied exactly to the others has an infinite VIF: the model is not identified (a column that does
    not vary is the one a model's identification leaves out)."""
    rng = np.random.default_rng(4)
    a, b = rng.standard_normal((2, 3000))
    y = a + 0.5 * b + 0.01 * rng.standard_normal(3000)
    weakest, largest = term_identification(np.column_stack([a, 0.7 * a, b]), y)
    assert largest == np.inf and weakest < 5.0
    weakest, largest = term_identification(np.column_stack([a, b, np.full(3000, 2.0)]), y)
    assert largest < 1.1 and weakest > 100.0
