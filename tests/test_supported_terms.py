"""Terms the flight supports beyond the pick (identification.supported_terms): a small term the rows pin down
is named with its paired t and loss change; a term of pure chance is not; identify writes the names to the
model file and the terminal and keeps the pick; the setting is validated. Seeded synthetic rows."""

from __future__ import annotations

import numpy as np
import pytest
import sympy

from bridge.errors import UserError
from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns
from identification.collinearity import term_shapes
from identification.cross_validation import FoldedRows
from identification.cv_polish import move_candidate
from identification.engine_settings import load_engine_settings
from identification.supported_terms import SupportedTerm, common_factor, supported_additions, supported_line
from identification.true_model import random_states

S = PRIMITIVE_SYMBOLS
BIG = [S["u1"] * S["wz"], S["vb"] * S["wx"], S["wy"]]
SMALL = S["wx"] * S["wz"]
CHANCE = S["ub"] * S["u2"]


def _folded(seed: int, small: float) -> FoldedRows:
    xi, u = random_states(3000, seed)
    X = np.hstack([xi, u])
    big = expression_columns(BIG, X) @ np.array([2e-3, -0.7, 0.4])
    col = expression_columns([SMALL], X)[:, 0]
    noise = 0.01 * np.random.default_rng(seed + 1).standard_normal(len(X))
    y = big + small * 0.01 * col / np.std(col) + noise  # the small term: `small` x the noise's RMS
    return FoldedRows([(X[:2000], y[:2000], None, 5), (X[2000:], y[2000:], None, 5)], 5, 6)


def _candidates(folded: FoldedRows):
    folded.prepare([*BIG, SMALL, CHANCE])
    made = [move_candidate(shapes, folded.terms_loss(shapes, "squared"), folded, "squared", "test")
            for shapes in (BIG, [*BIG, SMALL], [*BIG, CHANCE])]
    assert all(c is not None for c in made)
    return made


@pytest.mark.parametrize("seed", [3, 8])
def test_a_small_term_the_rows_pin_down_is_named_and_a_term_of_chance_is_not(seed):
    folded = _folded(seed, 0.4)
    chosen, *others = _candidates(folded)
    found = supported_additions(chosen, [chosen, *others], folded, "squared", 5.0)
    assert [f.term for f in found] == [SMALL], found
    assert found[0].paired_t <= -5.0 and -0.2 < found[0].loss_change < -0.02
    # the most significant first, up to `limit`, also where a lower bar names more
    assert [f.term for f in supported_additions(chosen, [chosen, *others], folded, "squared", 1e-9,
                                                limit=1)] == [SMALL]
    line = supported_line("dwx", found, folded.blocks)
    assert "wx*wz (t " in line and "30 blocks" in line and line.startswith("note: dwx:")


def test_without_the_small_term_in_the_data_nothing_is_named():
    folded = _folded(3, 0.0)
    chosen, *others = _candidates(folded)
    assert supported_additions(chosen, [chosen, *others], folded, "squared", 5.0) == []


def test_identify_names_a_supported_term_in_the_model_file_and_keeps_the_pick():
    """Through identify, with a tolerance wide enough to leave out a small term the rows pin down: the
    model file's identifiability names it, the chosen expression does not hold it."""
    from dataclasses import replace

    from synthetic_data import synthetic_dataset

    from identification.engine import EngineSettings
    from identification.identify import identify

    ds = synthetic_dataset(4000, seed=5)
    rng = np.random.default_rng(6)
    col = expression_columns([SMALL], np.hstack([ds.xi, ds.u]))[:, 0]
    sigma = 1e-3 * float(np.std(ds.targets[:, 3]))
    ds.targets[:, 3] += sigma * (0.3 * col / np.std(col) + rng.standard_normal(len(col)))
    base = EngineSettings()
    settings = replace(base, selection=replace(base.selection, rel_tol=0.1))
    model = identify(ds, engine="discovery", budget=3, seed=5, progress=False, targets="dwx",
                     settings=settings)
    listed = model.extra["identifiability"]["targets"]["dwx"].get("supported_additions", [])
    assert [entry["term"] for entry in listed][:1] == [str(SMALL)], listed
    assert listed[0]["paired_t"] <= -5.0 and listed[0]["loss_change"] < 0.0
    assert SMALL not in term_shapes(model.targets["dwx"].expression)


def test_a_negative_count_is_a_clear_error(tmp_path):
    path = tmp_path / "engine.yaml"
    path.write_text("selection:\n  report_supported: -1\n", encoding="utf-8")
    with pytest.raises(UserError, match="report_supported"):
        load_engine_settings(path)


def test_the_note_names_a_factor_every_supported_term_shares():
    """The racer's wx' (seed 89) named three look-alikes of the missing wy^2: the note says what they hold."""
    u, wy = S["u1"], S["wy"]
    terms = [S["u4"] * wy**2, wy**2 * sympy.sqrt(u**2 + S["u2"] ** 2), u * wy**2]
    assert common_factor(terms) == wy**2
    assert common_factor([S["wx"] * S["wz"], S["wy"]]) is None and common_factor(terms[:1]) is None
    line = supported_line("dwx", [SupportedTerm(t, -5.2, -0.037) for t in terms], 30)
    assert "each wy**2 times another factor" in line and line.count("(t 5.2, loss -3.7%)") == 3
