"""pyoperon behind the engine interface: finds wx' with f2 as an input, a parsable front, repeatable runs."""

from __future__ import annotations

import numpy as np

from identification.engine import (
    Candidate,
    EngineSettings,
    OperonSettings,
    split_holdout,
)
from identification.metrics import loss, r2
from identification.model_file import expression_to_string, parse_expression
from identification.operon_engine import OperonEngine
from identification.pareto import attach_holdout, pareto_front, select
from identification.true_model import random_states, true_model

SMALL = OperonSettings(
    population_size=200, max_length=20, optimizer_iterations=5, n_threads=2
)


def _dwx(n: int, seed: int):
    xi, u = random_states(n, seed)
    X = np.hstack([xi, u])
    return X, true_model("fang-chen-buaa").accelerations(xi, u)[:, 3]


def test_operon_finds_the_roll_torque_term_beats_a_constant_and_repeats():
    X, y = _dwx(1000, seed=21)
    Xt, yt, Xh, yh = split_holdout(X, y)
    runs = []
    for _ in range(2):
        cands = OperonEngine(SMALL).fit(Xt, yt, "dwx", 12, seed=5, loss="absolute")
        assert cands and all(c.engine == "operon" for c in cands)
        runs.append([expression_to_string(c.expression) for c in cands])
    assert runs[0] == runs[1]  # same seed, generation budget: the same front

    attach_holdout(cands, Xh, yh, "absolute")
    best = select(cands, EngineSettings().selection, float(np.std(yh)))
    constant = loss(yh, np.full_like(yh, np.median(yt)), "absolute")
    assert best.holdout_loss < 0.2 * constant
    assert r2(yh, best.evaluate(Xh)) > 0.95
    terms = {str(k) for k in best.expression.expand().as_coefficients_dict()}
    assert {"u1**2", "u2**2", "u3**2", "u4**2"} <= terms  # f2, re-expressed in the raw rotor speeds
    for c in pareto_front(cands):  # every front member is a formula in the 16 variable names, read back
        again = Candidate(parse_expression(expression_to_string(c.expression)), 0, 0.0)
        np.testing.assert_allclose(again.evaluate(Xh), c.evaluate(Xh), rtol=1e-9, atol=1e-9)
