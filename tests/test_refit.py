"""The chosen structure refit on the fit and pick rows (SelectionSettings.refit_with_pick_rows): the same
terms, coefficients equal to a least-squares fit of those terms on both row sets, the validation rows
untouched, and the model file saying which rows fitted the coefficients."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import sympy
from synthetic_data import synthetic_dataset

from identification.body_frame import expression_columns
from identification.collinearity import term_shapes
from identification.data_roles import assign_roles
from identification.engine import EngineSettings
from identification.engine_settings import load_engine_settings
from identification.identify import identify
from identification.metrics import table_metrics
from identification.model_file import load_model, save_model


def _coefficients(expr: sympy.Expr) -> dict[str, float]:
    return {str(shape): float(c) for c, shape in (t.as_coeff_Mul() for t in sympy.Add.make_args(expr))}


@pytest.mark.parametrize("target", ["dwy", "ax"])
def test_the_refit_keeps_the_terms_and_fits_them_on_the_fit_and_pick_rows(tmp_path, target):
    data = synthetic_dataset(3000, seed=21, noise=0.05)
    default = EngineSettings()  # the pick rows alone pick (no cross-validation), with and without the refit
    plain = replace(default, selection=replace(default.selection, cv_folds=0))
    refit = replace(plain, selection=replace(plain.selection, refit_with_pick_rows=True))
    before = identify(data, engine="sparse", targets=[target], loss="squared", settings=plain, progress=False)
    after = identify(data, engine="sparse", targets=[target], loss="squared", settings=refit, progress=False)
    e0, e1 = before.targets[target].expression, after.targets[target].expression
    assert sorted(map(str, term_shapes(e0))) == sorted(map(str, term_shapes(e1)))
    c0, c1 = _coefficients(e0), _coefficients(e1)
    assert any(abs(c1[k] - c0[k]) > 1e-9 * abs(c0[k]) for k in c0)  # the pick rows moved them

    roles = assign_roles(data)
    # the refit's rows: fit and pick (the chosen terms of the pick-rows pick, refit)
    j = ["ax", "ay", "az", "dwx", "dwy", "dwz"].index(target)
    X = np.vstack([np.hstack([r.xi, r.u]) for r in (roles.fit, roles.pick)])
    y = np.concatenate([r.targets[:, j] for r in (roles.fit, roles.pick)])
    shapes = term_shapes(e1)
    cols = expression_columns(shapes, X)
    expected = np.linalg.lstsq(cols, y, rcond=None)[0]
    for shape, value in zip(shapes, expected, strict=True):
        assert c1[str(shape)] == pytest.approx(value, rel=1e-6, abs=1e-12)

    saved = load_model(save_model(after, tmp_path / "m.yaml"))
    assert "fit and pick rows" in saved.extra["data"]["coefficients_fitted_on"]
    assert before.extra["data"]["coefficients_fitted_on"] == "fit rows"
    val = roles.validate  # validation: the refit model on rows that neither fitted nor picked
    pred = saved.evaluate(val.xi, val.u)[:, 0]
    assert saved.targets[target].metrics["validation"]["r2"] == pytest.approx(
        table_metrics(val.targets[:, j], pred)["r2"], rel=1e-9)


def test_the_refit_is_read_from_yaml(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("selection:\n  refit_with_pick_rows: true\n")
    assert load_engine_settings(path).selection.refit_with_pick_rows is True
    assert EngineSettings().selection.refit_with_pick_rows is False
