"""Body-frame learning: body targets, the exact composition a = R f_b + g e_z, the body section."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sympy
import yaml

from bridge.errors import UserError
from identification.body_frame import (
    PRIMITIVE_SYMBOLS,
    body_targets,
    compose_ned,
    composed_targets,
    expression_columns,
    primitive_definitions,
    primitive_info,
    primitive_matrix,
    to_variables,
)
from identification.dataset import Dataset
from identification.effects_physics import Effects, body_expressions, flight_rows
from identification.engine_settings import DiscoverySettings, EngineSettings
from identification.identify import identify
from identification.model_file import TARGET_NAMES, BodyModel, Model, TargetModel, load_model, save_model
from identification.true_model import random_states, true_model, true_model_expressions
from identification.validate import compare_models, expression_terms

VEHICLE = "fang-chen-buaa"
GRAVITY = 9.8


def test_composition_of_the_true_body_model_is_the_true_ned_model():
    body = body_expressions(VEHICLE)
    composed = compose_ned(body, GRAVITY)
    truth = true_model_expressions(VEHICLE)
    xi, u = random_states(400, 11)
    ned = Model({**composed, **{n: to_variables(body[n]) for n in ("dwx", "dwy", "dwz")}})
    np.testing.assert_allclose(ned.accelerations(xi, u), true_model(VEHICLE).accelerations(xi, u),
                               rtol=1e-12, atol=1e-9)
    for name in ("ax", "ay", "az"):  # the same monomials: the term comparison stays meaningful in NED
        got, ref = expression_terms(composed[name]), expression_terms(truth[name])
        assert set(got) == set(ref), name
        for k, c in ref.items():
            assert got[k] == pytest.approx(c, rel=1e-12)


def test_body_targets_invert_the_composition():
    xi, u, ned = flight_rows(300, 4, VEHICLE, Effects(rotor_drag=2e-4))
    fb = body_targets(xi, ned, GRAVITY)
    body = body_expressions(VEHICLE, Effects(rotor_drag=2e-4))
    names = ("ub", "vb", "wb", "wx", "wy", "wz", "u1", "u2", "u3", "u4", "h")
    P = primitive_matrix(np.hstack([xi, u]), names)
    fn = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in names], [body[n] for n in ("fx", "fy", "fz")])
    expected = np.column_stack(fn(*[P[:, k] for k in range(len(names))]))
    np.testing.assert_allclose(fb[:, :3], expected, rtol=1e-10, atol=1e-9)
    np.testing.assert_array_equal(fb[:, 3:], ned[:, 3:])


def test_primitives_match_their_definitions():
    xi, u = random_states(50, 2)
    X = np.hstack([xi, u])
    defs = primitive_definitions()
    names = ("ub", "vb", "wb", "h", "u3", "wy")
    P = primitive_matrix(X, names)
    syms = [sympy.Symbol(n, real=True) for n in ("x", "y", "z", "vx", "vy", "vz", "phi", "theta", "psi",
                                                 "wx", "wy", "wz", "u1", "u2", "u3", "u4")]
    for k, n in enumerate(names):
        fn = sympy.lambdify(syms, defs[n])
        np.testing.assert_allclose(fn(*X.T), P[:, k], rtol=1e-12, atol=1e-12)
    speed = np.linalg.norm(P[:, :3], axis=1)  # a rotation keeps the speed
    np.testing.assert_allclose(speed, np.linalg.norm(xi[:, 3:6], axis=1), rtol=1e-12)


def _body_model(effects: Effects) -> BodyModel:
    body = body_expressions(VEHICLE, effects)
    return BodyModel({n: TargetModel(n, e) for n, e in body.items()}, primitive_info(), GRAVITY)


def test_the_ned_metrics_composed_from_the_body_values_are_the_composed_expressions_metrics():
    """identify's workers hand back each body target's values, and the NED targets' metrics are composed from
    them in numbers (composed_values: R f_b + g e_z) rather than by compiling the composed expressions (1.3 s
    of a closed-loop racer's wall): the same metrics on every split, for ax ay az and the rates, on a
    model with a ground-effect law and rotor drag."""
    body = _body_model(Effects(ground_effect=0.08, rotor_drag=0.01))
    splits, predictions = {}, {n: {} for n in body.targets}
    for k, split in enumerate(("train", "pick", "validation")):
        xi, u, ned = flight_rows(300, 20 + k, VEHICLE, Effects(ground_effect=0.08, rotor_drag=0.01))
        X = np.hstack([xi, u])
        noisy = ned + 0.1 * ned.std(axis=0) * np.random.default_rng(k).standard_normal(ned.shape)  # R^2 < 1
        splits[split] = (X, noisy)
        for n, t in body.targets.items():
            predictions[n][split] = expression_columns([t.expression], X)[:, 0]
    wanted = ("ax", "az", "dwy", "dwz")
    by_values = composed_targets(body, wanted, splits, None, predictions)
    by_expressions = composed_targets(body, wanted, splits)
    assert set(by_values) == set(wanted)
    for n in wanted:
        assert by_values[n].expression == by_expressions[n].expression
        for split in splits:
            for key, value in by_expressions[n].metrics[split].items():
                assert by_values[n].metrics[split][key] == pytest.approx(value, rel=1e-9, abs=1e-12), (n, key)
        assert by_values[n].metrics["validation"]["r2"] < 0.99999  # the noise shows: values that could differ


def test_model_file_2_round_trip_keeps_the_body_section(tmp_path: Path):
    body = _body_model(Effects(ground_effect=0.08))
    exprs = compose_ned({n: body.targets[n].expression for n in ("fx", "fy", "fz")}, GRAVITY)
    exprs.update({n: to_variables(body.targets[n].expression) for n in ("dwx", "dwy", "dwz")})
    model = Model(exprs, body=body)
    path = save_model(model, tmp_path / "m.yaml")
    data = yaml.safe_load(path.read_text())
    assert data["format"] == "quadsr-model/2"
    assert "h" in data["body"]["targets"]["fz"]["expression"]  # written in the primitive names
    again = load_model(path)
    assert again.body is not None and again.body.gravity == GRAVITY
    assert set(again.body.targets) == {"fx", "fy", "fz", "dwx", "dwy", "dwz"}
    xi, u, ned = flight_rows(200, 5, VEHICLE, Effects(ground_effect=0.08))
    np.testing.assert_allclose(again.accelerations(xi, u), ned, rtol=1e-9, atol=1e-9)
    for name in ("fz", "dwx"):
        assert sympy.simplify(again.body.targets[name].expression - body.targets[name].expression) == 0


def test_old_format_1_files_still_load(tmp_path: Path):
    exprs = true_model_expressions(VEHICLE)
    from identification.model_file import expression_to_string

    data = {
        "format": "quadsr-model/1",
        "kind": "true-model",
        "targets": {n: {"expression": expression_to_string(exprs[n])} for n in TARGET_NAMES},
    }
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(data))
    model = load_model(path)
    assert model.body is None
    xi, u = random_states(100, 6)
    expected = true_model(VEHICLE).accelerations(xi, u)
    np.testing.assert_allclose(model.accelerations(xi, u), expected, rtol=1e-12)


def test_a_malformed_body_section_is_a_user_error_naming_the_key(tmp_path: Path):
    body = _body_model(Effects())
    model = Model(true_model_expressions(VEHICLE), body=body)
    path = save_model(model, tmp_path / "m.yaml")
    data = yaml.safe_load(path.read_text())
    data["body"]["targets"]["fz"]["expression"] = "airspeed*2"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(UserError, match=r"body\.targets\.fz\.expression.*airspeed"):
        load_model(path)
    data["body"]["targets"]["fq"] = data["body"]["targets"].pop("fz")
    data["body"]["targets"]["fq"]["expression"] = "ub"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(UserError, match=r"body\.targets\.fq.*not a body target"):
        load_model(path)
    data["format"] = "quadsr-model/9"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(UserError, match="cannot read"):
        load_model(path)


def test_identify_learns_in_the_body_frame_and_composes_the_six_targets(tmp_path: Path):
    effects = Effects(rotor_drag=2e-4)
    xi, u, ned = flight_rows(900, 8, VEHICLE, effects)
    data = Dataset(t=np.arange(900) * 0.004, xi=xi, u=u, targets=ned, source="synthetic", format="synthetic",
                   target_source="truth")
    small = DiscoverySettings(rounds=2, operon_population=40)
    settings = EngineSettings(discovery=small)
    model = identify(data, settings=settings, budget=2, progress=False, gravity=GRAVITY)
    assert model.body is not None and set(model.body.targets) == {"fx", "fy", "fz", "dwx", "dwy", "dwz"}
    path = save_model(model, tmp_path / "model.yaml")
    again = load_model(path)
    reference_body = body_expressions(VEHICLE, effects)
    reference = Model({**compose_ned(reference_body, GRAVITY),
                       **{n: to_variables(reference_body[n]) for n in ("dwx", "dwy", "dwz")}})
    for c in compare_models(again, reference):
        assert c.same_terms, (c.target, c.missing, c.extra)
        assert c.max_relative_error < 1e-3
    assert "u1*ub" in {str(k) for k in expression_terms(again.body.targets["fx"].expression)}
    for name in TARGET_NAMES:
        assert again.targets[name].metrics["validation"]["r2"] > 0.999999
