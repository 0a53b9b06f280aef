"""The pick's ground-effect law refit beside its other terms (identification.law_refit)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns
from identification.cross_validation import FoldedRows
from identification.engine import EngineSettings
from identification.engine_settings import load_engine_settings
from identification.hub_law import HubLaw
from identification.law_refit import is_hub_law, refit_law
from identification.true_model import random_states

S = PRIMITIVE_SYMBOLS
OFFSETS = ((0.16, 0.16, -0.04), (-0.16, -0.16, -0.04), (0.16, -0.16, -0.04), (-0.16, 0.16, -0.04))


def _rows(n: int, seed: int) -> np.ndarray:
    """States near the ground: heights 0.4-1.5 m, tilts within 0.3 rad, rotors 400-600 rad/s."""
    xi, u = random_states(n, seed)
    rng = np.random.default_rng(seed)
    xi[:, 2] = -rng.uniform(0.4, 1.5, n)
    xi[:, 6:8] = rng.uniform(-0.3, 0.3, (n, 2))
    xi[:, 3:6] *= 0.3
    return np.hstack([xi, 400.0 + 0.2 * u])


def _law(scale: np.ndarray) -> sympy.Expr:
    b = np.array([[2e-8, 5e-9, 1e-9]] * 4) * scale[:, None]
    c = np.array([[4e-5, 1e-5, 2e-6]] * 4) * scale[:, None]
    return HubLaw(OFFSETS, tuple(map(tuple, b)), tuple(map(tuple, c))).expression()


def test_a_stale_law_is_refit_to_the_flights_law_beside_the_other_terms():
    """The law's parts, fitted beside other terms than the pick's, are rescaled by least squares beside the
    pick's terms: the refit law is the flight's law, its other terms and order kept."""
    X = _rows(3000, 21)
    true_law = _law(np.array([1.0, 0.94, 1.0, 1.0]))  # rotor 2 weaker
    stale = _law(np.array([1.3, 0.7, 1.1, 0.8]))
    y = expression_columns([S["wx"], true_law], X) @ np.array([-0.004, 1.0])
    rows = FoldedRows([(X[:2000], y[:2000], None, 5), (X[2000:], y[2000:], None, 5)], 5)
    refit = refit_law([S["wx"], stale], rows)
    assert refit is not None and refit[0] == S["wx"] and is_hub_law(refit[1])
    law_values, true_values = expression_columns([refit[1], true_law], X).T
    assert np.max(np.abs(law_values - true_values)) < 1e-9 * np.max(np.abs(true_values))
    assert refit_law(refit, rows) is None  # refit once more: the same law


@pytest.mark.parametrize("term", [S["wz"] * (S["u1"] - S["u2"] + S["u3"] - S["u4"]),
                                  (S["u1"] ** 2 + S["u2"] ** 2) / S["h"] ** 2, S["wx"] + S["h"]])
def test_only_a_hub_law_is_refit(term):
    """A rotor pattern, a height term of the series or a sum without the hubs' heights is not a hub law:
    a model without one has nothing to refit."""
    assert not is_hub_law(term) and is_hub_law(_law(np.ones(4)))
    X = _rows(500, 22)
    rows = FoldedRows([(X[:400], X[:400, 9], None, 5), (X[400:], X[400:, 9], None, 5)], 5)
    assert refit_law([S["wx"], term], rows) is None


def test_the_settings_file_without_the_law_refit_loads():
    path = Path(__file__).resolve().parent.parent / "bench" / "settings" / "no-law-refit.yaml"
    assert load_engine_settings(path).selection.cv_polish_law_refits == 0
    assert EngineSettings().selection.cv_polish_law_refits == 2
