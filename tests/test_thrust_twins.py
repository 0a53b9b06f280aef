"""Thrust twins in the cross-validated polish: a height term of the pick without rotor speeds is offered
times the rotors' thrust sum (identification.cv_polish.thrust_twins), as a ground effect scales the thrust;
the polish swaps it in where the data say so. Seeded, small synthetic data."""

from __future__ import annotations

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns
from identification.collinearity import term_shapes
from identification.cross_validation import FoldedRows
from identification.cv_polish import move_candidate, polish_by_cross_validation, thrust_twins
from identification.engine import EngineSettings
from identification.true_model import random_states

S = PRIMITIVE_SYMBOLS
U2 = sum(S[f"u{i}"] ** 2 for i in range(1, 5))


def test_a_height_term_without_rotors_is_offered_times_the_thrust() -> None:
    h, wx, u1, gx = S["h"], S["wx"], S["u1"], S["gx"]
    assert thrust_twins([h**-2, u1 / h, wx, sympy.Integer(1), gx / h**3]) == [U2 / h**2, U2 * gx / h**3]
    assert thrust_twins([]) == []


def test_the_polish_takes_the_law_times_the_thrust_near_hover() -> None:
    """Near hover (rotor speeds 500 +- 50 rad/s) a bare 1/h^2 fits a thrust-scaled ground effect nearly as
    well, and the screening takes the simpler; offered the thrust twin, the polish swaps it in and the
    cross-validated loss falls. Without it, nothing the candidates hold brings the thrust in."""
    rng = np.random.default_rng(3)
    xi, u = random_states(6000, 3)
    xi[:, 2] = -rng.uniform(0.3, 3.0, len(xi))  # NED z: heights 0.3-3 m
    u = rng.uniform(450.0, 550.0, u.shape)
    X = np.hstack([xi, u])
    one, ub, h = sympy.Integer(1), S["ub"], S["h"]
    y = expression_columns([one, ub, U2 / h**2], X) @ np.array([0.03, -0.4, -2e-6])
    y = y + 0.02 * float(np.std(y)) * rng.standard_normal(len(y))
    rows = FoldedRows([(X[:4800], y[:4800], None, 3), (X[4800:], y[4800:], None, 3)], folds=5)
    bare = [one, ub, h**-2]
    picked = move_candidate(bare, rows.loss(sum(bare), "absolute"), rows, "absolute", "t")
    selection = EngineSettings().selection
    alone = polish_by_cross_validation(picked, [picked], rows, "absolute", selection, lambda new: None)
    assert h**-2 in term_shapes(alone.expression)
    final = polish_by_cross_validation(picked, [picked], rows, "absolute", selection, lambda new: None,
                                       extra=thrust_twins(bare))
    assert set(term_shapes(final.expression)) == {one, ub, U2 / h**2}
    assert final.holdout_loss < picked.holdout_loss
