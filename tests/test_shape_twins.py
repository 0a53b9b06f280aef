"""Shape twins in the cross-validated polish: the engine proposes, for each term of the pick, the features of
its space over the same primitives most correlated with it (DiscoveryEngine.nearest_features), and the polish
may swap them in though no candidate holds them (identification.cv_polish, SelectionSettings.cv_polish_twins).
Seeded, small synthetic data."""

from __future__ import annotations

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns
from identification.collinearity import term_shapes
from identification.cross_validation import FoldedRows
from identification.cv_polish import move_candidate, polish_by_cross_validation
from identification.discovery import DiscoveryEngine
from identification.effects_physics import Effects, flight_rows
from identification.engine import EngineSettings
from identification.engine_settings import DiscoverySettings
from identification.true_model import random_states

S = PRIMITIVE_SYMBOLS


def _twin_rows(seed: int) -> tuple[FoldedRows, sympy.Expr, sympy.Expr, sympy.Expr]:
    xi, u = random_states(6000, seed)
    X = np.hstack([xi, u])
    one, vb, wz = sympy.Integer(1), S["vb"], S["wz"]
    y = expression_columns([one, vb, wz**2], X) @ np.array([0.1, -0.4, 0.6])
    y = y + 0.05 * float(np.std(y)) * np.random.default_rng(seed).standard_normal(len(y))
    return FoldedRows([(X[:4800], y[:4800], None, 3), (X[4800:], y[4800:], None, 3)], folds=5), one, vb, wz


def test_the_polish_swaps_in_a_twin_no_candidate_holds():
    rows, one, vb, wz = _twin_rows(7)
    twin = sympy.Abs(wz)  # even in wz as wz^2 is: the paths may stop there
    picked = move_candidate([one, vb, twin], rows.loss(one + vb + twin, "absolute"), rows, "absolute", "t")
    selection = EngineSettings().selection
    alone = polish_by_cross_validation(picked, [picked], rows, "absolute", selection, lambda new: None)
    assert twin in term_shapes(alone.expression)  # nothing else to swap in
    final = polish_by_cross_validation(picked, [picked], rows, "absolute", selection, lambda new: None,
                                       extra=[wz**2, wz**3])
    assert {str(s) for s in term_shapes(final.expression)} == {"1", "vb", "wz**2"}
    assert final.holdout_loss < picked.holdout_loss


def test_the_engine_proposes_twins_over_the_same_primitives():
    xi, u, _ = flight_rows(1500, 0, "fang-chen-buaa", Effects())
    X = np.hstack([xi, u])
    wx, wy, wz = (S[n] for n in ("wx", "wy", "wz"))
    y = expression_columns([wx * wy, wz**2, wy], X) @ np.array([2.0, 0.5, -1.5])
    engine = DiscoveryEngine(DiscoverySettings(rounds=1, polish_passes=0))
    assert engine.nearest_features([sympy.Abs(wz)], 3) == []  # no fit yet: no space
    engine.fit(X, y, "dwy", budget=0, seed=0)
    near = engine.nearest_features([sympy.Abs(wz)], 3)
    assert len(near) == 3 and wz**2 in near and sympy.Abs(wz) not in near
    assert all(e.free_symbols == {wz} for e in near)
    both = engine.nearest_features([sympy.Abs(wz), wx * wy], 2)
    assert both[:2] == near[:2] and all(e.free_symbols == {wx, wy} for e in both[2:]) and len(both) == 4
    assert engine.nearest_features([sympy.Abs(wz)], 0) == []
