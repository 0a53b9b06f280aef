"""Closed-loop identifiability (issue 12 point 3), small seeded synthetic data with a known answer.

- a genetic-programming term with a pole inside the data (a quotient by a quantity that crosses zero) is no
  physical law and never joins the refit; quotients by quantities that keep their sign do;
- two tied terms that differ by a factor (the rate damping wx and the rotor drag's wx (u1+..+u4) when the
  rotor sum barely varies) are named with the excitation that separates them: vary that factor.
"""

from __future__ import annotations

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, PRIMITIVES, primitive_matrix
from identification.collinearity import model_collinearity, tie_factor
from identification.discovery import inverse_notes, pole_in_data
from identification.engine_settings import DiscoverySettings
from identification.identify import body_collinearity
from identification.model_file import SYMBOLS
from identification.true_model import random_states

P = PRIMITIVE_SYMBOLS


def test_a_term_with_a_pole_inside_the_data_is_recognised():
    xi, u = random_states(500, 3)  # body velocities of both signs, rotor speeds positive
    X = np.hstack([xi, u])
    X[:, 2] = -np.random.default_rng(4).uniform(0.2, 5.0, len(X))  # h in 0.2..5 m
    names = tuple(PRIMITIVES)
    prims = primitive_matrix(X, names)
    vb = prims[:, names.index("vb")]
    assert vb.min() < 0 < vb.max()
    assert pole_in_data(sympy.Abs(P["ub"]) / (P["h"] ** 2 * P["vb"]), names, prims)
    assert pole_in_data(P["wx"] / (P["ub"] + P["vb"]), names, prims)
    assert not pole_in_data(1 / P["h"] ** 2, names, prims)  # h > 0: far from its pole
    assert not pole_in_data(P["vb"] / (P["u2"] * P["u4"]), names, prims)
    assert not pole_in_data(P["ub"] * P["wz"], names, prims)  # no denominator


def test_tied_terms_that_differ_by_a_factor_are_named_with_that_factor():
    rng = np.random.default_rng(7)
    n = 3000
    X = np.zeros((n, 16))
    X[:, 9] = rng.normal(0.0, 1.0, n)  # wx
    X[:, 12:16] = 600.0 * (1.0 + rng.uniform(-0.01, 0.01, (n, 4)))  # rotor sum within ~1 %: collective flat
    wx, total = SYMBOLS["wx"], sum(SYMBOLS[f"u{i}"] for i in range(1, 5))
    model = -5.7e-4 * wx * total  # the damping wx left out: it is the same column times a near constant
    cand = X[:, [9]]
    coll = model_collinearity(model, X, (cand, ["wx"]))
    assert coll.confounders and coll.confounders[0].partner == "wx"
    advice = coll.advice()
    assert "vary u1 + u2 + u3 + u4 more" in advice
    # no factor between unrelated terms, nor a quotient: the per-kind advice stands alone
    assert tie_factor("wy*wz", "wy*u3**2") == ""
    assert tie_factor("u3*wx", "u1*wx") == ""
    assert tie_factor("u1**2 - u2**2", "z*(u1**2 - u2**2)") == "z"
    assert advice.count("vary u1 + u2 + u3 + u4 more") == 1


def test_body_frame_terms_are_named_in_the_primitives_they_were_learned_in():
    xi, u = random_states(800, 11)
    X = np.hstack([xi, u])
    total = P["u1"] + P["u2"] + P["u3"] + P["u4"]
    expr = -1.7e-4 * P["ub"] * total - 0.04 * P["ub"] * sympy.Abs(P["ub"]) + 0.3
    coll = body_collinearity(expr, X)
    assert sorted(t.term for t in coll.terms) == ["ub*(u1 + u2 + u3 + u4)", "ub*Abs(ub)"]


def test_a_flight_that_passes_near_the_ground_says_it_cannot_identify_a_height_law():
    xi, u = random_states(1000, 5)
    X = np.hstack([xi, u])
    rng = np.random.default_rng(6)
    h = rng.uniform(2.7, 4.3, len(X))
    h[:15] = np.linspace(0.2, 1.0, 15)  # a take-off: 1.5 % of the rows near the ground
    X[:, 2] = -h
    notes = inverse_notes(DiscoverySettings(), X)
    assert len(notes) == 1 and notes[0].startswith("h: no 1/h^k features") and "low hover" in notes[0]
    X[:15, 2] = -2.7  # no take-off in the rows: 1/h features are built, nothing to say
    assert inverse_notes(DiscoverySettings(), X) == []
