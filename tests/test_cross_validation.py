"""Blocked K-fold cross-validation as the pick's evidence (identification.cross_validation,
SelectionSettings.cv_folds): each held-out prediction from a fit without its fold and the gap rows, the
loss that ranks a true structure over a near-twin on noisy data, and identify's record of it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import sympy
from synthetic_data import synthetic_dataset

from bridge.errors import UserError
from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns
from identification.collinearity import term_shapes
from identification.cross_validation import FoldedRows
from identification.cv_polish import move_candidate, polish_by_cross_validation
from identification.engine import EngineSettings
from identification.engine_settings import load_engine_settings
from identification.identify import identify
from identification.pareto import select
from identification.true_model import random_states
from identification.weak_form import WeakSettings, weak_operator

S = PRIMITIVE_SYMBOLS


def _rows(n: int, seed: int) -> np.ndarray:
    xi, u = random_states(n, seed)
    return np.hstack([xi, u])


@pytest.mark.parametrize("per_fold", [1, 3])
def test_each_held_out_prediction_comes_from_a_fit_without_its_fold_and_the_gap(per_fold):
    X = _rows(900, 3)
    shapes = [sympy.Integer(1), S["u1"] * S["wz"], S["vb"] * S["wx"]]
    y = expression_columns(shapes, X) @ np.array([0.3, 2e-3, -0.7])
    y = y + 0.05 * np.random.default_rng(4).standard_normal(len(y))
    rows = FoldedRows([(X[:600], y[:600], None, 7), (X[600:], y[600:], None, 7)], 4, per_fold)
    pred = rows.predictions(shapes)
    a = expression_columns(shapes, X)
    bounds = np.linspace(0, 900, 4 * per_fold + 1).round().astype(int)
    for k in range(4):
        train, held = np.ones(900, bool), np.zeros(900, bool)
        for b in range(k, 4 * per_fold, 4):  # fold k: blocks k, k + 4, ...
            train[max(bounds[b] - 7, 0):bounds[b + 1] + 7] = False
            held[bounds[b]:bounds[b + 1]] = True
        coef = np.linalg.lstsq(a[train], y[train], rcond=None)[0]
        np.testing.assert_allclose(pred[held], a[held] @ coef, rtol=1e-7, atol=1e-9)
    rows.prepare([S["wy"], *shapes, S["u2"]])  # from the Gram matrices of a pool of terms: the same
    np.testing.assert_allclose(rows.predictions(shapes), pred, rtol=1e-7, atol=1e-9)
    direct = FoldedRows(rows.parts, 4, per_fold).predictions(shapes[1:])
    np.testing.assert_allclose(rows.predictions(shapes[1:]), direct, rtol=1e-7, atol=1e-9)


def test_weak_rows_are_folded_after_integration():
    X = _rows(1200, 5)
    t = np.arange(1200) * 0.004
    op = weak_operator(t, WeakSettings(half_window_s=0.05, stride_s=0.02))
    shapes = [S["u1"] * S["wz"], S["wy"]]
    y = expression_columns(shapes, X) @ np.array([1e-3, -0.4])
    rows = FoldedRows([(X, y, op, 5)], folds=5)
    assert len(rows.y) == op.shape[0]
    np.testing.assert_allclose(rows.column(shapes[1]), op @ X[:, 10], rtol=1e-12)
    assert rows.loss(sympy.Add(*shapes), "squared") < 1e-9 * np.std(rows.y)  # exact terms: no error


def test_a_moves_t_ratios_use_the_fit_rows_stated_noise():
    """cv_polish's moves are measured on the fit rows as the engine's candidates are: under the whitener
    of those weak rows when one is given (collinearity.term_identification), else by effective rows."""
    from identification.collinearity import term_identification
    from identification.cv_polish import move_candidate
    from identification.weak_noise import STEP_DIFFERENCE, weak_whitener

    rng = np.random.default_rng(4)
    X = _rows(1200, 5)
    t = np.arange(1200) * 0.004
    op = weak_operator(t, WeakSettings(half_window_s=0.05, stride_s=0.02))
    shapes = [S["u1"] * S["wz"], S["wy"]]
    y = expression_columns(shapes, X) @ np.array([1e-3, -0.4]) + np.diff(rng.normal(0, 0.05, 1201)) / 0.004
    noise = weak_whitener(op, t, None, STEP_DIFFERENCE)
    for given in (noise, None):
        rows = FoldedRows([(X, y, op, 5)], folds=5, fit_noise=given)
        move = move_candidate(shapes, 1.0, rows, "squared", "test")
        a, yy, lag = rows.fit_part(shapes)
        # the same least squares (without stated noise: from the pool's factorisation, to rounding)
        assert move.measured().weakest_t == pytest.approx(term_identification(a, yy, lag, given)[0], rel=1e-9)
    assert term_identification(a, yy, lag, noise)[0] != term_identification(a, yy, lag)[0]


def test_the_cross_validated_loss_ranks_the_true_term_over_its_near_twin():
    # u wz against u^2 wz with u in a narrow band (rotors near one level): nearly one column
    rng = np.random.default_rng(11)
    X = _rows(5000, 7)
    X[:, 12] = 500.0 + 40.0 * np.sin(np.arange(5000) * 0.01) + 5 * rng.standard_normal(5000)
    true, twin = S["u1"] * S["wz"], S["u1"] ** 2 * S["wz"]
    y = 3e-4 * expression_columns([true], X)[:, 0] + 0.02 * rng.standard_normal(5000)
    rows = FoldedRows([(X[:4000], y[:4000], None, 3), (X[4000:], y[4000:], None, 3)], folds=5)
    assert rows.loss(true, "absolute") < rows.loss(twin, "absolute")


def test_identify_records_the_cross_validation_and_refits_on_the_folds(tmp_path):
    data = synthetic_dataset(7500, seed=9, noise=0.03)  # 30 s: 6000 fit and pick rows, 0.4 s gaps
    cv = EngineSettings()  # the default: 5 folds
    base = replace(cv, selection=replace(cv.selection, cv_folds=0))
    model = identify(data, engine="sparse", targets=["dwx"], loss="squared", settings=cv, progress=False)
    record = model.extra["data"]
    # blocks of at least 4 gaps (400 rows): 14 blocks fit, so 2 per fold
    assert record["pick_evidence"] == ("blocked 5-fold cross-validation over the fit and pick rows "
                                       "(2 blocks per fold)")
    assert record["coefficients_fitted_on"].startswith("fit and pick rows")
    assert model.targets["dwx"].metrics["validation"]["r2"] > 0.99
    assert model.extra["identifiability"]["targets"]["dwx"]["pick_t_rows"] == "fit and pick rows"
    plain = identify(data, engine="sparse", targets=["dwx"], loss="squared", settings=base, progress=False)
    assert plain.extra["data"]["pick_evidence"] == "pick rows"
    assert plain.extra["identifiability"]["targets"]["dwx"]["pick_t_rows"] == "fit rows"


def test_a_flight_too_short_for_the_folds_and_their_gaps_is_picked_on_the_pick_rows(capsys):
    data = synthetic_dataset(1500, seed=9, noise=0.03)  # 6 s: 1200 fit and pick rows, 100-row gaps
    model = identify(data, engine="sparse", targets=["dwx"], loss="squared", progress=False)
    assert model.extra["data"]["pick_evidence"] == "pick rows (too few rows for cross-validation)"
    assert model.extra["data"]["coefficients_fitted_on"] == "fit rows"
    assert "too few for 5-fold cross-validation with 0.4 s gaps" in capsys.readouterr().err
    assert model.targets["dwx"].metrics["validation"]["r2"] > 0.99


def test_cv_folds_is_read_from_yaml_and_checked(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("selection:\n  cv_folds: 0\n")
    assert load_engine_settings(path).selection.cv_folds == 0
    assert EngineSettings().selection.cv_folds == 5
    path.write_text("selection:\n  cv_folds: 1\n")
    with pytest.raises(UserError, match="cv_folds"):
        load_engine_settings(path)


def test_the_polish_swaps_in_a_term_another_candidate_found_when_the_folds_prefer_it():
    # the pick holds u1^2 wz and a constant (a bias); the true u1 wz is only in a candidate without it
    rng = np.random.default_rng(12)
    X = _rows(6000, 13)
    X[:, 12] = 500.0 + 30.0 * np.sin(np.arange(6000) * 0.003) + 5 * rng.standard_normal(6000)
    one, vb, true, twin = sympy.Integer(1), S["vb"], S["u1"] * S["wz"], S["u1"] ** 2 * S["wz"]
    y = expression_columns([one, vb, true], X) @ np.array([0.2, -0.4, 3e-4])
    y = y + 0.05 * rng.standard_normal(6000)
    rows = FoldedRows([(X[:4800], y[:4800], None, 3), (X[4800:], y[4800:], None, 3)], folds=5)
    picked = move_candidate([one, vb, twin], rows.loss(one + vb + twin, "absolute"), rows, "absolute", "t")
    other = move_candidate([vb, true], rows.loss(vb + true, "absolute"), rows, "absolute", "t")
    candidates = [picked, other]
    selection = EngineSettings().selection
    assert select(candidates, selection, scale=rows.scale) is picked
    final = polish_by_cross_validation(picked, candidates, rows, "absolute", selection, lambda new: None)
    assert {str(s) for s in term_shapes(final.expression)} == {"1", "vb", "u1*wz"}
    assert final.holdout_loss < picked.holdout_loss
    assert len(candidates) > 2  # the moves joined the candidates the model file's front is drawn from


def test_the_polish_leaves_a_pick_without_a_finite_score_alone():
    X = _rows(3000, 2)
    y = expression_columns([S["vb"]], X)[:, 0]
    rows = FoldedRows([(X, y, None, 3)], folds=5)
    picked = move_candidate([S["vb"], S["wx"]], float("nan"), rows, "absolute", "t")
    candidates = [picked]
    final = polish_by_cross_validation(picked, candidates, rows, "absolute", EngineSettings().selection,
                                       lambda new: None)
    assert final is picked and candidates == [picked]


def test_the_polish_keeps_a_small_term_the_folds_pin_down():
    # a term whose removal costs less than the tolerance's absolute part (abs_tol of the target's spread)
    # but is worse on the held-out rows far beyond their noise: the flight pins it down, so it stays; with
    # cv_polish_z 0 (the tolerance alone) it is dropped as the simpler model
    selection = EngineSettings().selection
    size = selection.abs_tol  # the term's and the noise's RMS
    rng = np.random.default_rng(5)
    X = _rows(6000, 6)
    one, vb, small = sympy.Integer(1), S["vb"], S["wx"] * S["wz"]
    c = size / float(np.std(expression_columns([small], X)))
    y = expression_columns([one, vb, small], X) @ np.array([0.2, -0.4, c]) + size * rng.standard_normal(6000)
    rows = FoldedRows([(X[:4800], y[:4800], None, 3), (X[4800:], y[4800:], None, 3)], folds=5)
    picked = move_candidate([one, vb, small], rows.loss(one + vb + small, "absolute"), rows, "absolute", "t")
    removed = rows.loss(one + vb, "absolute")
    assert removed < picked.holdout_loss * (1 + selection.rel_tol) + selection.abs_tol * rows.scale
    kept = polish_by_cross_validation(picked, [picked], rows, "absolute", selection, lambda new: None)
    assert small in term_shapes(kept.expression)
    tolerance_alone = replace(selection, cv_polish_z=0.0)
    loose = polish_by_cross_validation(picked, [picked], rows, "absolute", tolerance_alone, lambda new: None)
    assert small not in term_shapes(loose.expression)


def test_a_term_the_pick_rows_excite_is_identified_on_the_rows_that_refit_it():
    """The t and VIF rules measure a model on the fit and pick rows (SelectionSettings.identify_on_pick_rows),
    the rows its coefficients are refit on: a yaw term whose rate barely varies on the fit rows and swings
    on the pick rows is not identified by the fit rows and is by both; identify_on re-aims a candidate
    measured on the fit rows (the engine's) at those rows."""
    from identification.collinearity import term_identification
    from identification.cross_validation import identify_on

    rng = np.random.default_rng(21)
    X = _rows(5000, 13)
    X[:4000, 11] = 0.05 * np.sin(np.arange(4000) * 0.003)  # wz (rad/s): small on the fit rows
    X[4000:, 11] = 1.5 * np.sin(np.arange(1000) * 0.01)  # and swinging on the pick rows
    shapes = [sympy.Integer(1), S["vb"] * S["wx"], S["wz"] ** 2]
    y = expression_columns(shapes, X) @ np.array([0.1, -0.7, 0.02])
    y = y + 0.05 * rng.standard_normal(len(y))
    parts = [(X[:4000], y[:4000], None, 3), (X[4000:], y[4000:], None, 3)]
    fit_only = FoldedRows(parts, folds=5)
    both = FoldedRows(parts, folds=5, identify_on_all=True)
    a, yy, lag = fit_only.fit_part(shapes)
    assert fit_only.identification(shapes) == term_identification(a, yy, lag)
    assert fit_only.identification(shapes)[0] < 5.0 < both.identification(shapes)[0]
    move = move_candidate(shapes, 1.0, both, "squared", "test")
    assert move.measured().weakest_t == both.identification(shapes)[0]
    engine_side = move_candidate(shapes, 1.0, fit_only, "squared", "test").measured()
    unmeasured = move_candidate(shapes, 1.0, fit_only, "squared", "test")
    unmeasured.measure = None  # as an engine that does not measure its candidates (not linear in terms)
    identify_on([engine_side, unmeasured], both)
    assert engine_side.measured().weakest_t == pytest.approx(both.identification(shapes)[0], rel=1e-9)
    assert unmeasured.measured().weakest_t is None



def test_the_pick_keeps_a_term_only_the_pick_rows_excite():
    """Through the pick's own rule (pareto.select over cross-validated candidates): measured on the fit and
    pick rows, the model with the yaw term is identified and picked (its cross-validated loss is far
    lower); measured on the fit rows alone, where the yaw rate barely varies, it is set aside."""
    from identification.engine_settings import SelectionSettings

    rng = np.random.default_rng(8)
    X = _rows(5000, 17)
    X[:4000, 11] = rng.uniform(-0.3, 0.3, 4000)  # wz (rad/s): small on the fit rows, swinging after
    X[4000:, 11] = rng.uniform(-2.0, 2.0, 1000)
    truth = [S["wx"] * S["wy"], S["wz"] ** 2]
    y = expression_columns(truth, X) @ np.array([-0.02, 0.05]) + 0.05 * rng.standard_normal(5000)
    parts = [(X[:4000], y[:4000], None, 3), (X[4000:], y[4000:], None, 3)]
    picked = {}
    for on_all in (True, False):
        rows = FoldedRows(parts, folds=5, identify_on_all=on_all)
        models = [[sympy.Integer(1), truth[0]], [sympy.Integer(1), *truth]]
        candidates = [move_candidate(m, rows.terms_loss(m, "squared"), rows, "squared", "test")
                      for m in models]
        picked[on_all] = term_shapes(select(candidates, SelectionSettings(), scale=rows.scale).expression)
        with_yaw = candidates[1].measured()
        assert (with_yaw.weakest_t >= 5.0) == on_all, with_yaw.weakest_t
    assert S["wz"] ** 2 in picked[True] and S["wz"] ** 2 not in picked[False]


@pytest.mark.parametrize("kind", ["absolute", "squared"])
def test_the_one_term_moves_scored_at_once_are_the_moves_scored_one_by_one(kind):
    """move_losses (the polish's thousands of swaps and additions from one solve per fold and kept set) gives
    each move the loss terms_loss gives it, and no loss (inf) to a move whose new term is a combination of
    the kept ones (there the Schur complement is rounding: the rows cannot tell the terms apart)."""
    X = _rows(1000, 8)
    current = [sympy.Integer(1), S["u1"] * S["wz"], S["vb"] * S["wx"], S["wy"]]
    y = expression_columns(current, X) @ np.array([0.3, 2e-3, -0.7, 0.2])
    y = y + 0.05 * np.random.default_rng(9).standard_normal(len(y))
    dependent = 2 * S["wy"] + S["u1"] * S["wz"]  # a combination of two current terms
    others = [S["u2"], S["ub"] * S["wz"], S["wx"] ** 2, dependent, S["u3"] * S["wy"]]
    rows = FoldedRows([(X[:700], y[:700], None, 5), (X[700:], y[700:], None, 5)], 5)
    rows.prepare([*current, *others])
    swaps, adds = rows.move_losses(current, others, kind)
    for p, other in enumerate(others):
        for i in range(len(current)):
            model = current[:i] + [other] + current[i + 1:]
            if other == dependent and i not in (1, 3):  # still a combination of the kept terms
                assert swaps[i, p] == np.inf
            else:
                assert swaps[i, p] == pytest.approx(rows.terms_loss(model, kind), rel=1e-9)
        if other == dependent:
            assert adds[p] == np.inf
        else:
            assert adds[p] == pytest.approx(rows.terms_loss([*current, other], kind), rel=1e-9)
    assert FoldedRows(rows.parts, 5).move_losses(current, others, kind) is None  # not prepared


def _assert_moves_scored_one_by_one(rows: FoldedRows, current: list, others: list, kind: str,
                                    rel: float) -> None:
    """Every swap and addition move_losses scores has the loss terms_loss gives its model."""
    swaps, adds = rows.move_losses(current, others, kind)
    for p, other in enumerate(others):
        assert adds[p] == pytest.approx(rows.terms_loss([*current, other], kind), rel=rel)
        for i in range(len(current)):
            model = current[:i] + [other] + current[i + 1:]
            assert swaps[i, p] == pytest.approx(rows.terms_loss(model, kind), rel=rel)


@pytest.mark.parametrize("tie", [0.0, 1e-3, 1e-5])
def test_the_moves_of_a_model_with_nearly_tied_terms_are_scored_as_one_by_one(tie):
    """The moves' losses come from rank-one changes of the model's fit per fold, which lose digits when its
    own terms are nearly tied (wy beside wy + 1e-5 wx^2: 1e-4 of the loss); there too (and with no tie) each
    move's loss is the one terms_loss gives it."""
    X = _rows(1000, 12)
    wy_twin = S["wy"] + tie * S["wx"] ** 2 if tie else S["wy"] * S["u1"]
    current = [sympy.Integer(1), S["u1"] * S["wz"], S["wy"], wy_twin]
    y = expression_columns(current[:3], X) @ np.array([0.3, 2e-3, 0.2])
    y = y + 0.05 * np.random.default_rng(12).standard_normal(len(y))
    others = [S["u2"], S["ub"] * S["wz"], S["wx"] * S["wz"]]
    rows = FoldedRows([(X[:700], y[:700], None, 5), (X[700:], y[700:], None, 5)], 5)
    rows.prepare([*current, *others])
    _assert_moves_scored_one_by_one(rows, current, others, "absolute", rel=1e-7)


def test_a_model_holding_a_term_of_no_pool_is_still_scored_at_once():
    """The polish's rotor patterns bring in terms the pool was not prepared with; a model holding one was
    scored move by move (thousands of refits: 114 of 170 s on one target of a closed-loop flight), so the
    polish prepares the model's terms too (include), and the moves' losses are those terms_loss gives."""
    X = _rows(1000, 8)
    pool = [sympy.Integer(1), S["u1"] * S["wz"], S["wy"], S["u2"], S["wx"] ** 2]
    new = S["wy"] * (S["u1"] - S["u2"] + S["u3"] - S["u4"])  # a pattern the pool does not hold
    current = [sympy.Integer(1), S["u1"] * S["wz"], new]
    y = expression_columns(current, X) @ np.array([0.3, 2e-3, -0.01])
    y = y + 0.05 * np.random.default_rng(10).standard_normal(len(y))
    rows = FoldedRows([(X[:700], y[:700], None, 5), (X[700:], y[700:], None, 5)], 5)
    rows.prepare(pool)
    others = [S["wy"], S["u2"], S["wx"] ** 2]
    assert rows.move_losses(current, others, "squared") is None  # the model's term was not prepared
    rows.include(current)
    _assert_moves_scored_one_by_one(rows, current, others, "squared", rel=1e-9)
    # the terms prepared before keep their columns' values: the same losses as before include
    assert rows.terms_loss(pool[:3], "squared") == pytest.approx(
        FoldedRows(rows.parts, 5).terms_loss(pool[:3], "squared"), rel=1e-12)


def test_terms_included_later_give_the_equations_a_pool_prepared_with_them_would():
    """include() computes only the new terms' blocks of the Gram matrices (over all rows, each fold's dropped
    rows and the fit rows): every model's held-out predictions and fit coefficients are then those of a
    pool prepared with every term at once, and a term already prepared is not added twice."""
    X = _rows(1000, 9)
    pool = [sympy.Integer(1), S["u1"] * S["wz"], S["wy"]]
    later = [S["u2"], S["wx"] ** 2, S["wy"] * (S["u1"] - S["u2"]), S["wy"]]
    y = expression_columns(pool + later[:3], X) @ np.array([0.3, 2e-3, -0.01, 1e-3, 0.2, 1e-4])
    y = y + 0.05 * np.random.default_rng(12).standard_normal(len(y))
    parts = [(X[:700], y[:700], None, 5), (X[700:], y[700:], None, 5)]
    joined, fresh = FoldedRows(parts, 5), FoldedRows(parts, 5)
    joined.prepare(pool)
    joined.include(later)
    fresh.prepare(pool + later)
    assert joined._index == fresh._index  # the same columns in the same order, wy once
    np.testing.assert_allclose(joined._pool.gram, fresh._pool.gram, rtol=1e-12, atol=1e-12)
    for shapes in (pool + later[:3], [sympy.Integer(1), *later[:2]], later[1:3]):
        np.testing.assert_allclose(joined.predictions(shapes), fresh.predictions(shapes), rtol=1e-10)
        np.testing.assert_allclose(joined.fit_coefficients(shapes), fresh.fit_coefficients(shapes),
                                   rtol=1e-10)


def test_a_moves_fit_from_the_prepared_equations_is_least_squares_on_the_fit_rows():
    """fit_coefficients (the polish's move fits) gives the least-squares coefficients on the fit rows alone,
    per term in the term's own unit (terms 1e6 apart in size), and leaves to lstsq what it cannot answer:
    a term not prepared, and two terms equal on the fit rows."""
    X = _rows(1000, 14)
    shapes = [sympy.Integer(1), S["u1"] ** 2, S["u1"] * S["wz"], S["vb"] * S["wx"]]
    y = expression_columns(shapes, X) @ np.array([0.3, 2e-6, 2e-3, -0.7])
    y = y + 0.05 * np.random.default_rng(15).standard_normal(len(y))
    rows = FoldedRows([(X[:700], y[:700], None, 5), (X[700:], y[700:], None, 5)], 5)
    assert rows.fit_coefficients(shapes) is None  # nothing prepared
    twin = 2 * S["vb"] * S["wx"]  # the same column as vb wx, twice
    rows.prepare([*shapes, twin])
    a, b, _ = rows.fit_part(shapes)
    assert len(b) == 700
    expected = np.linalg.lstsq(a, b, rcond=None)[0]
    np.testing.assert_allclose(rows.fit_coefficients(shapes), expected, rtol=1e-9)
    assert rows.fit_coefficients([*shapes, twin]) is None
    assert rows.fit_coefficients([*shapes[:2], S["ub"]]) is None  # ub was not prepared


def test_a_move_the_prepared_equations_cannot_fit_is_fitted_on_unit_rms_columns():
    """A move holding a term not prepared is fitted by lstsq on its columns scaled to unit RMS: on the raw
    columns (u1^4 u2^2 ~ 1e16 beside wx ~ 1) lstsq's cutoff, relative to the largest singular value, drops
    wx's direction and the constant's, and their coefficients with them."""
    X = _rows(1000, 16)
    shapes = [sympy.Integer(1), S["u1"] ** 4 * S["u2"] ** 2, S["wx"]]
    y = expression_columns(shapes, X) @ np.array([0.1, 1e-17, 0.5])
    rows = FoldedRows([(X[:700], y[:700], None, 5), (X[700:], y[700:], None, 5)], 5)
    a, b, _ = rows.fit_part(shapes)
    raw = np.linalg.lstsq(a, b, rcond=None)
    assert raw[2] < 3  # the raw columns' cutoff drops a direction
    c = move_candidate(shapes, 0.0, rows, "absolute", "test")
    assert c is not None and c.linear is not None
    np.testing.assert_allclose(c.linear[1], [0.1, 1e-17, 0.5], rtol=1e-6)


def test_a_moves_training_loss_is_its_loss_on_the_fit_rows_once_read():
    """A polish move's training loss is computed when first read (Candidate.trained: the pick reads the
    held-out loss, the model file's front the training loss): then the loss of its fit on the fit rows."""
    X = _rows(1000, 17)
    shapes = [sympy.Integer(1), S["u1"] * S["wz"], S["vb"] * S["wx"]]
    y = expression_columns(shapes, X) @ np.array([0.2, 1e-3, -0.4])
    y = y + 0.05 * np.random.default_rng(18).standard_normal(len(y))
    rows = FoldedRows([(X[:700], y[:700], None, 5), (X[700:], y[700:], None, 5)], 5)
    rows.prepare(shapes)
    c = move_candidate(shapes, 0.123, rows, "absolute", "test")
    assert c is not None and np.isnan(c.train_loss) and c.holdout_loss == 0.123
    a, b, _ = rows.fit_part(shapes)
    fitted = np.linalg.lstsq(a, b, rcond=None)[0]
    expected = float(np.mean(np.abs(b - a @ fitted)))
    assert c.trained().train_loss == pytest.approx(expected, rel=1e-9)
    assert c.train is None  # computed once
    assert select([c], EngineSettings().selection) is c
