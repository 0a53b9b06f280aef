"""The pick's physical rules: anti-damping candidates set aside (identification.self_feedback, pareto.select),
the physics-only candidates compared, and a target the flight does not excite given the minimal physical
model with a flag (pareto.excited, identify)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import sympy

from bridge.rotations import rotation_matrix
from identification.body_frame import PRIMITIVE_SYMBOLS, body_targets, primitive_matrix
from identification.candidate import Candidate
from identification.dataset import Dataset
from identification.engine_settings import DiscoverySettings, EngineSettings, SelectionSettings
from identification.identify import identify
from identification.metrics import loss
from identification.model_file import SYMBOLS
from identification.pareto import anti_damping, attach_holdout, select
from identification.physics_candidates import fit_terms
from identification.refit import terms_candidate
from identification.self_feedback import mark_self_feedback

DT = 0.02  # s: 50 Hz, as PX4's vehicle_angular_velocity in a ULog


def _smooth(rng: np.random.Generator, n: int, spread: float, width: int = 25) -> np.ndarray:
    """A smooth random signal (moving average of white noise) with standard deviation `spread`."""
    x = np.convolve(rng.standard_normal(n + width), np.ones(width), mode="valid")[:n]
    return spread * (x - x.mean()) / x.std()


def _hover_rows(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """States xi (N,12) and rotor speeds u (N,4) rad/s of a vehicle near hover: small attitudes, rates that
    are noise (0.01 rad/s), forward speed and rotor speeds varied."""
    rng = np.random.default_rng(seed)
    xi = np.zeros((n, 12))
    xi[:, 2] = -5.0 + _smooth(rng, n, 0.5)
    xi[:, 6] = _smooth(rng, n, 0.03)
    xi[:, 7] = _smooth(rng, n, 0.03)
    xi[:, 8] = 0.4 + _smooth(rng, n, 0.05)
    rot = rotation_matrix(xi[:, 6], xi[:, 7], xi[:, 8])
    vb = np.column_stack([_smooth(rng, n, 1.0), _smooth(rng, n, 0.3), _smooth(rng, n, 0.3)])
    xi[:, 3:6] = np.einsum("nij,nj->ni", rot, vb)
    xi[:, 9:12] = 0.01 * rng.standard_normal((n, 3))
    u = 620.0 + _smooth(rng, n, 25.0)[:, None] + _smooth(rng, 4 * n, 8.0).reshape(n, 4)
    return xi, u


def test_the_pick_sets_aside_a_candidate_with_anti_damping_while_another_passes():
    n = 2000
    xi, u = _hover_rows(n, seed=3)
    X = np.hstack([xi, u])
    f2 = -(u[:, 0] ** 2) + u[:, 1] ** 2 + u[:, 2] ** 2 - u[:, 3] ** 2
    w = xi[:, 9]
    # a rate derivative estimated by a backward difference of noisy rates: +1/dt correlation with wx
    y = 1e-5 * f2 + (w - np.roll(w, 1)) / DT
    y[0] = y[1]
    fit, pick = slice(0, 1500), slice(1500, n)
    anti = fit_terms(("1", "f2", "wx"), X[fit], y[fit], "absolute")
    physics = fit_terms(("1", "f2"), X[fit], y[fit], "absolute")
    candidates = [anti, physics]
    attach_holdout(candidates, X[pick], y[pick], "absolute")
    settings = SelectionSettings()
    scale = float(np.std(y[pick]))
    assert anti.holdout_loss < physics.holdout_loss  # the artefact predicts the held-out rows better
    assert select(candidates, settings, scale) is anti  # and without the self-feedback rule it wins
    mark_self_feedback(candidates, X[fit], y[fit], "dwx")
    assert anti.self_feedback > 25.0 and anti.self_feedback > 10 * anti.self_feedback_se  # ~ +1/dt, sure
    assert physics.self_feedback == 0.0 and not anti_damping(physics, settings)
    assert select(candidates, settings, scale) is physics
    assert select([anti], settings, scale) is anti  # nothing passes: the pick keeps it (and the check flags)


def test_a_small_positive_self_feedback_within_its_standard_error_is_not_set_aside():
    n = 1500
    xi, u = _hover_rows(n, seed=4)
    X = np.hstack([xi, u])
    y = 0.5 * np.random.default_rng(5).standard_normal(n)  # nothing to do with wx
    c = Candidate(sympy.Float(0.2) * SYMBOLS["wx"], 3, 0.0, "test")
    c.train_loss = loss(y, c.evaluate(X), "absolute")
    mark_self_feedback([c], X, y, "dwx")
    assert 0.19 < c.self_feedback < 0.21  # the slope of 0.2 wx
    assert c.self_feedback_se > 1.0  # noise 0.5 over wx spread 0.01 and ~1500 rows: se ~ 1.3
    assert not anti_damping(c, SelectionSettings())


def test_a_fitted_sum_of_terms_has_the_slope_of_its_evaluated_sum():
    """A candidate fitted as coefficients times terms (refit.terms_candidate: the polish's moves) gets its
    slope from its terms' mean slopes, kept per term: the slope evaluating its sum on the moved rows gives,
    also where a term is not finite on some rows (there only the rows where it is count)."""
    n = 1500
    xi, u = _hover_rows(n, seed=6)
    X = np.hstack([xi, u])
    S = PRIMITIVE_SYMBOLS
    shapes = [sympy.Integer(1), S["wx"], S["wx"] * S["wz"], S["wx"] * S["u1"], S["wx"] ** 2 * S["ub"]]
    coef = np.array([0.1, -0.3, 2.0, 1e-3, 0.5])
    fitted = terms_candidate(shapes, coef, "test")
    assert fitted.linear is not None
    plain = dataclasses.replace(fitted, linear=None)  # the same sum, evaluated as one
    X_hole = X.copy()
    X_hole[::7, 12] = np.nan  # u1 unknown on a seventh of the rows: wx u1 is not finite there
    for rows in (X, X_hole):
        y = np.zeros(n)
        mark_self_feedback([fitted, plain], rows, y, "dwx")
        assert np.isfinite(fitted.self_feedback)
        assert fitted.self_feedback == pytest.approx(plain.self_feedback, rel=1e-12)
    mark_self_feedback([fitted], X, np.zeros(n), "dwx")
    ub = primitive_matrix(X, ("ub",))[:, 0]
    exact = np.mean(-0.3 + 2.0 * X[:, 11] + 1e-3 * X[:, 12] + 1.0 * X[:, 9] * ub)  # d/d(wx), averaged
    assert fitted.self_feedback == pytest.approx(exact, rel=1e-9)


def _flight_with_unexcited_fy(n: int, seed: int) -> Dataset:
    """A flight whose body forces are fx = -0.4 ub (drag), fz = 0.3 - 2.5e-5 f1 (thrust) and fy pure noise
    (the vehicle never moved sideways in a way the log shows): NED targets a = R f_b + g e_z."""
    xi, u = _hover_rows(n, seed)
    X = np.hstack([xi, u])
    rng = np.random.default_rng(seed + 100)
    ub = primitive_matrix(X, ("ub",))[:, 0]
    f1 = (u**2).sum(axis=1)
    fb = np.column_stack([
        -0.4 * ub + 0.02 * rng.standard_normal(n),
        0.03 * rng.standard_normal(n),
        0.3 - 2.5e-5 * f1 + 0.05 * rng.standard_normal(n),
    ])
    rot = rotation_matrix(xi[:, 6], xi[:, 7], xi[:, 8])
    a = np.einsum("nij,nj->ni", rot, fb)
    a[:, 2] += 9.80665
    targets = np.column_stack([a, np.zeros((n, 3))])
    return Dataset(t=np.arange(n) * DT, xi=xi, u=u, targets=targets, source="unexcited-fy", format="arrays",
                   target_source="truth")


def test_a_target_the_flight_does_not_excite_gets_the_minimal_physical_model_and_a_flag(capsys):
    data = _flight_with_unexcited_fy(1000, seed=6)
    small = EngineSettings(
        discovery=DiscoverySettings(rounds=2, screen=20, max_terms=8, operon_population=30)
    )
    model = identify(data, targets=["ax", "ay", "az"], budget=2, seed=0, settings=small, progress=False)
    flagged = model.extra["checks"]["not_excited"]
    assert set(flagged) == {"fy"}, flagged  # fx (drag) and fz (thrust) are excited, fy is noise
    assert flagged["fy"]["model_terms"] == ["1"]
    assert flagged["fy"]["best_pick_loss"] > flagged["fy"]["constant_pick_loss"] * 0.95
    fy = model.body.targets["fy"].expression
    assert fy.is_number and abs(float(fy)) < 0.01  # the constant (its fit-rows median), not fitted noise
    assert any(line.startswith("fy: not excited by this flight") for line in model.engine["flags"])
    assert "warning: fy: not excited" in capsys.readouterr().err
    # the excited ones are real models: thrust in fz, drag in fx, and as good as the plain physics on the
    # pick rows (the physics-only candidates are among those the pick compares)
    fz = model.body.targets["fz"]
    assert {SYMBOLS[f"u{i}"] for i in range(1, 5)} <= fz.expression.free_symbols
    assert "ub" in str(model.body.targets["fx"].expression)
    pick = model.extra["data"]["pick"][0]
    rows = (data.t >= pick["t_start_s"] - 1e-9) & (data.t <= pick["t_end_s"] + 1e-9)
    fit_rows = data.t < model.extra["data"]["fit"][0]["t_end_s"] + 1e-9
    X = np.hstack([data.xi, data.u])
    fb = body_targets(data.xi, data.targets, 9.80665)
    physics = fit_terms(("1", "f1"), X[fit_rows], fb[fit_rows, 2], "absolute")
    attach_holdout([physics], X[rows], fb[rows, 2], "absolute")
    assert fz.metrics["pick"]["mae"] <= physics.holdout_loss * 1.02 + 1e-4 * np.std(fb[rows, 2])


def test_rate_noise_with_its_differentiation_artefact_gives_no_anti_damping_model():
    """A hover log's rates are noise and its rate derivative a difference of them (PX4's xyz_derivative on
    px4_sitl_quad_takeoff.ulg: +52 1/s against wx): the sparse engine's library holds wx, and the pick
    must neither keep the +1/dt artefact nor fit noise: dwx is flagged not excited, its model a constant."""
    n = 1200
    xi, u = _hover_rows(n, seed=7)
    w = xi[:, 9]
    dwx = (w - np.roll(w, 1)) / DT
    dwx[0] = dwx[1]
    data = Dataset(t=np.arange(n) * DT, xi=xi, u=u, targets=np.column_stack([np.zeros((n, 3)), dwx,
                   np.zeros((n, 2))]), source="rate-noise", format="arrays", target_source="truth")
    model = identify(data, engine="sparse", targets=["dwx"], progress=False)
    assert set(model.extra["checks"]["not_excited"]) == {"dwx"}
    expr = model.targets["dwx"].expression
    assert expr.is_number, expr
    plain = fit_terms(("1", "wx"), np.hstack([xi, u]), dwx, "squared")
    assert "wx" in str(plain.expression) and plain.weakest_t > 5  # the artefact is there to be fitted


def test_a_body_forces_slope_takes_the_step_of_the_rows_it_is_measured_on():
    """fx's own state is the body velocity ub, moved along the body x axis by 5 % of its spread on the rows
    (self_feedback._step, kept per rows array): a cubic term's central difference is 3 ub^2 + h^2, so its
    slope tells the step used; marked alone or beside another candidate, on rows of another spread."""
    n = 1500
    xi, u = _hover_rows(n, seed=8)
    X = np.hstack([xi, u])
    X[:, 3:6] += np.array([2.0, -1.0, 0.5])  # some forward flight: ub spreads
    ub = PRIMITIVE_SYMBOLS["ub"]
    for rows in (X, np.hstack([X[:, :3], 3 * X[:, 3:6], X[:, 6:]])):
        b = primitive_matrix(rows, ("ub",))[:, 0]
        h = 0.05 * float(np.std(b))
        expected = float(np.mean(3 * b**2)) + h**2
        cubic = terms_candidate([ub**3], np.array([1.0]), "test")
        linear = terms_candidate([ub], np.array([-0.4]), "test")
        mark_self_feedback([cubic, linear], rows, np.zeros(n), "fx")
        assert cubic.self_feedback == pytest.approx(expected, rel=1e-9)
        assert linear.self_feedback == pytest.approx(-0.4, rel=1e-9)
        again = terms_candidate([ub**3], np.array([1.0]), "test")
        mark_self_feedback([again], rows, np.zeros(n), "fx")
        assert again.self_feedback == cubic.self_feedback
