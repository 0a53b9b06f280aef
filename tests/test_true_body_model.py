"""The SITL's true equations in the body frame (identification.true_model.true_body_expressions), the
discovery benchmark's vehicle files (bench/vehicles/), and the body-frame term comparison."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sympy
from physics_targets import sitl_accelerations

from bridge.vehicle import load_vehicle
from identification.body_frame import BODY_TARGET_NAMES, PRIMITIVE_SYMBOLS, body_targets, primitive_matrix
from identification.true_model import random_states, true_body_expressions
from identification.validate import compare_expressions

REPO = Path(__file__).resolve().parent.parent
BENCH_VEHICLES = sorted((REPO / "bench" / "vehicles").glob("*.yaml"))
NAMES = ("ub", "vb", "wb", "wx", "wy", "wz", "u1", "u2", "u3", "u4", "h", "phi", "theta")


def evaluate_body(exprs: dict[str, sympy.Expr], xi: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The body-frame expressions (primitive names) at each state, (N, 6)."""
    P = primitive_matrix(np.hstack([xi, u]), NAMES)
    fn = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in NAMES], [exprs[n] for n in BODY_TARGET_NAMES], "numpy")
    cols = fn(*[P[:, k] for k in range(P.shape[1])])
    return np.column_stack([np.broadcast_to(np.asarray(c, float), (len(xi),)) for c in cols])


@pytest.mark.parametrize("name,ground", [("fang-chen-buaa", "plane"), ("fang-chen-aero", "plane"),
                                         ("fang-chen-aero", "none"),
                                         *[(str(p), "plane") for p in BENCH_VEHICLES]])
def test_true_body_expressions_are_the_sitls_body_frame_derivative(name, ground):
    vehicle = load_vehicle(name).with_overrides(ground=ground)
    xi, u = random_states(120, seed=11)
    xi[:, 2] = np.random.default_rng(12).uniform(-1.5, -0.01, len(xi))  # near the ground: its effect and cap
    expected = body_targets(xi, sitl_accelerations(vehicle, xi, u), vehicle.gravity)
    got = evaluate_body(true_body_expressions(vehicle), xi, u)
    scale = np.maximum(np.abs(expected), 1e-3 * np.abs(expected).max(axis=0))
    assert np.max(np.abs(got - expected) / scale) < 1e-9


def test_the_body_frame_truth_of_open_loop_flights_is_in_the_default_primitives():
    # no ground: no attitude (phi, theta) and no height in the physics; the paper's vehicle has 33 monomials
    free = set()
    for e in true_body_expressions(load_vehicle("fang-chen-aero").with_overrides(ground="none")).values():
        free |= {str(s) for s in e.free_symbols}
    assert free <= {"ub", "vb", "wb", "wx", "wy", "wz", "u1", "u2", "u3", "u4"}
    plain = true_body_expressions("fang-chen-buaa")
    assert sum(len(sympy.Add.make_args(sympy.expand(e))) for e in plain.values()) == 33


def test_bench_vehicles_switch_on_what_their_file_says():
    v = {p.stem: load_vehicle(p) for p in BENCH_VEHICLES}
    assert v["buaa-rotor-drag"].aero.rotor_drag is not None
    assert v["buaa-translational-lift"].aero.translational_lift > 0
    assert any(v["buaa-frame-drag"].aero.frame_drag)
    assert v["buaa-ground-effect"].aero.ground_effect is not None
    cts = [r.thrust_coefficient for r in v["buaa-weak-rotor"].rotor_set]
    assert cts[2] == pytest.approx(0.92 * cts[0], rel=1e-3) and cts[0] == cts[1] == cts[3]
    assert v["buaa-px4-thrust"].motor_curve.kind == "px4" and v["buaa-px4-thrust"].paper_physics
    iris = v["iris-wide-cg"]
    assert [r.position[:2] for r in iris.rotor_set] == [(0.1515, 0.245), (-0.1515, -0.1875), (0.1515, -0.245),
                                                        (-0.1515, 0.1875)]
    assert any(iris.center_of_gravity)
    assert v["heavy-650"].mass > 2 * v["buaa-rotor-drag"].mass


def test_frame_drag_compared_in_the_body_frame_is_one_term_not_its_ned_expansion():
    p = PRIMITIVE_SYMBOLS
    speed = sympy.sqrt(p["ub"] ** 2 + p["vb"] ** 2 + p["wb"] ** 2)
    ref = {"fx": -0.02 * p["ub"] * speed - 0.0393 * p["ub"] * sympy.Abs(p["ub"])}
    got = {"fx": -0.0201 * speed * p["ub"] - 0.0393 * sympy.Abs(p["ub"]) * p["ub"]}
    (c,) = compare_expressions(got, ref)
    assert c.same_terms and c.max_relative_error == pytest.approx(0.005)
    worse = {"fx": got["fx"] + 1e-4 * p["ub"]}
    (c,) = compare_expressions(worse, ref)
    assert c.extra == ["ub"] and not c.missing
